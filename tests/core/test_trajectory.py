"""Scan trajectories: generators, rig limits checked before any move, motion-time order,
planned views through the scan folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plantscan_core import cli
from plantscan_core.acquire import acquire, plan
from plantscan_core.adaptive import record_round
from plantscan_core.errors import RecipeError, ScanFolderError
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import PLANNED_VIEWS_JSONL, ScanFolder
from plantscan_core.testing import tiny_recipe
from plantscan_core.timing import AxisTiming
from plantscan_core.trajectory import (
    MotionModel,
    PlannedStop,
    Stop,
    ViewPlan,
    order_stops,
)

# The seed's rig (recipes/default.yaml): turntable 12 deg/s, 24 deg/s2; tilt arm 4, 8; the
# Phidget default settle 0.3 s; gphoto2 default capture and download 1 s.
SEED_RIG = MotionModel(AxisTiming(12.0, 24.0, 0.3), AxisTiming(4.0, 8.0, 0.3), 1.0, 1.0)


def _tiny(trajectory=None, **scan) -> dict:
    raw = tiny_recipe()
    raw["scan"]["tilt_arm"] = {"plugin": "tiny"}
    raw["scan"]["roles"]["calibration"]["enabled"] = False
    if trajectory is not None:
        raw["scan"]["trajectory"] = trajectory
    raw["scan"].update(scan)
    return raw


@pytest.mark.parametrize("trajectory, n, tilts", [
    ({"kind": "grid", "tilts_deg": [0, 20], "images_per_revolution": 12}, 24, {0.0, 20.0}),
    ({"kind": "per-tilt", "rings": [{"tilt_deg": 0, "stops": 24}, {"tilt_deg": 30, "stops": 8}]},
     32, {0.0, 30.0}),
    ({"kind": "spiral", "stops": 40, "tilt_range_deg": [-10, 30], "turns": 4}, 40,
     {-10.0, -5.0, 0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0}),
    ({"kind": "golden-angle", "stops": 40, "tilt_range_deg": [-10, 30]}, 40,
     {-10.0, -5.0, 0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0}),
    ({"kind": "views", "views": [[0, 0], [370, 10], [45.5, -5]]}, 3, {0.0, 10.0, -5.0}),
])
def test_generators_give_their_stops_within_range(tiny_rig_manager, trajectory, n, tilts):
    recipe = validate_recipe(_tiny(trajectory), tiny_rig_manager.registry)
    stops = recipe.scan.role_stops("plant")
    assert len(stops) == n
    assert {s.tilt_deg for s in stops} == tilts
    assert all(0.0 <= s.pan_deg < 360.0 for s in stops)
    # every tilt a plant view is taken at has its background plate, by default
    assert set(recipe.scan.role_tilts("background")) >= tilts
    views = [v for v in plan(recipe, tiny_rig_manager.registry) if v.role == "plant"]
    assert len(views) == 2 * n and len({v.key for v in views}) == 2 * n


def test_golden_angle_stops_spread_over_the_band():
    from plantscan_core.trajectory import GoldenAngleTrajectory

    stops = GoldenAngleTrajectory(kind="golden-angle", stops=60, tilt_range_deg=(-10, 30),
                                  tilt_step_deg=0).stops()
    # the sine of the tilt rises evenly (equal-area bands on the view sphere)
    s = np.sin(np.radians([st.tilt_deg for st in stops]))
    assert np.allclose(np.diff(s), np.diff(s)[0])
    # any first part of the list covers every azimuth sector of 60 deg
    first = np.array([st.pan_deg for st in stops[:12]])
    assert len(np.unique((first // 60).astype(int))) == 6


def test_a_stop_outside_the_rigs_limits_is_refused_before_anything_moves(tmp_path, capsys):
    out = tmp_path / "scan"
    rc = cli.main(["scan", "--recipe", "plastic-dicot", "--out", str(out),
                   "--set", "scan.limits.tilt_deg=[-20, 45]",
                   "--set", "scan.trajectory={kind: views, views: [[0, 0], [90, 10], "
                            "[180, 60], [270, 80]]}"])
    err = capsys.readouterr().err
    assert rc == cli.EXIT_USER_ERROR
    # each offending stop named by its place in the list, with the limit it breaks
    assert "scan.trajectory.views.2: stop 2 (pan 180, tilt 60 deg): tilt 60 outside the " \
           "rig's tilt range [-20, 45]" in err
    assert "scan.trajectory.views.3" in err
    assert not out.exists()  # nothing built, nothing captured, no motor moved


def test_axes_faster_than_the_rig_allows_are_refused(capsys):
    rc = cli.main(["recipe", "check", "default", "--set", "scan.limits.tilt_velocity_deg_s=2",
                   "--set", "scan.limits.turntable_acceleration_deg_s2=10"])
    err = capsys.readouterr().err
    assert rc == cli.EXIT_USER_ERROR
    assert "scan.tilt_arm.params.velocity_deg_s: 4 deg/s is more than the rig allows" in err
    assert "scan.turntable.params.acceleration_deg_s2: 24 deg/s² is more than" in err


def test_generated_stops_outside_the_limits_and_repeated_stops_are_named(tiny_rig_manager):
    raw = _tiny({"kind": "spiral", "stops": 30, "tilt_range_deg": [0, 60], "turns": 3},
                limits={"tilt_deg": [-10, 40]})
    with pytest.raises(RecipeError) as exc:
        validate_recipe(raw, tiny_rig_manager.registry)
    msgs = [m for _, m in exc.value.errors]
    assert any("stops in all are outside the rig's tilt range" in m for m in msgs)
    raw = _tiny({"kind": "views", "views": [[0, 0], [10, 0], [370, 0]]})
    with pytest.raises(RecipeError, match="stop 2 repeats stop 1"):
        validate_recipe(raw, tiny_rig_manager.registry)


def test_order_avoids_turntable_rewinds_and_tilt_moves():
    grid = [Stop(i * 10.0, t, i) for t in (0.0, 10.0, 20.0) for i in range(36)]
    rng = np.random.default_rng(0)
    shuffled = [grid[i] for i in rng.permutation(len(grid))]
    order, seconds = order_stops(shuffled, SEED_RIG)
    # every stop once
    assert sorted(s.position for s in order) == sorted(s.position for s in grid)
    # ring by ring, every other ring backwards: no 350 deg rewind of the turntable
    # (29 s at 12 deg/s) between rings, two tilt moves in all
    tilt_moves = sum(a.tilt_deg != b.tilt_deg for a, b in zip(order, order[1:]))
    assert tilt_moves == 2
    assert SEED_RIG.tour_s(order) == min(seconds.values())
    assert SEED_RIG.tour_s(order) < seconds["by-tilt"] - 2 * 25.0
    assert SEED_RIG.tour_s(order) < 0.5 * seconds["as-given"]


def test_acquisition_takes_the_trajectory_in_the_quickest_order(tiny_rig_manager):
    views = [[(i * 97.0) % 360.0, [0.0, 20.0, 10.0][i % 3]] for i in range(15)]
    recipe = validate_recipe(_tiny({"kind": "views", "views": views}),
                             tiny_rig_manager.registry)
    planned = [v for v in plan(recipe, tiny_rig_manager.registry) if v.role == "plant"]
    positions = [(v.angle_deg, v.tilt_deg) for v in planned[::2]]
    # the tiny axes have no timing parameters: every move is free, so the order given wins
    # ties (deterministic); the keys follow the list, whatever the order.
    assert positions == [(p % 360.0, t) for p, t in views]
    assert [v.angle_index for v in planned[::2]] == list(range(15))


def test_planned_views_round_trip_through_the_scan_folder(tiny_rig_manager, tmp_path):
    raw = _tiny(None, adaptive={"tilts_deg": [0.0, 20.0], "max_plant_images": 40})
    recipe = validate_recipe(raw, tiny_rig_manager.registry)
    scan = acquire(recipe, tmp_path / "scan", tiny_rig_manager, raw_recipe=raw)
    base = len(scan.views_by_role("plant"))
    assert base == 12
    stops = [PlannedStop(15.0, 20.0, 120.0, "carves the cup"), PlannedStop(200.0, 0.0, 40.0, "x")]
    rnd = record_round(scan, recipe, ViewPlan(stops=stops, unsure_volume_mm3=500.0,
                                              hull_volume_mm3=9000.0, predicted_carve_mm3=160.0),
                       "next-best-view", {"planner_s": 1.5})
    assert [s.index for s in rnd.stops] == [6, 7]  # after the base grid's angle indices 0-5
    again = ScanFolder.open(scan.root).planned_rounds()
    assert [r.to_dict() for r in again] == [rnd.to_dict()]
    assert again[0].stops[0].reason == "carves the cup"
    assert again[0].figures["planner_s"] == 1.5
    # a resumed scan captures exactly the planned stops, with both cameras, once
    scan = acquire(recipe, scan.root, tiny_rig_manager, raw_recipe=raw, resume=True)
    new = scan.views_by_role("plant")[base:]
    assert sorted((v.camera, v.commanded_angle_deg, v.tilt_deg, v.angle_index) for v in new) == \
        sorted((c, s.pan_deg, s.tilt_deg, 6 + i) for i, s in enumerate(stops)
               for c in ("cam0", "cam1"))
    scan = acquire(recipe, scan.root, tiny_rig_manager, raw_recipe=raw, resume=True)
    assert len(scan.views_by_role("plant")) == base + 4
    # a damaged line is refused naming file and line
    path = scan.root / PLANNED_VIEWS_JSONL
    line = json.loads(path.read_text().splitlines()[0])
    line["stops"][0]["tilt_deg"] = 120.0
    path.write_text(json.dumps(line) + "\n")
    with pytest.raises(ScanFolderError, match=r"planned_views.jsonl:1: malformed planned round"):
        ScanFolder.open(scan.root).planned_rounds()


def test_dry_run_prints_the_trajectorys_capture_time(capsys):
    golden = "scan.trajectory={kind: golden-angle, stops: 50, tilt_range_deg: [0, 30]}"
    rc = cli.main(["scan", "--recipe", "default", "--dry-run", "--set", golden])
    # the recipe calibrates at tilt 0 only: no tilt axis for the trajectory's other tilts
    assert rc == cli.EXIT_USER_ERROR
    assert "scan.roles.calibration.tilts_deg: plant tilts [5.0, 10.0, 15.0, 20.0, 25.0, " \
           "30.0] are not calibrated" in capsys.readouterr().err
    rc = cli.main(["scan", "--recipe", "default", "--dry-run", "--set", golden,
                   "--set", "scan.roles.calibration.tilts_deg=[0, 30]"])
    out = capsys.readouterr().out
    assert rc == 0
    plant = next(line for line in out.splitlines() if line.startswith("plant"))
    stops, images = (int(x) for x in plant.split()[1:3])
    assert (stops, images) == (50, 100)

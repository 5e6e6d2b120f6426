"""scan --adaptive on the tiny rig: rounds recorded, budgets kept, a resumed scan continues."""

from __future__ import annotations

import plantscan_hull.plugin as hull_plugin
import plantscan_plan.plugin as plan_plugin
import pytest

from plantscan_core.adaptive import PLANNING_DIR, plan_next, record_round, scan_adaptive
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.testing import tiny_processing_plugin, tiny_recipe


@pytest.fixture
def manager(tiny_rig_manager):
    tiny_rig_manager.register(tiny_processing_plugin, name="tiny-processing")
    tiny_rig_manager.register(hull_plugin, name="hull")
    tiny_rig_manager.register(plan_plugin, name="plan")
    return tiny_rig_manager


def _recipe(manager, **adaptive):
    raw = tiny_recipe()
    raw["scan"]["roles"]["calibration"]["enabled"] = False
    # the tiny exact calibrator knows tilt 0 only: the planner picks turntable angles there
    raw["scan"]["adaptive"] = {"tilts_deg": [0.0], "pan_step_deg": 15.0, "resolution": 48,
                               "min_gain_fraction": 0.0, **adaptive}
    raw.update(calibrate={"plugin": "tiny-exact"}, segment={"plugin": "tiny-dark"},
               reconstruct={"plugin": "octree-hull", "params": {"k": 0, "floor_z_mm": None}})
    return validate_recipe(raw, manager.registry), raw


def test_adaptive_scan_plans_rounds_within_the_image_budget(manager, tmp_path):
    recipe, raw = _recipe(manager, max_plant_images=20, stops_per_round=2, max_rounds=5)
    lines: list[str] = []
    scan = scan_adaptive(recipe, tmp_path / "scan", manager, raw_recipe=raw, log=lines.append)
    rounds = scan.planned_rounds()
    # 6 base stops (12 images), then two rounds of 2 stops (2 cameras each): 20 images
    assert len(scan.views_by_role("plant")) == 20
    assert [len(r.stops) for r in rounds] == [2, 2, 0]
    assert rounds[-1].stop_reason.startswith("image budget spent (20 of 20")
    for r in rounds[:2]:
        assert r.planner == "next-best-view"
        assert r.figures["planner_s"] >= 0 and r.figures["hull_volume_mm3"] > 0
        for s in r.stops:  # every planned stop was taken by both cameras
            taken = [v for v in scan.views_by_role("plant") if v.angle_index == s.index]
            assert sorted(v.camera for v in taken) == ["cam0", "cam1"]
            assert taken[0].commanded_angle_deg == pytest.approx(s.pan_deg)
    assert (scan.root / PLANNING_DIR / "plan.json").exists()
    assert "round 2" in lines[1] and "image budget spent" in lines[-1]


def test_resumed_adaptive_scan_takes_the_recorded_stops_then_goes_on(manager, tmp_path):
    recipe, raw = _recipe(manager, max_plant_images=24, stops_per_round=2, max_rounds=2)
    out = tmp_path / "scan"
    from plantscan_core.acquire import acquire

    scan = acquire(recipe, out, manager, raw_recipe=raw)
    # the first round was planned and recorded, then the scan was killed before capturing
    rr = plan_next(out, recipe, manager)
    first = record_round(scan, recipe, rr.view_plan, rr.planner)
    assert len(first.stops) == 2
    scan = scan_adaptive(recipe, out, manager, raw_recipe=raw, resume=True, log=lambda _: None)
    rounds = scan.planned_rounds()
    assert rounds[0].to_dict() == first.to_dict()  # kept, not planned again
    assert [len(r.stops) for r in rounds] == [2, 2, 0]
    assert rounds[-1].stop_reason == "max_rounds reached (2)"
    taken = {v.angle_index for v in scan.views_by_role("plant")}
    assert {s.index for r in rounds for s in r.stops} <= taken
    assert len(scan.views_by_role("plant")) == 12 + 8
    # a finished adaptive scan resumed again does nothing more
    again = scan_adaptive(recipe, out, manager, raw_recipe=raw, resume=True, log=lambda _: None)
    assert len(again.views) == len(scan.views)
    assert len(ScanFolder.open(out).planned_rounds()) == 3

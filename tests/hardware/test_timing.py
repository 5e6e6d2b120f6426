"""The scan timing model (``plantscan scan --dry-run``)."""

from __future__ import annotations

import hwfakes
import pytest
from plantscan_gphoto import plugin as gphoto_plugin
from plantscan_phidget import plugin as phidget_plugin

from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe
from plantscan_core.timing import estimate_scan_time, move_time_s


@pytest.fixture
def registry():
    m = new_manager()
    for mod, name in ((gphoto_plugin, "gphoto"), (phidget_plugin, "phidget"),
                      (hwfakes, "fakes")):
        m.register(mod, name=name)
    return m.registry


def _recipe(registry, tilts=(0.0,), n=36, cam=None, turntable=None, tilt_arm=None, roles=None):
    raw = {"scan": {
        "cameras": [{"name": f"cam{i}", "plugin": "gphoto2", "params": dict(cam or {})}
                    for i in range(2)],
        "turntable": {"plugin": "phidget", "params": dict(turntable or {})},
        "tilts_deg": list(tilts), "images_per_revolution": n,
        "roles": roles or {"calibration": {"enabled": False}, "background": {"enabled": False},
                           "plant": {}},
    }}
    if len(tilts) > 1 or tilt_arm is not None:
        raw["scan"]["tilt_arm"] = {"plugin": "phidget", "params": dict(tilt_arm or {})}
    return validate_recipe(raw, registry)


def test_small_protocol_matches_a_hand_computed_timeline(registry):
    cam = {"capture_s": 0.5, "download_s": 2.0}
    tt = {"velocity_deg_s": 10.0, "acceleration_deg_s2": 20.0, "settle_s": 0.0}
    est = estimate_scan_time(_recipe(registry, n=4, cam=cam, turntable=tt), registry)
    move90 = 2 * 10 / 20 + (90 - 10 * 10 / 20) / 10  # ramps 1 s + cruise 8.5 s
    assert move_time_s(90, 10, 20) == pytest.approx(move90)
    # stop 0 at 0 deg: capture; stops 1-3: move (hides the 2 s download) + capture;
    # then the last download.
    assert est.total_s == pytest.approx(0.5 + 3 * (move90 + 0.5) + 2.0)
    # sequential: each stop, both cameras capture + download in turn, plus 3 moves
    assert est.sequential_s == pytest.approx(4 * 2 * 2.5 + 3 * move90)
    assert est.images == 8


def test_downloads_longer_than_moves_are_waited_for(registry):
    cam = {"capture_s": 0.2, "download_s": 5.0}
    tt = {"velocity_deg_s": 90.0, "acceleration_deg_s2": 1e9, "settle_s": 0.0}
    est = estimate_scan_time(_recipe(registry, n=4, cam=cam, turntable=tt), registry)
    # each 90 deg move takes ~1 s, the download 5 s: 4 s of waiting per stop after the first
    assert est.roles[0].download_wait_s == pytest.approx(3 * 4.0 + 5.0, abs=1e-6)


SEED_TILT_ARM = {"velocity_deg_s": 0.1, "acceleration_deg_s2": 1.0}
"""The seed's tilt arm runs on a threaded rod; it reports no speed.  0.1 deg/s (a 15 deg tilt
step in 2.5 min) is the value that, with everything else at the plugins' defaults, explains
the 27 extra minutes of its 360-image protocol over the 72-image one."""


def test_seed_protocols_take_the_seed_times(registry):
    """Seed: 72 images (2 cameras x 36 angles) in 3 min, 360 (x 5 tilts) in 30 min.

    The seed's software did one thing after another, so its figures are compared with the
    model's ``sequential_s``, with the plugins' default timings (typical 18 MP DSLR over
    USB 2, geared NEMA 17 turntable).  Tolerance 15 %: defaults are typical values, not
    the seed's measured ones, and the seed's times are rounded.
    """
    est72 = estimate_scan_time(_recipe(registry, tilt_arm=SEED_TILT_ARM), registry)
    est360 = estimate_scan_time(_recipe(registry, tilts=(0.0, 15.0, 30.0, 45.0, 60.0),
                                        tilt_arm=SEED_TILT_ARM), registry)
    assert est72.images == 72 and est360.images == 360
    assert est72.sequential_s == pytest.approx(180.0, rel=0.15)
    assert est360.sequential_s == pytest.approx(1800.0, rel=0.15)
    # The overlap hides each 1 s download behind the ~1.6 s move and triggers both cameras
    # together: per stop 1.6 + 1.0 s instead of 1.6 + 2 x (1.0 + 1.0) s.
    assert est72.total_s < 0.6 * est72.sequential_s
    assert est360.total_s < est360.sequential_s - 0.45 * 180 * 3.0


def test_table_and_unmodelled_devices(registry):
    raw = hwfakes.fake_recipe(n_angles=6)
    est = estimate_scan_time(validate_recipe(raw, registry), registry)
    text = str(est)
    assert "calibration" in text and "plant" in text
    assert "camera cam0 (fake)" in est.unmodelled and "turntable (fake)" in est.unmodelled
    assert est.total_s == 0.0
    est = estimate_scan_time(_recipe(registry), registry)
    assert "saves" in str(est) and "min" in str(est)


def test_approach_adds_the_overshoot_to_backward_moves(registry):
    tt = {"velocity_deg_s": 10.0, "acceleration_deg_s2": 1e12, "settle_s": 0.0}
    cam = {"capture_s": 0.0, "download_s": 0.0}
    roles = {"calibration": {"images_per_revolution": 2}, "background": {"enabled": False},
             "plant": {"images_per_revolution": 2}}
    plain = estimate_scan_time(_recipe(registry, cam=cam, turntable=tt, roles=roles), registry)
    tt["approach_deg"] = 5.0
    anti = estimate_scan_time(_recipe(registry, cam=cam, turntable=tt, roles=roles), registry)
    # calibration 0 -> 180, then plant starts with 180 -> 0 (backwards): +2 x 5 deg at 10 deg/s
    assert anti.total_s - plain.total_s == pytest.approx(1.0, abs=1e-6)



def test_the_virtual_rig_is_modelled_by_its_render_time():
    # `scan --dry-run` on the virtual scanner estimated 0.0 s for a scan of minutes: the
    # sim camera gives its render time, which grows with the image's pixels.
    pytest.importorskip("plantscan_sim")
    from plantscan_core.plugins import get_manager
    from plantscan_core.recipe import load_recipe

    registry = get_manager().registry
    est = {size: estimate_scan_time(load_recipe(
        "plastic-dicot", [f"scan.image_size=[{size[0]},{size[1]}]"], registry), registry)
        for size in ((640, 427), (1296, 864))}
    small, large = est[(640, 427)], est[(1296, 864)]
    assert not any(u.startswith("camera") for u in small.unmodelled), small.unmodelled
    plant = next(r for r in small.roles if r.role == "plant")
    assert plant.images == 72 and plant.capture_s > 0
    # Each stop costs its render time by the camera's own model (the cameras of a stop
    # render in parallel), and the motion does not depend on the image size: so the
    # estimate must grow by exactly stops x the model's per-image difference (the bug was
    # a constant 0 s; a per-stop sum of both cameras would double it).
    from plantscan_sim.plugin import SimCamera
    from plantscan_sim.rig import SimCameraParams

    for r_small, r_large in zip(small.roles, large.roles):
        assert (r_small.role, r_small.stops) == (r_large.role, r_large.stops)
        assert r_large.move_s == pytest.approx(r_small.move_s, abs=1e-9)
        per_image = [SimCamera.capture_time_s(SimCameraParams(), size, r_small.role)
                     for size in ((640, 427), (1296, 864))]
        assert r_small.capture_s == pytest.approx(r_small.stops * per_image[0], rel=1e-9)
        assert r_large.capture_s - r_small.capture_s == pytest.approx(
            r_small.stops * (per_image[1] - per_image[0]), rel=1e-9)
    assert large.total_s > 1.5 * small.total_s

"""Fast checks of the sfm calibrator's parts: printed plate, projection kernel, pose tables."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from plantscan_calib.model import project_mats, rotmats, turn_deg

from plantscan_core.errors import DataError


def test_dot_texture_covers_a_quarter_of_the_plate_with_separate_dots():
    from plantscan_sim.texture import DotTexture

    tex = DotTexture(200.0, 0.0, 10.0, seed=3)
    x, y = np.meshgrid(np.linspace(-140, 140, 700), np.linspace(-140, 140, 700))
    p = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    a = tex.albedo(p)
    # Dot radius uniform in [0.18, 0.38] pitch: E[pi r^2] / pitch^2 = 0.257; the grid
    # samples 2.5 points per mm, so the fraction is within a few per cent of it.
    assert 0.22 < float(np.mean(a == tex.dot)) < 0.29
    assert np.array_equal(a, DotTexture(200.0, 0.0, 10.0, seed=3).albedo(p))
    assert not np.array_equal(a, DotTexture(200.0, 0.0, 10.0, seed=4).albedo(p))
    with pytest.raises(ValueError, match="valid: plain, random-dots"):
        from plantscan_sim.texture import plate_textures

        plate_textures("checkers", 200, 60, 30, 10, 0)


def _track(rng, n_obs):
    intr = np.array([1800.0, 640.0, 430.0, -0.07, 0.012, 1.0])
    pose = np.concatenate([[1.9, 0.1, -0.05], [10.0, -1300.0, 400.0]])
    stops = rng.normal(0, 0.3, n_obs)
    scale = 1.0002
    x = np.array([30.0, -20.0, 150.0])
    thetas = np.arange(n_obs) * 10.0
    return intr, pose, stops, scale, x, thetas


def test_track_kernel_is_the_chessboard_solvers_projection():
    from plantscan_sfm.bundle import _observe_track

    rng = np.random.default_rng(0)
    intr, pose, stops, scale, x, thetas = _track(rng, 4)
    # Block layout of one track: point, intrinsics, pose, stops..., scale.
    p = np.concatenate([x, intr, pose, stops, [scale]])
    offsets = np.array([[3, 9, 15 + o, 19, 0] for o in range(4)])
    uv_obs = rng.normal(0, 1, (4, 2)) + 500
    res = np.zeros(8)
    jac = np.zeros((8, len(p)))
    assert _observe_track(p, offsets, thetas, uv_obs, res, jac, True)
    for o in range(4):
        ref = project_mats(intr[None], rotmats(pose[:3]), pose[None, 3:], np.eye(3)[None],
                           np.zeros((1, 3)), turn_deg(thetas[o], np.array([scale]),
                                                      np.array([stops[o]])), x[None])[0, 0]
        # Same closed form, other code: agree to rounding (1e-9 px).
        assert np.allclose(res[2 * o:2 * o + 2], ref - uv_obs[o], atol=1e-9)

    def resid(q):
        out = np.zeros(8)
        _observe_track(q, offsets, thetas, uv_obs, out, np.zeros((1, 1)), False)
        return out

    num = np.zeros_like(jac)
    for k in range(len(p)):
        h = 1e-5 * max(1.0, abs(p[k]))
        e = np.zeros(len(p))
        e[k] = h
        num[:, k] = (resid(p + e) - resid(p - e)) / (2 * h)
    # Central differences both: agree far below the 1e-3 px per unit that would mislead LM.
    assert np.allclose(jac, num, rtol=1e-4, atol=1e-6)


def test_pan_tilt_roll_round_trip_and_camera_looks_where_it_says():
    from plantscan_sfm.priors import pan_tilt_roll, rotation_from_pan_tilt

    r = rotation_from_pan_tilt(90.0, -30.0, 5.0)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.allclose(pan_tilt_roll(r), (90.0, -30.0, 5.0), atol=1e-9)
    # Looking along +Y, 30 deg down: the optical axis (third row) is that direction.
    assert np.allclose(r[2], [0.0, math.cos(math.radians(30)), -0.5], atol=1e-12)
    # Image rows stay horizontal at roll 0: the camera's x axis has no vertical part.
    assert abs(rotation_from_pan_tilt(40.0, -20.0)[0, 2]) < 1e-12


def test_pose_table_import_round_trips(tmp_path):
    from plantscan_sfm.priors import import_poses, read_prior_poses, rotation_from_pan_tilt

    scan = tmp_path / "scan"
    (scan / "images").mkdir(parents=True)
    (scan / "scan.yaml").write_text("plant_id: p\n")
    lines = [json.dumps({"index": i, "role": "plant", "camera": c, "tilt_index": 0,
                         "tilt_deg": 0.0, "angle_index": i, "commanded_angle_deg": 30.0 * i,
                         "measured_angle_deg": None, "file": f"images/{c}_{i}.png"})
             for i, c in enumerate(["cam0", "cam1"])]
    (scan / "views.jsonl").write_text("\n".join(lines) + "\n")
    table = tmp_path / "poses.csv"
    table.write_text("camera,tilt_index,x_mm,y_mm,z_mm,pan_deg,tilt_deg,roll_deg,f_px\n"
                     "cam0,0,0,-1300,400,90,-8,0,1880\n"
                     "cam1,0,0,-870,1186,90,-48,0.5,\n")
    out = import_poses(table, scan)
    poses, focal = read_prior_poses(out)
    assert focal == {"cam0": 1880.0}
    assert np.allclose(poses[("cam0", 0)].centre, [0, -1300, 400], atol=1e-9)
    assert np.allclose(poses[("cam1", 0)].R, rotation_from_pan_tilt(90, -48, 0.5), atol=1e-12)
    # A table that misses a camera of the scan is refused, naming it; nothing written.
    out.unlink()
    table.write_text("camera,tilt_index,x_mm,y_mm,z_mm,pan_deg,tilt_deg\ncam0,0,0,-1,0,90,0\n")
    with pytest.raises(DataError, match="no pose for camera cam1 tilt 0"):
        import_poses(table, scan)
    assert not out.exists()
    bad = tmp_path / "bad.csv"
    bad.write_text("camera,tilt_index,x_mm\ncam0,0,1\n")
    with pytest.raises(DataError, match="row 1: missing y_mm"):
        import_poses(bad, scan)


def test_too_few_reconstructed_points_name_what_to_change():
    """A scan whose photos share too few true matches (the real PhenoArch photos 30 degrees
    apart: 0-6 points) is told what to photograph differently, not only that it failed."""
    from plantscan_sfm.calibrate import SfmError
    from plantscan_sfm.scale import metric_frame

    pts = np.random.default_rng(0).normal(size=(6, 3))
    with pytest.raises(SfmError, match="only 6 points.*smaller turntable steps.*print the plate"):
        metric_frame(pts, 1.0, "camera-distance", None, 5446.0)

"""The solver on synthetic detections: exact projections through CameraModel + known noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from plantscan_calib.evaluate import compare_calibrations
from plantscan_calib.solver import (
    CalibrationError,
    SolveOptions,
    calibrate_turntable,
    label_identical_boards,
)
from plantscan_calib.synthetic import make_rig, synthetic_detections, volume_points

from plantscan_core.data import Calibration, Pose

ANGLES_36 = np.arange(0.0, 360.0, 10.0)


def _sizes(rig):
    return {c: (m.width, m.height) for c, m in rig.truth.models.items()}


def test_noise_free_detections_give_the_exact_rig():
    # Exact corners: every error must vanish up to the solver's tolerances.
    rig = make_rig(tilts_deg=(0.0, 20.0))
    rig.truth.angle_scale = 1.0004  # a turntable gear-ratio error, to be found
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.0)
    # No distortion prior here: with exact data its pull (0.002 mm) would be the only error.
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg,
                              SolveOptions(fit_angle_scale=True, cross_validate=False,
                                           distortion_prior=None))
    err = compare_calibrations(cal, rig.truth, volume_points())
    assert err["camera_centre_error_mm"]["max"] < 1e-4
    assert err["rotation_error_deg"]["max"] < 1e-5
    assert err["volume_reprojection_px_rms"] < 1e-4
    assert abs(cal.angle_scale - 1.0004) < 1e-8
    assert cal.quality["rejected_corners"] == 0


def _paper360(rig, seed, **kw):
    """paper-360 protocol (2 cameras x 5 tilts x 36 stops), 0.2 px corner noise, 1 % of
    corners moved by 3-15 px; returns the detections and the set of corrupted corners."""
    clean = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=seed)
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, corrupt_fraction=0.01, seed=seed)
    corrupted = {(i, j) for i, (a, b) in enumerate(zip(clean, dets, strict=True))
                 for j in np.nonzero(np.linalg.norm(a.uv - b.uv, axis=1) > 1.0)[0]}
    assert 0.005 < len(corrupted) / sum(len(d.uv) for d in dets) < 0.02
    return dets, corrupted


def _rejected(cal, dets):
    # view_index is -1 for synthetic detections: match by (camera, tilt, angle, board, corner)
    key = {(d.camera, d.tilt_index, d.angle_deg, d.board): i for i, d in enumerate(dets)}
    return {(key[(r["camera"], r["tilt_index"], r["angle_deg"], r["board"])], r["corner"])
            for r in cal.quality["rejected"]}


# The recommended target (docs/calibration.md): two 14x11-square boards of 25 mm
# (350x275 mm, A3 prints), back to back on the plate.
RECOMMENDED = dict(boards=2, cols=13, rows=10)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow),
                                  pytest.param(2, marks=pytest.mark.slow),
                                  pytest.param(3, marks=pytest.mark.slow)])
def test_paper360_recommended_target_meets_the_issue_figures(seed):
    """The issue's figures (<= 0.1 mm mean centre error, <= 0.01 deg max rotation error,
    <= 0.05 px plant-volume reprojection) with 1 % corrupted corners, on every seed.

    Measured over seeds 0-3: 0.011-0.025 mm, 0.0016-0.0023 deg, 0.012-0.040 px.
    """
    rig = make_rig(tilts_deg=(0.0, 10.0, 20.0, 30.0, 40.0), **RECOMMENDED)
    dets, corrupted = _paper360(rig, seed)
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg,
                              SolveOptions(cross_validate=False))
    q = cal.quality
    rejected = _rejected(cal, dets)
    assert corrupted <= rejected, "every corrupted corner is rejected"
    # Gaussian 4-sigma tail: exp(-8) of ~25000 corners, ~8 false rejections expected.
    assert len(rejected - corrupted) <= 25
    assert q["tilt_axis"]["joint"] and not q["flags"]
    err = compare_calibrations(cal, rig.truth, volume_points())
    assert err["camera_centre_error_mm"]["mean"] <= 0.1
    assert err["rotation_error_deg"]["max"] <= 0.01
    assert err["volume_reprojection_px_rms"] <= 0.05
    # Each pose within 4 sigma of Ceres' covariance (sigma is the 3-D spread).
    sig = q["sigma"]["poses"]
    for k, e in err["per_pose"].items():
        assert e["centre_error_mm"] < 4 * sig[k]["centre_mm"], k
        assert e["rotation_error_deg"] < 4 * sig[k]["rotation_deg"], k


def test_paper360_single_small_board_is_limited_by_its_data():
    """One 9x6-corner board (200x125 mm, the first session's target): the errors are what
    its data allow (Ceres' covariance), above the issue's figures."""
    rig = make_rig(tilts_deg=(0.0, 10.0, 20.0, 30.0, 40.0))
    dets, corrupted = _paper360(rig, 3)
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg, SolveOptions())
    q = cal.quality
    rejected = _rejected(cal, dets)
    assert corrupted <= rejected, "every corrupted corner is rejected"
    assert len(rejected - corrupted) <= 10
    err = compare_calibrations(cal, rig.truth, volume_points())
    sig = q["sigma"]["poses"]
    for k, e in err["per_pose"].items():
        assert e["centre_error_mm"] < 4 * sig[k]["centre_mm"], k
        assert e["rotation_error_deg"] < 4 * sig[k]["rotation_deg"], k
    # Measured 0.054-0.069 mm, 0.0065-0.014 deg, 0.06-0.15 px over seeds 0-3 (1 sigma per
    # pose ~0.07 mm, 0.012 deg): the data, not the solver, are the limit here.
    assert err["camera_centre_error_mm"]["mean"] < 0.2
    assert err["rotation_error_deg"]["max"] < 0.03
    assert err["volume_reprojection_px_rms"] < 0.3
    # Residuals consistent with the simulated noise (0.2 px per axis -> 0.28 px norm RMS).
    assert 0.17 < q["corner_noise_px"] < 0.23
    assert abs(q["cross_validation"]["difference_px"]) < 0.05


def test_non_rigid_arm_falls_back_to_free_poses():
    # cam0's mount flexes at tilt 1: its centre is 1 mm off the rigid-arm motion.
    rig = make_rig(tilts_deg=(0.0, 20.0, 40.0))
    p = rig.truth.poses[("cam0", 1)]
    rig.truth.poses[("cam0", 1)] = Pose(p.R, p.t - p.R @ np.array([1.0, 0.0, 0.0]))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=6)
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg,
                              SolveOptions(cross_validate=False, covariance=False))
    q = cal.quality
    assert any("not one rigid rotation" in f for f in q["flags"])
    assert not q["tilt_axis"]["joint"]
    assert q["tilt_axis"]["worst_rms_ratio"] > 1.05
    err = compare_calibrations(cal, rig.truth, volume_points())
    # The free poses still find the flexed camera (measured ~0.1 mm).
    assert err["per_pose"]["cam0/t1"]["centre_error_mm"] < 0.3


def test_refinement_beats_the_seed_initialisation():
    rig = make_rig(tilts_deg=(0.0, 20.0))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=1)
    opt = SolveOptions(cross_validate=False, covariance=False)
    seed = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg,
                               opt.model_copy(update={"refine": False}))
    refined = calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg, opt)
    pts = volume_points()
    e0 = compare_calibrations(seed, rig.truth, pts)
    e1 = compare_calibrations(refined, rig.truth, pts)
    assert e1["volume_reprojection_px_rms"] < e0["volume_reprojection_px_rms"] / 2
    # The poses are already close after the initialisation with this much data (~0.12 mm,
    # 0.01-0.015 deg for both); the intrinsics are not, and the volume error shows it.


def test_tilt_axis_gives_cameras_at_uncalibrated_tilts():
    # Truth at 0..40 deg every 10; calibrated only at 0, 20 and 40.
    rig = make_rig(tilts_deg=(0.0, 10.0, 20.0, 30.0, 40.0))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=2, tilt_indices={0, 2, 4})
    tilts = {i: rig.truth.tilts_deg[i] for i in (0, 2, 4)}
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), tilts,
                              SolveOptions(cross_validate=False, covariance=False))
    assert cal.tilt_axis is not None
    assert {t for _, t in cal.poses} == {0, 2, 4}
    err = compare_calibrations(cal, rig.truth, volume_points())
    un = err["uncalibrated_tilts"]
    assert {10.0, 30.0} <= set(un["tilts"])
    # Interpolated poses are about as good as calibrated ones (same noise; measured
    # 0.1-0.2 mm, 0.01-0.02 deg).
    assert un["camera_centre_error_mm"]["max"] < 0.5
    assert un["rotation_error_deg"]["max"] < 0.05
    assert un["volume_reprojection_px_rms"] < 2 * err["volume_reprojection_px_rms"] + 0.1
    # The round trip through YAML keeps the axis.
    again = Calibration.from_dict(cal.to_dict())
    cam = again.camera_at_tilt("cam0", 10.0, 30.0)
    assert np.linalg.norm(cam.pose.centre - cal.camera_at_tilt("cam0", 10.0, 30.0).pose.centre) \
        < 1e-9


def test_two_boards_fixed_principal_point_and_no_distortion():
    # The configuration of the real PhenoArch corners: two boards, lens modelled distortion-free.
    rig = make_rig(tilts_deg=(0.0,), boards=2, distortion=False)
    dets = synthetic_detections(rig, np.arange(0.0, 360.0, 3.0), noise_px=0.2, seed=4)
    assert {d.board for d in dets} == {0, 1}
    pp = {c: (m.cu, m.cv) for c, m in rig.truth.models.items()}
    cal = calibrate_turntable(dets, rig.boards, _sizes(rig), {0: 0.0}, SolveOptions(
        fix_principal_point=True, principal_points=pp, fix_distortion=True,
        cross_validate=False))
    for c, m in cal.models.items():
        assert (m.cu, m.cv, m.d1, m.d2) == (pp[c][0], pp[c][1], 0.0, 0.0)
    err = compare_calibrations(cal, rig.truth, volume_points())
    # Measured 0.1-0.3 mm and 0.31 px (one tilt, board covering a small part of the view).
    assert err["camera_centre_error_mm"]["max"] < 0.4
    assert err["volume_reprojection_px_rms"] < 0.5


def test_identical_boards_are_told_apart_by_their_arcs():
    # Two identical boards back to back: every detection arrives as board 0.
    rig = make_rig(tilts_deg=(0.0, 20.0, 40.0), boards=2)
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=7)
    labelled = label_identical_boards([replace(d, board=0) for d in dets], 2)
    mapping = {(d.board, e.board) for d, e in zip(dets, labelled, strict=True)}
    assert len(mapping) == 2 and len({b for _, b in mapping}) == 2  # one consistent naming
    cal = calibrate_turntable(labelled, rig.boards, _sizes(rig), rig.truth.tilts_deg,
                              SolveOptions(cross_validate=False, covariance=False))
    assert cal.quality["rejected_corners"] < 10
    err = compare_calibrations(cal, rig.truth, volume_points())
    assert err["camera_centre_error_mm"]["mean"] < 0.2
    # A board seen by cam0 at 90 deg, between the two boards' arcs (50 and 130 deg): a third
    # arc for two boards is refused, naming camera and tilt.
    extra = replace(dets[0], board=0, angle_deg=90.0)
    assert (extra.camera, extra.tilt_index) == ("cam0", 0)
    with pytest.raises(CalibrationError, match=r"camera cam0 tilt 0: .* more than 2 arcs"):
        label_identical_boards([replace(d, board=0) for d in dets] + [extra], 2)


def test_symmetric_board_flips_are_undone():
    # An 8x6 board looks the same turned by 180 deg; a detector may number it from either end.
    rig = make_rig(tilts_deg=(0.0,), cols=8, rows=6)
    dets = synthetic_detections(rig, np.arange(0.0, 360.0, 5.0), noise_px=0.2, seed=5)
    flipped = [replace(d, uv=d.uv[::-1].copy()) if i % 3 == 1 else d for i, d in enumerate(dets)]
    cal = calibrate_turntable(flipped, rig.boards, _sizes(rig), {0: 0.0},
                              SolveOptions(cross_validate=False, covariance=False),
                              symmetric_boards=True)
    assert cal.quality["rejected_corners"] < 5
    assert cal.quality["rms_px"] < 0.35


def test_too_few_detections_names_camera_and_tilt():
    rig = make_rig(tilts_deg=(0.0, 20.0))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2)
    few = [d for d in dets if (d.camera, d.tilt_index) != ("cam1", 1)]
    few += [d for d in dets if (d.camera, d.tilt_index) == ("cam1", 1)][:2]
    with pytest.raises(CalibrationError, match=r"camera cam1 tilt 1: 2"):
        calibrate_turntable(few, rig.boards, _sizes(rig), rig.truth.tilts_deg, SolveOptions())


def test_board_spec_mismatch_is_refused():
    # Corners of a 9x6 board solved with the object points of a 6x9 one: no rig fits.
    rig = make_rig(tilts_deg=(0.0,))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2)
    j, i = np.mgrid[0:9, 0:6]
    wrong = {0: np.stack([i.ravel() * 25.0, j.ravel() * 25.0, np.zeros(54)], axis=1)}
    with pytest.raises(CalibrationError, match=r"board spec .* does not match"):
        calibrate_turntable(dets, wrong, _sizes(rig), {0: 0.0},
                            SolveOptions(cross_validate=False, covariance=False))


def test_the_same_detections_give_the_same_calibration_to_the_bit():
    # OpenCV's calibrateCamera summed on several threads in a varying order and moved the
    # initialisation (then the result) by ~1e-9 relative from run to run: a rerun of a
    # scan must reproduce its calibration, and the traits measured through it, exactly.
    rig = make_rig(tilts_deg=(0.0, 20.0))
    dets = synthetic_detections(rig, ANGLES_36, noise_px=0.2, seed=3)
    opt = SolveOptions(cross_validate=False, covariance=False)
    runs = [calibrate_turntable(dets, rig.boards, _sizes(rig), rig.truth.tilts_deg, opt)
            for _ in range(3)]
    for cal in runs[1:]:
        assert cal.models == runs[0].models
        assert all(np.array_equal(cal.poses[k].R, runs[0].poses[k].R)
                   and np.array_equal(cal.poses[k].t, runs[0].poses[k].t) for k in cal.poses)


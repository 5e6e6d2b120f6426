"""The `turntable` and `fixed` calibrators on scan folders, the evaluate hook, bad input."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
from plantscan_calib import plugin as calib_plugin
from plantscan_calib.evaluate import compare_calibrations, evaluate_run
from plantscan_calib.plugin import CalibrationError, FixedCalibrator, TurntableCalibrator
from plantscan_calib.synthetic import make_rig, volume_points, write_board_scan
from pydantic import ValidationError

from plantscan_core.errors import DataError
from plantscan_core.plugins import new_manager
from plantscan_core.scanfolder import ScanFolder

ANGLES = np.arange(0.0, 360.0, 15.0)


@pytest.fixture(scope="module")
def board_scan(tmp_path_factory):
    """48 rendered calibration views (2 cameras, 1 tilt, 24 stops), 960x640, no lens distortion."""
    rig = make_rig(image_size=(960, 640), tilts_deg=(0.0,), distortion=False)
    root = tmp_path_factory.mktemp("scan") / "board-scan"
    write_board_scan(root, rig, ANGLES, noise=2.0)
    return rig, root


def _params(**kw):
    return TurntableCalibrator.Params(**{"cols": 9, "rows": 6, "square_mm": 25.0, **kw})


def test_registered_through_the_hook():
    manager = new_manager()
    manager.register(calib_plugin, name="calib")
    assert manager.registry.names("calibrator") == ["fixed", "turntable"]
    with pytest.raises(ValidationError):
        manager.build("calibrator", "turntable", {"colz": 9})


def test_turntable_calibrates_a_rendered_scan(board_scan, tmp_path):
    rig, root = board_scan
    scan = ScanFolder.open(root)
    calibrator = TurntableCalibrator(_params())
    cal = calibrator.calibrate(scan)
    q = cal.quality
    assert set(q["board_found"]) == {"cam0/t0", "cam1/t0"}
    # The stage's report: the counts and figures a user checks first, the flags coded.
    report = calibrator.report
    assert report.counts["detections"] == sum(v["found"] for v in q["board_found"].values())
    assert report.counts["corners"] == q["corners"]
    assert report.figures["rms_px"] == q["rms_px"]
    assert [w.message for w in report.warnings] == q["flags"]
    assert all(v["found"] >= 5 for v in q["board_found"].values())
    err = compare_calibrations(cal, rig.truth, volume_points())
    # 960x640 images (1 px ~ 0.75 mm at the board), ~20 views of 54 corners per camera:
    # measured ~0.2-0.5 mm, ~0.03 deg, ~0.1-0.2 px.
    assert err["camera_centre_error_mm"]["mean"] < 1.0
    assert err["rotation_error_deg"]["max"] < 0.1
    assert err["volume_reprojection_px_rms"] < 0.5
    assert q["rms_px"] < 0.3
    # The evaluate hook reads the run's and the truth's calibration.yaml.
    run, truth = tmp_path / "run", tmp_path / "truth"
    run.mkdir()
    truth.mkdir()
    cal.save(run / "calibration.yaml")
    rig.truth.save(truth / "calibration.yaml")
    section = calib_plugin.plantscan_evaluate(run_dir=run, truth_dir=truth)["calibration"]
    for key in ("camera_centre_error_mm", "rotation_error_deg"):
        assert set(section[key]) == {"mean", "max"}  # documented keys of `plantscan evaluate`
    assert section["volume_reprojection_px_rms"] == pytest.approx(
        err["volume_reprojection_px_rms"], rel=0.5)
    assert evaluate_run(tmp_path / "nowhere", truth) is None


def test_board_spec_that_matches_no_photo(board_scan, tmp_path):
    _, root = board_scan
    # A wrong pattern makes findChessboardCorners slow: 4 views are enough to show the error.
    copy = tmp_path / "wrong-spec"
    shutil.copytree(root, copy)
    lines = (copy / "views.jsonl").read_text().splitlines(keepends=True)
    (copy / "views.jsonl").write_text("".join(lines[:4]))
    with pytest.raises(CalibrationError, match=r"no 11x8-corner chessboard found in any of the 4"):
        TurntableCalibrator(_params(cols=11, rows=8)).calibrate(ScanFolder.open(copy))


def test_too_few_views_names_camera_and_tilt(board_scan):
    _, root = board_scan
    with pytest.raises(CalibrationError, match=r"camera cam0 tilt 0: found in \d+ of 24 views"):
        TurntableCalibrator(_params(min_views=24)).calibrate(ScanFolder.open(root))


def test_mixed_image_sizes_are_refused(board_scan, tmp_path):
    _, root = board_scan
    copy = tmp_path / "mixed"
    shutil.copytree(root, copy)
    scan = ScanFolder.open(copy)
    view = [v for v in scan.views if v.camera == "cam1"][5]
    img = cv2.imread(str(copy / view.file))
    cv2.imwrite(str(copy / view.file), cv2.resize(img, (480, 320)))
    with pytest.raises(DataError, match=rf"camera cam1: .*{view.file} is 480x320"):
        TurntableCalibrator(_params()).calibrate(scan)


def test_two_charuco_boards(tmp_path):
    """Two ChArUco boards (different marker ids) on the plate, told apart in every image."""
    rig = make_rig(image_size=(960, 640), tilts_deg=(0.0,), distortion=False, boards=2,
                   kind="charuco", marker_mm=18.0)
    write_board_scan(tmp_path / "charuco", rig, np.arange(0.0, 360.0, 20.0), px_per_mm=6.0)
    cal = TurntableCalibrator(_params(board="charuco", marker_mm=18.0, boards=2)).calibrate(
        ScanFolder.open(tmp_path / "charuco"))
    assert set(cal.quality["boards"]) == {"0", "1"}
    err = compare_calibrations(cal, rig.truth, volume_points())
    # Same image size and board as the chessboard scan above; partial views add corners.
    assert err["camera_centre_error_mm"]["mean"] < 1.0
    assert err["volume_reprojection_px_rms"] < 0.5


@pytest.mark.slow
def test_two_identical_chessboards_back_to_back(tmp_path):
    """Two identical chessboards back to back: told apart by the angles each faces a camera."""
    rig = make_rig(image_size=(960, 640), tilts_deg=(0.0, 20.0), distortion=False, boards=2)
    write_board_scan(tmp_path / "two", rig, np.arange(0.0, 360.0, 20.0), px_per_mm=6.0)
    scan = ScanFolder.open(tmp_path / "two")
    cal = TurntableCalibrator(_params(boards=2)).calibrate(scan)
    assert set(cal.quality["boards"]) == {"0", "1"}
    assert cal.quality["rejected_fraction"] < 0.01  # a mislabelled view would be all outliers
    err = compare_calibrations(cal, rig.truth, volume_points())
    # As the ChArUco pair above (same image size and boards), two tilts.
    assert err["camera_centre_error_mm"]["mean"] < 1.0
    assert err["volume_reprojection_px_rms"] < 0.5


def test_fixed_calibrator(board_scan, tmp_path):
    rig, root = board_scan
    copy = tmp_path / "imported"
    shutil.copytree(root, copy)
    scan = ScanFolder.open(copy)
    with pytest.raises(DataError, match=r"calibration.yaml: calibration file not found"):
        FixedCalibrator(FixedCalibrator.Params()).calibrate(scan)
    rig.truth.save(copy / "calibration.yaml")
    cal = FixedCalibrator(FixedCalibrator.Params()).calibrate(scan)
    assert cal.models == rig.truth.models
    one_cam = type(rig.truth)({"cam0": rig.truth.models["cam0"]},
                              {("cam0", 0): rig.truth.poses[("cam0", 0)]})
    one_cam.save(tmp_path / "other.yaml")
    with pytest.raises(DataError, match=r"other.yaml: has no camera cam1"):
        FixedCalibrator(FixedCalibrator.Params(path=str(tmp_path / "other.yaml"))).calibrate(scan)

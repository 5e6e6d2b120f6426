"""The ``sfm`` calibrator on small virtual scans, against the virtual scanner's truth."""

from __future__ import annotations

import pytest

from plantscan_core.data import Calibration


def _scan(root, **kw):
    from plantscan_sim import make_scan

    return make_scan(root, preset="plastic-dicot", roles=["plant"], supersampling=1, **kw)


def test_plain_plate_gives_the_named_error(tmp_path):
    """A plain plate and a smooth plant: the error says the scene is too plain, and how to
    fix it, instead of a wrong calibration."""
    from plantscan_sfm.plugin import SfmCalibrator, SfmError

    scan = _scan(tmp_path / "plain", image_size=(360, 240), images_per_revolution=6)
    cal = SfmCalibrator(SfmCalibrator.Params(plate_diameter_mm=400))
    with pytest.raises(SfmError, match=r"too few features to calibrate from.*too plain.*"
                       r"random-dot pattern"):
        cal.calibrate(scan)


@pytest.mark.slow
def test_small_printed_scan_calibrates_against_truth(tmp_path):
    from plantscan_calib.evaluate import compare_calibrations, plant_volume_points
    from plantscan_sfm.plugin import SfmCalibrator

    # Cameras 12 deg apart in elevation (8 and 20): their photos share plate features, which
    # links them (40 deg apart, as in paper-72, they share none: see docs/sfm.md).
    scan = _scan(tmp_path / "printed", image_size=(640, 427), images_per_revolution=18,
                 scene={"plate_texture": "random-dots"},
                 overrides=["scan.cameras.1.params.elevation_deg=20"])
    cal = SfmCalibrator(SfmCalibrator.Params(plate_diameter_mm=400)).calibrate(scan)
    truth = Calibration.load(scan.ground_truth_dir / "calibration.yaml")
    res = compare_calibrations(cal, truth, plant_volume_points(scan.ground_truth_dir))
    q = cal.quality
    assert q["registered_views"] == q["views"] == 36
    assert set(cal.view_angles_deg) == {v.index for v in scan.views_by_role("plant")}
    print(res["camera_centre_error_mm"], res["rotation_error_deg"],
          res["volume_reprojection_px_rms"], {c: cal.models[c].f / truth.models[c].f - 1
                                               for c in cal.models})

"""Acquisition through the real orchestrator: determinism, resume, errors before rendering."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml
from plantscan_sim import RigError, make_scan, read_truth_cameras, scan_recipe

from plantscan_core.acquire import plan
from plantscan_core.errors import RecipeError, ScanFolderError
from plantscan_core.recipe import validate_recipe

SMALL = dict(preset="plastic-dicot", image_size=(360, 240), images_per_revolution=6,
             calibration_images_per_revolution=2)  # as conftest.small_scan


def test_interrupted_scan_resumes_to_exactly_the_protocol(small_scan, tmp_path):
    out = tmp_path / "scan"
    first = make_scan(out, **SMALL, stop_after=7)
    assert len(first.views) == 7
    before = {v.file: (out / v.file).stat() for v in first.views}
    scan = make_scan(out, **SMALL, resume=True)
    raw = scan_recipe(**SMALL)
    keys = [v.key for v in scan.views]
    assert len(keys) == len(set(keys))
    expected = plan(validate_recipe({k: raw[k] for k in ("name", "plant", "scan")}))
    assert sorted(keys) == sorted(v.key for v in expected)
    for f, st in before.items():  # none rewritten
        now = (out / f).stat()
        assert (now.st_ino, now.st_mtime_ns) == (st.st_ino, st.st_mtime_ns)
    # Same seed, same recipe: the resumed scan's images are the uninterrupted scan's, byte
    # for byte (noise is seeded per view, not per run).
    ref = {v.file: v for v in small_scan.views}
    for v in scan.views:
        assert (out / v.file).read_bytes() == (small_scan.root / v.file).read_bytes(), v.file
        assert ref[v.file].index == v.index
    # Truth of the resumed scan: one camera line and one mask per view, as uninterrupted.
    assert (out / "ground_truth/cameras.jsonl").read_text() == (
        small_scan.root / "ground_truth/cameras.jsonl").read_text()
    assert sorted(p.name for p in (out / "ground_truth/masks").iterdir()) == sorted(
        p.name for p in (small_scan.root / "ground_truth/masks").iterdir())


def test_another_seed_gives_other_images(small_scan, tmp_path):
    scan = make_scan(tmp_path / "s", **{**SMALL, "seed": 1}, roles=["background"])
    view = scan.views[0]
    other = small_scan.read_image(next(v for v in small_scan.views if v.file == view.file))
    img = scan.read_image(view)
    assert img.shape == other.shape and not np.array_equal(img, other)


@pytest.mark.slow
def test_board_corners_detected_where_the_truth_projects_them(tmp_path):
    # Noise-free renders: OpenCV's sub-pixel chessboard corners agree with the truth
    # projection of the board corners, proof that the renderer and CameraModel agree
    # (distortion included).  A model mismatch would show as a systematic offset, so the
    # mean error vector must be < 0.02 px; the RMS distance must be < 0.1 px (the scatter
    # is cornerSubPix's own, about 0.05 px on 15-25 px squares; single corners on the most
    # oblique views reach ~0.25 px, so no per-corner bound).
    scan = make_scan(tmp_path / "cal", image_size=(800, 534), images_per_revolution=8,
                     noise_sigma=0.0, roles=["calibration"])
    gt = scan.ground_truth_dir
    scene = yaml.safe_load((gt / "scene.yaml").read_text())
    corners = np.array(scene["board"]["corners_world_mm"])
    pattern = tuple(scene["board"]["inner_corners"])
    cams = read_truth_cameras(gt)
    found, errors = 0, []
    for view in scan.views:
        gray = cv2.cvtColor(scan.read_image(view), cv2.COLOR_BGR2GRAY)
        ok, det = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
        if not ok:
            continue
        det = cv2.cornerSubPix(gray, det, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4))
        det = det.reshape(-1, 2)
        truth = cams[view.index].project(corners)
        nearest = np.linalg.norm(det[:, None] - truth[None], axis=2).argmin(axis=1)
        assert len(set(nearest)) == len(corners)  # one detection per true corner
        errors.append(det - truth[nearest])
        found += 1
    assert found >= 4, f"board found in only {found} of {len(scan.views)} views"
    err = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert np.abs(err.mean(axis=0)).max() < 0.02, f"systematic offset {err.mean(axis=0)} px"
    assert rms < 0.1, f"RMS corner error {rms:.3f} px"


def test_unknown_preset_is_refused_before_anything(tmp_path):
    with pytest.raises(RecipeError, match="preset.*cactus"):
        make_scan(tmp_path / "x", **{**SMALL, "preset": "cactus"})
    assert not (tmp_path / "x").exists()
    # The same through a recipe: the scene's Params name the valid presets.
    with pytest.raises(RecipeError, match="scan.scene.params.preset"):
        make_scan(tmp_path / "y", **SMALL, overrides=["scan.scene.params.preset=cactus"])
    assert not (tmp_path / "y").exists()


def test_camera_inside_the_plant_is_refused_before_rendering(tmp_path):
    with pytest.raises(RigError, match="inside the plant"):
        make_scan(tmp_path / "x", **SMALL, overrides=["scan.cameras.0.params.distance_mm=80"])
    assert not list((tmp_path / "x" / "images").rglob("*.png"))


def test_board_never_visible_is_refused_before_rendering(tmp_path):
    with pytest.raises(RigError, match="never fully visible"):
        make_scan(tmp_path / "x", **SMALL, scene={"board_height_mm": 1500.0})
    assert not list((tmp_path / "x" / "images").rglob("*.png"))


def test_unwritable_output_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(ScanFolderError, match="cannot write"):
        make_scan(blocker / "scan", **SMALL)


def test_backlash_is_recorded_in_the_truth(tmp_path):
    # A turntable with 2 deg of backlash and 0.3 deg random error: the images are taken at
    # the true angles (cameras.jsonl), the views keep the commanded ones (open loop).
    small = {**SMALL, "images_per_revolution": 4}
    scan = make_scan(tmp_path / "b", **small, roles=["plant"], overrides=[
        "scan.turntable.params.backlash_deg=2.0", "scan.turntable.params.error_sigma_deg=0.3"])
    lines = [json.loads(x) for x in
             (scan.ground_truth_dir / "cameras.jsonl").read_text().splitlines()]
    errs = [d["true_angle_deg"] - d["commanded_angle_deg"] for d in lines]
    assert all(v.measured_angle_deg is None for v in scan.views)
    assert np.std(errs) > 0.05 and abs(np.mean(errs) + 1.0) < 0.5  # lag of half the band


def test_tilt_arm_jpeg_and_encoder_axes(tmp_path):
    # Two tilts through a sim tilt arm, JPEG images, a turntable that reports its position:
    # the views carry the measured (true) angle, the truth calibration's tilt-axis model
    # gives every image's exact camera, and the images are JPEG files.
    scan = make_scan(tmp_path / "t", image_size=(320, 214), images_per_revolution=3,
                     tilts_deg=[0.0, 20.0], image_format="jpg", roles=["plant"], overrides=[
                         "scan.turntable.params.report_position=true",
                         "scan.turntable.params.error_sigma_deg=0.5"])
    from plantscan_core.data import Calibration, Camera

    gt = scan.ground_truth_dir
    cal = Calibration.load(gt / "calibration.yaml")
    lines = {json.loads(x)["index"]: json.loads(x)
             for x in (gt / "cameras.jsonl").read_text().splitlines()}
    pts = np.random.default_rng(1).uniform([-200, -200, 0], [200, 200, 400], (40, 3))
    assert {v.tilt_index for v in scan.views} == {0, 1}
    for v in scan.views:
        assert (scan.root / v.file).read_bytes()[:2] == b"\xff\xd8"  # JPEG magic
        truth = lines[v.index]
        assert v.measured_angle_deg == pytest.approx(truth["true_angle_deg"])
        exact = Camera.from_dict(truth["camera"])
        assert np.abs(cal.camera_for_view(v).project(pts) - exact.project(pts)).max() < 1e-6
        # and through the tilt-axis model from the reference tilt
        via_axis = cal.camera_at_tilt(v.camera, v.tilt_deg, v.measured_angle_deg)
        assert np.abs(via_axis.project(pts) - exact.project(pts)).max() < 1e-6

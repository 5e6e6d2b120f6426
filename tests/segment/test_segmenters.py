"""Segmenters against the virtual scanner's exact masks, plus analytic and bad-input checks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from plantscan_segment.baselines import (
    GivenMasksSegmenter,
    GreenSegmenter,
    MOG2Segmenter,
    ThresholdSegmenter,
)
from plantscan_segment.lab import LabShadowSegmenter, lab_shadow_score, median_background
from plantscan_segment.metrics import mask_metrics, summarise, thin_structure_mask

from plantscan_core.data import ViewRecord
from plantscan_core.errors import DataError
from plantscan_core.runfolder import read_mask


def _views(scan):
    plates = {(v.camera, v.tilt_index): scan.read_image(v)
              for v in scan.views_by_role("background")}
    for v in scan.views_by_role("plant"):
        truth = read_mask(scan.ground_truth_dir / "masks" / f"{v.index:05d}.png")
        yield v, scan.read_image(v), plates[(v.camera, v.tilt_index)], truth


def _evaluate(segmenter, scan):
    return summarise([mask_metrics(segmenter.segment(img, bg, v), truth, img, bg)
                      for v, img, bg, truth in _views(scan)])


def _assert_targets(s, iou_min):
    # Targets of the issue: IoU >= 0.98 and thin-structure recall >= 0.97.
    assert s["iou"]["mean"] >= 0.98, s
    assert s["iou"]["min"] >= iou_min, s
    assert s["thin_recall"] >= 0.97, s
    assert s["thin_pixels"] > 200, "too few thin pixels for the recall to mean anything"
    # The scans have real hard shadows, and lab-shadow keeps nearly all of them out.
    assert s["shadow_pixels"] > 5000
    assert s["shadow_false_positive_rate"] < 0.01, s


def test_lab_shadow_meets_the_issue_targets_on_the_dicot(sim_scans):
    # Broad leaves: even at 480 x 320 px every view reaches the target.
    _assert_targets(_evaluate(LabShadowSegmenter(), sim_scans["plastic-dicot"]), 0.98)


@pytest.mark.slow
def test_lab_shadow_meets_the_issue_targets_on_wheat(wheat_recipe_size):
    # Wheat blades are 4-8 px wide at 1200 x 800: one mixed pixel on each rim is 25-50 %
    # of the width, so single views measure 0.979-0.985 (benchmark); 0.975 leaves room
    # for the view-to-view spread, the mean must meet 0.98.
    _assert_targets(_evaluate(LabShadowSegmenter(), wheat_recipe_size), 0.975)


def test_lab_shadow_on_small_wheat_images_keeps_thin_blades(sim_scans):
    # At 480 x 320 blades are 2-3 px wide and IoU is bound by rim pixels (measured
    # 0.963-0.970, docs/segmentation.md); thin structures are still found.
    s = _evaluate(LabShadowSegmenter(), sim_scans["wheat"])
    assert s["iou"]["min"] >= 0.955, s
    assert s["thin_recall"] >= 0.97, s
    assert s["shadow_false_positive_rate"] < 0.01, s


def test_clean_up_steps_do_not_cost_thin_recall(sim_scans):
    # The edge test, the chromaticity shadow test and the 3 px blob removal together
    # must raise IoU without losing more than 1 % of thin-structure recall.
    scan = sim_scans["wheat"]
    full = _evaluate(LabShadowSegmenter(), scan)
    bare = _evaluate(LabShadowSegmenter(LabShadowSegmenter.Params(
        edge_fraction=0, shadow_chroma_max=None, min_blob_px=0)), scan)
    assert full["iou"]["mean"] > bare["iou"]["mean"] + 0.01, (full, bare)
    assert full["thin_recall"] >= bare["thin_recall"] - 0.01, (full, bare)


def test_plain_threshold_keeps_the_shadows(sim_scans):
    lab = _evaluate(LabShadowSegmenter(), sim_scans["plastic-dicot"])
    thr = _evaluate(ThresholdSegmenter(), sim_scans["plastic-dicot"])
    assert thr["shadow_false_positive_rate"] > 0.5  # why the seed needed a shadow-robust score
    assert lab["iou"]["mean"] > thr["iou"]["mean"] + 0.1


def test_seed_score_by_hand():
    # Two pixels side by side; plate grey, image: left pixel green, right unchanged.
    bg = np.full((1, 2, 3), 128, np.uint8)
    img = bg.copy()
    img[0, 0] = (40, 160, 40)
    lab = cv2.cvtColor(img, cv2.COLOR_BGR2LAB).astype(float)
    lb = cv2.cvtColor(bg, cv2.COLOR_BGR2LAB).astype(float)
    delta = abs(lab[0, 0, 0] - lb[0, 0, 0])
    theta = abs(lab[0, 0, 1] - lb[0, 0, 1]) + abs(lab[0, 0, 2] - lb[0, 0, 2])
    # Texture: only the horizontal ratio changes (one row: the vertical ratio is 1 for both).
    psi = abs((lab[0, 0, 0] + 1) / (lab[0, 1, 0] + 1) - 1.0)
    omega = lab_shadow_score(img, bg, 0.1, 0.5, 0.4)
    assert omega[0, 0] == pytest.approx((0.1 * delta + 0.5 * theta + 0.4 * psi), rel=1e-5)


def test_shadow_dark_pot_and_thin_leaf_analytic():
    plate = np.full((60, 80, 3), (200, 190, 185), np.uint8)
    img = plate.copy()
    img[:, 40:] = (plate[:, 40:] * 0.6).astype(np.uint8)       # hard shadow on the right
    img[10:50, 10:20] = (25, 25, 28)                             # dark pot
    img[5:55, 60] = (40, 140, 50)                                # 1 px wide green leaf in shadow
    mask = LabShadowSegmenter().segment(img, plate)
    assert mask[10:50, 10:20].all(), "the dark pot is foreground"
    assert mask[5:55, 60].all(), "the thin leaf survives inside the shadow"
    shadow = np.zeros_like(mask)
    shadow[:, 41:] = True
    shadow[:, 59:62] = False
    assert not mask[shadow].any(), "the shadow is background"
    seed_only = LabShadowSegmenter(LabShadowSegmenter.Params(suppress_shadows=False, threshold=5,
                                                             edge_fraction=0, min_blob_px=0))
    assert seed_only.segment(img, plate)[shadow].mean() > 0.9  # this shadow is too deep for t=5


def test_thin_structure_mask_is_the_narrow_part():
    truth = np.zeros((40, 40), bool)
    truth[5:35, 5:20] = True    # broad blade
    truth[5:35, 30:32] = True   # 2 px wide tip
    thin = thin_structure_mask(truth)
    assert thin[5:35, 30:32].all()
    assert not thin[10:30, 8:17].any()


def test_median_background_recovers_the_plate_behind_a_moving_object():
    plate = np.random.default_rng(1).integers(100, 200, (30, 60, 3), dtype=np.uint8)
    views = []
    for x in range(0, 50, 10):
        v = plate.copy()
        v[5:25, x:x + 8] = (0, 255, 0)
        views.append(v)
    assert np.array_equal(median_background(views), plate)


def test_missing_and_mismatched_plates_are_named():
    view = ViewRecord(7, "plant", "cam1", 2, 20.0, 3, 30.0, None, "images/plant/cam1_t02_a003.png")
    img = np.zeros((20, 30, 3), np.uint8)
    with pytest.raises(DataError, match=r"view 7 \(images/plant/cam1_t02_a003.png, camera cam1"):
        LabShadowSegmenter().segment(img, None, view)
    with pytest.raises(DataError, match="30x20.*|.*20x30"):
        LabShadowSegmenter().segment(img, np.zeros((21, 30, 3), np.uint8), view)
    with pytest.raises(DataError, match="no background plate"):
        MOG2Segmenter().segment(img, None, view)


def test_given_masks_reads_the_scan_masks(tiny_scan):
    from plantscan_core.stages import StageContext

    view = tiny_scan.views_by_role("plant")[0]
    img = tiny_scan.read_image(view)
    seg = GivenMasksSegmenter(context=StageContext(scan=tiny_scan))
    with pytest.raises(DataError, match=Path(view.file).stem + ".png"):
        seg.segment(img, None, view)
    (tiny_scan.root / "masks").mkdir()
    mask = np.zeros(img.shape[:2], np.uint8)
    mask[3:9, 4:7] = 255
    cv2.imwrite(str(tiny_scan.root / "masks" / f"{Path(view.file).stem}.png"), mask)
    assert np.array_equal(seg.segment(img, None, view), mask > 0)


def test_green_needs_no_plate():
    img = np.full((300, 300, 3), 230, np.uint8)
    img[20:280, 150] = (40, 150, 45)       # a 1 px wide green stem, 260 px long
    img[100:140, 100:200] = (50, 120, 40)  # a darker leaf on it
    img[5, 5] = (40, 150, 45)              # a green speck, < 0.5 % of the plant
    mask = GreenSegmenter().segment(img, None)
    truth = np.zeros(mask.shape, bool)
    truth[20:280, 150] = truth[100:140, 100:200] = True
    assert np.array_equal(mask, truth)


def test_undistorted_mask_puts_a_point_where_the_pinhole_camera_sees_it():
    from plantscan_segment.undistort import distort_mask, undistort_mask

    from plantscan_core.data import CameraModel

    model = CameraModel(f=300.0, cu=159.5, cv=119.5, d1=-0.2, d2=0.05, width=320, height=240)
    xy = np.array([[0.4, -0.3]])                     # normalised pinhole coordinates
    u, v = model.distort(xy)[0]                      # where the real lens images it
    mask = np.zeros((240, 320), bool)
    cv2.circle(mask.view(np.uint8), (round(u), round(v)), 4, 1, -1)
    und = undistort_mask(mask, model)
    ys, xs = np.nonzero(und)
    pin = xy[0] * model.f + (model.cu, model.cv)
    # The blob is re-sampled by the radial model: its centroid moves with it to within
    # the 0.5 px rounding of where it was drawn plus ~0.5 px of blob asymmetry.
    assert np.hypot(xs.mean() - pin[0], ys.mean() - pin[1]) < 1.0
    assert abs(np.hypot(xs.mean() - u, ys.mean() - v)) > 5  # the distortion is not negligible
    back = distort_mask(und, model)
    assert np.count_nonzero(back & mask) / np.count_nonzero(back | mask) > 0.8


def test_chromaticity_distance_matches_the_plain_formula():
    from plantscan_segment.lab import chromaticity_distance

    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (50, 60, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (50, 60, 3), dtype=np.uint8)
    fa, fb = a.astype(float) + 1, b.astype(float) + 1
    ref = np.abs(fa / fa.sum(2, keepdims=True) - fb / fb.sum(2, keepdims=True)).sum(2)
    # float32 OpenCV arithmetic vs float64: values are <= 2, so 1e-5 is float32 rounding.
    assert np.allclose(chromaticity_distance(a, b), ref, atol=1e-5)


def test_threads_give_the_same_masks_as_one_thread(sim_scans):
    # The pipeline calls segment() from several threads on one instance.
    from concurrent.futures import ThreadPoolExecutor

    items = list(_views(sim_scans["wheat"]))
    seg = LabShadowSegmenter()
    serial = [seg.segment(img, bg, v) for v, img, bg, _ in items]
    with ThreadPoolExecutor(4) as pool:
        threaded = list(pool.map(lambda it: seg.segment(it[1], it[2], it[0]), items))
    assert all(np.array_equal(a, b) for a, b in zip(serial, threaded, strict=True))


def test_median_plate_from_the_scan_views(sim_scans):
    from plantscan_core.stages import StageContext

    scan = sim_scans["plastic-dicot"]
    seg = LabShadowSegmenter(LabShadowSegmenter.Params(background="median"),
                             StageContext(scan=scan))
    items = list(_views(scan))
    # The plate is the per-pixel median of the plant views of the same camera and tilt.
    # (Its accuracy is poor on a turntable, measured in docs/segmentation.md.)
    for v, img, _, _ in items[:2]:
        same = [scan.read_image(w) for w, *_ in items
                if (w.camera, w.tilt_index) == (v.camera, v.tilt_index)]
        expected = LabShadowSegmenter().segment(img, median_background(same), v)
        assert np.array_equal(seg.segment(img, None, v), expected)
    with pytest.raises(DataError, match="needs >= 3 plant views"):
        other = ViewRecord(99, "plant", "nocam", 0, 0.0, 0, 0.0, None, "x.png")
        seg.segment(items[0][1], None, other)

"""The fast ``lab-shadow`` against its plain reference implementation (same masks)."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_segment import lab
from plantscan_segment.lab import (
    LabShadowSegmenter,
    fill_holes_fast,
    lab_shadow_mask,
    remove_tiny_blobs,
)
from plantscan_segment.lab_reference import (
    fill_small_holes,
    lab_shadow_mask_reference,
    remove_small_blobs,
)

# Parameter sets that switch each clean-up on and off and leave the weights unnormalised,
# so every branch of the fast path is compared with the reference.
PARAMS = [
    {},
    {"edge_fraction": 0.0, "shadow_chroma_max": None, "min_blob_px": 0, "max_hole_fraction": 0},
    {"suppress_shadows": False, "threshold": 5.0, "min_blob_px": 2},
    {"alpha": 0.3, "beta": 0.2, "gamma": 0.9, "shadow_ratio_min": 0.45, "min_blob_px": 5,
     "shadow_colour_max": 12.5},
]


def _plant_views(scan):
    plates = {(v.camera, v.tilt_index): scan.read_image(v)
              for v in scan.views_by_role("background")}
    return [(scan.read_image(v), plates[(v.camera, v.tilt_index)])
            for v in scan.views_by_role("plant")]


@pytest.mark.parametrize("preset", ["plastic-dicot", "wheat"])
@pytest.mark.parametrize("overrides", PARAMS)
def test_fast_path_gives_the_reference_masks_on_virtual_scans(sim_scans, preset, overrides):
    # Exactly equal, not within a tolerance: the fast path does the reference's float32
    # operations in the same order (or integer ones that are exact), so no pixel may flip.
    p = LabShadowSegmenter.Params(**overrides)
    views = _plant_views(sim_scans[preset])
    for image, plate in views:
        reference = lab_shadow_mask_reference(image, plate, p)
        assert reference.any() and not reference.all()
        # Default bands, and bands of 7 rows (320 = 45 * 7 + 5: a short last band), so the
        # one-row overlaps of the edge test and of the vertical ratios are exercised (once
        # per scan: the overlaps do not depend on the parameters).
        for band_rows in (None, 7) if not overrides else (None,):
            fast = lab_shadow_mask(image, plate, p, band_rows=band_rows)
            assert fast.dtype == bool and fast.shape == reference.shape
            assert np.array_equal(fast, reference), (
                f"{np.count_nonzero(fast != reference)} pixels differ ({overrides}, "
                f"bands of {band_rows} rows)")


def test_fast_path_on_tiny_and_one_row_images():
    rng = np.random.default_rng(3)
    p = LabShadowSegmenter.Params(threshold=2.0)
    for shape in [(1, 9), (2, 1), (5, 5), (17, 3)]:
        plate = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        image = plate.copy()
        image[rng.random(shape) < 0.4] = (30, 150, 40)
        reference = lab_shadow_mask_reference(image, plate, p)
        for band_rows in (None, 1, 2):
            assert np.array_equal(lab_shadow_mask(image, plate, p, band_rows=band_rows),
                                  reference), (shape, band_rows)
        # The region pass on images smaller than its 4 x 4 blocks.
        assert np.array_equal(LabShadowSegmenter(p).segment(image, plate), reference), shape


@pytest.mark.parametrize("fast, plain, density, sizes", [
    (remove_tiny_blobs, remove_small_blobs, (0.02, 0.5), (0, 1, 2, 3, 4)),
    (fill_holes_fast, fill_small_holes, (0.3, 0.97), (0, 1, 2, 5, 64)),
])
def test_fast_clean_ups_equal_labelling_every_component(fast, plain, density, sizes):
    rng = np.random.default_rng(2)
    for i in range(100):
        mask = rng.random((30, 40)) < rng.uniform(*density)
        for px in sizes:
            assert np.array_equal(fast(mask, px), plain(mask, px)), (i, px)


def test_small_holes_are_filled_and_gaps_to_the_outside_kept():
    mask = np.zeros((60, 80), bool)
    mask[10:50, 10:70] = True
    mask[20:23, 20:23] = False      # 9 px speck (a shaded pot read as shadow): filled
    mask[30, 40] = False            # 1 px speck: filled
    mask[25:35, 50:62] = False      # 120 px hole (a real gap between leaf and stem): kept
    mask[40:50, 30:33] = False      # a notch open to the outside: not a hole, kept
    mask[39, 33] = False            # a pixel touching the notch only diagonally: a hole
    out = fill_small_holes(mask, 64)
    assert np.array_equal(fill_holes_fast(mask, 64), out)
    assert out[20:23, 20:23].all() and out[30, 40] and out[39, 33]
    assert not out[25:35, 50:62].any() and not out[40:50, 30:33].any()
    assert np.array_equal(out & ~mask, out ^ mask)  # only ever adds pixels
    assert fill_small_holes(mask, 0) is mask
    assert not fill_small_holes(np.zeros((5, 5), bool), 64).any()
    # A hole touching the mask's bounding box from inside is still enclosed (4-connected).
    ring = np.ones((5, 5), bool)
    ring[2, 2] = False
    assert fill_small_holes(ring, 2).all()


def test_each_plate_is_converted_once_and_again_when_changed(sim_scans, monkeypatch):
    built = []
    original = lab.PlateTerms.build.__func__

    def counting_build(cls, background, *args):
        built.append(background)
        return original(cls, background, *args)

    monkeypatch.setattr(lab.PlateTerms, "build", classmethod(counting_build))
    seg = LabShadowSegmenter()
    views = _plant_views(sim_scans["plastic-dicot"])
    plates = {id(plate) for _, plate in views}
    for image, plate in views:
        seg.segment(image, plate)
    assert len(built) == len(plates) == 2  # one plate per camera, 2 views each
    # A plate array changed in place must not be served from the cache.
    image, plate = views[0]
    plate[:50] = 255 - plate[:50]
    mask = seg.segment(image, plate)
    assert len(built) == 3
    assert np.array_equal(mask, lab_shadow_mask_reference(image, plate, seg.params))


def test_reference_implementation_is_selectable(sim_scans):
    image, plate = _plant_views(sim_scans["wheat"])[0]
    seg = LabShadowSegmenter(LabShadowSegmenter.Params(implementation="reference"))
    assert np.array_equal(seg.segment(image, plate), LabShadowSegmenter().segment(image, plate))


def test_chromaticity_on_candidate_boxes_of_any_shape():
    # OpenCV's Python binding reads a (4, 1) or a (1, 1) float plane as a scalar: a 4 x 1
    # box and a single candidate pixel once crashed the chromaticity test.
    from plantscan_segment.lab import _suppress_chromatic_candidates

    rng = np.random.default_rng(4)
    plate = rng.integers(50, 200, (6, 5, 3), dtype=np.uint8)
    image = (plate * 0.6).astype(np.uint8)  # plate in shadow: same chromaticity
    image[2, 3] = (40, 150, 40)             # a green pixel among the candidates
    for box in [(slice(1, 5), slice(3, 4)), (slice(2, 3), slice(0, 4)), (slice(0, 6),) * 2,
                (slice(2, 3), slice(3, 4)), (slice(4, 5), slice(1, 2))]:
        shadow = np.zeros((6, 5), bool)
        shadow[box] = True
        expected = shadow.copy()
        expected[2, 3] = False
        _suppress_chromatic_candidates(shadow, image, plate, 0.06)
        assert np.array_equal(shadow, expected), box


@pytest.mark.parametrize("preset", ["plastic-dicot", "wheat"])
def test_scoring_the_plant_region_gives_the_whole_image_masks(sim_scans, preset):
    # Exactly equal: the region only skips pixels the whole image's test calls background.
    whole = LabShadowSegmenter(LabShadowSegmenter.Params(region="whole"))
    region = LabShadowSegmenter()
    for image, plate in _plant_views(sim_scans[preset]):
        assert np.array_equal(region.segment(image, plate), whole.segment(image, plate))
    counts = region.report.counts
    # The work saved, as a count: the plant and its shadow fill about half of these frames.
    assert 0 < counts["pixels_scored"] < 0.8 * counts["pixels_total"]


def _leaf_on_plate(shape=(240, 320)):
    rng = np.random.default_rng(5)
    plate = np.clip(rng.normal(170, 2, (*shape, 3)), 0, 255).astype(np.uint8)
    image = plate.copy()
    image[100:160, 120:200] = (40, 140, 60)      # a leaf, found by the reduced pass
    return image, plate


def test_a_plant_the_region_cut_is_scored_again_in_wider_columns():
    rng = np.random.default_rng(5)
    plate = np.clip(rng.normal(170, 2, (480, 1280, 3)), 0, 255).astype(np.uint8)
    image = plate.copy()
    image[200:320, 500:700] = (40, 140, 60)      # a leaf, found by the region pass
    # A 1 px stem running right from the leaf to near the image's edge, and one running up
    # through the bands above, too faint in the reduced pictures (1/4 of their 4 x 4 blocks,
    # under REGION_DIFF_DN) for the region pass to see.
    image[260, 700:1200] = (150, 175, 155)
    image[20:200, 600] = (150, 175, 155)
    p = LabShadowSegmenter.Params()
    whole = lab_shadow_mask(image, plate, p)
    assert whole[260, 700:1200].sum() > 450 and whole[20:200, 600].sum() > 160
    terms = lab.PlateTerms.build(plate, p.shadow_ratio_min, p.shadow_ratio_max)
    blocks = lab.plant_blocks(image, terms)
    assert not blocks[:, 720 // lab.REGION_FACTOR:].any()      # ... not in the region pass
    assert not blocks[:180 // lab.REGION_FACTOR].any()
    mask, scored, widened = lab.lab_shadow_mask_in_region(image, plate, p, terms)
    assert widened >= 2 and np.array_equal(mask, whole)
    # The bands scored again are still far from the whole image (4 bands of 102 rows here).
    assert scored < 0.6 * image.shape[0] * image.shape[1]


def test_an_empty_view_scores_no_pixel_at_full_size():
    image, plate = _leaf_on_plate()
    seg = LabShadowSegmenter()
    assert not seg.segment(plate.copy(), plate).any()
    assert seg.report.counts["pixels_scored"] == 0
    assert seg.segment(image, plate).sum() == 60 * 80

"""The seed's shadow-robust background subtraction in LAB colour (``lab-shadow``).

Per pixel, against a background plate of the same camera and tilt (OpenCV's
8-bit LAB: L, A, B in 0..255):

* luminance difference  Δ = |L − L'|
* colour difference     Θ = |A − A'| + |B − B'|
* texture difference    Ψ = |L(u,v)/L(u+1,v) − L'(u,v)/L'(u+1,v)|
                          + |L(u,v)/L(u,v+1) − L'(u,v)/L'(u,v+1)|
* score                 Ω = (αΔ + βΘ + γΨ) / (α + β + γ), plant where Ω > t.

A cast shadow darkens the backdrop (large Δ) but keeps its hue (small Θ) and
its texture ratios (Ψ ≈ 0, a shadow scales neighbours alike), so the seed's
weights α = 0.1, β = 0.5, γ = 0.4 keep shadows out while coloured leaves,
even thin and partly covered pixels, score high.

:func:`lab_shadow_mask` is the fast path the segmenter runs (plate terms
cached, integer Δ/Θ, bands of rows); :mod:`plantscan_segment.lab_reference`
keeps the plain implementation it is tested against (same masks; see
docs/segmentation.md).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from plantscan_core.data import ViewRecord, mask_box
from plantscan_core.errors import DataError
from plantscan_core.preflight import WorkEstimate, WorkPlan
from plantscan_core.stages import Segmenter, StageParams
from plantscan_segment.lab_reference import (
    L_OFFSET,
    NEIGHBOURHOOD,
    chromaticity_distance,
    chromaticity_distance_planes,
    hole_px,
    lab_shadow_mask_reference,
    lab_shadow_score,
    normalised_rgb,
    remove_small_blobs,
)

__all__ = ["LabShadowSegmenter", "lab_shadow_mask", "lab_shadow_score", "chromaticity_distance",
           "median_background", "remove_small_blobs", "fill_holes_fast"]

# How many plates one segmenter keeps converted: a scan has one per camera and tilt.
_PLATES_KEPT = 16
# The region pass (plant_blocks, lab_shadow_mask_in_region): pictures in 4 x 4 blocks; a
# block whose B, G or R mean differs from the plate's by more than 6 DN is where the plant
# may be (a 1 px stem of 40 DN averages 10 over its blocks; the virtual scanner's noise
# averages under 1); each band of rows scores the columns of the blocks within 16 px of it,
# widened by 16 px; a mask pixel within 5 px of a cut (the outer 2 px are scored with the
# band's own neighbours) means the cut went through the plant: that side moves out by 8 %
# of the image's width, or the neighbouring band scores the columns, and it is scored again.
REGION_FACTOR = 4
REGION_DIFF_DN = 6
REGION_MARGIN_PX = 16
REGION_RING_PX = 5
REGION_EXACT_PX = 2
REGION_GROW = 0.08
# Pixels per band of rows in lab_shadow_mask: the band's ~12 float32/uint8 planes stay
# within a core's share of the CPU cache (measured in docs/benchmarks/segmentation.md).
_BAND_PIXELS = 131072


@dataclass(frozen=True)
class PlateTerms:
    """Everything the score needs of one background plate, computed once per plate.

    Attributes
    ----------
    source : (H, W, 3) uint8 BGR, the caller's array (the cache key, by identity)
    pixels : a copy of it: a plate changed in place since is converted again
    lum, a, b : (H, W) uint8, OpenCV's 8-bit LAB planes
    right, down : (H, W) float32, L(u,v)/L(u+1,v) and L(u,v)/L(u,v+1) (with L + 1)
    shadow_lum_min, shadow_lum_max : (H, W) uint8, the image luminances whose ratio L/L'
        to this plate pixel lies in [shadow_ratio_min, shadow_ratio_max] (min > max:
        none)
    """

    source: np.ndarray
    pixels: np.ndarray
    lum: np.ndarray
    a: np.ndarray
    b: np.ndarray
    right: np.ndarray
    down: np.ndarray
    shadow_lum_min: np.ndarray
    shadow_lum_max: np.ndarray
    small: np.ndarray | None = None

    @classmethod
    def build(cls, background: np.ndarray, ratio_min: float, ratio_max: float) -> PlateTerms:
        lum, a, b = cv2.split(cv2.cvtColor(background, cv2.COLOR_BGR2LAB))
        right, down = _ratios(lum)
        lo, hi = _shadow_luminance_tables(ratio_min, ratio_max)
        return cls(background, background.copy(), lum, a, b, right, down,
                   cv2.LUT(lum, lo), cv2.LUT(lum, hi), _reduced(background))

    def columns(self, cols: slice) -> PlateTerms:
        """The terms of the plate's columns ``cols`` (views, no copy).

        The ratios keep the plate's own right neighbour at the last column, where
        the image's columns repeat their own: those pixels are not the whole
        image's (:func:`lab_shadow_mask_in_region` checks the plant is not there).
        """
        return PlateTerms(self.source[:, cols], self.pixels[:, cols],
                          *(plane[:, cols] for plane in (
                              self.lum, self.a, self.b, self.right, self.down,
                              self.shadow_lum_min, self.shadow_lum_max)))

    def matches(self, background: np.ndarray) -> bool:
        return (background is self.source and background.shape == self.pixels.shape
                and cv2.norm(background, self.pixels, cv2.NORM_INF) == 0)


def _shadow_luminance_tables(ratio_min: float, ratio_max: float):
    """Per plate luminance L' (0..255): the smallest and largest image L passing the ratio test.

    Evaluated with the reference's own float32 expression on every (L, L') pair,
    so the per-pixel test ``min <= L <= max`` decides exactly as the reference's
    ``ratio_min <= (L + 1) / (L' + 1) <= ratio_max``. For a fixed L' the ratio
    grows with L, so the passing L form one interval.
    """
    lum = np.arange(256, dtype=np.float32)[:, None]  # image L, rows
    lum_bg = np.arange(256, dtype=np.float32)[None, :]  # plate L', columns
    ratio = (lum + L_OFFSET) / (lum_bg + L_OFFSET)
    ok = (ratio >= ratio_min) & (ratio <= ratio_max)
    lo = np.full(256, 255, np.uint8)
    hi = np.zeros(256, np.uint8)
    for col in range(256):
        rows = np.flatnonzero(ok[:, col])
        if rows.size:
            if rows[-1] - rows[0] + 1 != rows.size:  # cannot happen: the ratio is monotone in L
                raise AssertionError("lab-shadow: shadow ratio test is not an interval")
            lo[col], hi[col] = rows[0], rows[-1]
    return lo, hi


def _ratios(lum: np.ndarray, reaches_last_row: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """L(u,v)/L(u+1,v) and L(u,v)/L(u,v+1) (with L + 1, float32) of rows of an 8-bit L.

    The same float32 operations as the reference's ``ratios`` (so the same
    values) without its float copies of the image. ``lum`` : (R, W) uint8,
    consecutive rows of the image; when they end at the image's last row
    (``reaches_last_row``) that row repeats its neighbour's vertical ratio and
    both outputs are (R, W); otherwise the last row only serves as the row
    below and the outputs are (R - 1, W). The last column repeats its neighbour.
    """
    l1 = np.add(lum, np.float32(L_OFFSET), dtype=np.float32)
    n, width = (l1.shape[0] if reaches_last_row else l1.shape[0] - 1), l1.shape[1]
    right = np.empty((n, width), np.float32)
    np.divide(l1[:n, :-1], l1[:n, 1:], out=right[:, :-1])
    right[:, -1] = right[:, -2] if width > 1 else 1.0
    down = np.empty((n, width), np.float32)
    np.divide(l1[:-1], l1[1:], out=down[:l1.shape[0] - 1])
    if reaches_last_row:
        down[-1] = down[-2] if n > 1 else 1.0
    return right, down


def _suppress_chromatic_candidates(shadow: np.ndarray, image: np.ndarray,
                                   background: np.ndarray, chroma_max: float) -> None:
    """Keep in ``shadow`` ((R, W) bool, in place) only pixels with the plate's chromaticity.

    ``image`` and ``background`` are the same (R, W, 3) rows. The distance is
    evaluated on the bounding box of the candidates only: shadows cover a few %
    of an image.
    """
    x, y, w, h = cv2.boundingRect(shadow.view(np.uint8))
    if w == 0:
        return
    rows, cols = slice(y, y + h), slice(x, x + w)
    # As one row of pixels, as the reference does: OpenCV's Python binding reads a (4, 1)
    # float plane as a scalar.
    chroma = chromaticity_distance_planes(
        normalised_rgb(image[rows, cols].reshape(1, -1, 3)),
        normalised_rgb(background[rows, cols].reshape(1, -1, 3)))
    shadow[rows, cols] &= (chroma < chroma_max).reshape(h, w)


def remove_tiny_blobs(mask: np.ndarray, min_px: int) -> np.ndarray:
    """:func:`remove_small_blobs` for ``min_px <= 3`` from neighbour counts, no labelling.

    A 1 px blob is a pixel with no 8-neighbour; a 2 px blob is a pair of pixels
    with exactly one neighbour each, each other. Two 3 x 3 box sums find both
    (~10x cheaper than labelling the image); larger ``min_px`` label components.
    """
    if min_px <= 1:
        return mask
    if min_px > 3:
        return remove_small_blobs(mask, min_px)
    # 3 x 3 sums of a 0/1 image (the pixel itself included); outside the image is background.
    count = cv2.boxFilter(mask.view(np.uint8), -1, (3, 3), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    drop = mask & (count == 1)
    if min_px == 3:
        single_neighbour = mask & (count == 2)
        pair = cv2.boxFilter(single_neighbour.view(np.uint8), -1, (3, 3), normalize=False,
                             borderType=cv2.BORDER_CONSTANT)
        drop |= single_neighbour & (pair == 2)
    return mask & ~drop


def fill_holes_fast(mask: np.ndarray, max_px: int) -> np.ndarray:
    """:func:`~plantscan_segment.lab_reference.fill_small_holes`, labelling only the holes.

    The background outside the plant is flood-filled from a 1 px frame around
    the mask's box; what is left are the holes, and only their own bounding
    box is labelled (4x cheaper at 2592x1728: 6 vs 23 ms; same masks, tested).
    """
    box = mask_box(mask) if max_px > 0 else None
    if box is None:
        return mask
    r0, c0 = box[0].start, box[1].start
    framed = np.zeros((box[0].stop - r0 + 2, box[1].stop - c0 + 2), np.uint8)
    framed[1:-1, 1:-1] = mask[box]
    cv2.floodFill(framed, None, (0, 0), 2, flags=4)  # 4-connected, as the holes are
    holes = framed == 0
    hr = np.flatnonzero(holes.any(axis=1))
    if hr.size == 0:
        return mask
    hc = np.flatnonzero(holes.any(axis=0))
    sub = holes[hr[0]:hr[-1] + 1, hc[0]:hc[-1] + 1]
    _, labels, stats, _ = cv2.connectedComponentsWithStats(sub.view(np.uint8), connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] < max_px
    small[0] = False  # label 0: not a hole
    out = mask.copy()
    # framed row/column i is mask row r0 - 1 + i (the frame adds one).
    out[r0 - 1 + hr[0]:r0 + hr[-1], c0 - 1 + hc[0]:c0 + hc[-1]] |= small[labels]
    return out


def _reduced(image: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) in blocks of ``REGION_FACTOR``² pixels, each its mean colour.

    (ceil(H / f), ceil(W / f), 3) uint8: the last row and column average the
    1..f - 1 rows or columns the division leaves over, so every pixel is in a block.
    """
    f = REGION_FACTOR
    height, width = image.shape[:2]
    h, w = height // f, width // f
    out = np.empty((-(-height // f), -(-width // f), 3), np.uint8)
    if h and w:
        out[:h, :w] = cv2.resize(image[:f * h, :f * w], (w, h), interpolation=cv2.INTER_AREA)
    if h < out.shape[0] and w:
        out[h:, :w] = cv2.resize(image[f * h:, :f * w], (w, 1), interpolation=cv2.INTER_AREA)
    if w < out.shape[1] and h:
        out[:h, w:] = cv2.resize(image[:f * h, f * w:], (1, h), interpolation=cv2.INTER_AREA)
    if h < out.shape[0] and w < out.shape[1]:
        out[h:, w:] = image[f * h:, f * w:].reshape(-1, 3).mean(axis=0).round()
    return out


def plant_blocks(image: np.ndarray, plate: PlateTerms) -> np.ndarray:
    """Where the plant can be: (ceil(H / f), ceil(W / f)) bool over blocks of f x f pixels.

    The region pass (issue #28), f = ``REGION_FACTOR``: a block whose mean B, G
    or R differs from the plate's by more than ``REGION_DIFF_DN`` is a
    candidate, cast shadows included (told from the plate by chromaticity in the
    reduced pictures, the dashes of a sub-pixel stem in a shadow were lost too:
    docs/segmentation.md). It only says where the full test runs: a plant cut
    by it is caught by :func:`lab_shadow_mask_in_region`.
    """
    small = _reduced(image)
    if plate.small is None or plate.small.shape != small.shape:
        raise DataError("lab-shadow: the plate's reduced picture does not match the image's")
    # Each channel compared on its own over the (h, 3 w) channel grid, then any of the three
    # (a reduction over the channel axis of the 3-D array costs 10x more).
    diff = cv2.absdiff(small, plate.small).reshape(small.shape[0], -1)
    over = cv2.compare(diff, REGION_DIFF_DN, cv2.CMP_GT).reshape(small.shape)
    return cv2.max(cv2.max(over[..., 0], over[..., 1]), over[..., 2]).view(bool)


def _band_columns(blocks: np.ndarray, top: int, bottom: int, width: int) -> list[int] | None:
    """Columns ``[lo, hi]`` of full-size rows ``top:bottom`` that may hold plant, or None.

    The candidate blocks of those rows and of ``REGION_MARGIN_PX`` above and
    below, their columns widened by ``REGION_MARGIN_PX``.
    """
    f, m = REGION_FACTOR, REGION_MARGIN_PX
    rows = blocks[max(0, (top - m) // f):(bottom - 1 + m) // f + 1]
    cols = np.flatnonzero(rows.any(axis=0))
    if cols.size == 0:
        return None
    return [max(0, f * int(cols[0]) - m), min(width, f * (int(cols[-1]) + 1) + m)]


def lab_shadow_mask_in_region(image: np.ndarray, background: np.ndarray, p,
                              plate: PlateTerms) -> tuple[np.ndarray, int, int]:
    """:func:`lab_shadow_mask`, each band of rows scored only where the plant can be.

    Returns ``(mask, pixels scored, times a band's columns were widened)``.
    Each band of rows is scored in the columns :func:`_band_columns` gives it
    (bands without a candidate block are not scored). A band's pixels at
    least ``REGION_RING_PX - 1`` from a cut side are scored exactly as in the
    whole image (the score looks one pixel right, the edge test one more
    around: at most ``REGION_EXACT_PX`` pixels next to a cut differ; the rows
    above and below are the band's own overlap, as in the whole image), and
    the blob and hole clean-ups run on the whole mask afterwards, as there. A
    plant crossing a cut therefore shows in the exactly scored pixels next to it:

    * a mask pixel within ``REGION_RING_PX`` of a cut side of its band: that
      side moves out by ``REGION_GROW`` of the image's width, the band is scored
      again;
    * a mask pixel in a band's first or last ``REGION_RING_PX`` rows whose
      column's 8-neighbours the neighbouring band did not score at least
      ``REGION_EXACT_PX`` inside its cut sides (where its pixels are exact, so
      a plant going on sideways from there meets its ring): the neighbour's
      columns grow to hold them and it is scored (again).

    Until nothing moves. So the mask equals the whole image's (tested on the
    virtual scanner's views) unless a separate piece of plant, faint in the
    reduced pictures, lies wholly outside the scored columns.
    """
    height, width = image.shape[:2]
    blocks = plant_blocks(image, plate)
    band_rows = max(8, _BAND_PIXELS // width)
    tops = list(range(0, height, band_rows))
    spans = [(t, min(t + band_rows, height)) for t in tops]
    want = [_band_columns(blocks, t, b, width) for t, b in spans]
    done: list[list[int] | None] = [None] * len(spans)
    mask = np.zeros((height, width), bool)
    alpha_delta = np.arange(256, dtype=np.float32) * np.float32(p.alpha)
    r, grow = REGION_RING_PX, max(1, int(REGION_GROW * width))
    scored = widened = 0

    def need(k: int, lo: int, hi: int) -> None:
        """Band ``k`` must score columns ``lo:hi``."""
        nonlocal widened
        lo, hi = max(0, lo), min(width, hi)
        cur = want[k]
        if cur is None:
            want[k] = [lo, hi]
        elif lo < cur[0] or hi > cur[1]:
            want[k] = [min(cur[0], lo), max(cur[1], hi)]
            widened += 1

    while True:
        todo = [k for k in range(len(spans)) if want[k] is not None and want[k] != done[k]]
        if not todo:
            break
        for k in todo:
            (top, bottom), (lo, hi) = spans[k], want[k]
            cols = slice(lo, hi)
            band = _band_mask(image[:, cols], background[:, cols],
                              plate.columns(cols), p, alpha_delta, top, bottom)
            mask[top:bottom] = False
            mask[top:bottom, cols] = band
            done[k] = [lo, hi]
            scored += (bottom - top) * (hi - lo)
            if lo > 0 and band[:, :r].any():
                need(k, lo - grow, lo)
            if hi < width and band[:, -r:].any():
                need(k, hi, hi + grow)
            for edge, other in ((band[:r], k - 1), (band[-r:], k + 1)):
                if 0 <= other < len(spans):
                    xs = np.flatnonzero(edge.any(axis=0))
                    if xs.size:  # the plant goes on next to these columns: exactly scored
                        need(other, lo + int(xs[0]) - 1 - REGION_EXACT_PX,
                             lo + int(xs[-1]) + 2 + REGION_EXACT_PX)
    return _clean_up(mask, p, (height, width)), scored, widened


def lab_shadow_mask(image: np.ndarray, background: np.ndarray, p,
                    plate: PlateTerms | None = None, band_rows: int | None = None) -> np.ndarray:
    """``lab-shadow``'s mask: (H, W) bool, True = plant or pot.

    The same decisions as :func:`lab_shadow_mask_reference` (tested equal on
    the virtual scanner's images), 4-9x faster: the plate's LAB planes and
    ratios converted once (``plate``), Δ and Θ in integers, the shadow ratio
    test as a per-pixel luminance interval, the chromaticity only on the
    bounding box of shadow candidates, tiny blobs removed without labelling,
    and all of it in bands of rows whose temporaries stay in the CPU cache
    (full-image float temporaries made it memory bound, and cost page faults
    on fresh threads).

    Parameters
    ----------
    image, background : (H, W, 3) uint8 BGR, the plant view and its plate
    p : ``LabShadowSegmenter.Params``
    plate : ``PlateTerms.build(background, ...)`` when the caller keeps it
    band_rows : rows per band (default: ~``_BAND_PIXELS`` pixels per band)
    """
    if plate is None:
        plate = PlateTerms.build(background, p.shadow_ratio_min, p.shadow_ratio_max)
    height, width = image.shape[:2]
    band_rows = band_rows or max(8, _BAND_PIXELS // width)
    mask = np.empty((height, width), bool)
    alpha_delta = np.arange(256, dtype=np.float32) * np.float32(p.alpha)  # αΔ for each Δ
    for top in range(0, height, band_rows):
        bottom = min(top + band_rows, height)
        mask[top:bottom] = _band_mask(image, background, plate, p, alpha_delta, top, bottom)
    return _clean_up(mask, p, mask.shape)


def _clean_up(mask: np.ndarray, p, shape: tuple[int, int]) -> np.ndarray:
    """Tiny blobs dropped and small holes filled, on the mask's box (all else is background)."""
    box = mask_box(mask)
    if box is None:
        return mask
    # One pixel of background around the box: the blob test's 3 x 3 counts see the same
    # neighbours as on the whole image.
    rows = slice(max(0, box[0].start - 1), min(shape[0], box[0].stop + 1))
    cols = slice(max(0, box[1].start - 1), min(shape[1], box[1].stop + 1))
    mask[rows, cols] = fill_holes_fast(remove_tiny_blobs(mask[rows, cols], p.min_blob_px),
                                       hole_px(shape, p.max_hole_fraction))
    return mask


def _band_mask(image, background, plate: PlateTerms, p, alpha_delta, top: int,
               bottom: int) -> np.ndarray:
    """Mask rows ``top:bottom`` ((bottom - top, W) bool) before the blob clean-up."""
    height = image.shape[0]
    # Ω is needed one row above and below (the edge test's 3 x 3 maximum), Ψ of a row
    # needs the row below it.
    first, last = max(top - 1, 0), min(bottom + 1, height)
    end = min(last + 1, height)
    lum, a, b = cv2.split(cv2.cvtColor(image[first:end], cv2.COLOR_BGR2LAB))
    n = last - first
    psi, down = _ratios(lum, reaches_last_row=end == height)
    psi, down, lum, a, b = psi[:n], down[:n], lum[:n], a[:n], b[:n]
    rows = slice(first, last)
    np.subtract(psi, plate.right[rows], out=psi)
    np.abs(psi, out=psi)
    np.subtract(down, plate.down[rows], out=down)
    np.abs(down, out=down)
    np.add(psi, down, out=psi)
    # Θ is a sum of integers (exact in float32); αΔ is looked up.
    theta = cv2.add(cv2.absdiff(a, plate.a[rows]), cv2.absdiff(b, plate.b[rows]),
                    dtype=cv2.CV_32F)
    # Ω = (αΔ + βΘ + γΨ) / (α + β + γ) in the reference's order of float32 operations.
    omega = cv2.LUT(cv2.absdiff(lum, plate.lum[rows]), alpha_delta)
    np.add(omega, np.multiply(theta, np.float32(p.beta)), out=omega)
    texture_like_plate = psi < p.shadow_texture_max if p.suppress_shadows else None
    np.multiply(psi, np.float32(p.gamma), out=psi)
    np.add(omega, psi, out=omega)
    weights = p.alpha + p.beta + p.gamma
    if weights != 1.0:
        np.divide(omega, np.float32(weights), out=omega)
    inner = slice(top - first, bottom - first)  # the band's own rows among first:last
    mask = omega[inner] > p.threshold
    if p.edge_fraction > 0:
        local_max = cv2.dilate(omega, NEIGHBOURHOOD)[inner]
        np.multiply(local_max, np.float32(p.edge_fraction), out=local_max)
        mask &= omega[inner] >= local_max
    if p.suppress_shadows:
        shadow = mask & texture_like_plate[inner]
        shadow &= theta[inner] < np.float32(p.shadow_colour_max)
        lum, own = lum[inner], slice(top, bottom)
        shadow &= lum >= plate.shadow_lum_min[own]
        shadow &= lum <= plate.shadow_lum_max[own]
        if p.shadow_chroma_max is not None:
            _suppress_chromatic_candidates(shadow, image[own], background[own],
                                           p.shadow_chroma_max)
        mask &= ~shadow
    return mask


def median_background(images: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median of views of one camera and tilt: a background plate estimate.

    Works where the plant covers any pixel in fewer than half of the views
    (a plant turning on a turntable in front of a fixed backdrop); the pot and
    the plant's axis region, always covered, stay in the estimate.
    """
    return np.median(np.stack(images), axis=0).astype(np.uint8)


# Peak memory of segmenting one image, per pixel: the decoded image and its plate (6 B) and the
# LAB planes, scores and masks of one ``segment`` call (22 B, peak RSS measured at 3000x2000
# and 5184x3456 px: 21.98 B/px both).
SEGMENT_BYTES_PER_PX = 28


class LabShadowSegmenter(Segmenter):
    """``lab-shadow``: the seed's LAB score against a background plate."""

    name = "lab-shadow"

    @classmethod
    def estimate(cls, params, plan: WorkPlan) -> WorkEstimate:
        """Images segmented at once (``plan.workers``) times the memory of one."""
        w, h = plan.image_size
        return WorkEstimate(stage="segment (lab-shadow)",
                            what=f"{plan.workers} images of {w}x{h} px at once",
                            peak_bytes=plan.workers * SEGMENT_BYTES_PER_PX * w * h, seconds=None,
                            parameter="scan.image_size (or segment.reduce)")

    class Params(StageParams):
        alpha: float = Field(default=0.1, ge=0, description="weight of luminance difference Δ")
        beta: float = Field(default=0.5, ge=0, description="weight of colour difference Θ")
        gamma: float = Field(default=0.4, ge=0, description="weight of texture difference Ψ")
        threshold: float = Field(default=8.0, ge=0, description="t: plant where Ω > t")
        suppress_shadows: bool = Field(
            default=True, description="also drop shadow-like pixels (False: the seed's score "
            "alone)")
        shadow_ratio_min: float = Field(default=0.5, gt=0, le=1,
                                        description="darkest shadow, as L / L' of the plate")
        shadow_ratio_max: float = Field(default=0.98, gt=0, le=1)
        shadow_colour_max: float = Field(default=12.0, ge=0, description="max Θ of a shadow")
        shadow_texture_max: float = Field(default=0.5, ge=0, description="max Ψ of a shadow")
        shadow_chroma_max: float | None = Field(
            default=0.06, ge=0, description="max L1 distance of normalised rgb between a shadow "
            "and its plate (None: no chromaticity test)")
        edge_fraction: float = Field(
            default=0.25, ge=0, le=1, description="drop pixels whose Ω is below this fraction of "
            "the largest Ω in their 3x3 neighbourhood: mixed edge pixels mostly covered by "
            "background (0: off); measured against thin recall in docs/segmentation.md")
        min_blob_px: int = Field(
            default=3, ge=0, description="drop 8-connected foreground blobs smaller than this "
            "(0: off); 3 removes noise speckle in shadows at no measured thin-recall cost")
        max_hole_fraction: float = Field(
            default=1.5e-5, ge=0, lt=1, description="fill background holes inside the plant "
            "smaller than this fraction of the image's area (0: off; 1.5e-5 is 67 px at "
            "2592x1728, 2 px at 480x320): the shadow test speckles a shaded pot or leaf with "
            "false holes, which carve the hull (docs/segmentation.md)")
        background: Literal["plate", "median"] = Field(
            default="plate",
            description="plate: the scan's background view of the same camera and tilt; "
            "median: per-pixel median of the plant views of that camera and tilt "
            "(scans without a plate)")
        region: Literal["plant", "whole"] = Field(
            default="plant", description="plant: a pass over 4 x 4 blocks finds where the "
            "plant can be and each band of rows is scored only in those columns (the same "
            "masks: where the mask reaches a cut, the band is widened and scored again); "
            "whole: every pixel is scored (docs/segmentation.md)")
        implementation: Literal["fast", "reference"] = Field(
            default="fast", description="reference: the plain float32 code path the fast one "
            "is tested against (same masks, ~5x slower; docs/segmentation.md)")

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        if self.params.alpha + self.params.beta + self.params.gamma <= 0:
            raise DataError("lab-shadow: alpha + beta + gamma must be > 0")
        self._median_cache: dict[tuple[str, int], np.ndarray] = {}
        # segment() runs on several threads at once: one median per camera/tilt, built once.
        self._median_lock = threading.Lock()
        # Each plate serves every image of its camera and tilt: converted once, kept by identity.
        self._plates: OrderedDict[int, PlateTerms] = OrderedDict()
        self._plates_lock = threading.Lock()

    def _plate_terms(self, background: np.ndarray) -> PlateTerms:
        p = self.params
        with self._plates_lock:
            plate = self._plates.get(id(background))
            if plate is None or not plate.matches(background):
                plate = PlateTerms.build(background, p.shadow_ratio_min, p.shadow_ratio_max)
                self._plates[id(background)] = plate
                while len(self._plates) > _PLATES_KEPT:
                    self._plates.popitem(last=False)
            self._plates.move_to_end(id(background))
            return plate

    def _median_plate(self, view: ViewRecord) -> np.ndarray:
        key = (view.camera, view.tilt_index)
        with self._median_lock:
            if key not in self._median_cache:
                self._median_cache[key] = self._build_median_plate(view)
            return self._median_cache[key]

    def _build_median_plate(self, view: ViewRecord) -> np.ndarray:
        scan = self.context.scan
        if scan is None:
            raise DataError("lab-shadow: background 'median' needs the scan folder")
        views = [v for v in scan.views_by_role("plant")
                 if (v.camera, v.tilt_index) == (view.camera, view.tilt_index)]
        if len(views) < 3:
            raise DataError(f"lab-shadow: background 'median' for camera {view.camera}, tilt "
                            f"{view.tilt_index} needs >= 3 plant views, the scan has "
                            f"{len(views)}")
        images = []
        for v in views:
            img = scan.read_image(v)
            if images and img.shape != images[0].shape:
                raise DataError(f"{scan.path_of(v)}: {img.shape[1]}x{img.shape[0]} px, but "
                                f"{views[0].file} is {images[0].shape[1]}x"
                                f"{images[0].shape[0]} (camera {view.camera}, tilt "
                                f"{view.tilt_index})")
            images.append(img)
        return median_background(images)

    def segment(self, image, background, view=None):
        p = self.params
        if p.background == "median":
            if view is None:
                raise DataError("lab-shadow: background 'median' needs the view")
            background = self._median_plate(view)
        if background is None:
            where = f"view {view.index} ({view.file}, camera {view.camera}, tilt " \
                    f"{view.tilt_index})" if view is not None else "this image"
            raise DataError(f"lab-shadow: no background plate for {where}; capture the "
                            "'background' role or set segment.params.background=median")
        if background.shape != image.shape:
            raise DataError(f"lab-shadow: background plate is {background.shape[1]}x"
                            f"{background.shape[0]} but the image is {image.shape[1]}x"
                            f"{image.shape[0]}")
        if p.implementation == "reference":
            return lab_shadow_mask_reference(image, background, p)
        plate = self._plate_terms(background)
        if p.region == "whole":
            return lab_shadow_mask(image, background, p, plate)
        mask, scored, grown = lab_shadow_mask_in_region(image, background, p, plate)
        self.report.count("pixels_scored", scored)
        self.report.count("pixels_total", image.shape[0] * image.shape[1])
        self.report.count("region_widened", grown)
        return mask

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
"""

from __future__ import annotations

import threading
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from plantscan_core.data import ViewRecord
from plantscan_core.errors import DataError
from plantscan_core.stages import Segmenter, StageParams

# Ratios of L use L + 1: an 8-bit L of 0 (pure black) must not divide by zero, and
# one DN of offset changes a ratio of mid-grey pixels by < 1 %.
_L_OFFSET = 1.0
_NEIGHBOURHOOD = np.ones((3, 3), np.uint8)


def to_lab(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR -> (H, W, 3) float32 LAB on OpenCV's 8-bit scale."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2LAB).astype(np.float32)


def _ratios(lum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L(u,v)/L(u+1,v) and L(u,v)/L(u,v+1); the last column/row repeats its neighbour."""
    l1 = lum + _L_OFFSET
    right = np.empty_like(l1)
    right[:, :-1] = l1[:, :-1] / l1[:, 1:]
    right[:, -1] = right[:, -2] if l1.shape[1] > 1 else 1.0
    down = np.empty_like(l1)
    down[:-1] = l1[:-1] / l1[1:]
    down[-1] = down[-2] if l1.shape[0] > 1 else 1.0
    return right, down


def lab_terms(image_lab: np.ndarray, background_lab: np.ndarray):
    """Δ, Θ, Ψ and the luminance ratio L/L' per pixel (each (H, W) float32)."""
    lum, lum_bg = image_lab[..., 0], background_lab[..., 0]
    delta = np.abs(lum - lum_bg)
    theta = np.abs(image_lab[..., 1] - background_lab[..., 1]) + np.abs(
        image_lab[..., 2] - background_lab[..., 2])
    r, d = _ratios(lum)
    rb, db = _ratios(lum_bg)
    psi = np.abs(r - rb) + np.abs(d - db)
    ratio = (lum + _L_OFFSET) / (lum_bg + _L_OFFSET)
    return delta, theta, psi, ratio


def lab_shadow_score(
    image: np.ndarray,
    background: np.ndarray,
    alpha: float = 0.1,
    beta: float = 0.5,
    gamma: float = 0.4,
) -> np.ndarray:
    """The seed's score Ω per pixel.

    Parameters
    ----------
    image, background : (H, W, 3) uint8 BGR arrays of the same size
    alpha, beta, gamma : weights of luminance, colour and texture differences

    Returns
    -------
    omega : (H, W) float32, in 8-bit LAB units
    """
    delta, theta, psi, _ = lab_terms(to_lab(image), to_lab(background))
    return (alpha * delta + beta * theta + gamma * psi) / (alpha + beta + gamma)


def chromaticity_distance(image: np.ndarray, background: np.ndarray) -> np.ndarray:
    """L1 distance of normalised rgb ``(B, G, R) / (B + G + R)`` per pixel ((H, W) float32).

    A shadow scales the plate's light by a factor: normalised rgb is unchanged
    (also through a power-law tone curve), whereas OpenCV's a*, b* shrink
    towards neutral when a tinted plate darkens; brown soil or a grey-brown
    stem keep a clearly different chromaticity from the plate.
    """
    # Per channel with OpenCV calls: a numpy reduction over the last axis of (H, W, 3)
    # is ~5x slower at 18 MP.
    f = cv2.split(image.astype(np.float32) + 1.0)  # + 1: black pixels must not divide by zero
    fb = cv2.split(background.astype(np.float32) + 1.0)
    inv = cv2.divide(1.0, cv2.add(cv2.add(f[0], f[1]), f[2]))
    inv_b = cv2.divide(1.0, cv2.add(cv2.add(fb[0], fb[1]), fb[2]))
    out = None
    for ch, ch_b in zip(f, fb, strict=True):
        d = cv2.absdiff(cv2.multiply(ch, inv), cv2.multiply(ch_b, inv_b))
        out = d if out is None else cv2.add(out, d)
    return out


def shadow_like(theta, psi, ratio, ratio_min, ratio_max, colour_max, texture_max,
                chroma=None, chroma_max=None) -> np.ndarray:
    """Pixels that look like the plate in a cast shadow ((H, W) bool).

    A shadow darkens the plate by a bounded factor (ambient over ambient plus
    key light: never to black), keeps its colour (small Θ, and small
    chromaticity distance ``chroma`` when given) and its texture ratios (small
    Ψ); dark objects (a black pot) are darker than any shadow, and leaves and
    soil differ in colour.
    """
    out = ((ratio >= ratio_min) & (ratio <= ratio_max) & (theta < colour_max)
           & (psi < texture_max))
    if chroma is not None and chroma_max is not None:
        out &= chroma < chroma_max
    return out


def remove_small_blobs(mask: np.ndarray, min_px: int) -> np.ndarray:
    """Drop 8-connected foreground blobs smaller than ``min_px`` pixels."""
    if min_px <= 1:
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False
    return keep[labels]


def median_background(images: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median of views of one camera and tilt: a background plate estimate.

    Works where the plant covers any pixel in fewer than half of the views
    (a plant turning on a turntable in front of a fixed backdrop); the pot and
    the plant's axis region, always covered, stay in the estimate.
    """
    return np.median(np.stack(images), axis=0).astype(np.uint8)


class LabShadowSegmenter(Segmenter):
    """``lab-shadow``: the seed's LAB score against a background plate."""

    name = "lab-shadow"

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
        background: Literal["plate", "median"] = Field(
            default="plate",
            description="plate: the scan's background view of the same camera and tilt; "
            "median: per-pixel median of the plant views of that camera and tilt "
            "(scans without a plate)")

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        if self.params.alpha + self.params.beta + self.params.gamma <= 0:
            raise DataError("lab-shadow: alpha + beta + gamma must be > 0")
        self._median_cache: dict[tuple[str, int], np.ndarray] = {}
        # segment() runs on several threads at once: one median per camera/tilt, built once.
        self._median_lock = threading.Lock()

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
        delta, theta, psi, ratio = lab_terms(to_lab(image), to_lab(background))
        omega = (p.alpha * delta + p.beta * theta + p.gamma * psi) / (p.alpha + p.beta + p.gamma)
        mask = omega > p.threshold
        if p.edge_fraction > 0:
            # A pixel half covered by a leaf has, after the camera's tone curve, Ω ~ 0.3 of a
            # fully covered neighbour; along a 1 px leaf the neighbours are as weak, so it stays.
            local_max = cv2.dilate(omega, _NEIGHBOURHOOD)
            mask &= omega >= p.edge_fraction * local_max
        if p.suppress_shadows:
            shadow = mask & shadow_like(theta, psi, ratio, p.shadow_ratio_min,
                                        p.shadow_ratio_max, p.shadow_colour_max,
                                        p.shadow_texture_max)
            if p.shadow_chroma_max is not None:
                # Chromaticity only where it can still decide (shadow candidates, a few % of
                # the image): the full-image version is a third of the run time at 18 MP.
                rows, cols = np.nonzero(shadow)
                if rows.size:
                    chroma = chromaticity_distance(image[rows, cols][None],
                                                   background[rows, cols][None])[0]
                    shadow[rows, cols] = chroma < p.shadow_chroma_max
            mask &= ~shadow
        return remove_small_blobs(mask, p.min_blob_px)

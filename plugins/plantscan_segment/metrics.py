"""Mask quality against truth: IoU, thin-structure recall, shadow false positives."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

THIN_WIDTH_PX = 5
"""Structures narrower than this many pixels count as thin (a leaf edge-on, a wheat tip)."""

SHADOW_DARKENING = 0.85
"""A background pixel whose luminance is below this fraction of the plate's is in shadow."""


def thin_structure_mask(truth: np.ndarray, width_px: int = THIN_WIDTH_PX) -> np.ndarray:
    """Truth pixels of structures narrower than ``width_px``: what an opening removes.

    Parameters
    ----------
    truth : (H, W) bool
    width_px : odd int, diameter of the opening's disc

    Returns
    -------
    (H, W) bool
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (width_px, width_px))
    opened = cv2.morphologyEx(truth.astype(np.uint8), cv2.MORPH_OPEN, kernel) > 0
    return truth & ~opened


def shadow_mask(image: np.ndarray, background: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Background pixels (in truth) that are clearly darker than the plate: cast shadow."""
    lum = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)
    lum_bg = cv2.cvtColor(background, cv2.COLOR_BGR2GRAY).astype(np.float32)
    # Keep clear of the plant's rim, where anti-aliasing also darkens pixels.
    near = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return (lum < SHADOW_DARKENING * lum_bg) & ~near


@dataclass
class MaskMetrics:
    iou: float
    thin_recall: float | None
    thin_pixels: int
    shadow_false_positive_rate: float | None
    shadow_pixels: int


def mask_metrics(
    predicted: np.ndarray,
    truth: np.ndarray,
    image: np.ndarray | None = None,
    background: np.ndarray | None = None,
) -> MaskMetrics:
    """Compare one predicted mask with its truth (and, given the images, shadow errors)."""
    predicted = np.asarray(predicted, bool)
    truth = np.asarray(truth, bool)
    if predicted.shape != truth.shape:
        raise ValueError(f"mask shapes differ: {predicted.shape} vs {truth.shape}")
    union = np.count_nonzero(predicted | truth)
    iou = np.count_nonzero(predicted & truth) / union if union else 1.0
    thin = thin_structure_mask(truth)
    n_thin = int(np.count_nonzero(thin))
    thin_recall = np.count_nonzero(predicted & thin) / n_thin if n_thin else None
    shadow_fp, n_shadow = None, 0
    if image is not None and background is not None:
        shadow = shadow_mask(image, background, truth)
        n_shadow = int(np.count_nonzero(shadow))
        shadow_fp = np.count_nonzero(predicted & shadow) / n_shadow if n_shadow else None
    return MaskMetrics(float(iou), thin_recall, n_thin, shadow_fp, n_shadow)


def summarise(metrics: list[MaskMetrics]) -> dict:
    """The ``silhouettes`` section of ``plantscan evaluate`` from per-view metrics.

    Thin recall and shadow false-positive rate are pooled over all views
    (pixel-weighted), so a view with a few thin pixels does not dominate.
    """
    if not metrics:
        return {}
    ious = [m.iou for m in metrics]
    thin_px = sum(m.thin_pixels for m in metrics)
    thin_hit = sum(m.thin_recall * m.thin_pixels for m in metrics if m.thin_recall is not None)
    sh_px = sum(m.shadow_pixels for m in metrics)
    sh_fp = sum(m.shadow_false_positive_rate * m.shadow_pixels for m in metrics
                if m.shadow_false_positive_rate is not None)
    out = {"iou": {"mean": float(np.mean(ious)), "min": float(np.min(ious))},
           "views": len(metrics), "thin_pixels": thin_px, "shadow_pixels": sh_px}
    out["thin_recall"] = thin_hit / thin_px if thin_px else None
    out["shadow_false_positive_rate"] = sh_fp / sh_px if sh_px else None
    return out

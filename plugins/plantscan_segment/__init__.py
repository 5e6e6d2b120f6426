"""Background subtraction: the seed's shadow-robust LAB score, baselines, mask metrics."""

from __future__ import annotations

from plantscan_segment.lab import LabShadowSegmenter, lab_shadow_score
from plantscan_segment.metrics import MaskMetrics, mask_metrics, thin_structure_mask

__all__ = ["LabShadowSegmenter", "lab_shadow_score", "MaskMetrics", "mask_metrics",
           "thin_structure_mask"]

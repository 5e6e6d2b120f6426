"""Registration of the segmenters and the silhouette evaluator."""

from __future__ import annotations

from pathlib import Path

from plantscan_core.hookspecs import hookimpl
from plantscan_segment.baselines import (
    GivenMasksSegmenter,
    GreenSegmenter,
    KNNSegmenter,
    MOG2Segmenter,
    ThresholdSegmenter,
)
from plantscan_segment.lab import LabShadowSegmenter


@hookimpl
def plantscan_register_stages(registry) -> None:
    for cls in (LabShadowSegmenter, ThresholdSegmenter, MOG2Segmenter, KNNSegmenter,
                GivenMasksSegmenter, GreenSegmenter):
        registry.add(cls)


@hookimpl
def plantscan_evaluate(run_dir: Path, truth_dir: Path):
    from plantscan_segment.evaluate import evaluate_silhouettes

    return evaluate_silhouettes(run_dir, truth_dir)

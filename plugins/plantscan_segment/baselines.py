"""Baseline segmenters of the same contract, for comparison with ``lab-shadow``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from plantscan_core.errors import DataError
from plantscan_core.runfolder import read_mask
from plantscan_core.stages import Segmenter, StageParams


def _need_plate(name: str, image, background, view) -> None:
    if background is None:
        where = f"view {view.index} ({view.file})" if view is not None else "this image"
        raise DataError(f"{name}: no background plate for {where} (camera/tilt); capture the "
                        "'background' role")
    if background.shape != image.shape:
        raise DataError(f"{name}: background plate is {background.shape[1]}x"
                        f"{background.shape[0]} but the image is {image.shape[1]}x"
                        f"{image.shape[0]}")


class ThresholdSegmenter(Segmenter):
    """``threshold``: plant where any BGR channel differs from the plate by more than t."""

    name = "threshold"

    class Params(StageParams):
        threshold: int = Field(default=30, ge=0, le=255, description="8-bit DN")

    def segment(self, image, background, view=None):
        _need_plate(self.name, image, background, view)
        diff = cv2.absdiff(image, background).max(axis=2)
        return diff > self.params.threshold


class _OpenCVSubtractor(Segmenter):
    """Feed the plate as the learnt background, then classify the image (no learning)."""

    def _make(self):
        raise NotImplementedError

    def segment(self, image, background, view=None):
        _need_plate(self.name, image, background, view)
        sub = self._make()
        for _ in range(self.params.plate_frames):
            sub.apply(background, learningRate=1.0 / self.params.plate_frames)
        fg = sub.apply(image, learningRate=0.0)
        return fg == 255  # 127 = shadow (detectShadows), 0 = background


class MOG2Segmenter(_OpenCVSubtractor):
    """``mog2``: OpenCV's Gaussian-mixture subtractor with its shadow detector."""

    name = "mog2"

    class Params(StageParams):
        var_threshold: float = Field(default=16.0, gt=0)
        detect_shadows: bool = True
        plate_frames: int = Field(default=5, ge=1, description="times the plate is learnt")

    def _make(self):
        return cv2.createBackgroundSubtractorMOG2(history=self.params.plate_frames,
                                                  varThreshold=self.params.var_threshold,
                                                  detectShadows=self.params.detect_shadows)


class KNNSegmenter(_OpenCVSubtractor):
    """``knn``: OpenCV's k-nearest-neighbour subtractor with its shadow detector."""

    name = "knn"

    class Params(StageParams):
        dist2_threshold: float = Field(default=400.0, gt=0)
        detect_shadows: bool = True
        plate_frames: int = Field(default=5, ge=1)

    def _make(self):
        return cv2.createBackgroundSubtractorKNN(history=self.params.plate_frames,
                                                 dist2Threshold=self.params.dist2_threshold,
                                                 detectShadows=self.params.detect_shadows)


class GivenMasksSegmenter(Segmenter):
    """``given-masks``: masks made elsewhere, ``SCAN/<folder>/<image file stem>.png``."""

    name = "given-masks"

    class Params(StageParams):
        folder: str = "masks"

    def segment(self, image, background, view=None):
        scan = self.context.scan
        if scan is None or view is None:
            raise DataError("given-masks: needs the scan folder and the view")
        path = Path(scan.root) / self.params.folder / f"{Path(view.file).stem}.png"
        if not path.exists():
            raise DataError(f"{path}: mask of view {view.index} ({view.file}) missing")
        mask = read_mask(path)
        if mask.shape != image.shape[:2]:
            raise DataError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} but image "
                            f"{view.file} is {image.shape[1]}x{image.shape[0]}")
        return mask


class GreenSegmenter(Segmenter):
    """``green``: plant where the excess-green index is high; needs no background plate.

    For scans without a background plate (e.g. a phenotyping cabin whose
    photos were all taken with the plant in place).  Per pixel the normalised
    excess green ``ExG = (2G - R - B) / (R + G + B)`` (Woebbecke et al. 1995)
    is compared with ``exg_min``; then only 8-connected components of at least
    ``keep_fraction`` of the largest one are kept (the plant is one big green
    component; the cabin's frames and JPEG noise give scattered specks).
    Non-green organs (flowers, a dry stem) and the pot are not found: the
    price of having no plate.  Measured on the PhenoArch maize photos:
    docs/segmentation.md.
    """

    name = "green"

    class Params(StageParams):
        exg_min: float = Field(default=0.07, ge=-1, le=2,
                               description="plant where (2G - R - B) / (R + G + B) > exg_min")
        keep_fraction: float = Field(default=0.005, ge=0, le=1,
                                     description="drop components smaller than this fraction "
                                     "of the largest (0: keep all)")

    def segment(self, image, background, view=None):
        bgr = image.astype(np.float32)
        b, g, r = cv2.split(bgr)
        total = b + g + r + 1.0  # + 1: black pixels must not divide by zero
        exg = (2.0 * g - r - b) / total
        return keep_large_components(exg > self.params.exg_min, self.params.keep_fraction)


def keep_large_components(mask: np.ndarray, fraction: float) -> np.ndarray:
    """Keep the 8-connected components of ``mask`` with area >= ``fraction`` x the largest."""
    if fraction <= 0:
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask
    area = stats[:, cv2.CC_STAT_AREA]
    keep = area >= fraction * area[1:].max()
    keep[0] = False
    return keep[labels]

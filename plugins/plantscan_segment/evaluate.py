"""``plantscan evaluate``: the ``silhouettes`` section (run masks vs the virtual scanner's)."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import cv2
import numpy as np

from plantscan_core.errors import PlantScanError
from plantscan_core.parallel import thread_map
from plantscan_core.runfolder import read_mask
from plantscan_core.scanfolder import ScanFolder
from plantscan_segment.metrics import MaskMetrics, mask_metrics, summarise


def evaluate_silhouettes(run_dir: Path, truth_dir: Path) -> dict | None:
    masks_dir, truth_masks = Path(run_dir) / "masks", Path(truth_dir) / "masks"
    if not masks_dir.is_dir() or not truth_masks.is_dir():
        return None
    scan = None
    try:
        info = json.loads((Path(run_dir) / "run.json").read_text())
        scan = ScanFolder.open(Path(info["scan"]))
    except (OSError, ValueError, KeyError):
        pass
    views = {v.index: v for v in scan.views} if scan is not None else {}
    plates = {}
    if scan is not None:
        for v in scan.views_by_role("background"):
            plates[(v.camera, v.tilt_index)] = v
    pairs = [(path, truth_masks / path.name) for path in sorted(masks_dir.glob("*.png"))]
    pairs = [(path, truth_path) for path, truth_path in pairs if truth_path.exists()]
    plate_cache: dict[tuple[str, int, int], np.ndarray | None] = {}
    lock = threading.Lock()

    def plate(view, reduce: int) -> np.ndarray | None:
        # One decode per background plate (10 plates serve 360 views at paper-360), not
        # one per view; a plate that cannot be read is remembered as missing.
        key = (view.camera, view.tilt_index, reduce)
        with lock:
            if key in plate_cache:
                return plate_cache[key]
        try:
            image = scan.read_image(plates[(view.camera, view.tilt_index)], reduce=reduce)
        except PlantScanError:
            image = None
        with lock:
            return plate_cache.setdefault(key, image)

    def one(path: Path, truth_path: Path) -> MaskMetrics:
        mask, truth = read_mask(path), read_mask(truth_path)
        reduce = 1
        if mask.shape != truth.shape:
            # Masks made at 1/reduce size (recipe segment.reduce) are compared with the
            # truth at that size: a pixel is plant when most of its footprint is.
            reduce = round(truth.shape[1] / mask.shape[1])
            small = cv2.resize(truth.astype(np.float32), mask.shape[::-1],
                               interpolation=cv2.INTER_AREA)
            truth = small > 0.5
        image = background = None
        view = views.get(int(path.stem)) if path.stem.isdigit() else None
        if view is not None and (view.camera, view.tilt_index) in plates:
            background = plate(view, reduce)
            if background is not None:
                try:
                    image = scan.read_image(view, reduce=reduce)
                except PlantScanError:
                    image = None  # images moved away: IoU and thin recall only
            if image is None or image.shape != background.shape:
                image = background = None
        return mask_metrics(mask, truth, image, background)

    # Decoding (PNG, JPEG) and the OpenCV metrics release the GIL: views on both cores
    # (paper-360 at 18 MP: one view is ~0.3 s, most of it decoding).
    metrics = thread_map(one, [p for p, _ in pairs], [t for _, t in pairs])
    return {"silhouettes": summarise(metrics)} if metrics else None

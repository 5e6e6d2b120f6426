"""Segmentation benchmark: accuracy on virtual scans, real photos, undistortion, speed.

Run ``python benchmarks/segmentation.py [--size 1200x800] [--views 4] [--scans DIR]``.
Writes nothing by itself; the figures go into docs/benchmarks/segmentation.md by hand.

1. Virtual plastic-dicot and wheat scans with hard shadows: every segmenter on
   the same images, against the exact truth masks (IoU, thin recall, shadow
   false-positive rate).
2. Real PhenoArch photos (no background plate): ``lab-shadow`` with the
   per-pixel median plate, and ``green``, against the shipped silhouettes.
3. Undistortion: IoU of truth masks undistorted then re-distorted (the loss a
   pipeline that carves undistorted masks pays on top of the segmentation).
4. Speed at 18 MP, one thread: megapixels per second per core.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import cv2
import numpy as np
from plantscan_segment.baselines import (
    GreenSegmenter,
    KNNSegmenter,
    MOG2Segmenter,
    ThresholdSegmenter,
)
from plantscan_segment.lab import LabShadowSegmenter, median_background
from plantscan_segment.metrics import mask_metrics, summarise
from plantscan_segment.undistort import distort_mask, undistort_mask

from plantscan_core.data import CameraModel
from plantscan_core.pipeline import read_mask
from plantscan_core.scanfolder import ScanFolder

REAL = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / \
    "phenoarch_maize_plant1"


def segmenters():
    return {
        "lab-shadow": LabShadowSegmenter(),
        "lab-shadow (seed score only, t=8)": LabShadowSegmenter(
            LabShadowSegmenter.Params(suppress_shadows=False, min_blob_px=0)),
        "threshold": ThresholdSegmenter(),
        "mog2": MOG2Segmenter(),
        "knn": KNNSegmenter(),
    }


def virtual_scan(root: pathlib.Path, preset: str, size: tuple[int, int], views: int):
    from plantscan_sim import make_scan

    d = root / f"{preset}-{size[0]}x{size[1]}-{views}"
    if (d / "views.jsonl").exists() and (d / "ground_truth" / "masks").is_dir():
        return ScanFolder.open(d)
    return make_scan(d, preset=preset, image_size=size, images_per_revolution=views,
                     roles=["background", "plant"])


def accuracy(scan: ScanFolder) -> dict[str, dict]:
    plates = {(v.camera, v.tilt_index): scan.read_image(v)
              for v in scan.views_by_role("background")}
    per = {name: [] for name in segmenters()}
    for v in scan.views_by_role("plant"):
        img, bg = scan.read_image(v), plates[(v.camera, v.tilt_index)]
        truth = read_mask(scan.ground_truth_dir / "masks" / f"{v.index:05d}.png")
        for name, seg in segmenters().items():
            per[name].append(mask_metrics(seg.segment(img, bg, v), truth, img, bg))
    return {name: summarise(m) for name, m in per.items()}


def undistortion_loss(scan: ScanFolder) -> dict[str, float]:
    """Resampling cost of undistorted masks: distort(undistort(truth)) vs truth.

    Returns the mean IoU, the worst view's fraction of thin-structure pixels
    kept, and the mean number of pixels the undistortion itself changes (how
    far the lens moves the silhouette at all).
    """
    from plantscan_segment.metrics import thin_structure_mask

    cams = {}
    for line in (scan.ground_truth_dir / "cameras.jsonl").read_text().splitlines():
        d = json.loads(line)
        cams[d["index"]] = CameraModel.from_dict(d["camera"]["model"])
    ious, thin_kept, moved = [], [], []
    for v in scan.views_by_role("plant"):
        truth = read_mask(scan.ground_truth_dir / "masks" / f"{v.index:05d}.png")
        und = undistort_mask(truth, cams[v.index])
        back = distort_mask(und, cams[v.index])
        thin = thin_structure_mask(truth)
        ious.append(np.count_nonzero(back & truth) / np.count_nonzero(back | truth))
        thin_kept.append(np.count_nonzero(back & thin) / max(np.count_nonzero(thin), 1))
        moved.append(np.count_nonzero(und ^ truth))
    return {"iou": float(np.mean(ious)), "thin_kept_min": float(np.min(thin_kept)),
            "pixels_changed_by_undistortion": float(np.mean(moved))}


def real_photos() -> dict | None:
    raw, binary = REAL / "raw" / "side", REAL / "bin" / "side"
    if not raw.is_dir():
        return None
    names = sorted(p.stem for p in raw.glob("*.jpg"))
    images = [cv2.imread(str(raw / f"{n}.jpg")) for n in names]
    plate = median_background(images)
    out = {}
    for label, seg, bg in [
        ("lab-shadow, median plate", LabShadowSegmenter(), plate),
        ("threshold, median plate", ThresholdSegmenter(), plate),
        ("green (no plate)", GreenSegmenter(), None),
    ]:
        ious, precision, recall = [], [], []
        for n, img in zip(names, images, strict=True):
            truth = cv2.imread(str(binary / f"{n}.png"), cv2.IMREAD_GRAYSCALE) > 0
            m = seg.segment(img, bg)
            inter = np.count_nonzero(m & truth)
            ious.append(inter / np.count_nonzero(m | truth))
            precision.append(inter / max(np.count_nonzero(m), 1))
            recall.append(inter / np.count_nonzero(truth))
        out[label] = (float(np.mean(ious)), float(np.min(ious)), float(np.mean(precision)),
                      float(np.mean(recall)))
    return out


def speed(size=(5184, 3456), repeats=3) -> dict[str, float]:
    """Megapixels per second of CPU time on one thread (one core) at 18 MP.

    Process CPU time, not wall time: on a shared machine the wall clock also
    counts other people's work; with one OpenCV thread (numpy is single
    threaded) CPU seconds are core seconds.
    """
    rng = np.random.default_rng(0)
    h, w = size[1], size[0]
    bg = np.full((h, w, 3), (200, 195, 190), np.uint8)
    bg = cv2.add(bg, rng.integers(0, 6, (h, w, 3), dtype=np.uint8))
    img = bg.copy()
    cv2.ellipse(img, (w // 2, h // 2), (w // 6, h // 4), 30, 0, 360, (40, 140, 50), -1)
    img[:, : w // 3] = (img[:, : w // 3] * 0.6).astype(np.uint8)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = {}
        for name, seg in {**segmenters(), "green": GreenSegmenter()}.items():
            seg.segment(img, bg)
            t0 = time.process_time()
            for _ in range(repeats):
                seg.segment(img, bg)
            out[name] = w * h * 1e-6 * repeats / (time.process_time() - t0)
        return out
    finally:
        cv2.setNumThreads(threads)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1200x800", help="virtual image size WxH")
    ap.add_argument("--views", type=int, default=4, help="plant views per revolution")
    ap.add_argument("--scans", default="/tmp/plantscan-bench-segmentation",
                    help="where the virtual scans are rendered (reused when present)")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--only-speed", action="store_true")
    args = ap.parse_args()
    size = tuple(int(x) for x in args.size.split("x"))
    root = pathlib.Path(args.scans)
    if args.only_speed:
        print_speed()
        return

    print(f"## Virtual scans {size[0]}x{size[1]}, {args.views} views x 2 cameras\n")
    print("| scan | segmenter | IoU mean | IoU min | thin recall | shadow FP rate |")
    print("|---|---|---|---|---|---|")
    losses = {}
    for preset in ("plastic-dicot", "wheat"):
        scan = virtual_scan(root, preset, size, args.views)
        for name, s in accuracy(scan).items():
            print(f"| {preset} | {name} | {s['iou']['mean']:.4f} | {s['iou']['min']:.4f} | "
                  f"{s['thin_recall']:.4f} | {s['shadow_false_positive_rate']:.4f} |")
        losses[preset] = undistortion_loss(scan)
    print("\n## Undistort then re-distort the truth masks (mean IoU vs truth)\n")
    for preset, loss in losses.items():
        print(f"- {preset}: IoU {loss['iou']:.5f}, thin pixels kept (worst view) "
              f"{loss['thin_kept_min']:.4f}, pixels the undistortion changes "
              f"{loss['pixels_changed_by_undistortion']:.0f} per view")

    real = real_photos()
    print("\n## Real PhenoArch side photos vs shipped silhouettes\n")
    if real is None:
        print("(../shared/data/phenoarch_maize_plant1 absent: skipped)")
    else:
        print("| method | IoU mean | IoU min | precision | recall |")
        print("|---|---|---|---|---|")
        for label, (iou, iou_min, prec, rec) in real.items():
            print(f"| {label} | {iou:.4f} | {iou_min:.4f} | {prec:.4f} | {rec:.4f} |")

    if not args.skip_speed:
        print_speed()


def print_speed() -> None:
    print("\n## Speed at 18 MP (5184x3456), one thread, CPU time\n")
    print("| segmenter | MP/s per core |")
    print("|---|---|")
    for name, mps in speed().items():
        print(f"| {name} | {mps:.1f} |", flush=True)


if __name__ == "__main__":
    main()

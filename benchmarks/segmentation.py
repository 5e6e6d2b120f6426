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
5. ``lab-shadow`` fast path against its plain reference in the same run, at the
   pipeline's 4.5 MP (18 MP decoded at 1/2) and at 18 MP, on a synthetic scene
   and on virtual-scanner views (JPEG q95 round trip), 1 and 2 threads.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
from concurrent.futures import ThreadPoolExecutor

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
from plantscan_core.runfolder import read_mask
from plantscan_core.scanfolder import ScanFolder

REAL = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / \
    "phenoarch_maize_plant1"


def segmenters():
    return {
        "lab-shadow": LabShadowSegmenter(),
        "lab-shadow (reference implementation)": LabShadowSegmenter(
            LabShadowSegmenter.Params(implementation="reference")),
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


def synthetic_scene(size=(5184, 3456)) -> tuple[np.ndarray, np.ndarray]:
    """(image, plate), (H, W, 3) uint8: a noisy grey plate, a green ellipse and a hard
    shadow over the left third of the frame (a pessimistic share of shadow)."""
    rng = np.random.default_rng(0)
    h, w = size[1], size[0]
    bg = np.full((h, w, 3), (200, 195, 190), np.uint8)
    bg = cv2.add(bg, rng.integers(0, 6, (h, w, 3), dtype=np.uint8))
    img = bg.copy()
    cv2.ellipse(img, (w // 2, h // 2), (w // 6, h // 4), 30, 0, 360, (40, 140, 50), -1)
    img[:, : w // 3] = (img[:, : w // 3] * 0.6).astype(np.uint8)
    return img, bg


def speed(size=(5184, 3456), repeats=3) -> dict[str, float]:
    """Megapixels per second of CPU time on one thread (one core) at 18 MP.

    Process CPU time, not wall time: on a shared machine the wall clock also
    counts other people's work; with one OpenCV thread (numpy is single
    threaded) CPU seconds are core seconds.
    """
    img, bg = synthetic_scene(size)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = {}
        for name, seg in {**segmenters(), "green": GreenSegmenter()}.items():
            seg.segment(img, bg)
            t0 = time.process_time()
            for _ in range(repeats):
                seg.segment(img, bg)
            out[name] = img.shape[0] * img.shape[1] * 1e-6 * repeats / (time.process_time() - t0)
        return out
    finally:
        cv2.setNumThreads(threads)


def virtual_views(root: pathlib.Path, size: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(image, plate) of every plant view of a 2-view-per-camera dicot scan at ``size``,
    through a JPEG q95 round trip (the virtual scanner's default image format)."""
    scan = virtual_scan(root, "plastic-dicot", size, 2)

    def jpeg(a):
        return cv2.imdecode(cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, 95])[1],
                            cv2.IMREAD_COLOR)

    plates = {(v.camera, v.tilt_index): jpeg(scan.read_image(v))
              for v in scan.views_by_role("background")}
    return [(jpeg(scan.read_image(v)), plates[(v.camera, v.tilt_index)])
            for v in scan.views_by_role("plant")]


def lab_shadow_speed(pairs, threads: int, rounds: int = 3) -> dict[str, dict[str, float]]:
    """Reference, fast and fast-in-the-plant's-region ``lab-shadow`` on the same pairs, interleaved.

    Each round segments every pair with ``threads`` threads (one OpenCV thread
    each, as images are the unit of parallelism); one segmenter per
    implementation serves all rounds, so the fast path's plate conversion is paid
    once per plate as in the pipeline. Returns per implementation: ``mp_per_cpu_s``
    (megapixels per CPU second = per core), ``mp_per_wall_s`` and ``cpu_s`` per
    image (median round).
    """
    mp = sum(img.shape[0] * img.shape[1] for img, _ in pairs) * 1e-6
    segs = {name: LabShadowSegmenter(LabShadowSegmenter.Params(**params)) for name, params in (
        ("reference", {"implementation": "reference"}),
        ("fast, whole image", {"region": "whole"}),
        ("fast, region: plant (default)", {}))}
    per: dict[str, list[tuple[float, float]]] = {impl: [] for impl in segs}
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(threads) as pool:
            for r in range(rounds + 1):
                for impl, seg in segs.items():
                    c0, w0 = time.process_time(), time.perf_counter()
                    list(pool.map(lambda pair, seg=seg: seg.segment(*pair), pairs))
                    if r:  # round 0 warms up (and converts the plates)
                        per[impl].append((time.process_time() - c0, time.perf_counter() - w0))
    finally:
        cv2.setNumThreads(opencv_threads)
    out = {}
    for impl, runs in per.items():
        cpu = float(np.median([c for c, _ in runs]))
        wall = float(np.median([w for _, w in runs]))
        out[impl] = {"mp_per_cpu_s": mp / cpu, "mp_per_wall_s": mp / wall,
                     "cpu_s_per_image": cpu / len(pairs)}
    return out


def print_lab_shadow_speed(root: pathlib.Path) -> None:
    print(f"\n## lab-shadow: fast path vs reference, same run (load {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores)\n")
    print("| images | threads | implementation | MP/s per core (CPU) | MP/s wall | "
          "CPU s per image |")
    print("|---|---|---|---|---|---|")
    cases = [
        ("synthetic 4.5 MP (1/3 in shadow)", [synthetic_scene((2592, 1728))] * 4),
        ("virtual dicot 4.5 MP, JPEG", virtual_views(root, (2592, 1728))),
        ("synthetic 18 MP (1/3 in shadow)", [synthetic_scene()] * 2),
    ]
    for label, pairs in cases:
        for threads in (1, 2):
            for impl, s in lab_shadow_speed(pairs, threads).items():
                print(f"| {label} | {threads} | {impl} | {s['mp_per_cpu_s']:.1f} | "
                      f"{s['mp_per_wall_s']:.1f} | {s['cpu_s_per_image']:.3f} |", flush=True)


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
        print_lab_shadow_speed(root)
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
        print_lab_shadow_speed(root)
        print_speed()


def print_speed() -> None:
    print("\n## Speed at 18 MP (5184x3456), one thread, CPU time\n")
    print("| segmenter | MP/s per core |")
    print("|---|---|")
    for name, mps in speed().items():
        print(f"| {name} | {mps:.1f} |", flush=True)


if __name__ == "__main__":
    main()

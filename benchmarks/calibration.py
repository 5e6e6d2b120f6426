"""Calibration benchmark: accuracy of the seed's initialisation vs the Ceres refinement, and
speed of pyramid vs plain full-resolution chessboard detection on 18 MP images.

    python benchmarks/calibration.py [--images 72] [--plain-images 8] [--out DIR] [--quick]
                                     [--accuracy-only] [--speed-only]

Everything is measured in one run, side by side; the markdown table printed at
the end is what docs/benchmarks/calibration.md holds.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    import plantscan_calib  # noqa: F401
except ImportError:  # editable install older than the plugin folder
    sys.path.insert(0, str(ROOT / "plugins"))

from plantscan_calib.detect import BoardSpec, detect_chessboard, detect_chessboard_plain  # noqa: E402
from plantscan_calib.evaluate import compare_calibrations  # noqa: E402
from plantscan_calib.plugin import detect_views  # noqa: E402
from plantscan_calib.solver import SolveOptions, calibrate_turntable  # noqa: E402
from plantscan_calib.synthetic import (  # noqa: E402
    make_rig,
    synthetic_detections,
    volume_points,
    write_board_scan,
)

TARGETS = {"one 9x6-corner board (250x175 mm)": {},
           "two 13x10-corner boards (350x275 mm, back to back; recommended)": dict(
               boards=2, cols=13, rows=10)}


def accuracy_synthetic(seeds=(0, 1, 2, 3)) -> list[dict]:
    """paper-360 (2 cameras x 5 tilts x 36 stops), 0.2 px noise, 1 % corners off by 3-15 px."""
    rows = []
    for target, kw in TARGETS.items():
        rig = make_rig(tilts_deg=(0.0, 10.0, 20.0, 30.0, 40.0), **kw)
        sizes = {c: (m.width, m.height) for c, m in rig.truth.models.items()}
        for seed in seeds:
            dets = synthetic_detections(rig, np.arange(0, 360, 10.0), noise_px=0.2,
                                        corrupt_fraction=0.01, seed=seed)
            opt = SolveOptions(cross_validate=False)
            for label, o in (("seed init (plane+circle)", replace(opt, refine=False)),
                             ("refined, free pose per (camera, tilt)",
                              replace(opt, joint_tilt_axis=False)),
                             ("refined, joint tilt-arm model", opt)):
                t0 = time.process_time()
                cal = calibrate_turntable(dets, rig.boards, sizes, rig.truth.tilts_deg, o)
                dt = time.process_time() - t0
                e = compare_calibrations(cal, rig.truth, volume_points())
                sig = cal.quality.get("sigma", {}).get("poses", {})
                rows.append({"data": f"{target}, seed {seed}", "method": label,
                             "centre_mm": e["camera_centre_error_mm"]["mean"],
                             "rot_deg": e["rotation_error_deg"]["max"],
                             "vol_px": e["volume_reprojection_px_rms"], "seconds": dt,
                             "views": len(dets),
                             "sig_c": np.mean([v["centre_mm"] for v in sig.values()])
                             if sig else float("nan"),
                             "sig_r": max((v["rotation_deg"] for v in sig.values()),
                                          default=float("nan"))})
    return rows


def accuracy_real() -> list[dict]:
    """Real PhenoArch corners: mean reprojection over all corners (no truth there)."""
    from plantscan_calib.phenoarch import load_corners, load_original_calibration, project_original

    data = ROOT.parent / "shared" / "data" / "phenoarch_maize_plant1"
    if not data.exists():
        return []
    dets, boards, sizes = load_corners(data / "chessboard" / "points")
    pp = {c: (w / 2.0, h / 2.0) for c, (w, h) in sizes.items()}
    base = SolveOptions(principal_points=pp, fix_distortion=True, fit_angle_scale=True,
                        min_views=1, max_rejected_fraction=0.12, cross_validate=False,
                        covariance=False)
    rows = []
    for label, o in (
            ("seed init (plane+circle)", replace(base, refine=False, fix_principal_point=True)),
            ("refined: single f, pp fixed (the seed's model)",
             replace(base, fix_principal_point=True)),
            ("refined: f + aspect, pp fixed (the original's model)",
             replace(base, fix_principal_point=True, fit_aspect=True)),
            ("refined: f + aspect, pp fitted (tests/calib/test_realdata.py)",
             replace(base, fit_aspect=True)),
            ("refined: f + aspect, pp, d1, d2 fitted", replace(
                base, fit_aspect=True, fix_distortion=False, distortion_prior=None))):
        t0 = time.process_time()
        cal = calibrate_turntable(dets, boards, sizes, {0: 0.0}, o, symmetric_boards=True)
        dt = time.process_time() - t0
        bw = {int(b): (np.array(v["R"]), np.array(v["t"]))
              for b, v in cal.quality["boards"].items()}
        err = np.concatenate([np.linalg.norm(cal.camera_at(d.camera, 0, d.angle_deg).project(
            boards[d.board] @ bw[d.board][0].T + bw[d.board][1]) - d.uv, axis=1) for d in dets])
        rows.append({"method": label, "mean_px": float(err.mean()),
                     "median_px": float(np.median(err)), "seconds": dt,
                     "kept": 1.0 - cal.quality.get("rejected_fraction", 0.0)})
    orig, ob = load_original_calibration(data / "calibration" / "calibration_cameras.json", boards)
    err = np.concatenate([np.linalg.norm(project_original(orig, ob, d, boards) - d.uv, axis=1)
                          for d in dets])
    rows.append({"method": "original software (fx, fy; pp at centre)",
                 "mean_px": float(err.mean()), "median_px": float(np.median(err)),
                 "seconds": float("nan"), "kept": float("nan")})
    return rows


def detection_speed(out: Path, n_images: int, n_plain: int) -> dict:
    """72 rendered 18 MP calibration images: pyramid detection + solve vs plain detection."""
    import cv2

    from plantscan_core.scanfolder import ScanFolder

    rig = make_rig(image_size=(5184, 3456), tilts_deg=(0.0,))
    angles = np.arange(0.0, 360.0, 360.0 / (n_images // 2))
    root = out / "scan-18mp"
    if not (root / "scan.yaml").exists():
        t0 = time.perf_counter()
        write_board_scan(root, rig, angles, px_per_mm=10.0)
        print(f"rendered {n_images} images in {time.perf_counter() - t0:.0f} s", flush=True)
    scan = ScanFolder.open(root)
    views = scan.views_by_role("calibration")
    spec = BoardSpec("chessboard", 9, 6, 25.0)
    t0 = time.process_time()
    dets, sizes, found = detect_views(scan, views, spec, 800, workers=1)
    t_detect = time.process_time() - t0
    t0 = time.process_time()
    cal = calibrate_turntable(dets, {0: spec.object_points()}, sizes, {0: 0.0},
                              SolveOptions(cross_validate=False))
    t_solve = time.process_time() - t0
    err = compare_calibrations(cal, rig.truth, volume_points())
    # Plain full-resolution detection on a subset: half with a board, half without.
    with_board = {d.view_index for d in dets}
    pick = [v for v in views if v.index in with_board][: n_plain // 2] + \
        [v for v in views if v.index not in with_board][: n_plain - n_plain // 2]
    t_pyr, t_plain, agree = [], [], []
    for v in pick:
        gray = cv2.imread(str(scan.path_of(v)), cv2.IMREAD_GRAYSCALE)
        t0 = time.process_time()
        a = detect_chessboard(gray, 9, 6, 800)
        t_pyr.append(time.process_time() - t0)
        t0 = time.process_time()
        b = detect_chessboard_plain(gray, 9, 6)
        t_plain.append(time.process_time() - t0)
        if a is not None and b is not None:
            agree.append(float(np.abs(a - b).max()))
        elif (a is None) != (b is None):
            agree.append(float("inf"))
    frac = len(with_board) / len(views)
    per_pyr = [np.mean([t for t, v in zip(t_pyr, pick, strict=True)
                        if (v.index in with_board) == k]) for k in (True, False)]
    per_plain = [np.mean([t for t, v in zip(t_plain, pick, strict=True)
                          if (v.index in with_board) == k]) for k in (True, False)]
    return {"images": len(views), "found": len(dets), "t_detect_all": t_detect,
            "t_solve": t_solve, "pyr_board_s": per_pyr[0], "pyr_empty_s": per_pyr[1],
            "plain_board_s": per_plain[0], "plain_empty_s": per_plain[1],
            "plain_72_est_s": len(views) * (frac * per_plain[0] + (1 - frac) * per_plain[1]),
            "max_diff_px": max(agree) if agree else float("nan"), "n_plain": len(pick),
            "centre_mm": err["camera_centre_error_mm"]["mean"],
            "vol_px": err["volume_reprojection_px_rms"], "rms_px": cal.quality["rms_px"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=72)
    ap.add_argument("--plain-images", type=int, default=8)
    ap.add_argument("--out", type=Path, default=None, help="keep rendered images here")
    ap.add_argument("--quick", action="store_true", help="accuracy only, one seed")
    ap.add_argument("--speed-only", action="store_true", help="detection speed only")
    ap.add_argument("--accuracy-only", action="store_true", help="accuracy only, all seeds")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}", flush=True)
    lines = [] if args.speed_only else [
        "### Accuracy: seed initialisation vs refinement (same detections)", "",
        "| data | method | centre err mean (mm) | rotation err max (deg) | "
        "volume reproj RMS (px) | Ceres 1σ centre mean (mm) / rotation max (deg) | "
        "CPU time (s) |", "|---|---|---|---|---|---|---|"]
    for r in [] if args.speed_only else accuracy_synthetic((0,) if args.quick else (0, 1, 2, 3)):
        lines.append(f"| {r['data']} ({r['views']} board views) | {r['method']} | "
                     f"{r['centre_mm']:.3f} | {r['rot_deg']:.4f} | {r['vol_px']:.3f} | "
                     f"{r['sig_c']:.3f} / {r['sig_r']:.4f} | {r['seconds']:.1f} |")
        print(lines[-1], flush=True)
    real = [] if args.speed_only else accuracy_real()
    if real:
        lines += ["", "### Real PhenoArch corners (4416 corners, 92 views, two boards)", "",
                  "| method | mean reproj, all corners (px) | median (px) | corners kept | "
                  "CPU time (s) |", "|---|---|---|---|---|"]
        for r in real:
            lines.append(f"| {r['method']} | {r['mean_px']:.4f} | {r['median_px']:.4f} | "
                         f"{r['kept']:.3f} | {r['seconds']:.1f} |")
            print(lines[-1], flush=True)
    if not (args.quick or args.accuracy_only):
        out = args.out or Path(tempfile.mkdtemp(prefix="calib-bench-"))
        s = detection_speed(out, args.images, args.plain_images)
        lines += ["", f"### Detection at 18 MP (5184x3456, {s['images']} images, board in "
                  f"{s['found']})", "",
                  "CPU seconds (process time: robust to other jobs on a shared machine).", "",
                  "| step | pyramid (top <= 800 px) | plain full-res findChessboardCorners |",
                  "|---|---|---|",
                  f"| per image with a board (s) | {s['pyr_board_s']:.2f} | "
                  f"{s['plain_board_s']:.2f} |",
                  f"| per image without a board (s) | {s['pyr_empty_s']:.2f} | "
                  f"{s['plain_empty_s']:.2f} |",
                  f"| all {s['images']} images, detection incl. decode (s) | "
                  f"{s['t_detect_all']:.1f} | ~{s['plain_72_est_s']:.0f} (from {s['n_plain']} "
                  "images) |",
                  f"| solve (s) | {s['t_solve']:.1f} | - |",
                  f"| max corner difference (px) | {s['max_diff_px']:.3f} | |",
                  "", f"Calibration from these images: corner RMS {s['rms_px']:.3f} px, "
                  f"camera centre error {s['centre_mm']:.3f} mm, volume reprojection "
                  f"{s['vol_px']:.3f} px RMS."]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

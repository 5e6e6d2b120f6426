"""Structure-from-motion calibration: the turntable-constrained ``sfm`` calibrator beside
COLMAP's own unconstrained incremental reconstruction, on the same features and matches.

    python benchmarks/sfm.py --scan /work/cache/sfm24/scans/dicot-72 --plate-diameter 400 \
        [--chessboard] [--no-colmap] [--principal-point-from-truth] [--compare-track-check] \
        [--board-view] [--json out.json]

Per scan: SIFT extraction and matching once (timed, shared by both), then

* ``sfm``: initialisation + turntable bundle adjustment (``solve_tracks``); with
  ``--principal-point-from-truth`` a second solve on the same tracks with the lens's
  principal point given (``principal_point_px``, as a lab would from a one-off lens
  calibration; the virtual scanner's, on a virtual scan);
  with ``--compare-track-check`` each variant also with the per-track consistency
  check (``reject_sigma`` 3; off by default); with ``--board-view`` one more with one board
  photo per camera (``board``: the scan's calibration photos, the recipe's board);
* COLMAP: ``pycolmap.incremental_mapping`` on the same database (a pose per
  photo, a RADIAL camera per scanner camera), its registered photos and mean
  reprojection error;
* on a virtual scan, the ``sfm`` result against the truth
  (``plantscan_calib.evaluate.compare_calibrations``) and, with
  ``--chessboard``, the chessboard calibrator's on the same scan.

Wall and CPU seconds are both reported: the machine is shared, and CPU seconds
(all threads of this process) do not grow with other people's load.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "plugins"))


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def colmap_baseline(db: Path, images: Path, out: Path, threads: int) -> dict:
    """COLMAP's incremental mapper on ``db``: registered photos, reprojection error."""
    import pycolmap

    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    opt = pycolmap.IncrementalPipelineOptions()
    opt.num_threads = threads
    recs, t = _timed(lambda: pycolmap.incremental_mapping(db, images, out, opt))
    if not recs:
        return {"registered_views": 0, **t}
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    return {"registered_views": int(best.num_reg_images()), "models": len(recs),
            "points": int(best.num_points3D()),
            "mean_reprojection_px": float(best.compute_mean_reprojection_error()), **t}


def run_scan(scan_dir: Path, plate_mm: float, work: Path, threads: int, chessboard: bool,
             colmap: bool = True, pp_from_truth: bool = False, compare_reject: bool = False,
             board: bool = False) -> dict:
    from plantscan_calib.evaluate import compare_calibrations, plant_volume_points
    from plantscan_sfm.calibrate import (
        SfmError,
        SfmSettings,
        _image_sizes,
        match_scan,
        solve_tracks,
    )

    from plantscan_core.data import Calibration
    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(scan_dir)
    views = scan.views_by_role("plant")
    work.mkdir(parents=True, exist_ok=True)
    st = SfmSettings(plate_diameter_mm=plate_mm, threads=threads, workspace=work)
    (sv, db, tracks), t_match = _timed(lambda: match_scan(scan, views, st, work))
    sizes = _image_sizes(scan, views)
    row = {"scan": str(scan_dir), "photos": len(views),
           "image_size": sorted({f"{w}x{h}" for w, h in sizes.values()}),
           "features_and_matching": {**t_match, **st.timings, **tracks.stats}}
    truth_path = scan_dir / "ground_truth" / "calibration.yaml"
    truth = Calibration.load(truth_path) if truth_path.exists() else None
    pts = plant_volume_points(scan_dir / "ground_truth") if truth is not None else None
    variants = {"sfm": {}}
    if compare_reject:
        variants["sfm_track_check"] = {"reject_sigma": 3.0}
    if pp_from_truth and truth is not None:
        pp = {c: (m.cu, m.cv) for c, m in truth.models.items()}
        variants["sfm_principal_point_given"] = {"principal_point_px": pp}
        if compare_reject:
            variants["sfm_principal_point_given_track_check"] = {
                "principal_point_px": pp, "reject_sigma": 3.0}
    if board and scan.views_by_role("calibration"):
        from plantscan_sfm.calibrate import detect_board_views

        p = scan.recipe_dict.get("calibrate", {}).get("params", {})
        spec = {"kind": p.get("board", "chessboard"), "cols": p["cols"], "rows": p["rows"],
                "square_mm": p["square_mm"]}
        corners = detect_board_views(scan, SfmSettings(board=spec, threads=threads))
        row["board_photos_found"] = {c: len(v) for c, v in corners.items()}
        variants["sfm_one_board_view"] = {"board": spec, "board_corners": corners}
        variants["sfm_one_board_view_on_turntable"] = {"board": spec, "board_corners": corners,
                                                       "board_on_turntable": True}
        if compare_reject:
            variants["sfm_one_board_view_track_check"] = {
                "board": spec, "board_corners": corners, "reject_sigma": 3.0}
    cal = None
    for name, extra in variants.items():
        sv_st = SfmSettings(plate_diameter_mm=plate_mm, threads=threads, workspace=work,
                            **extra)
        try:
            c, t_sfm = _timed(lambda s=sv_st: solve_tracks(sv, tracks, sizes, s))
        except SfmError as exc:  # a named failure is a result too
            row[name] = {"error": str(exc)}
            continue
        q = c.quality
        row[name] = {**t_sfm, **sv_st.timings, "registered_views": q["registered_views"],
                     "rms_px": q["rms_px"], "observations": q["observations"],
                     "tracks": q["tracks"], "scale": q["scale"],
                     "inconsistent_observations": q.get("inconsistent_observations"),
                     "board_views": q.get("board_views"),
                     "principal_point_px": {cm: (m.cu, m.cv) for cm, m in c.models.items()},
                     "principal_point_sigma_px": {cm: {k: v for k, v in sd.items()
                                                       if k in ("cu", "cv")}
                                                  for cm, sd in q["sigma"]["models"].items()}}
        if truth is not None:
            row[name]["vs_truth"] = _summary(compare_calibrations(c, truth, pts), c, truth)
        cal = c if name == "sfm" else cal
    if colmap:
        row["colmap"] = colmap_baseline(db, work / "images", work / "colmap", threads)
    if truth is not None and chessboard and scan.views_by_role("calibration"):
        from plantscan_calib.plugin import TurntableCalibrator

        recipe = scan.recipe_dict.get("calibrate", {}).get("params", {})
        board = TurntableCalibrator(TurntableCalibrator.Params(**recipe))
        cb, t_cb = _timed(lambda: board.calibrate(scan))
        row["chessboard"] = {**t_cb, "vs_truth": _summary(
            compare_calibrations(cb, truth, pts), cb, truth)}
    if cal is not None:
        cal.save(work / "calibration-sfm.yaml")
    return row


def _summary(res: dict, est, truth) -> dict:
    focal = {c: 100.0 * (est.models[c].f / truth.models[c].f - 1.0) for c in est.models
             if c in truth.models}
    return {"centre_mm": {k: v["centre_error_mm"] for k, v in res["per_pose"].items()},
            "rotation_deg": {k: v["rotation_error_deg"] for k, v in res["per_pose"].items()},
            "focal_error_pct": focal,
            "volume_reprojection_px_rms": res["volume_reprojection_px_rms"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scan", action="append", required=True, help="scan folder (repeatable)")
    ap.add_argument("--plate-diameter", type=float, default=400.0, help="mm")
    ap.add_argument("--work", default="/tmp/plantscan-bench-sfm", help="workspaces")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--chessboard", action="store_true",
                    help="also calibrate from the scan's board views (virtual scans)")
    ap.add_argument("--no-colmap", action="store_true",
                    help="skip COLMAP's own mapper (31+ min on the paper-72 dicot)")
    ap.add_argument("--principal-point-from-truth", action="store_true",
                    help="also solve with the virtual lens's principal point given")
    ap.add_argument("--compare-track-check", action="store_true",
                    help="also solve each variant with the per-track consistency check "
                    "(reject_sigma 3; the default is off)")
    ap.add_argument("--board-view", action="store_true",
                    help="also solve with one board photo per camera (the scan's calibration "
                    "photos, the recipe's board; the most oblique one per camera)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    rows = []
    for s in args.scan:
        p = Path(s)
        rows.append(run_scan(p, args.plate_diameter, Path(args.work) / p.name, args.threads,
                             args.chessboard, not args.no_colmap,
                             args.principal_point_from_truth, args.compare_track_check,
                             args.board_view))
        print(json.dumps(rows[-1], indent=1, default=str), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())

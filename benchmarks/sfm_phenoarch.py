"""The ``sfm`` calibrator on real photos: PhenoArch maize plant 1 (issue #24).

Another lab's turntable (``../shared/data/phenoarch_maize_plant1``, its README):
one side camera 5.4 m from the axis, 12 plant photos 30 degrees apart, no printed
plate, no markers, a static cabin behind the plant.  The lab's own chessboard
calibration of the same rig is the reference.  What is measured, whatever it shows:

1. ``sfm`` as a new user would run it (focal length free, scale from the camera's
   distance to the axis);
2. the focal length given (the lab's value, as a lens's nominal focal length);
3. the lab's own poses given as priors (a rig that knows its poses);
4. the verified two-view matches scored against the lab's calibration: how many are
   of one 3D point (triangulated with the lab's cameras, reprojected within 3 px in
   both photos), by the angle between the two photos.

When a run calibrates, its poses and focal length are compared with the lab's
(camera distance to the axis, elevation, focal length), the lab's chessboard
corners are reprojected with it (each board's pose fitted), and the hull of the 12
side silhouettes is scored by IoU against the one from the lab's calibration::

    python benchmarks/sfm_phenoarch.py          # writes docs/benchmarks/sfm_phenoarch.md
"""

from __future__ import annotations

import argparse
import math
import shutil
import sqlite3
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "phenoarch_maize_plant1"
PAIR_ID_BASE = 2147483647  # COLMAP's pair id = i1 * base + i2
CONSISTENT_PX = 3.0        # a match is of one point when both reprojections are this close
STATIONARY_PX = 4.0        # a raw match moving less than this between two photos is of the cabin


def make_scan(root: Path, data: Path):
    """A plantscan scan folder of the 12 side photos (clockwise turntable: angle = -recorded)."""
    from plantscan_core.data import ViewRecord
    from plantscan_core.scanfolder import ScanFolder

    shutil.rmtree(root, ignore_errors=True)
    scan = ScanFolder.create(root, {"plant_id": "phenoarch-maize-1", "species": "maize"})
    files = sorted((data / "raw" / "side").glob("*.jpg"), key=lambda p: float(p.stem))
    for i, path in enumerate(files):
        view = ViewRecord(index=i, role="plant", camera="side", tilt_index=0, tilt_deg=0.0,
                          angle_index=i, commanded_angle_deg=-float(path.stem),
                          measured_angle_deg=None, file=f"images/plant/side_t00_a{i:03d}.jpg")
        scan.append_view(view, lambda tmp, p=path: shutil.copyfile(p, tmp))
    return scan


def lab_calibration(data: Path):
    from plantscan_calib.phenoarch import load_corners, load_original_calibration

    dets, boards, _ = load_corners(data / "chessboard" / "points")
    cal, _ = load_original_calibration(data / "calibration" / "calibration_cameras.json", boards)
    return cal, dets, boards


def camera_distance(cal) -> float:
    pose = cal.poses[("side", 0)]
    return float(np.linalg.norm((-pose.R.T @ pose.t)[:2]))


def elevation_deg(cal) -> float:
    """Elevation of the side camera's viewing direction (negative: looking down)."""
    z = cal.poses[("side", 0)].R[2]
    return math.degrees(math.asin(float(np.clip(z[2], -1, 1))))


def score_matches(ws: Path, scan, lab) -> dict:
    """Verified matches of the run's database, scored against the lab's cameras."""
    import cv2

    db = sqlite3.connect(ws / "database.db")
    names = dict(db.execute("select image_id, name from images"))
    kp = {i: np.frombuffer(b, np.float32).reshape(r, c)[:, :2]
          for i, r, c, b in db.execute("select image_id, rows, cols, data from keypoints")}
    angle = {Path(v.file).name: v.commanded_angle_deg for v in scan.views}
    raw = db.execute("select count(*), coalesce(sum(rows), 0) from matches").fetchone()
    stationary = 0
    for pid, rows, blob in db.execute("select pair_id, rows, data from matches where rows > 0"):
        i2 = pid % PAIR_ID_BASE
        m = np.frombuffer(blob, np.uint32).reshape(rows, 2)
        moved = np.linalg.norm(kp[(pid - i2) // PAIR_ID_BASE][m[:, 0]] - kp[i2][m[:, 1]], axis=1)
        stationary += int(np.count_nonzero(moved < STATIONARY_PX))
    by_step = defaultdict(lambda: [0, 0, 0])

    def cam(i):
        return lab.camera_at("side", 0, angle[Path(names[i]).name])

    def proj(c):
        m = c.model
        k = np.array([[m.f, 0, m.cu], [0, m.f * m.aspect, m.cv], [0, 0, 1.0]])
        return k @ np.hstack([c.pose.R, c.pose.t[:, None]])

    for pid, rows, blob in db.execute(
            "select pair_id, rows, data from two_view_geometries where rows > 0"):
        i2 = pid % PAIR_ID_BASE
        i1 = (pid - i2) // PAIR_ID_BASE
        m = np.frombuffer(blob, np.uint32).reshape(rows, 2)
        c1, c2 = cam(i1), cam(i2)
        # COLMAP puts the top-left pixel's centre at (0.5, 0.5), plantscan at (0, 0)
        u1, u2 = kp[i1][m[:, 0]] - 0.5, kp[i2][m[:, 1]] - 0.5
        x = cv2.triangulatePoints(proj(c1), proj(c2), u1.T.astype(float), u2.T.astype(float))
        x = (x[:3] / x[3]).T
        err = np.maximum(np.linalg.norm(c1.project(x) - u1, axis=1),
                         np.linalg.norm(c2.project(x) - u2, axis=1))
        step = round(abs((angle[Path(names[i1]).name] - angle[Path(names[i2]).name] + 180)
                         % 360 - 180))
        row = by_step[step]
        row[0] += 1
        row[1] += rows
        row[2] += int(np.count_nonzero(err < CONSISTENT_PX))
    keypoints = [len(v) for v in kp.values()]
    return {"keypoints_per_photo": (min(keypoints), int(np.median(keypoints)), max(keypoints)),
            "raw_pairs": raw[0], "raw_matches": raw[1], "stationary": stationary,
            "by_step": {k: tuple(v) for k, v in sorted(by_step.items())}}


def compare(cal, lab, dets, boards, data: Path) -> dict:
    """A calibration that came out: against the lab's (poses, corners, hull IoU)."""
    import cv2
    from plantscan_calib.phenoarch import load_silhouettes
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull
    from plantscan_sim.render import silhouette_mask
    from scipy.optimize import least_squares

    from plantscan_core.data import Silhouettes

    out = {"distance_mm": (camera_distance(cal), camera_distance(lab)),
           "elevation_deg": (elevation_deg(cal), elevation_deg(lab)),
           "focal_px": (cal.models["side"].f, lab.models["side"].f)}
    side = [d for d in dets if d.camera == "side"]
    res = []
    for b, obj in boards.items():
        mine = [d for d in side if d.board == b]

        def resid(p, mine=mine, obj=obj):
            r = cv2.Rodrigues(p[:3])[0]
            xw = obj @ r.T + p[3:]
            return np.concatenate([(cal.camera_at("side", 0, d.angle_deg).project(
                xw[d.corner_ids]) - d.uv).ravel() for d in mine])
        fit = least_squares(resid, np.r_[0.1, 0.1, 0.1, 0, 0, 0], loss="soft_l1", f_scale=2.0)
        res.append(fit.fun.reshape(-1, 2))
    res = np.linalg.norm(np.vstack(res), axis=1)
    out["corner_rms_px"] = float(np.sqrt(np.mean(res ** 2)))
    out["corner_median_px"] = float(np.median(res))
    sils = Silhouettes([s for s in load_silhouettes(data / "bin") if s.view.camera == "side"])
    ious = {}
    for name, c in (("sfm", cal), ("lab", lab)):
        vol = OctreeHull(OctreeHull.Params(resolution=256, k=1, floor_z_mm=None)
                         ).reconstruct(sils, c)
        mesh = MarchingCubesMesher(MarchingCubesMesher.Params(pot="none")).mesh(vol)
        per = []
        for s in sils:
            # the exact projection (one triangle at a time: cv2.fillPoly of overlapping
            # triangles fills by parity, benchmarks/hull.py)
            h = silhouette_mask(mesh.vertices, mesh.faces, c.camera_for_view(s.view))
            per.append(np.count_nonzero(h & s.mask) / np.count_nonzero(h | s.mask))
        ious[name] = float(np.mean(per))
    out["hull_iou"] = (ious["sfm"], ious["lab"])
    return out


def run(args) -> str:
    from plantscan_sfm.calibrate import SfmSettings, calibrate_scan

    lab, dets, boards = lab_calibration(args.data)
    dist = camera_distance(lab)
    f_lab = lab.models["side"].f
    scan = make_scan(args.work / "scan", args.data)
    cases = [
        ("as a new user: focal free", {}),
        ("focal length given (the lab's)", {"focal_px": {"side": f_lab}}),
        ("focal given + the lab's poses as priors", {
            "focal_px": {"side": f_lab}, "prior_poses": {("side", 0): lab.poses[("side", 0)]},
            "prior_focal": {"side": f_lab}}),
    ]
    lines = ["# `sfm` on real photos: PhenoArch maize plant 1 (`benchmarks/sfm_phenoarch.py`)", "",
             f"## {time.strftime('%Y-%m-%d')}: the calibrator as a new user would run it", "",
             "12 side photos 30° apart (2056×2454 JPEG), no plate print, no markers; scale "
             f"from the camera's distance to the axis ({dist:.0f} mm, the lab's); "
             "`python benchmarks/sfm_phenoarch.py`.", "",
             "| run | result | seconds |", "|---|---|---|"]
    first_ws = None
    for k, (label, extra) in enumerate(cases):
        ws = args.work / f"ws{k}"
        shutil.rmtree(ws, ignore_errors=True)
        s = SfmSettings(scale="camera-distance", camera_distance_mm=dist, workspace=ws,
                        threads=args.threads, **extra)
        t0 = time.perf_counter()
        try:
            cal = calibrate_scan(scan, s)
        except Exception as exc:  # the named errors are the result
            result = f"**{type(exc).__name__}**: {exc}"
        else:
            c = compare(cal, lab, dets, boards, args.data)
            result = ("calibrated: distance {:.0f} / {:.0f} mm, elevation {:.2f} / {:.2f}°, "
                      "f {:.0f} / {:.0f} px (sfm / lab); the lab's corners {:.2f} px RMS "
                      "(median {:.2f}); hull IoU {:.3f} / {:.3f}").format(
                *c["distance_mm"], *c["elevation_deg"], *c["focal_px"], c["corner_rms_px"],
                c["corner_median_px"], *c["hull_iou"])
        lines.append(f"| {label} | {result} | {time.perf_counter() - t0:.0f} |")
        print(lines[-1], flush=True)
        first_ws = first_ws or ws
    m = score_matches(first_ws, scan, lab)
    lo, med, hi = m["keypoints_per_photo"]
    lines += ["", f"SIFT keypoints per photo {lo}–{hi} (median {med}); {m['raw_matches']} raw "
              f"matches in {m['raw_pairs']} pairs, {m['stationary']} of them moving less than "
              f"{STATIONARY_PX:g} px between the two photos (the static cabin: dropped as "
              "stationary). The verified matches against the lab's calibration (a match is "
              f"of one point when, triangulated with the lab's cameras, both reprojections "
              f"are within {CONSISTENT_PX:g} px):", "",
              "| angle between the photos | pairs | verified matches | of one point |",
              "|---|---|---|---|"]
    tot = [0, 0]
    for step, (pairs, rows, good) in m["by_step"].items():
        lines.append(f"| {step}° | {pairs} | {rows} | {good} ({100 * good / max(rows, 1):.0f} %) |")
        tot[0] += rows
        tot[1] += good
    lines.append(f"| all | | {tot[0]} | {tot[1]} ({100 * tot[1] / max(tot[0], 1):.0f} %) |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--work", type=Path, default=Path("/tmp/plantscan-sfm-phenoarch"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "docs/benchmarks/sfm_phenoarch.md")
    args = ap.parse_args(argv)
    if not (args.data / "raw" / "side").is_dir():
        print(f"{args.data}: no raw/side photos (the shared PhenoArch data)", file=sys.stderr)
        return 2
    text = run(args)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Approximate camera poses from other rigs, attached to a scan as priors for ``sfm``.

A gantry or robot arm knows where its camera is only roughly (a CNC's x, y, z,
pan, tilt); ``plantscan import poses FILE --scan S`` turns such a table into
``S/prior_poses.yaml``, which the ``sfm`` calibrator uses as its starting
point and as soft priors, and reports how far it moved them.

Table columns (CSV with a header, or JSON: a list of objects with these keys):
``camera, tilt_index, x_mm, y_mm, z_mm, pan_deg, tilt_deg[, roll_deg][, f_px]``
in the turntable frame at turntable angle 0 (axis = +Z, origin on the axis at
the plate's top).  ``pan_deg`` is the azimuth of the viewing direction about
+Z from +X, ``tilt_deg`` its elevation (negative: looking down), ``roll_deg``
a turn of the image about the viewing direction (0: image rows horizontal).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import yaml

from plantscan_core.data import Pose
from plantscan_core.errors import DataError

PRIOR_POSES_FILE = "prior_poses.yaml"
FORMAT = "plantscan-prior-poses/1"
COLUMNS = ("camera", "tilt_index", "x_mm", "y_mm", "z_mm", "pan_deg", "tilt_deg")


def rotation_from_pan_tilt(pan_deg: float, tilt_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """World -> camera rotation (3, 3) of a camera looking along (pan, tilt), rolled by roll."""
    p, t = math.radians(pan_deg), math.radians(tilt_deg)
    z = np.array([math.cos(t) * math.cos(p), math.cos(t) * math.sin(p), math.sin(t)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:  # looking straight up or down: rows along +X
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll @ r


def pan_tilt_roll(r: np.ndarray) -> tuple[float, float, float]:
    """Inverse of ``rotation_from_pan_tilt``: (pan, tilt, roll) deg of rotation ``r``."""
    z = r[2]
    pan = math.degrees(math.atan2(z[1], z[0]))
    tilt = math.degrees(math.asin(float(np.clip(z[2], -1, 1))))
    r0 = rotation_from_pan_tilt(pan, tilt)
    d = r @ r0.T
    roll = math.degrees(math.atan2(d[1, 0], d[0, 0]))
    return pan, tilt, roll


def _rows(path: Path) -> list[dict]:
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            rows = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(rows, list):
            raise DataError(f"{path}: expected a JSON list of pose objects")
        return rows
    return list(csv.DictReader(text.splitlines()))


def read_pose_table(path: Path) -> tuple[dict[tuple[str, int], Pose], dict[str, float]]:
    """Approximate poses (and focal lengths, where given) from a CSV or JSON table."""
    rows = _rows(Path(path))
    if not rows:
        raise DataError(f"{path}: no poses")
    poses: dict[tuple[str, int], Pose] = {}
    focal: dict[str, float] = {}
    errors = []
    for i, row in enumerate(rows):
        missing = [c for c in COLUMNS if c not in row or row[c] in ("", None)]
        if missing:
            errors.append(f"row {i + 1}: missing {', '.join(missing)}")
            continue
        try:
            key = (str(row["camera"]), int(row["tilt_index"]))
            c = np.array([float(row["x_mm"]), float(row["y_mm"]), float(row["z_mm"])])
            r = rotation_from_pan_tilt(float(row["pan_deg"]), float(row["tilt_deg"]),
                                       float(row.get("roll_deg") or 0.0))
            if row.get("f_px") not in (None, ""):
                focal[key[0]] = float(row["f_px"])
        except (TypeError, ValueError) as exc:
            errors.append(f"row {i + 1}: {exc}")
            continue
        if key in poses:
            errors.append(f"row {i + 1}: camera {key[0]} tilt {key[1]} given twice")
        poses[key] = Pose(r, -r @ c)
    if errors:
        raise DataError(f"{path}: " + "; ".join(errors))
    return poses, focal


def write_prior_poses(path: Path, poses: dict[tuple[str, int], Pose],
                      focal: dict[str, float] | None = None, source: str = "") -> None:
    from plantscan_core.scanfolder import atomic_write_text

    doc = {"format": FORMAT, "source": source, "units": {"length": "mm", "angle": "deg"},
           "poses": [{"camera": c, "tilt_index": t,
                      "centre_mm": [float(x) for x in p.centre],
                      "R": [[float(x) for x in row] for row in p.R]}
                     for (c, t), p in sorted(poses.items())],
           "focal_px": {k: float(v) for k, v in sorted((focal or {}).items())}}
    atomic_write_text(Path(path), yaml.safe_dump(doc, sort_keys=False))


def read_prior_poses(path: Path) -> tuple[dict[tuple[str, int], Pose], dict[str, float]]:
    """The poses of ``prior_poses.yaml`` and the focal lengths (px) it gives, if any."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as exc:
        raise DataError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise DataError(f"{path}: not a {FORMAT} file")
    poses = {}
    for i, p in enumerate(doc.get("poses") or []):
        try:
            r = np.array(p["R"], dtype=float).reshape(3, 3)
            c = np.array(p["centre_mm"], dtype=float).reshape(3)
            poses[(str(p["camera"]), int(p["tilt_index"]))] = Pose(r, -r @ c)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{path}: poses[{i}]: {exc}") from None
    if not poses:
        raise DataError(f"{path}: no poses")
    return poses, {str(k): float(v) for k, v in (doc.get("focal_px") or {}).items()}


def import_poses(table: Path, scan_dir: Path) -> Path:
    """``plantscan import poses``: the table's poses as ``SCAN/prior_poses.yaml``.

    Every (camera, tilt) of the scan's photos must have a pose; the file is
    checked in full before anything is written.
    """
    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(Path(scan_dir))
    poses, focal = read_pose_table(Path(table))
    groups = sorted({(v.camera, v.tilt_index) for v in scan.views})
    missing = [g for g in groups if g not in poses]
    if missing:
        raise DataError(f"{table}: no pose for " + ", ".join(
            f"camera {c} tilt {t}" for c, t in missing) + f" (photos of {scan.root})")
    out = Path(scan.root) / PRIOR_POSES_FILE
    write_prior_poses(out, poses, focal, source=str(table))
    return out


def add_import_command(subparsers) -> None:
    """``plantscan import poses TABLE --scan SCAN`` (adds the ``import`` group if needed)."""
    group = subparsers.choices.get("import")
    if group is None:
        group = subparsers.add_parser("import", help="import scans from other rigs")
        group.set_defaults(func=lambda a: (group.print_help(), 2)[1])
        group._plantscan_sub = group.add_subparsers(  # type: ignore[attr-defined]
            dest="import_command", metavar="FORMAT")
    sub = getattr(group, "_plantscan_sub", None)
    if sub is None:
        sub = group.add_subparsers(dest="import_command", metavar="FORMAT")
    p = sub.add_parser("poses", help="approximate camera poses (CSV/JSON: camera, tilt_index, "
                       "x_mm, y_mm, z_mm, pan_deg, tilt_deg[, roll_deg, f_px]) as priors for "
                       "calibrate: sfm")
    p.add_argument("table", metavar="TABLE", help="CSV or JSON pose table")
    p.add_argument("--scan", required=True, metavar="SCAN", help="scan folder to attach them to")
    p.set_defaults(func=_cmd_import_poses)


def _cmd_import_poses(args) -> int:
    out = import_poses(Path(args.table), Path(args.scan))
    print(f"{out}: approximate poses from {args.table} (used by calibrate: sfm)")
    return 0

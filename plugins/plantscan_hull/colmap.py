"""``plantscan import colmap``: a COLMAP text model + images (+ masks) -> a scan folder.

Each COLMAP image becomes one ``plant`` view with its own calibrated pose:
camera ``colmap<CAMERA_ID>``, ``tilt_index`` = the view's index, turntable
angle 0, so ``Calibration.camera_for_view`` returns exactly COLMAP's camera.
The calibration is written to ``SCAN/calibration.yaml`` (read by the
``fixed`` calibrator), masks to ``SCAN/masks/<image stem>.png`` (read by the
``given-masks`` segmenter), and ``scan.yaml`` carries a processing recipe.

COLMAP conventions converted: the centre of the top-left pixel is (0.5, 0.5)
in COLMAP and (0, 0) here; poses are world -> camera in both (``x = R X + t``,
``R`` from the quaternion ``QW QX QY QZ``).  Lengths are multiplied by
``--scale`` (mm per model unit; COLMAP's scale is arbitrary).  The world
frame is COLMAP's: the pot fit assumes +Z up, so the recipe turns it off.
"""

from __future__ import annotations

import argparse
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plantscan_core.bounds import MAX_IMAGE_SIDE_PX
from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord
from plantscan_core.errors import DataError
from plantscan_core.scanfolder import ScanFolder, atomic_write_bytes, now_iso
from plantscan_core.userfiles import read_text

SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FOCAL_RTOL = 0.02  # a real pixel aspect ratio is within 1e-3 of 1; 2 % is a mistyped line


@dataclass
class ColmapImage:
    image_id: int
    q: np.ndarray      # (4,) qw, qx, qy, qz
    t: np.ndarray      # (3,) model units
    camera_id: int
    name: str


# Parameters of each supported COLMAP camera model, in the order of cameras.txt.
MODEL_PARAMS = {"SIMPLE_PINHOLE": ("f", "cx", "cy"), "PINHOLE": ("fx", "fy", "cx", "cy"),
                "SIMPLE_RADIAL": ("f", "cx", "cy", "k"), "RADIAL": ("f", "cx", "cy", "k1", "k2"),
                "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}
MAX_ABS = 1e9  # no focal, centre, distortion or translation of a real model is larger


def _read(path: Path) -> list[str]:
    if not path.exists():
        raise DataError(f"{path}: not found (a COLMAP text model needs cameras.txt and "
                        "images.txt; export it with `colmap model_converter --output_type TXT`)")
    return read_text(path).splitlines()


def _lines(path: Path) -> list[tuple[int, str]]:
    return [(n, line) for n, line in enumerate(_read(path), start=1)
            if line.strip() and not line.lstrip().startswith("#")]


def _numbers(tokens: list[str], where: str, what: str) -> np.ndarray:
    """``tokens`` as finite floats of at most ``MAX_ABS``; ``DataError`` naming the value."""
    try:
        values = np.array([float(t) for t in tokens], dtype=float)
    except ValueError as exc:
        raise DataError(f"{where}: {what}: {exc}") from None
    bad = [t for t, v in zip(tokens, values) if not (np.isfinite(v) and abs(v) <= MAX_ABS)]
    if bad:
        raise DataError(f"{where}: {what} must be finite numbers of at most {MAX_ABS:g}, "
                        f"got {', '.join(bad)}")
    return values


def read_cameras(path: Path) -> dict[int, CameraModel]:
    """cameras.txt -> plantscan camera models (pixel centres converted)."""
    out = {}
    first: dict[int, int] = {}
    for n, line in _lines(path):
        parts = line.split()
        if len(parts) < 4:
            raise DataError(f"{path}:{n}: malformed camera line (expected CAMERA_ID MODEL "
                            f"WIDTH HEIGHT PARAMS..., got {len(parts)} fields)")
        try:
            cam_id, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
        except ValueError as exc:
            raise DataError(f"{path}:{n}: malformed camera line ({exc})") from None
        where = f"{path}:{n} (camera {cam_id}, {model})"
        if model not in MODEL_PARAMS:
            raise DataError(f"{where}: camera model not supported; valid: {', '.join(SUPPORTED)}")
        names = MODEL_PARAMS[model]
        if len(parts) - 4 != len(names):
            raise DataError(f"{where}: {len(parts) - 4} parameters, the model has "
                            f"{len(names)} ({' '.join(names)})")
        if not (0 < w <= MAX_IMAGE_SIDE_PX and 0 < h <= MAX_IMAGE_SIDE_PX):
            raise DataError(f"{where}: image size {w}x{h} px out of range "
                            f"(1..{MAX_IMAGE_SIDE_PX})")
        if cam_id in first:
            raise DataError(f"{where}: camera id {cam_id} is defined again (first at line "
                            f"{first[cam_id]})")
        first[cam_id] = n
        p = dict(zip(names, _numbers(parts[4:], where, "parameters")))
        for focal in ("f", "fx", "fy"):
            if focal in p and p[focal] <= 0:
                raise DataError(f"{where}: focal length {focal}={p[focal]:g} must be > 0")
        aspect = 1.0
        f = p.get("f", p.get("fx"))
        if "fy" in p:
            aspect = _aspect(p["fx"], p["fy"], where)
        d1, d2 = p.get("k", p.get("k1", 0.0)), p.get("k2", 0.0)
        if abs(p.get("p1", 0.0)) > 1e-9 or abs(p.get("p2", 0.0)) > 1e-9:
            raise DataError(
                f"{where}: tangential distortion (p1={p['p1']:g}, p2={p['p2']:g}) is not in "
                "plantscan's camera model (f, cu, cv, d1, d2); undistort the images "
                "first (`colmap image_undistorter`) and import the PINHOLE model")
        out[cam_id] = CameraModel(f=float(f), cu=float(p["cx"]) - 0.5, cv=float(p["cy"]) - 0.5,
                                  d1=float(d1), d2=float(d2), width=w, height=h, aspect=aspect)
    if not out:
        raise DataError(f"{path}: no camera")
    return out


def _aspect(fx: float, fy: float, where: str) -> float:
    """fy / fx; a ratio far from 1 is a mistyped model, not a lens."""
    if fx <= 0 or fy <= 0 or abs(fx - fy) > FOCAL_RTOL * max(abs(fx), abs(fy)):
        raise DataError(f"{where}: fx={fx:g} and fy={fy:g} differ by more than "
                        f"{FOCAL_RTOL:.0%} (pixel aspect ratio); check the camera line")
    return fy / fx


def _looks_like_image_line(parts: list[str]) -> bool:
    """IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME: not a (X, Y, POINT3D_ID) triple list."""
    if len(parts) < 10:
        return False
    try:
        int(parts[0]), [float(x) for x in parts[1:8]], int(parts[8])
    except ValueError:
        return False
    return len(parts) % 3 != 0 or not _is_number(parts[9])


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_images(path: Path) -> list[ColmapImage]:
    """images.txt -> posed images (the 2D point lines are skipped, their shape checked)."""
    lines = _read(path)
    body = [(n, ln) for n, ln in enumerate(lines, start=1) if not ln.lstrip().startswith("#")]
    out = []
    first_id: dict[int, int] = {}
    first_name: dict[str, int] = {}
    # Pairs of lines; the second (2D points) may be empty, so pair by position.
    i = 0
    while i < len(body):
        n, line = body[i]
        if not line.strip():
            i += 1
            continue
        parts = line.split()
        if len(parts) < 10:
            raise DataError(f"{path}:{n}: malformed image line (expected IMAGE_ID QW QX QY QZ "
                            f"TX TY TZ CAMERA_ID NAME, got {len(parts)} fields)")
        try:
            image_id, camera_id = int(parts[0]), int(parts[8])
        except ValueError as exc:
            raise DataError(f"{path}:{n}: malformed image line ({exc})") from None
        where = f"{path}:{n} (image {image_id})"
        q = _numbers(parts[1:5], where, "quaternion QW QX QY QZ")
        t = _numbers(parts[5:8], where, "translation TX TY TZ")
        if np.linalg.norm(q) < 1e-6:
            raise DataError(f"{where}: the quaternion {' '.join(parts[1:5])} is zero (no "
                            "rotation); check the line")
        img = ColmapImage(image_id, q, t, camera_id, " ".join(parts[9:]))
        if image_id in first_id:
            raise DataError(f"{where}: image id {image_id} is used again (first at line "
                            f"{first_id[image_id]})")
        if img.name in first_name:
            raise DataError(f"{where}: image name {img.name!r} is listed again (first at line "
                            f"{first_name[img.name]})")
        first_id[image_id], first_name[img.name] = n, n
        if i + 1 < len(body):
            m, points = body[i + 1]
            if _looks_like_image_line(points.split()):
                raise DataError(
                    f"{path}:{m}: an image line where the 2D points line of image {image_id} "
                    f"(line {n}) belongs: every image takes two lines (leave the second empty "
                    "when it has no points); the model would lose every other image")
        out.append(img)
        i += 2
    if not out:
        raise DataError(f"{path}: no image")
    return sorted(out, key=lambda im: im.image_id)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the unit quaternion ``(qw, qx, qy, qz)`` (COLMAP's order)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Inverse of ``quaternion_to_matrix`` (``qw >= 0``)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(r, dtype=float)).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def _find_mask(masks: Path, name: str) -> Path | None:
    base = Path(name)
    for cand in (masks / f"{name}.png", masks / base.with_suffix(".png"), masks / name,
                 masks / f"{base.name}.png", masks / base.with_suffix(".png").name):
        if cand.is_file():
            return cand
    return None


def import_colmap(sparse_dir: Path, images_dir: Path, out: Path, masks_dir: Path | None = None,
                  scale: float = 1.0, plant_id: str | None = None) -> ScanFolder:
    """Write a scan folder from a COLMAP text model; see the module docstring.

    Raises
    ------
    DataError
        Missing or malformed model files, unsupported camera models, a missing
        image or mask, or a mask/image whose size differs from its camera's
        (each names the file).
    """
    import cv2

    sparse_dir, images_dir, out = Path(sparse_dir), Path(images_dir), Path(out)
    if not (math.isfinite(scale) and 0 < scale <= MAX_ABS):
        raise DataError(f"--scale: must be a finite number > 0 (mm per model unit), got {scale}")
    cameras = read_cameras(sparse_dir / "cameras.txt")
    images = read_images(sparse_dir / "images.txt")
    missing_cam = sorted({im.camera_id for im in images} - set(cameras))
    if missing_cam:
        raise DataError(f"{sparse_dir / 'images.txt'}: images use camera ids {missing_cam} that "
                        f"{sparse_dir / 'cameras.txt'} does not define")
    # Check every input before writing anything.
    plan = []
    for i, im in enumerate(images):
        src = images_dir / im.name
        if not src.is_file():
            raise DataError(f"{src}: image {im.name!r} (COLMAP image {im.image_id}) not found")
        model = cameras[im.camera_id]
        size = _image_size(src)
        if size != (model.width, model.height):
            raise DataError(f"{src}: is {size[0]}x{size[1]} px but COLMAP camera "
                            f"{im.camera_id} is {model.width}x{model.height} px")
        mask_src = None
        if masks_dir is not None:
            mask_src = _find_mask(Path(masks_dir), im.name)
            if mask_src is None:
                raise DataError(f"{masks_dir}: no mask for image {im.name!r} (looked for "
                                f"{im.name}.png and {Path(im.name).with_suffix('.png')})")
            m = cv2.imread(str(mask_src), cv2.IMREAD_GRAYSCALE)
            if m is None:
                raise DataError(f"{mask_src}: cannot read mask")
            if (m.shape[1], m.shape[0]) != (model.width, model.height):
                raise DataError(f"{mask_src}: mask is {m.shape[1]}x{m.shape[0]} px but image "
                                f"{im.name!r} is {model.width}x{model.height} px (masks do not "
                                "match the images)")
        flat = im.name.replace("/", "__")
        plan.append((i, im, src, mask_src, f"images/plant/{flat}"))

    cam_names = {cid: f"colmap{cid}" for cid in cameras}
    calibration = Calibration(
        models={cam_names[cid]: m for cid, m in cameras.items()
                if any(im.camera_id == cid for im in images)},
        poses={(cam_names[im.camera_id], i): Pose(quaternion_to_matrix(im.q), im.t * scale)
               for i, im, *_ in plan},
        tilts_deg={i: 0.0 for i, *_ in plan},
        quality={"source": "colmap", "sparse_dir": str(sparse_dir), "scale_mm_per_unit": scale},
    )
    recipe = import_recipe(sorted(calibration.models), plant_id or out.name)
    scan = ScanFolder.create(out, {
        "plant_id": plant_id or out.name, "species": "", "recipe_name": recipe["name"],
        "recipe": recipe,
        "rig": {"source": "colmap", "cameras": sorted(calibration.models), "tilts_deg": [0.0]},
    })
    calibration.save(out / "calibration.yaml")
    for i, im, src, mask_src, rel in plan:
        view = ViewRecord(index=i, role="plant", camera=cam_names[im.camera_id], tilt_index=i,
                          tilt_deg=0.0, angle_index=0, commanded_angle_deg=0.0,
                          measured_angle_deg=None, file=rel, captured_at=now_iso())
        scan.append_view(view, lambda tmp, s=src: shutil.copyfile(s, tmp))
        if mask_src is not None:
            m = cv2.imread(str(mask_src), cv2.IMREAD_GRAYSCALE)
            ok, buf = cv2.imencode(".png", np.where(m > 127, 255, 0).astype(np.uint8))
            atomic_write_bytes(out / "masks" / f"{Path(rel).stem}.png", buf.tobytes())
    return scan


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: cannot decode image")
    return img.shape[1], img.shape[0]


def import_recipe(camera_names: list[str], plant_id: str) -> dict:
    """The processing recipe stored with an imported scan (no acquisition happens)."""
    return {
        "name": "colmap-import",
        "description": "Imported from a COLMAP model: fixed calibration, given masks",
        "plant": {"id": plant_id, "species": ""},
        "scan": {
            "protocol": "colmap-import",
            # Acquisition is not run for an imported scan; the rig entries only name cameras.
            "cameras": [{"name": n, "plugin": "opencv", "params": {}} for n in camera_names],
            "turntable": {"plugin": "sim", "params": {}},
            "tilts_deg": [0.0],
            "images_per_revolution": 1,
        },
        "calibrate": {"plugin": "fixed", "params": {}},
        "segment": {"plugin": "given-masks", "params": {}},
        # COLMAP's frame has no turntable plate at z = 0.
        "reconstruct": {"plugin": "octree-hull", "params": {"floor_z_mm": None}},
        "mesh": {"plugin": "marching-cubes", "params": {"pot": "none"}},
    }


def add_import_command(subparsers: argparse._SubParsersAction) -> None:
    """``plantscan import colmap ...`` (adds the ``import`` group if nobody else did)."""
    group = subparsers.choices.get("import")
    if group is None:
        group = subparsers.add_parser("import", help="import scans from other rigs")
        group.set_defaults(func=lambda a: (group.print_help(), 2)[1])
        sub = group.add_subparsers(dest="import_command", metavar="FORMAT")
        group._plantscan_sub = sub  # type: ignore[attr-defined]
    sub = getattr(group, "_plantscan_sub", None)
    if sub is None:  # another plugin made the group its own way
        sub = group.add_subparsers(dest="import_command", metavar="FORMAT")
    p = sub.add_parser("colmap", help="COLMAP text model (cameras.txt, images.txt) + images")
    p.add_argument("sparse", metavar="SPARSE_TXT_DIR", help="folder with cameras.txt, images.txt")
    p.add_argument("--images", required=True, metavar="DIR", help="folder of the images")
    p.add_argument("--masks", metavar="DIR", help="plant masks (<image name>.png, 0/255)")
    p.add_argument("--out", required=True, metavar="SCAN", help="scan folder to write")
    p.add_argument("--scale", type=float, default=1.0, help="mm per model unit (default 1)")
    p.add_argument("--plant-id", help="plant id (default: the scan folder name)")
    p.set_defaults(func=_cmd_import_colmap)


def _cmd_import_colmap(args) -> int:
    scan = import_colmap(Path(args.sparse), Path(args.images), Path(args.out),
                         Path(args.masks) if args.masks else None, args.scale, args.plant_id)
    print(f"{scan.root}: {len(scan.views)} views imported from {args.sparse}"
          + ("" if args.masks else " (no masks: give --masks or choose a segmenter)"))
    return 0


def export_colmap_text(calibration: Calibration, views: list[ViewRecord], out_dir: Path,
                       scale: float = 1.0) -> None:
    """Write cameras.txt / images.txt (RADIAL) for ``views``: the inverse of the import.

    One COLMAP camera per plantscan camera model; used by the round-trip test
    and handy for feeding plantscan calibrations to COLMAP.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = sorted({v.camera for v in views})
    ids = {n: i + 1 for i, n in enumerate(names)}
    cam_lines = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for n in names:
        m = calibration.models[n]
        if m.aspect == 1.0:
            cam_lines.append(f"{ids[n]} RADIAL {m.width} {m.height} {m.f!r} {m.cu + 0.5!r} "
                             f"{m.cv + 0.5!r} {m.d1!r} {m.d2!r}")
        else:
            cam_lines.append(f"{ids[n]} OPENCV {m.width} {m.height} {m.f!r} {m.fy!r} "
                             f"{m.cu + 0.5!r} {m.cv + 0.5!r} {m.d1!r} {m.d2!r} 0.0 0.0")
    img_lines = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, v in enumerate(views, start=1):
        cam = calibration.camera_for_view(v)
        q = matrix_to_quaternion(cam.pose.R)
        t = cam.pose.t / scale
        img_lines.append(" ".join([str(i), *(repr(float(x)) for x in q),
                                   *(repr(float(x)) for x in t), str(ids[v.camera]),
                                   Path(v.file).name]))
        img_lines.append("")
    (out_dir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (out_dir / "images.txt").write_text("\n".join(img_lines) + "\n")

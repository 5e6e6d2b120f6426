"""Readers for the PhenoArch (openalea/phenomenal) turntable calibration files.

The real corners in ``phenoarch_maize_plant1/chessboard/points/`` come from
another lab's rig: two boards on the turntable, a side and a top camera,
3-degree steps, a clockwise turntable, no lens distortion modelled and the
principal point at the image centre.  These readers turn them into solver
input and turn the original calibration into a plantscan ``Calibration`` so
both can be scored on the same corners.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from plantscan_calib.model import Detection
from plantscan_core.data import (
    Calibration,
    CameraModel,
    Pose,
    Silhouette,
    Silhouettes,
    ViewRecord,
    rotation_x,
    rotation_y,
    rotation_z,
)
from plantscan_core.errors import DataError


def board_points(shape: tuple[int, int], square_mm: float) -> np.ndarray:
    """(cols*rows, 3) corners in the PhenoArch board frame, mm.

    As openalea.phenomenal's ``Chessboard.get_corners_local_3d``: rows from
    the top, x to the right, y up, origin at ``(cols, rows) * square / 2``.
    """
    cols, rows = shape
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel() * square_mm - cols * square_mm / 2.0,
                     (rows - 1 - j.ravel()) * square_mm - rows * square_mm / 2.0,
                     np.zeros(cols * rows)], axis=1)


def load_corners(points_dir: Path) -> tuple[list[Detection], dict[int, np.ndarray],
                                            dict[str, tuple[int, int]]]:
    """Detections from ``image_points_target_*.json``.

    The turntable turns clockwise, so the angle passed to the solver is
    minus the recorded one (plantscan's angles are counter-clockwise).

    Returns
    -------
    detections, boards (board number -> object points), image sizes
    """
    files = sorted(Path(points_dir).glob("image_points_target_*.json"))
    if not files:
        raise DataError(f"{points_dir}: no image_points_target_*.json")
    dets: list[Detection] = []
    boards: dict[int, np.ndarray] = {}
    sizes: dict[str, tuple[int, int]] = {}
    for path in files:
        b = int(path.stem.rsplit("_", 1)[1])
        d = json.loads(path.read_text())
        boards[b] = board_points(tuple(d["shape"]), float(d["square_size"]))
        for cam, (w, h) in d["image_sizes"].items():
            sizes[cam] = (int(w), int(h))
        for cam, per_angle in d["image_points"].items():
            for angle, pts in per_angle.items():
                uv = np.asarray(pts, dtype=float).reshape(-1, 2)
                dets.append(Detection(cam, 0, -float(angle), b, np.arange(len(uv)), uv))
    return dets, boards, sizes


def load_original_calibration(path: Path, boards: dict[int, np.ndarray]
                              ) -> tuple[Calibration, dict[int, Pose]]:
    """The original software's calibration as a plantscan Calibration (+ board poses).

    Follows the README: ``M = Rz Ry Rx``; ``x_cam = M^T Rz(alpha) X - M^T C`` with
    ``alpha = -angle * angle_factor`` for a clockwise turntable.  Its separate
    ``fx``, ``fy`` become ``f = fx``, ``aspect = fy / fx`` (exact); they are also
    kept in ``quality["fx_fy"]``.
    """
    d = json.loads(Path(path).read_text())
    models, poses, fxfy = {}, {}, {}
    for cam, p in d["cameras_parameters"].items():
        w, h = int(p["_width_image"]), int(p["_height_image"])
        fx, fy = float(p["_focal_length_x"]), float(p["_focal_length_y"])
        models[cam] = CameraModel(fx, w / 2.0, h / 2.0, 0.0, 0.0, w, h, fy / fx)
        fxfy[cam] = (fx, fy)
        m = _euler(p)
        c = np.array([p["_pos_x"], p["_pos_y"], p["_pos_z"]], dtype=float)
        poses[(cam, 0)] = Pose(m.T, -m.T @ c)
    board_poses = {}
    for name, p in d["targets_parameters"].items():
        b = int(name.rsplit("_", 1)[1])
        board_poses[b] = Pose(_euler(p), np.array([p["_pos_x"], p["_pos_y"], p["_pos_z"]]))
    scale = float(d["angle_factor"])
    cal = Calibration(models, poses, {0: 0.0}, scale, None, {"fx_fy": fxfy})
    return cal, board_poses


def _euler(p) -> np.ndarray:
    return (rotation_z(math.degrees(p["_rot_z"])) @ rotation_y(math.degrees(p["_rot_y"]))
            @ rotation_x(math.degrees(p["_rot_x"])))


def project_original(cal: Calibration, board_poses: dict[int, Pose], det: Detection,
                     boards: dict[int, np.ndarray]) -> np.ndarray:
    """Pixels ``(N, 2)`` of a detection's corners under the original calibration (fx != fy)."""
    pose = board_poses[det.board]
    xw = boards[det.board][det.corner_ids] @ pose.R.T + pose.t
    cam = cal.camera_at(det.camera, det.tilt_index, det.angle_deg)
    xc = cam.pose.apply(xw)
    fx, fy = cal.quality["fx_fy"][det.camera]
    m = cal.models[det.camera]
    return np.stack([fx * xc[:, 0] / xc[:, 2] + m.cu, fy * xc[:, 1] / xc[:, 2] + m.cv], axis=1)


def load_silhouettes(bin_dir: Path) -> Silhouettes:
    """The original software's plant silhouettes (``bin/{side,top}/<angle>.png``) as views.

    File names are turntable angles in degrees; the turntable turns clockwise, so
    each view's angle is minus the recorded one, as for the corners.  Views are
    ordered by camera, then angle.
    """
    import cv2

    items: list[Silhouette] = []
    for cam_dir in sorted(p for p in Path(bin_dir).iterdir() if p.is_dir()):
        files = sorted(cam_dir.glob("*.png"), key=lambda p: float(p.stem))
        for i, path in enumerate(files):
            mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise DataError(f"{path}: not a readable image")
            view = ViewRecord(index=len(items), role="plant", camera=cam_dir.name, tilt_index=0,
                              tilt_deg=0.0, angle_index=i,
                              commanded_angle_deg=-float(path.stem), measured_angle_deg=None,
                              file=str(path))
            items.append(Silhouette(view, mask > 0))
    if not items:
        raise DataError(f"{bin_dir}: no <camera>/<angle>.png silhouettes")
    return Silhouettes(items)

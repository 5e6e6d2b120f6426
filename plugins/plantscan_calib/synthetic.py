"""Synthetic turntable rigs with exact answers, for tests and benchmarks.

``make_rig`` builds a rig like the seed's (two cameras on a tilting arm, a
board standing on the turntable) as a ground-truth ``Calibration``;
``synthetic_detections`` projects the board corners through it with
``CameraModel`` (exact), adds Gaussian corner noise and corrupts a fraction of
corners by a few pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plantscan_calib.detect import BoardSpec
from plantscan_calib.model import Detection
from plantscan_core.data import (
    Calibration,
    CameraModel,
    Pose,
    TiltAxis,
    rotation_about_axis,
    rotation_x,
    rotation_z,
)


@dataclass
class SyntheticRig:
    """A ground-truth rig and its boards."""

    truth: Calibration
    boards: dict[int, np.ndarray]          # board -> (N, 3) mm, board frame
    board_poses: dict[int, Pose]           # board -> board->world (R, t) at angle 0
    spec: BoardSpec


# Where boards stand on the plate: (azimuth of the board's outward normal from -Y, deg;
# lean back from vertical, deg; height of the board centre, mm), at radius 60 mm.
# Two boards back to back (the recommended target, docs/calibration.md): each camera sees
# one or the other over most of a revolution.
BACK_TO_BACK = ((0.0, 20.0, 110.0), (180.0, 20.0, 130.0))


def make_rig(image_size: tuple[int, int] = (5184, 3456), tilts_deg=(0.0, 20.0, 40.0),
             cameras: int = 2, boards: int = 1, cols: int = 9, rows: int = 6,
             square_mm: float = 25.0, distortion: bool = True, kind: str = "chessboard",
             marker_mm: float = 0.0, placements=BACK_TO_BACK) -> SyntheticRig:
    """A two-camera tilting-arm rig, tilt axis horizontal through the plant volume.

    Camera ``cam0`` looks at the plant from 700 mm at 150 mm height, ``cam1``
    from above it (tilted down 35 deg); the arm tilts both about the world X
    axis through (0, 0, 200) mm.  Board ``b`` stands on the plate at radius
    60 mm, facing outward, placed by ``placements[b]`` = (azimuth deg, lean
    back deg, centre height mm).
    """
    w, h = image_size
    f = 1.05 * w  # ~ a 24 mm lens on an APS-C body
    models, poses = {}, {}
    bases = [Pose.look_at((0.0, -700.0, 150.0), (0.0, 0.0, 150.0)),
             Pose.look_at((0.0, -600.0, 520.0), (0.0, 0.0, 120.0))][:cameras]
    axis = TiltAxis(np.array([0.0, 0.0, 200.0]), np.array([1.0, 0.0, 0.0]), 0)
    for c, base in enumerate(bases):
        name = f"cam{c}"
        models[name] = CameraModel(f * (1 + 0.02 * c), w / 2 + 13.0 - 7 * c, h / 2 - 9.0 + 5 * c,
                                   -0.08 if distortion else 0.0,
                                   0.05 if distortion else 0.0, w, h)
        for ti, tilt in enumerate(tilts_deg):
            q = rotation_about_axis(axis.direction, tilt - tilts_deg[0])
            o = axis.origin
            poses[(name, ti)] = Pose(base.R @ q.T, base.R @ (o - q.T @ o) + base.t)
    truth = Calibration(models, poses, {i: float(t) for i, t in enumerate(tilts_deg)}, 1.0,
                        axis if len(tilts_deg) > 1 else None)
    spec = BoardSpec(kind, cols, rows, square_mm, marker_mm)
    pts = spec.object_points()
    centre = pts.mean(axis=0)
    bp, bd = {}, {}
    if boards > len(placements):
        raise ValueError(f"{boards} boards but only {len(placements)} placements")
    for b in range(boards):
        azimuth, lean, height = placements[b]
        # Board plane faces -Y at azimuth 0 (toward cam0), leaning back, on the plate.
        r = rotation_z(azimuth) @ rotation_x(-90.0 - lean)
        t = rotation_z(azimuth) @ np.array([0.0, -60.0, height]) - r @ centre
        bp[b] = Pose(r, t)
        bd[b] = pts
    return SyntheticRig(truth, bd, bp, spec)


def synthetic_detections(rig: SyntheticRig, angles_deg, noise_px: float = 0.2,
                         corrupt_fraction: float = 0.0, corrupt_px=(3.0, 15.0),
                         max_obliquity_deg: float = 60.0, seed: int = 0,
                         tilt_indices=None) -> list[Detection]:
    """Project the boards through the true rig at each angle, as a detector would report them.

    A board is "found" when its plane faces the camera within
    ``max_obliquity_deg`` and every corner is inside the image (like
    ``findChessboardCorners``, all or nothing).
    """
    rng = np.random.default_rng(seed)
    # A separate stream for corruption: the same seed gives the same noise with or without it.
    bad_rng = np.random.default_rng(seed + 7919)
    out = []
    truth = rig.truth
    keys = sorted(truth.poses)
    if tilt_indices is not None:
        keys = [k for k in keys if k[1] in tilt_indices]
    for cam, ti in keys:
        for a in angles_deg:
            camera = truth.camera_at(cam, ti, a)
            for b, bpose in rig.board_poses.items():
                # Everything in the turntable frame: the camera turns around the board.
                xw = rig.boards[b] @ bpose.R.T + bpose.t
                view_dir = xw.mean(axis=0) - camera.pose.centre
                facing = bpose.R[:, 2] @ view_dir / np.linalg.norm(view_dir)
                if abs(facing) < math.cos(math.radians(max_obliquity_deg)):
                    continue
                if facing < 0:   # the back of the board (its +z points away from the viewer)
                    continue
                uv = camera.project(xw)
                m = truth.models[cam]
                if not np.all(np.isfinite(uv)) or uv.min() < 5 or uv[:, 0].max() > m.width - 5 \
                        or uv[:, 1].max() > m.height - 5:
                    continue
                uv = uv + rng.normal(0.0, noise_px, uv.shape)
                if corrupt_fraction > 0:
                    bad = bad_rng.random(len(uv)) < corrupt_fraction
                    mag = bad_rng.uniform(*corrupt_px, bad.sum())
                    ang = bad_rng.uniform(0, 2 * math.pi, bad.sum())
                    uv[bad] += np.stack([mag * np.cos(ang), mag * np.sin(ang)], axis=1)
                out.append(Detection(cam, ti, float(a), b, np.arange(len(uv)), uv))
    return out


def volume_points(radius_mm: float = 120.0, z_range_mm=(0.0, 400.0), n: int = 600,
                  seed: int = 1) -> np.ndarray:
    """(n, 3) points spread uniformly through a plant-sized cylinder, mm, world frame."""
    rng = np.random.default_rng(seed)
    r = radius_mm * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * math.pi, n)
    z = rng.uniform(*z_range_mm, n)
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)


# --------------------------------------------------------------------------- rendered boards
def board_texture(spec: BoardSpec, px_per_mm: float, margin_mm: float | None = None,
                  index: int = 0) -> tuple[np.ndarray, float]:
    """(H, W) uint8 image of a board (``cols+1`` x ``rows+1`` squares) with a white margin.

    Returns the image and the margin (mm) between the image edge and the
    board's outer corner; inner corner 0 is one square further in.  A ChArUco
    board (board ``index``'s marker ids) comes from OpenCV, without margin.
    """
    if spec.kind == "charuco":
        w = int(round((spec.cols + 1) * spec.square_mm * px_per_mm))
        h = int(round((spec.rows + 1) * spec.square_mm * px_per_mm))
        return spec.charuco_board(index).generateImage((w, h), marginSize=0), 0.0
    m = spec.square_mm if margin_mm is None else margin_mm
    nx, ny = spec.cols + 1, spec.rows + 1
    w = int(round((nx * spec.square_mm + 2 * m) * px_per_mm))
    h = int(round((ny * spec.square_mm + 2 * m) * px_per_mm))
    # Pixel centre (u, v) sits at board mm ((u + 0.5) / ppm - m, ...) from the outer corner.
    u = (np.arange(w) + 0.5) / px_per_mm - m
    v = (np.arange(h) + 0.5) / px_per_mm - m
    iu = np.floor(u / spec.square_mm).astype(int)
    iv = np.floor(v / spec.square_mm).astype(int)
    inside = (iu[None, :] >= 0) & (iu[None, :] < nx) & (iv[:, None] >= 0) & (iv[:, None] < ny)
    black = ((iu[None, :] + iv[:, None]) % 2 == 0) & inside
    img = np.where(black, 25, 230).astype(np.uint8)
    return img, m


def render_board_view(camera, board_pose: Pose, spec: BoardSpec, texture: np.ndarray,
                      px_per_mm: float, margin_mm: float, background: int = 128,
                      supersample: int = 1) -> np.ndarray:
    """(H, W) uint8 image of the board seen by a distortion-free ``camera`` (homography warp).

    ``board_pose`` maps board-frame mm (inner corner 0 at the origin, as
    ``BoardSpec.object_points``) to the camera's world frame.
    """
    import cv2

    m = camera.model
    if supersample > 1:
        # Render finer and area-average: an anti-aliased image whose corners sit exactly
        # where the camera model puts them (CameraModel.scaled keeps pixel centres).
        big = m.scaled(supersample)
        from plantscan_core.data import Camera

        fine = render_board_view(Camera(big, camera.pose), board_pose, spec, texture, px_per_mm,
                                 margin_mm, background, supersample=1)
        return cv2.resize(fine, (m.width, m.height), interpolation=cv2.INTER_AREA)
    k = m.K
    r = camera.pose.R @ board_pose.R
    t = camera.pose.R @ board_pose.t + camera.pose.t
    h_img_board = k @ np.column_stack([r[:, 0], r[:, 1], t])
    # texture pixel centre (u, v) -> board mm of the inner-corner frame
    off = spec.square_mm + margin_mm
    h_board_tex = np.array([[1 / px_per_mm, 0, 0.5 / px_per_mm - off],
                            [0, 1 / px_per_mm, 0.5 / px_per_mm - off], [0, 0, 1.0]])
    hmat = h_img_board @ h_board_tex
    return cv2.warpPerspective(texture, hmat, (m.width, m.height), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=background)


def write_board_scan(root, rig: SyntheticRig, angles_deg, noise: float = 2.0, seed: int = 0,
                     px_per_mm: float = 8.0):
    """A scan folder of rendered calibration views of ``rig`` (distortion-free cameras).

    Every (camera, tilt, angle) gets an image; the board is visible in some.
    """
    import cv2

    from plantscan_core.data import ViewRecord
    from plantscan_core.scanfolder import ScanFolder

    rng = np.random.default_rng(seed)
    textures = {b: board_texture(rig.spec, px_per_mm, index=b) for b in rig.board_poses}
    scan = ScanFolder.create(root, {"plant_id": "synthetic-board", "rig": {
        "tilts_deg": [rig.truth.tilts_deg[i] for i in sorted(rig.truth.tilts_deg)]}})
    idx = 0
    for (cam, ti) in sorted(rig.truth.poses):
        for ai, a in enumerate(angles_deg):
            camera = rig.truth.camera_at(cam, ti, a)
            img = np.full((camera.model.height, camera.model.width), 128, np.uint8)
            for b, bp in rig.board_poses.items():
                xw = rig.boards[b] @ bp.R.T + bp.t
                view_dir = xw.mean(axis=0) - camera.pose.centre
                if bp.R[:, 2] @ view_dir <= 0:  # back of the board
                    continue
                tex, margin = textures[b]
                layer = render_board_view(camera, bp, rig.spec, tex, px_per_mm, margin, 0, 2)
                cover = render_board_view(camera, bp, rig.spec, np.full_like(tex, 255),
                                          px_per_mm, margin, 0, 2)
                img = np.where(cover > 127, layer, img)
            img = np.clip(img + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)
            name = f"images/calibration/{cam}_t{ti:02d}_a{ai:03d}.png"
            view = ViewRecord(idx, "calibration", cam, ti, rig.truth.tilts_deg[ti], ai, float(a),
                              None, name)
            scan.append_view(view, lambda p, im=img: cv2.imwrite(str(p), im) or
                             (_ for _ in ()).throw(OSError(f"cannot write {p}")))
            idx += 1
    return scan

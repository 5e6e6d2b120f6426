"""Bounding box of the plant from the silhouettes.

The seed took the silhouettes of the most horizontal views and the turntable
axis; that needs the turntable frame, which an imported rig (COLMAP) does not
have.  Here the initial box is the axis-aligned box of the intersection of
every silhouette's bounding frustum (a linear program per box face, exact for
the undistorted silhouette extents), which needs no rig knowledge; it is then
enlarged and refined by a quick coarse carve (128 voxels on the longest
side) with the same ``k`` tolerance as the real carve.  Occupied voxels on
the faces of the enlarged box mean the plant does not fit: the box grows and
the carve is repeated, and a box that still clips is reported.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from scipy.optimize import linprog

from plantscan_core.errors import DataError
from plantscan_hull.carve import Grid, carve_octree
from plantscan_hull.views import ViewField

# Views used for the linear programs (evenly spread); more add constraints, not accuracy.
MAX_LP_VIEWS = 72
# Views used by the quick carve.  Fewer views never remove more (the hull of a subset
# contains the hull of all), so the box stays safe; the final carve checks clipping.
MAX_BOX_CARVE_VIEWS = 48
# How far below ``floor_z`` the silhouettes may put the plant before the floor is taken
# for a frame mistake: the frustum box of a potted plant ends within ~15 mm of a
# plantscan plate (18 MP dicot scans: 5-15 mm above it); a calibration whose z = 0 is
# elsewhere (PhenoArch: the camera's height) puts it hundreds of mm below.
FLOOR_SLACK_MM = 50.0
FLOOR_SLACK_SHARE = 0.1  # of the frustum box's height, if more


class BoundingBoxError(DataError):
    """The carving box clips the plant (occupied voxels on its faces)."""


def _frustum_rows(view: ViewField) -> tuple[list[np.ndarray], list[float]]:
    """Half-space rows ``a . p <= b`` of the frustum of one silhouette's extent."""
    h, w = view.sd.shape
    mask = (view.sd > 0).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(float)
    # Pixel corners around each boundary pixel, so the frustum contains whole pixels.
    pts = (pts[:, None, :] + np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])
           ).reshape(-1, 2) + np.array([view.u0, view.v0])
    xy = view.camera.model.undistort_points(pts)
    rot, t = view.camera.pose.R, view.camera.pose.t
    rows, rhs = [], []
    u_min, v_min, u_max, v_max = view.box
    touches = {"u_lo": u_min <= 0, "u_hi": u_max >= view.width - 1,
               "v_lo": v_min <= 0, "v_hi": v_max >= view.height - 1}
    for axis, (lo_key, hi_key) in enumerate((("u_lo", "u_hi"), ("v_lo", "v_hi"))):
        lo, hi = xy[:, axis].min(), xy[:, axis].max()
        # x_c - lo z_c >= 0  and  hi z_c - x_c >= 0 (a side cut by the image edge is open).
        if not touches[lo_key]:
            rows.append(-(rot[axis] - lo * rot[2]))
            rhs.append(float(t[axis] - lo * t[2]))
        if not touches[hi_key]:
            rows.append(-(hi * rot[2] - rot[axis]))
            rhs.append(float(hi * t[2] - t[axis]))
    return rows, rhs


def frustum_box(views: Sequence[ViewField]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box ``(lo, hi)`` (mm) of the intersection of the silhouette frusta."""
    pick = np.unique(np.linspace(0, len(views) - 1, min(len(views), MAX_LP_VIEWS)).astype(int))
    rows, rhs = [], []
    for i in pick:
        r, b = _frustum_rows(views[i])
        rows += r
        rhs += b
    a = np.array(rows)
    b = np.array(rhs)
    lo, hi = np.zeros(3), np.zeros(3)
    for axis in range(3):
        for sign, out in ((1.0, lo), (-1.0, hi)):
            c = np.zeros(3)
            c[axis] = sign
            res = linprog(c, A_ub=a, b_ub=b, bounds=[(None, None)] * 3, method="highs")
            if res.status != 0:
                raise BoundingBoxError(
                    "cannot bound the plant from the silhouettes: the views' silhouette frusta "
                    f"{'do not intersect' if res.status == 2 else 'are unbounded'} (check the "
                    "calibration, or give reconstruct.params.bbox)")
            out[axis] = res.x[axis]
    return lo, hi


def touching_faces(occupied: np.ndarray) -> list[str]:
    """Names of the grid faces (``x-``, ``x+``...) with an occupied voxel."""
    faces = []
    for axis, name in enumerate("xyz"):
        sl = [slice(None)] * 3
        sl[axis] = 0
        if occupied[tuple(sl)].any():
            faces.append(f"{name}-")
        sl[axis] = -1
        if occupied[tuple(sl)].any():
            faces.append(f"{name}+")
    return faces


def auto_box(views: Sequence[ViewField], k: int, margin_mm: float, coarse: int = 128,
             grow: float = 0.25, attempts: int = 3, backend: str = "numpy",
             min_seen: int = 0, floor_z: float | None = None,
             ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Initial frustum box, refined by a ``coarse``-voxel carve; returns ``(lo, hi, info)``.

    ``floor_z`` (mm): nothing is below it (the turntable plate); cameras above
    the plate cannot carve under the pot, so the box stops there.
    """
    lo0, hi0 = frustum_box(views)
    if floor_z is not None:
        depth = floor_z - lo0[2]
        if depth > max(FLOOR_SLACK_MM, FLOOR_SLACK_SHARE * (hi0[2] - lo0[2])):
            raise BoundingBoxError(
                f"the silhouettes put the plant down to z = {lo0[2]:.0f} mm, {depth:.0f} mm "
                f"below reconstruct.params.floor_z_mm = {floor_z:g} mm (the top of the "
                "turntable plate in a plantscan calibration), and nothing below the floor is "
                "kept: the plant would be cut off there. The calibration's height gauge is "
                "the first suspect: a wrong calibrate.params.lowest_corner_height_mm (the "
                "board's lowest corner above the plate) shifts every camera up or down by the "
                "error; check it and calibrate again. If this calibration's z = 0 is not "
                "the plate (a calibration imported from another rig or program), set "
                "reconstruct.params.floor_z_mm to the plate's height, or to null")
        lo0[2] = max(lo0[2], floor_z)
        hi0[2] = max(hi0[2], floor_z + 1.0)
    lo, hi = lo0.copy(), hi0.copy()
    if len(views) > MAX_BOX_CARVE_VIEWS:
        from plantscan_hull.carve import interleaved

        subset = interleaved(views)[:MAX_BOX_CARVE_VIEWS]
        # Looser than the scaled rule: a subset may see a point less often than all views.
        min_seen = max(k + 1, int(0.8 * min_seen * len(subset) / len(views)))
        views = subset
    for attempt in range(attempts):
        ext = hi - lo
        lo_big, hi_big = lo - grow * ext - margin_mm, hi + grow * ext + margin_mm
        if floor_z is not None:
            lo_big[2] = max(lo_big[2], floor_z)
        grid = Grid.from_box(lo_big, hi_big, coarse)
        phi, stats = carve_octree(views, grid, k, top_cell=16, backend=backend,
                                  min_seen=min_seen)
        occ = phi > -0.5
        if not occ.any():
            raise BoundingBoxError(
                "the quick carve removed everything: the silhouettes do not agree on any "
                f"point (k={k}); check the calibration or the masks")
        faces = touching_faces(occ)
        if floor_z is not None and lo_big[2] <= floor_z:
            faces = [f for f in faces if f != "z-"]  # resting on the plate is not clipping
        if not faces:
            idx = np.argwhere(occ)
            s = grid.voxel_size
            lo_f = grid.centres(idx.min(axis=0)) - s - margin_mm
            hi_f = grid.centres(idx.max(axis=0)) + s + margin_mm
            if floor_z is not None:
                lo_f[2] = max(lo_f[2], floor_z)
            info = {"frustum_box_mm": [lo0.tolist(), hi0.tolist()],
                    "coarse_voxel_mm": s, "attempts": attempt + 1}
            return lo_f, hi_f, info
        lo, hi = lo_big, hi_big
    raise BoundingBoxError(
        f"the plant still touches the bounding box faces {', '.join(faces)} after {attempts} "
        f"enlargements ({lo_big.round(1).tolist()} .. {hi_big.round(1).tolist()} mm); "
        "the silhouettes probably cut the plant at the image edges: give "
        "reconstruct.params.bbox")

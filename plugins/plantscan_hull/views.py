"""Per-view preparation: the 2D signed distance to a silhouette's boundary.

A voxel is carved against the signed distance ``sd`` (px) from its projection
to the silhouette boundary, > 0 inside the mask, < 0 outside.  The field is
1-Lipschitz, so one sample at a cell's projected centre bounds the whole cell:
``sd(centre) > r`` means every point of the cell projects inside, ``< -r``
every point outside, where ``r`` bounds the cell's projected radius.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from plantscan_core.data import Calibration, Camera, CameraModel, Silhouette
from plantscan_core.errors import DataError
from plantscan_core.parallel import thread_map

# Pixels kept around the mask's bounding box in the distance table; beyond it
# the distance to the box is used (a lower bound of the distance to the mask).
ROI_MARGIN_PX = 24


@dataclass
class ViewField:
    """Signed distance to one silhouette's boundary, plus the posed camera.

    Attributes
    ----------
    camera : Camera
        World (turntable frame, mm) -> pixels, distortion included.
    sd : (h, w) int16 array, units of ``SD_STEP`` px
        Signed distance at the pixel centres of the region of interest
        ``[u0, u0 + w) x [v0, v0 + h)``, > 0 inside the mask, in fixed point
        (``sd * SD_STEP`` px, see ``signed_distance_table``).  The tables of
        ``prepare_views`` share one buffer.
    u0, v0 : int, px
        Top-left pixel of the region of interest in the image.
    box : (4,) float64 array, px
        ``u_min, v_min, u_max, v_max`` of the mask's pixels.
    width, height : int, px
        Image size.
    gain : float, px per mm at unit depth
        Upper bound of the local magnification of the projection (focal
        length times the worst distortion stretch and obliquity in the image),
        so ``gain * rho / (depth - rho)`` bounds the projected radius of a
        ball of radius ``rho`` (mm).
    label : str
        Names the view in error messages.
    """

    camera: Camera
    sd: np.ndarray
    u0: int
    v0: int
    box: np.ndarray
    width: int
    height: int
    gain: float
    label: str

    @property
    def focal(self) -> float:
        return float(self.camera.model.f)


# The 5x5 chamfer distance of OpenCV is within 2 % of Euclidean (3-8x faster than the
# exact transform); its Lipschitz constant w.r.t. image distance is below this bound,
# which the conservative cell tests multiply projected radii by.
DISTANCE_LIPSCHITZ = 1.02


# Fixed-point step (px) of the distance tables.  Rounding to the nearest step moves a
# value by <= SD_STEP / 2, so two table reads differ by at most 1.02 |a - b| + SD_STEP:
# the cell tests' slack (CELL_SLACK_PX = 1.5 px, of which 1.02 * 1.42 = 1.45 px are used
# by the pixel readings) still holds with 1/32 px (1.48 px).  The int16 range is then
# +-1024 px; saturation moves values towards 0, which keeps every cell test
# conservative and changes no clamped voxel value while a voxel spans < 1024 px.
SD_STEP = 1.0 / 32.0
SD_DTYPE = np.int16


_scratch = threading.local()


def _scratch_buffers(shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """This thread's reusable float32, float32, uint8, uint8 arrays of ``shape``.

    Fresh multi-MB temporaries for every view come from the kernel as zeroed
    pages; reused ones are already mapped (minor page faults for 360 views at
    2592x1728: 2e5 -> 1e4).
    """
    n = shape[0] * shape[1]
    bufs = getattr(_scratch, "buffers", None)
    if bufs is None or bufs[0].size < n:
        bufs = (np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.uint8),
                np.empty(n, np.uint8))
        _scratch.buffers = bufs
    return tuple(b[:n].reshape(shape) for b in bufs)


def _chamfer(mask: np.ndarray, reuse: bool = False, at: tuple[int, int] | None = None,
             shape: tuple[int, int] | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(d_in, d_out, m)``: OpenCV's 5x5 chamfer distances of the mask and its inverse.

    With ``reuse`` the results live in this thread's scratch buffers (valid
    until its next call); then ``mask`` may also be a crop placed at row,
    column ``at`` of an otherwise empty region of ``shape``, written straight
    into the scratch mask (a full-size region per view is 2.4 MB of fresh
    pages at 3000x2000).
    """
    if not reuse:
        m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
        d_in = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_5)
        d_out = cv2.distanceTransform(m ^ 1, cv2.DIST_L2, cv2.DIST_MASK_5)
    else:
        d_in, d_out, m, inv = _scratch_buffers(mask.shape if shape is None else shape)
        if at is None:
            np.copyto(m, mask, casting="unsafe")  # bool -> 0/1
        else:
            m.fill(0)
            (v, u), (ch, cw) = at, mask.shape
            np.copyto(m[v:v + ch, u:u + cw], mask, casting="unsafe")
        np.bitwise_xor(m, 1, out=inv)
        # OpenCV writes into ``dst`` (contiguous float32 of the right shape) and returns it.
        d_in = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_5, dst=d_in)
        d_out = cv2.distanceTransform(inv, cv2.DIST_L2, cv2.DIST_MASK_5, dst=d_out)
    return d_in, d_out, m


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (px) of every pixel centre to the boundary of ``mask``.

    Parameters
    ----------
    mask : (H, W) bool array

    Returns
    -------
    (H, W) float32 array, px
        ``+(d_in - 0.5)`` inside, ``-(d_out - 0.5)`` outside, so the zero
        level lies on the pixel edges between mask and background and a
        bilinear interpolation of it crosses zero there.  ``d`` is OpenCV's
        5x5 chamfer distance (within 2 % of Euclidean, exact near the edge).
    """
    # d_in = 0 outside and d_out = 0 inside: d_in - d_out + 0.5 - m is
    # d_in - 0.5 inside and 0.5 - d_out outside, in three passes without temporaries.
    d_in, d_out, m = _chamfer(mask)
    cv2.subtract(d_in, m, dst=d_in, dtype=cv2.CV_32F)
    cv2.subtract(d_in, d_out, dst=d_in)
    d_in += 0.5
    return d_in


def signed_distance_table(mask: np.ndarray, out: np.ndarray | None = None,
                          at: tuple[int, int] | None = None) -> np.ndarray:
    """``signed_distance(mask) / SD_STEP`` rounded to int16 (saturated), written into ``out``.

    Parameters
    ----------
    mask : (H, W) bool array, or with ``at`` a crop of it
    out : (H, W) int16 C-contiguous array, optional
        Where to write (a slice of the shared table buffer); allocated if None.
    at : (row, column), optional
        ``mask`` is the crop at this position of an otherwise empty (H, W) mask
        (``out`` gives the shape); the full mask is never built.

    Returns
    -------
    (H, W) int16 array, units of ``SD_STEP`` px: ``out`` itself when given.
    Half the memory of the float32 distances, from the same two transforms:
    one pass does the combination, the scaling and the conversion (round half
    to even, saturate): compiled (``kernels.distance_table``), or without numba
    OpenCV's ``subtract`` and ``addWeighted``, which give the same table.
    """
    if at is not None and out is None:
        raise ValueError("signed_distance_table: a crop position needs out (its shape)")
    from plantscan_hull import kernels

    d_in, d_out, m = _chamfer(mask, reuse=True, at=at, shape=None if at is None else out.shape)
    if out is None:
        out = np.empty(d_in.shape, dtype=SD_DTYPE)
    if kernels.distance_table(d_in, d_out, m, out):  # the same table in one pass
        return out
    cv2.subtract(d_in, m, dst=d_in, dtype=cv2.CV_32F)
    res = cv2.addWeighted(d_in, 1.0 / SD_STEP, d_out, -1.0 / SD_STEP, 0.5 / SD_STEP, dst=out,
                          dtype=cv2.CV_16S)
    if res is not out and not np.shares_memory(res, out):  # OpenCV reallocated: copy back
        out[...] = res
    return out


@functools.lru_cache(maxsize=64)
def projection_gain(model: CameraModel) -> float:
    """Upper bound of |d(pixel)| / (|d(point)| / depth) over the image (px).

    The pinhole Jacobian of ``(X/Z, Y/Z)`` has spectral norm
    ``sqrt(1 + r^2) / Z``; the radial model stretches by at most
    ``max(|s(r)|, |d(r s(r))/dr|)``.  Both are maximised over the normalised
    radii reached inside the image (its corners, undistorted).
    """
    w = model.width or 2 * (model.cu + 0.5)
    h = model.height or 2 * (model.cv + 0.5)
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_max = float(np.max(np.linalg.norm(model.undistort_points(corners), axis=1))) * 1.05
    r = np.linspace(0.0, r_max, 256)
    r2 = r * r
    s = 1.0 + model.d1 * r2 + model.d2 * r2 * r2
    ds = 1.0 + 3.0 * model.d1 * r2 + 5.0 * model.d2 * r2 * r2
    stretch = float(max(np.max(np.abs(s)), np.max(np.abs(ds))))
    return float(model.f) * stretch * math.sqrt(1.0 + r_max * r_max)


def view_label(sil: Silhouette) -> str:
    v = sil.view
    return (f"view {v.index} ({v.file}, camera {v.camera}, tilt {v.tilt_index}, "
            f"angle {v.angle_deg:g} deg)")


def _checked_region(sil: Silhouette, camera: Camera
                    ) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The silhouette's pixel box and its table's region of interest.

    Returns ``box`` (4,) float64 ``u_min, v_min, u_max, v_max`` px, and
    ``(u0, v0, u1, v1)``: the box plus ``ROI_MARGIN_PX``, within the image.

    Raises
    ------
    DataError
        The mask's size differs from the camera model's image size, or the
        mask is empty or all foreground (each names the view).
    """
    label = view_label(sil)
    # A Silhouette holds its mask cropped to the plant's box: the checks and the box come
    # from the crop, never from a full-size copy of the mask.
    crop = sil.crop
    if crop.ndim != 2:
        raise DataError(f"{label}: mask must be a 2D (H, W) array, got shape {crop.shape}")
    h, w = sil.shape
    model = camera.model
    if (model.width and model.width != w) or (model.height and model.height != h):
        raise DataError(
            f"{label}: mask is {w}x{h} px but the calibration's camera {sil.view.camera!r} "
            f"images are {model.width}x{model.height} px (masks do not match the calibration)"
        )
    if crop.size == 0:
        raise DataError(f"{label}: silhouette is empty (no plant pixel); check the segmentation")
    bh, bw = crop.shape
    if bw == w and bh == h and crop.all():
        raise DataError(f"{label}: silhouette is all foreground; check the segmentation "
                        "(a background plate may be missing)")
    u_min, v_min = sil.u0, sil.v0
    u_max, v_max = u_min + bw - 1, v_min + bh - 1
    roi = (max(0, u_min - ROI_MARGIN_PX), max(0, v_min - ROI_MARGIN_PX),
           min(w, u_max + ROI_MARGIN_PX + 1), min(h, v_max + ROI_MARGIN_PX + 1))
    return np.array([u_min, v_min, u_max, v_max], dtype=float), roi


def _view_field(sil: Silhouette, camera: Camera, box: np.ndarray,
                roi: tuple[int, int, int, int], out: np.ndarray | None) -> ViewField:
    u0, v0, u1, v1 = roi
    if out is None:
        out = np.empty((v1 - v0, u1 - u0), dtype=SD_DTYPE)
    # The crop placed in its table's region of interest.
    sd = signed_distance_table(sil.crop, out, at=(sil.v0 - v0, sil.u0 - u0))
    h, w = sil.shape
    return ViewField(camera=camera, sd=sd, u0=u0, v0=v0, box=box, width=w, height=h,
                     gain=projection_gain(camera.model), label=view_label(sil))


def prepare_view(sil: Silhouette, camera: Camera) -> ViewField:
    """Check one silhouette against its camera and build its distance table.

    Raises
    ------
    DataError
        The mask's size differs from the camera model's image size, or the
        mask is empty or all foreground (each names the view).
    """
    return _view_field(sil, camera, *_checked_region(sil, camera), None)


def prepare_views(silhouettes: Sequence[Silhouette], calibration: Calibration) -> list[ViewField]:
    """``prepare_view`` for every silhouette with its calibrated camera.

    All tables are written straight into one int16 buffer (each view's ``sd``
    is a slice of it): the carve kernels read them from there, so they are
    never copied, and the buffer is one allocation returned to the system
    when the views are dropped (360 separate tables of a few MB each stay in
    the allocator's arenas after they are freed).  Views are prepared on a
    small thread pool: OpenCV's distance transform releases the GIL.
    """
    cameras = []
    for sil in silhouettes:
        try:
            cameras.append(calibration.camera_for_view(sil.view))
        except KeyError as exc:
            raise DataError(f"{view_label(sil)}: no camera in the calibration ({exc})") from None
    checked = thread_map(_checked_region, silhouettes, cameras)
    sizes = [(r[3] - r[1]) * (r[2] - r[0]) for _, r in checked]
    buffer = np.empty(int(sum(sizes)), dtype=SD_DTYPE)
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    outs = [buffer[a:a + n].reshape(r[3] - r[1], r[2] - r[0])
            for a, n, (_, r) in zip(starts[:-1], sizes, checked, strict=True)]

    def one(i: int) -> ViewField:
        box, roi = checked[i]
        return _view_field(silhouettes[i], cameras[i], box, roi, outs[i])

    views = thread_map(one, range(len(cameras)))
    _scratch.__dict__.pop("buffers", None)  # this thread's, when it did the work (1 worker)
    return views


def project(view: ViewField, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(N, 3)`` mm -> pixels ``(N, 2)`` and depth ``(N,)`` mm.

    Uses the camera model's own projection (distortion included); NaN pixels
    behind the camera.
    """
    pc = view.camera.pose.apply(points)
    return view.camera.model.project_camera_points(pc), pc[:, 2]


def _outside_box_bound(view: ViewField, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """-(distance to the mask's bounding box): an upper bound of ``sd`` outside the ROI."""
    bu0, bv0, bu1, bv1 = view.box
    du = np.maximum(np.maximum(bu0 - 0.5 - u, u - bu1 - 0.5), 0.0)
    dv = np.maximum(np.maximum(bv0 - 0.5 - v, v - bv1 - 0.5), 0.0)
    return -np.hypot(du, dv)


def sample_nearest(view: ViewField, uv: np.ndarray) -> np.ndarray:
    """``sd`` (px) at the nearest pixel centre of ``uv`` ``(N, 2)``.

    Outside the table, the negative distance to the mask's box (never larger
    than the true value, so tests built on it stay conservative).
    """
    u, v = uv[:, 0], uv[:, 1]
    h, w = view.sd.shape
    lu = np.nan_to_num(u, nan=-1e9) - view.u0
    lv = np.nan_to_num(v, nan=-1e9) - view.v0
    # Within the table's pixels (half a pixel beyond its edge centres included).
    inside = (lu >= -0.5) & (lu <= w - 0.5) & (lv >= -0.5) & (lv <= h - 0.5)
    out = _outside_box_bound(view, u, v).astype(np.float32)
    iu = np.clip(np.rint(lu[inside]), 0, w - 1).astype(np.intp)
    iv = np.clip(np.rint(lv[inside]), 0, h - 1).astype(np.intp)
    out[inside] = view.sd[iv, iu].astype(np.float32) * np.float32(SD_STEP)
    return out


def sample_bilinear(view: ViewField, uv: np.ndarray) -> np.ndarray:
    """``sd`` (px) bilinearly interpolated at ``uv`` ``(N, 2)`` (sub-pixel boundary)."""
    u = np.nan_to_num(uv[:, 0], nan=-1e9) - view.u0
    v = np.nan_to_num(uv[:, 1], nan=-1e9) - view.v0
    h, w = view.sd.shape
    # Within half a pixel of the table's edge centres the edge value is held (the
    # table often ends at the image edge, where there is nothing further to read).
    inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    out = _outside_box_bound(view, uv[:, 0], uv[:, 1]).astype(np.float32)
    ui = np.clip(u[inside], 0, w - 1)
    vi = np.clip(v[inside], 0, h - 1)
    x0 = np.minimum(np.floor(ui).astype(np.intp), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(vi).astype(np.intp), h - 2 if h > 1 else 0)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (ui - x0).astype(np.float32)
    fy = (vi - y0).astype(np.float32)
    sd = view.sd
    # Same order of float32 operations as the compiled ``kernels._bilinear``.
    a, b = sd[y0, x0].astype(np.float32), sd[y0, x1].astype(np.float32)
    c, d = sd[y1, x0].astype(np.float32), sd[y1, x1].astype(np.float32)
    top = a * (1 - fx) + b * fx
    bot = c * (1 - fx) + d * fx
    out[inside] = (top * (1 - fy) + bot * fy) * np.float32(SD_STEP)
    return out

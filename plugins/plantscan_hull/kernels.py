"""Compiled (numba) versions of the two hot loops of ``carve``.

Same arithmetic as ``carve.voxel_field`` and ``carve.classify_cells`` (the
numpy reference), fused over views per point so a point stops being tested
as soon as its fate is sealed.  Only for the seed's camera model
(``CameraModel`` itself: pinhole + d1, d2); another model falls back to the
numpy path, which calls the model's own projection.  Tested against the numpy
path and ``dense-hull`` in ``tests/hull/test_kernels.py``.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from plantscan_core.data import CameraModel
from plantscan_hull.views import ViewField

try:  # numba is optional: the numpy path is complete without it
    import numba
    from numba import njit, prange

    # Debian's libtbb is older than numba wants; numba then uses OpenMP or its own
    # work queue by itself.  The warning says nothing a user can act on.
    warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB")
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False

# Per-view parameter row layout.
_R, _T, _F, _CU, _CV, _D1, _D2 = 0, 9, 12, 13, 14, 15, 16
_W, _H, _GAIN, _U0, _V0, _TW, _TH, _BOX, _OFF, _FY = 17, 18, 19, 20, 21, 22, 23, 24, 28, 29
_NPARAM = 30
# Points per chunk of the view-major loops (neighbours in the octree's order).
CHUNK = 2048


def supported(views: Sequence[ViewField]) -> bool:
    """True when numba is installed and every camera uses the seed's model."""
    return HAVE_NUMBA and all(type(v.camera.model) is CameraModel for v in views)


def pack(views: Sequence[ViewField]) -> tuple[np.ndarray, np.ndarray]:
    """(V, 30) float64 parameter rows and the concatenated float32 distance tables."""
    rows = np.zeros((len(views), _NPARAM))
    tables = []
    offset = 0
    for i, v in enumerate(views):
        m = v.camera.model
        rows[i, _R:_R + 9] = v.camera.pose.R.ravel()
        rows[i, _T:_T + 3] = v.camera.pose.t
        rows[i, [_F, _CU, _CV, _D1, _D2]] = [m.f, m.cu, m.cv, m.d1, m.d2]
        rows[i, [_W, _H, _GAIN, _U0, _V0]] = [v.width, v.height, v.gain, v.u0, v.v0]
        th, tw = v.sd.shape
        rows[i, [_TW, _TH]] = [tw, th]
        rows[i, _BOX:_BOX + 4] = v.box
        rows[i, _OFF] = offset
        rows[i, _FY] = m.fy
        tables.append(np.ascontiguousarray(v.sd, dtype=np.float32).ravel())
        offset += th * tw
    return rows, np.concatenate(tables) if tables else np.zeros(0, np.float32)


if HAVE_NUMBA:

    @njit(cache=True, inline="always")
    def _project(p, x, y, z):
        xc = p[0] * x + p[1] * y + p[2] * z + p[9]
        yc = p[3] * x + p[4] * y + p[5] * z + p[10]
        zc = p[6] * x + p[7] * y + p[8] * z + p[11]
        if zc <= 0.0:
            return np.nan, np.nan, zc
        xn = xc / zc
        yn = yc / zc
        r2 = xn * xn + yn * yn
        s = 1.0 + p[15] * r2 + p[16] * r2 * r2
        return p[12] * xn * s + p[13], p[29] * yn * s + p[14], zc

    @njit(cache=True, inline="always")
    def _box_bound(p, u, v):
        du = max(max(p[24] - 0.5 - u, u - p[26] - 0.5), 0.0)
        dv = max(max(p[25] - 0.5 - v, v - p[27] - 0.5), 0.0)
        return -np.float32(np.sqrt(du * du + dv * dv))

    @njit(cache=True, inline="always")
    def _bilinear(p, tables, u, v):
        w = int(p[22])
        h = int(p[23])
        lu = u - p[20]
        lv = v - p[21]
        if not (lu >= -0.5 and lu <= w - 0.5 and lv >= -0.5 and lv <= h - 0.5):
            return _box_bound(p, u, v)
        lu = min(max(lu, 0.0), w - 1.0)
        lv = min(max(lv, 0.0), h - 1.0)
        x0 = min(int(np.floor(lu)), w - 2 if w > 1 else 0)
        y0 = min(int(np.floor(lv)), h - 2 if h > 1 else 0)
        x1 = min(x0 + 1, w - 1)
        y1 = min(y0 + 1, h - 1)
        fx = np.float32(lu - x0)
        fy = np.float32(lv - y0)
        off = int(p[28])
        a = tables[off + y0 * w + x0]
        b = tables[off + y0 * w + x1]
        c = tables[off + y1 * w + x0]
        d = tables[off + y1 * w + x1]
        top = a * (1 - fx) + b * fx
        bot = c * (1 - fx) + d * fx
        return top * (1 - fy) + bot * fy

    @njit(cache=True, inline="always")
    def _nearest(p, tables, u, v):
        w = int(p[22])
        h = int(p[23])
        lu = u - p[20]
        lv = v - p[21]
        if not (lu >= -0.5 and lu <= w - 0.5 and lv >= -0.5 and lv <= h - 0.5):
            return _box_bound(p, u, v)
        iu = min(max(int(np.rint(lu)), 0), w - 1)
        iv = min(max(int(np.rint(lv)), 0), h - 1)
        return tables[int(p[28]) + iv * w + iu]

    @njit(cache=True, parallel=True)
    def _voxel_field(points, params, tables, voxel_size, k, min_seen, chunk):
        # View-major inside a chunk of neighbouring points: they project to a small
        # patch of each view's table, so the table reads stay in cache (point-major
        # order reads a different table every test and is memory bound).
        n = points.shape[0]
        nv = params.shape[0]
        nchunks = (n + chunk - 1) // chunk
        out = np.empty(n, dtype=np.float32)
        tests = np.zeros(nchunks, dtype=np.int64)
        for c in prange(nchunks):
            a = c * chunk
            m = min(n, a + chunk) - a
            kept = np.full((m, k + 1), np.inf, dtype=np.float32)
            seen = np.zeros(m, dtype=np.int32)
            done = np.zeros(m, dtype=np.bool_)
            count = 0
            for j in range(nv):
                p = params[j]
                for ii in range(m):
                    if done[ii]:
                        continue
                    i = a + ii
                    count += 1
                    u, v, zc = _project(p, points[i, 0], points[i, 1], points[i, 2])
                    if not (zc > 0 and u >= -0.5 and u <= p[17] - 0.5 and v >= -0.5
                            and v <= p[18] - 0.5):
                        continue
                    seen[ii] += 1
                    d = np.float32(_bilinear(p, tables, u, v) * (zc / (p[12] * voxel_size)))
                    worst = 0
                    for q in range(1, k + 1):
                        if kept[ii, q] > kept[ii, worst]:
                            worst = q
                    if d < kept[ii, worst]:
                        kept[ii, worst] = d
                        mx = kept[ii, 0]
                        for q in range(1, k + 1):
                            mx = max(mx, kept[ii, q])
                        if mx <= -1.0:
                            done[ii] = True  # k+1 views at <= -1: final after clamping
            for ii in range(m):
                mx = kept[ii, 0]
                for q in range(1, k + 1):
                    mx = max(mx, kept[ii, q])
                val = min(max(mx, np.float32(-1.0)), np.float32(1.0))
                if seen[ii] < min_seen and mx > -1.0:
                    val = np.float32(-1.0)
                out[a + ii] = val
            tests[c] = count
        return out, tests.sum()

    @njit(cache=True, parallel=True)
    def _classify(centres, half_size, voxel_size, params, tables, k, slack, min_seen, lip,
                  chunk):
        m_all = centres.shape[0]
        nv = params.shape[0]
        rho = half_size * np.sqrt(3.0)
        nchunks = (m_all + chunk - 1) // chunk
        decision = np.empty(m_all, dtype=np.int8)
        tests = np.zeros(nchunks, dtype=np.int64)
        max_off = nv - min_seen
        for c in prange(nchunks):
            a = c * chunk
            m = min(m_all, a + chunk) - a
            n_out = np.zeros(m, dtype=np.int32)
            n_amb = np.zeros(m, dtype=np.int32)
            n_on = np.zeros(m, dtype=np.int32)
            n_off = np.zeros(m, dtype=np.int32)
            count = 0
            for j in range(nv):
                p = params[j]
                lo_u, hi_u, lo_v, hi_v = -0.5, p[17] - 0.5, -0.5, p[18] - 0.5
                for ii in range(m):
                    if n_out[ii] > k or n_off[ii] > max_off:
                        continue  # removed already
                    i = a + ii
                    count += 1
                    u, v, zc = _project(p, centres[i, 0], centres[i, 1], centres[i, 2])
                    if zc + rho <= 0:
                        n_off[ii] += 1  # wholly behind the camera: not seen
                        continue
                    near = zc - rho
                    if near <= 0:
                        n_amb[ii] += 1
                        continue
                    inv = p[19] / near
                    r = rho * inv
                    if u + r < lo_u or u - r > hi_u or v + r < lo_v or v - r > hi_v:
                        n_off[ii] += 1  # footprint off the image: not seen
                        continue
                    if not (u - r >= lo_u and u + r <= hi_u and v - r >= lo_v
                            and v + r <= hi_v):
                        n_amb[ii] += 1
                        continue
                    n_on[ii] += 1
                    margin = lip * r + voxel_size * inv + slack
                    sd = _nearest(p, tables, u, v)
                    if sd < -margin:
                        n_out[ii] += 1
                    elif not sd > margin:
                        n_amb[ii] += 1
            for ii in range(m):
                if n_out[ii] > k or n_off[ii] > max_off:
                    decision[a + ii] = 0
                elif n_out[ii] + n_amb[ii] <= k and n_on[ii] >= min_seen:
                    decision[a + ii] = 1
                else:
                    decision[a + ii] = 2
            tests[c] = count
        return decision, tests.sum()


def voxel_field(packed, points: np.ndarray, voxel_size: float, k: int, stats=None,
                min_seen: int = 0) -> np.ndarray:
    """Compiled ``carve.voxel_field`` (``packed`` from ``pack``)."""
    params, tables = packed
    out, tests = _voxel_field(np.ascontiguousarray(points, dtype=np.float64), params, tables,
                              float(voxel_size), int(k), int(min_seen), CHUNK)
    if stats is not None:
        stats.voxel_view_tests += int(tests)
    return out


def classify_cells(packed, centres: np.ndarray, half_size: float, voxel_size: float, k: int,
                   slack: float, stats=None, min_seen: int = 0, lipschitz: float = 1.0,
                   ) -> np.ndarray:
    """Compiled ``carve.classify_cells``."""
    params, tables = packed
    decision, tests = _classify(np.ascontiguousarray(centres, dtype=np.float64),
                                float(half_size), float(voxel_size), params, tables, int(k),
                                float(slack), int(min_seen), float(lipschitz), CHUNK)
    if stats is not None:
        stats.cell_view_tests += int(tests)
    return decision


def threads() -> int:
    return int(numba.get_num_threads()) if HAVE_NUMBA else 1

"""Compiled (numba) versions of the hot loops of ``carve``.

Same arithmetic as ``carve.voxel_field`` and ``carve.classify_cells`` (the
numpy reference), fused over views per point so a point stops being tested
as soon as its fate is sealed.  Only for the seed's camera model
(``CameraModel`` itself: pinhole + d1, d2); another model falls back to the
numpy path, which calls the model's own projection.  Tested against the numpy
path and ``dense-hull`` in ``tests/hull/test_carve.py``; the field of the
octree is pinned to the bit in ``tests/hull/test_field_digest.py``.

What the kernels share travels in records, never as positional scalars:
``Packed`` (the views' parameter rows and distance tables), ``CarveConsts``
(the constants of one carve level), ``Tree`` (the cells' lists of views still
ambiguous), ``CellCounts`` (a level's decisions), and inside a kernel
``ViewRow`` (one view's constants), ``Block`` (a chunk of parents) and
``Passes`` (the scratch of the vectorised passes).
"""

from __future__ import annotations

import warnings
from collections import namedtuple
from collections.abc import Sequence

import numpy as np

from plantscan_core.data import CameraModel
from plantscan_hull.views import SD_DTYPE, SD_STEP, ViewField

try:  # numba is optional: the numpy path is complete without it
    import numba
    from numba import njit, prange, types
    from numba.core import cgutils
    from numba.extending import intrinsic, overload

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
# Outcomes of the conservative cell test in one view (``_cell_test``).
CELL_OFF, CELL_EDGE, CELL_OUT, CELL_IN, CELL_AMB = 0, 1, 2, 3, 4
# Decisions on a cell.
REMOVED, FULL, SPLIT = 0, 1, 2
# Fixed-point step of the distance tables (px), a compile-time constant of the kernels.
_SD_STEP = np.float32(SD_STEP)
_SQRT2 = float(np.sqrt(2.0))
# Parents per batch of ``classify_group``: its scratch lists (8 per parent, each as long as
# the parent's) exist for one batch at a time, not for the whole level (2.2 GB at 1024^3).
GROUP_BATCH = 1 << 16
# Points per chunk of the view-major loops (neighbours in the octree's order).
CHUNK = 2048
# Parent cells per chunk of the sibling-group kernels (1024: 12 % fewer ns per voxel test
# than 256 on the benchmark plant, single-threaded; 64 and 4096 are slower).
GROUP_CHUNK = 1024

Packed = namedtuple("Packed", ["params", "tables"])
Packed.__doc__ = """The views as the kernels read them (``pack``).

params : (V, 30) float64 array, one row per view (layout ``_R`` .. ``_FY``)
tables : (N,) int16 array, every view's distance table (row ``_OFF`` is its offset)
"""

CarveConsts = namedtuple("CarveConsts", ["half_size", "voxel_size", "k", "min_seen", "slack",
                                         "lip", "bil_r"])
CarveConsts.__doc__ = """The constants of one carve level (``carve_consts``).

half_size : float, mm -- half the side of the level's cells (0 for single voxels)
voxel_size : float, mm
k : int -- a point outside in more than k views is removed
min_seen : int -- a point seen by fewer views is removed
slack : float, px -- slack of the cell test reading the nearest pixel
lip : float -- Lipschitz constant of the distance tables (px per px)
bil_r : float, px -- largest footprint radius read bilinearly by the cell test
"""


def carve_consts(voxel_size: float, k: int, min_seen: int, half_size: float = 0.0,
                 slack: float = 0.0, lip: float = 0.0, bil_r: float = 0.0) -> CarveConsts:
    """A ``CarveConsts`` with the types the kernels are compiled for (one signature)."""
    return CarveConsts(float(half_size), float(voxel_size), int(k), int(min_seen), float(slack),
                       float(lip), float(bil_r))


Tree = namedtuple("Tree", ["start", "views", "n_out", "n_in", "n_off"])
Tree.__doc__ = """Octree carve state: per live cell, the views it left ambiguous.

start, views : CSR lists of the ambiguous views of each cell (int64 offsets, int16
    view indices in the packed, interleaved order)
n_out, n_in, n_off : (M,) int32 -- views already decided out, in, off the image
"""


def root_tree(n_views: int) -> Tree:
    """The ``Tree`` of one cell holding the whole grid: every view ambiguous."""
    zero = np.zeros(1, np.int32)
    return Tree(np.array([0, n_views], dtype=np.int64), np.arange(n_views, dtype=np.int16),
                zero, zero.copy(), zero.copy())


CellCounts = namedtuple("CellCounts", ["decision", "n_out", "n_in", "n_off", "n_amb", "amb",
                                       "amb_start"])
CellCounts.__doc__ = """What a level's cell kernels found, per cell.

decision : (M,) int8 -- REMOVED, FULL or SPLIT
n_out, n_in, n_off, n_amb : (M,) int32 -- views out, in, off, ambiguous
amb, amb_start : scratch lists of the ambiguous views (cell i's at amb_start[i]..,
    its first n_amb[i] entries, in the global view order)
"""


def supported(views: Sequence[ViewField]) -> bool:
    """True when numba is installed and every camera uses the seed's model."""
    return HAVE_NUMBA and all(type(v.camera.model) is CameraModel for v in views)


def pack(views: Sequence[ViewField]) -> Packed:
    """(V, 30) float64 parameter rows and one int16 buffer holding the distance tables.

    When every view's ``sd`` already lives in one buffer (``prepare_views``
    writes them so; any subset, any order) that buffer is used as it is: the
    rows hold each table's offset.  Otherwise (views prepared one by one) the
    tables are copied into a new buffer and each view's ``sd`` is re-pointed at
    its slice (same values), so the tables are held once from then on.
    """
    rows = np.zeros((len(views), _NPARAM))
    offsets = _offsets_in_shared_buffer(views)
    if offsets is None:
        sizes = [v.sd.size for v in views]
        tables = np.empty(int(sum(sizes)), dtype=SD_DTYPE)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        for v, o, n in zip(views, offsets, sizes, strict=True):
            part = tables[o:o + n].reshape(v.sd.shape)
            part[...] = v.sd
            v.sd = part
    else:
        tables = views[0].sd.base
    for i, v in enumerate(views):
        m = v.camera.model
        rows[i, _R:_R + 9] = v.camera.pose.R.ravel()
        rows[i, _T:_T + 3] = v.camera.pose.t
        rows[i, [_F, _CU, _CV, _D1, _D2]] = [m.f, m.cu, m.cv, m.d1, m.d2]
        rows[i, [_W, _H, _GAIN, _U0, _V0]] = [v.width, v.height, v.gain, v.u0, v.v0]
        th, tw = v.sd.shape
        rows[i, [_TW, _TH]] = [tw, th]
        rows[i, _BOX:_BOX + 4] = v.box
        rows[i, _OFF] = offsets[i]
        rows[i, _FY] = m.fy
    return Packed(rows, tables)


def _offsets_in_shared_buffer(views: Sequence[ViewField]) -> np.ndarray | None:
    """Offsets (elements) of the views' tables in the one 1-D buffer they all share, or None."""
    if not views:
        return None
    buf = views[0].sd.base
    if not (isinstance(buf, np.ndarray) and buf.ndim == 1 and buf.dtype == SD_DTYPE):
        return None
    start = buf.__array_interface__["data"][0]
    out = np.empty(len(views), dtype=np.int64)
    for i, v in enumerate(views):
        if v.sd.base is not buf or not v.sd.flags.c_contiguous or v.sd.dtype != SD_DTYPE:
            return None
        out[i] = (v.sd.__array_interface__["data"][0] - start) // buf.itemsize
    return out


# One view's constants in the kernels' inner loops, read from its ``params`` row once per
# view: indexing ``params`` inside a loop reloads them at every test (the compiler cannot
# prove the loop's stores do not alias it); a tuple stays in registers.
ViewRow = namedtuple("ViewRow", [
    "r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22", "t0", "t1", "t2",
    "f", "fy", "cu", "cv", "d1", "d2", "u_hi", "v_hi", "gain",
    "u0", "v0", "tw", "th", "off", "bu0", "bv0", "bu1", "bv1"])
# A chunk of parent cells lo..hi of a sibling kernel: per parent, the position of the next
# view in its list (``cursor``) and how many of its children are still live (``alive``).
Block = namedtuple("Block", ["lo", "hi", "cursor", "alive"])
# Scratch of the vectorised passes over the children of a block in one view: centres X, Y,
# Z (camera frame), table index IDX and fractions FX, FY of the (bilinear) reading, its 4
# corners A..D; cells: outcome RES, MARGIN, bilinear or not BIL; voxels: depth / (f voxel)
# ZF, seen ON, value DD; SEL the parents taking the view.
Passes = namedtuple("Passes", ["X", "Y", "Z", "IDX", "FX", "FY", "A", "B", "C", "D", "RES",
                               "MARGIN", "BIL", "ZF", "ON", "DD", "SEL"])

if HAVE_NUMBA:

    @intrinsic
    def _take(typingctx, counter):
        # Atomically counter[0] += 1; returns the value before: the next chunk of a
        # work-stealing loop (``_steal``).  numba has no CPU atomics of its own, and its
        # prange schedule is static halves (its chunk size setting gave none of the
        # interleaving with the omp or workqueue layers here, measured).
        sig = types.int64(counter)

        def codegen(context, builder, signature, args):
            ary = context.make_array(signature.args[0])(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, signature.args[0], ary,
                                           [context.get_constant(types.intp, 0)])
            return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1),
                                      "seq_cst")

        return sig, codegen

    @njit(cache=True, inline="always")
    def _row(params, j):
        p = params[j]
        return ViewRow(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11],
                       p[12], p[29], p[13], p[14], p[15], p[16], p[17] - 0.5, p[18] - 0.5, p[19],
                       p[20], p[21], int(p[22]), int(p[23]), int(p[28]),
                       p[24], p[25], p[26], p[27])

    @njit(cache=True, inline="always")
    def _cam(vr, x, y, z):
        # World (mm) -> camera frame (mm).
        return (vr.r00 * x + vr.r01 * y + vr.r02 * z + vr.t0,
                vr.r10 * x + vr.r11 * y + vr.r12 * z + vr.t1,
                vr.r20 * x + vr.r21 * y + vr.r22 * z + vr.t2)

    @njit(cache=True, inline="always")
    def _radial(vr, xc, yc, zc):
        # Camera frame -> pixels, the seed's radial model, for zc > 0 (branch-free: the
        # vectorised passes call it with any positive stand-in depth behind the camera).
        xn = xc / zc
        yn = yc / zc
        r2 = xn * xn + yn * yn
        s = 1.0 + vr.d1 * r2 + vr.d2 * r2 * r2
        return vr.f * xn * s + vr.cu, vr.fy * yn * s + vr.cv

    @njit(cache=True, inline="always")
    def _pixel(vr, xc, yc, zc):
        # Camera frame -> pixels; NaN behind the camera.
        if zc <= 0.0:
            return np.nan, np.nan
        return _radial(vr, xc, yc, zc)

    @njit(cache=True, inline="always")
    def _child_offsets(vr, half, out):
        # Camera-frame offsets (8, 3) of the 8 children's centres from their parent's,
        # in the order of ``carve._children`` (x: bit 4, y: bit 2, z: bit 1).
        for ch in range(8):
            sx = half if ch & 4 else -half
            sy = half if ch & 2 else -half
            sz = half if ch & 1 else -half
            out[ch, 0] = vr.r00 * sx + vr.r01 * sy + vr.r02 * sz
            out[ch, 1] = vr.r10 * sx + vr.r11 * sy + vr.r12 * sz
            out[ch, 2] = vr.r20 * sx + vr.r21 * sy + vr.r22 * sz

    @njit(cache=True, inline="always")
    def _takes_view(cursor, c, start, views, i, j):
        # Whether view j is next in parent i's list ``start``, ``views`` (global view
        # order); advances its cursor ``cursor[c]``.
        t = cursor[c]
        if t >= start[i + 1] or views[t] != j:
            return False
        cursor[c] = t + 1
        return True

    @njit(cache=True, inline="always")
    def _box_bound(vr, u, v):
        du = max(max(vr.bu0 - 0.5 - u, u - vr.bu1 - 0.5), 0.0)
        dv = max(max(vr.bv0 - 0.5 - v, v - vr.bv1 - 0.5), 0.0)
        return -np.float32(np.sqrt(du * du + dv * dv))

    @njit(cache=True, inline="always")
    def _lerp2(a, b, c, d, fx, fy):
        # Bilinear blend of the four int16 corner readings a (x0, y0), b (x1, y0),
        # c (x0, y1), d (x1, y1), in table steps (float32); one order of operations for
        # every kernel, so their fields agree to the bit.
        top = np.float32(a) * (1 - fx) + np.float32(b) * fx
        bot = np.float32(c) * (1 - fx) + np.float32(d) * fx
        return top * (1 - fy) + bot * fy

    @njit(cache=True, inline="always")
    def _bilinear_row(vr, tables, u, v):
        w = vr.tw
        h = vr.th
        lu = u - vr.u0
        lv = v - vr.v0
        if not (lu >= -0.5 and lu <= w - 0.5 and lv >= -0.5 and lv <= h - 0.5):
            return _box_bound(vr, u, v)
        lu = min(max(lu, 0.0), w - 1.0)
        lv = min(max(lv, 0.0), h - 1.0)
        x0 = min(int(np.floor(lu)), w - 2 if w > 1 else 0)
        y0 = min(int(np.floor(lv)), h - 2 if h > 1 else 0)
        x1 = min(x0 + 1, w - 1)
        y1 = min(y0 + 1, h - 1)
        fx = np.float32(lu - x0)
        fy = np.float32(lv - y0)
        return _lerp2(tables[vr.off + y0 * w + x0], tables[vr.off + y0 * w + x1],
                      tables[vr.off + y1 * w + x0], tables[vr.off + y1 * w + x1],
                      fx, fy) * _SD_STEP

    @njit(cache=True, inline="always")
    def _nearest_row(vr, tables, u, v):
        w = vr.tw
        h = vr.th
        lu = u - vr.u0
        lv = v - vr.v0
        if not (lu >= -0.5 and lu <= w - 0.5 and lv >= -0.5 and lv <= h - 0.5):
            return _box_bound(vr, u, v)
        iu = min(max(int(np.rint(lu)), 0), w - 1)
        iv = min(max(int(np.rint(lv)), 0), h - 1)
        return np.float32(tables[vr.off + iv * w + iu]) * _SD_STEP

    @njit(cache=True, inline="always")
    def _cell_test(vr, tables, xc, yc, zc, rho, cc):
        # A cell (voxel centres within rho mm of its centre xc, yc, zc, camera frame) in
        # one view: CELL_OFF its footprint is off the image (not seen), CELL_EDGE partly
        # off (or the camera within reach), CELL_OUT / CELL_IN every voxel of it beyond
        # the clamp outside / inside, CELL_AMB on the image and undecided.  See
        # ``carve.classify_cells``.
        if zc + rho <= 0:
            return CELL_OFF  # wholly behind the camera
        near = zc - rho
        if near <= 0:
            return CELL_EDGE
        u, v = _pixel(vr, xc, yc, zc)
        inv = vr.gain / near
        r = rho * inv
        if u + r < -0.5 or u - r > vr.u_hi or v + r < -0.5 or v - r > vr.v_hi:
            return CELL_OFF
        if not (u - r >= -0.5 and u + r <= vr.u_hi and v - r >= -0.5 and v + r <= vr.v_hi):
            return CELL_EDGE
        # One voxel in px at the nearest depth: the field is d = sd * z / (f * voxel),
        # so |sd| > f * voxel / near puts every voxel beyond the +-1 clamp.
        one_voxel = cc.voxel_size * vr.f / near
        # Small footprints (the 2- and often 4-voxel cells): the bilinear value at the
        # centre is within lip * sqrt(2) * r + one table step of the voxels' (see
        # ``carve.classify_cells``), tighter than the nearest pixel's lip * r + slack.
        lu = u - vr.u0
        lv = v - vr.v0
        if (r < cc.bil_r and lu - r >= -0.5
                and lu + r <= vr.tw - 0.5 and lv - r >= -0.5 and lv + r <= vr.th - 0.5):
            margin = cc.lip * _SQRT2 * r + _SD_STEP + one_voxel
            sd = _bilinear_row(vr, tables, u, v)
        else:
            margin = cc.lip * r + one_voxel + cc.slack
            sd = _nearest_row(vr, tables, u, v)
        if sd < -margin:
            return CELL_OUT
        if sd > margin:
            return CELL_IN
        return CELL_AMB

    @njit(cache=True, inline="always")
    def _removed(n_out, n_off, k, max_off):
        # Out in more than k views, or off more images than min_seen allows: removed.
        return n_out > k or n_off > max_off

    @njit(cache=True, inline="always")
    def _decide(n_out, n_in, n_off, n_amb, n_on_amb, max_off, cc):
        # A cell's decision from its views' outcomes (``carve.classify_cells``): full when
        # out or ambiguous in at most k views and wholly on at least min_seen images.
        if _removed(n_out, n_off, cc.k, max_off):
            return REMOVED
        if n_out + n_amb <= cc.k and n_out + n_in + n_on_amb >= cc.min_seen:
            return FULL
        return SPLIT

    @njit(cache=True, inline="always")
    def _voxel_test(vr, tables, xc, yc, zc, fs):
        # (seen, d): whether a voxel centre (camera frame) projects on the image, and its
        # cone distance d (voxels; ``fs`` = focal length * voxel size).
        u, v = _pixel(vr, xc, yc, zc)
        if not (zc > 0 and u >= -0.5 and u <= vr.u_hi and v >= -0.5 and v <= vr.v_hi):
            return False, np.float32(0.0)
        return True, np.float32(_bilinear_row(vr, tables, u, v) * (zc / fs))

    @njit(cache=True, inline="always")
    def _keep_smallest(kept, f, k, d):
        # Replace the largest of row f's k+1 smallest values by d (< it); returns the new
        # largest: the (k+1)-th smallest so far.
        worst = 0
        for q in range(1, k + 1):
            if kept[f, q] > kept[f, worst]:
                worst = q
        kept[f, worst] = d
        m = kept[f, 0]
        for q in range(1, k + 1):
            m = max(m, kept[f, q])
        return m

    @njit(cache=True, inline="always")
    def _final_value(kth, seen, min_seen):
        # A voxel's field: its clamped (k+1)-th smallest value, -1 when fewer than
        # min_seen views saw it (and it is not removed already).
        val = min(max(kth, np.float32(-1.0)), np.float32(1.0))
        if seen < min_seen and kth > -1.0:
            val = np.float32(-1.0)
        return val

    @njit(cache=True, parallel=True)
    def _voxel_field(points, packed, cc, chunk):
        # View-major inside a chunk of neighbouring points: they project to a small
        # patch of each view's table, so the table reads stay in cache (point-major
        # order reads a different table every test and is memory bound).
        params, tables, k = packed.params, packed.tables, cc.k
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
            mxs = np.full(m, np.inf, dtype=np.float32)
            count = 0
            for j in range(nv):
                vr = _row(params, j)
                fs = vr.f * cc.voxel_size
                for ii in range(m):
                    if done[ii]:
                        continue
                    i = a + ii
                    count += 1
                    xc, yc, zc = _cam(vr, points[i, 0], points[i, 1], points[i, 2])
                    on, d = _voxel_test(vr, tables, xc, yc, zc, fs)
                    if not on:
                        continue
                    seen[ii] += 1
                    if d < mxs[ii]:
                        mxs[ii] = _keep_smallest(kept, ii, k, d)
                        if mxs[ii] <= -1.0:
                            done[ii] = True  # k+1 views at <= -1: final after clamping
            for ii in range(m):
                mx = kept[ii, 0]
                for q in range(1, k + 1):
                    mx = max(mx, kept[ii, q])
                out[a + ii] = _final_value(mx, seen[ii], cc.min_seen)
            tests[c] = count
        return out, tests.sum()

    # ------------------------------------------------------------------ octree with inheritance
    # A cell's test in a view is conservative for every point of the cell: when a
    # parent is *out*, *in* or *off* in a view, so is every child and every voxel
    # (their clamped values are exactly -1, +1, or "not seen").  Children therefore
    # test only the views their parent left ambiguous.  Per cell: counts of the
    # decided views (out, in, off) and the list of ambiguous views (CSR, int16).

    # Records go into a parallel loop as arguments of the kernel, never made inside it
    # (numba 0.68 cannot type a record made in the function of a parallel loop, and
    # wrote nothing through one), and every kernel reads a record's fields into locals
    # before its loops: each read of a field holds a reference to its array, and those
    # counts in the inner loops made the kernels 1.35-1.8x slower (measured).

    @njit(cache=True)
    def _tree_range(lo, hi, centres, parent, tree, cc, packed, out):
        # Cells lo..hi, each a child of ``tree``'s cell parent[i], test their parent's
        # ambiguous views; their counts and decisions go to ``out`` (``cell_counts``).
        params, tables = packed.params, packed.tables
        rho = (cc.half_size - 0.5 * cc.voxel_size) * np.sqrt(3.0)  # voxel centres: see carve
        max_off = params.shape[0] - cc.min_seen
        decision, c_out, c_in, c_off, c_amb, amb, amb_start = out
        start, views, p_out, p_in, p_off = tree
        count = 0
        for i in range(lo, hi):
            q = parent[i]
            n_out = p_out[q]
            n_in = p_in[q]
            n_off = p_off[q]
            n_on_amb = 0
            na = 0  # ambiguous views, in the global view order
            w = amb_start[i]
            x = centres[i, 0]
            y = centres[i, 1]
            z = centres[i, 2]
            for t in range(start[q], start[q + 1]):
                if _removed(n_out, n_off, cc.k, max_off):
                    break
                j = views[t]
                count += 1
                vr = _row(params, j)
                xc, yc, zc = _cam(vr, x, y, z)
                res = _cell_test(vr, tables, xc, yc, zc, rho, cc)
                if res == CELL_OFF:
                    n_off += 1
                elif res == CELL_OUT:
                    n_out += 1
                elif res == CELL_IN:
                    n_in += 1
                else:
                    amb[w + na] = j  # ambiguous views, in the global view order
                    na += 1
                    n_on_amb += res == CELL_AMB
            c_out[i] = n_out
            c_in[i] = n_in
            c_off[i] = n_off
            c_amb[i] = na
            decision[i] = _decide(n_out, n_in, n_off, na, n_on_amb, max_off, cc)
        return count

    @njit(cache=True, parallel=True)  # on both cores: the other one idled here (#28)
    def _gather_lists(sel, counts, out_start):
        # The lists of the cells ``sel``: the first n_amb entries of each one's scratch.
        views = np.empty(out_start[-1], dtype=np.int16)
        for t in prange(sel.shape[0]):
            a = counts.amb_start[sel[t]]
            o = out_start[t]
            for q in range(counts.n_amb[sel[t]]):
                views[o + q] = counts.amb[a + q]
        return views

    # ------------------------------------------------------------------ the field in blocks
    # ``plantscan_core.data.BlockField``: index (BX, BY, BZ) int32, OUTSIDE -1 / INSIDE -2 /
    # a row of values (M, B, B, B) float32.  The carve writes only into the rows (the mixed
    # blocks, allocated from the split cells of the block's side); voxels beyond the grid
    # stay -1.

    @njit(cache=True, parallel=True)
    def _fill_minus_one(flat):
        for i in prange(flat.shape[0]):
            flat[i] = np.float32(-1.0)

    @njit(cache=True, inline="always")
    def _block_get(index, values, bs, a, b, c):
        row = index[a // bs, b // bs, c // bs]
        if row == -1:
            return np.float32(-1.0)
        if row == -2:
            return np.float32(1.0)
        return values[row, a % bs, b % bs, c % bs]

    @njit(cache=True)  # serial: cheap, and parallel compiles slowly
    def _fill_blocked(index, values, shape, cells, size, value):
        # Cells (corners ``cells`` (C, 3), side ``size`` <= the block's) inside mixed
        # blocks: their voxels within the grid get ``value``.
        bs = values.shape[1]
        nx, ny, nz = shape
        for t in range(cells.shape[0]):
            x0, y0, z0 = cells[t, 0], cells[t, 1], cells[t, 2]
            row = index[x0 // bs, y0 // bs, z0 // bs]
            a0, b0, e0 = x0 % bs, y0 % bs, z0 % bs
            for a in range(min(size, nx - x0)):
                for b in range(min(size, ny - y0)):
                    for e in range(min(size, nz - z0)):
                        values[row, a0 + a, b0 + b, e0 + e] = value

    @njit(cache=True, parallel=True)  # on both cores: the other one idled here (#28)
    def _scatter_fine_blocked(index, values, shape, cells, vals, valid, thin_value, keep_thin):
        # The fine voxels are the 8 children of the split 2-voxel cells with corners
        # ``cells`` (P, 3) (order of ``carve._children``; never materialised: 0.7 GB of
        # int64 indices at 1024^3), all in mixed blocks.  Writes their ``vals`` (P * 8,)
        # where ``valid``, then the thin-part rescue: only fine voxels can hold a value in
        # (-0.5, 0] (decided cells hold exactly -1 or +1); a candidate with no 6-neighbour
        # inside (before any rescue; a neighbour may lie in an implicit block) gets
        # ``thin_value``; exact zeros -> -1e-3.  Returns the number rescued.
        bs = values.shape[1]
        nx, ny, nz = shape
        n = cells.shape[0]
        # each loop writes only its own voxels (the three run one after the other)
        for p in prange(n):
            row = index[cells[p, 0] // bs, cells[p, 1] // bs, cells[p, 2] // bs]
            for ch in range(8):
                if valid[p * 8 + ch]:
                    values[row, cells[p, 0] % bs + (ch >> 2), cells[p, 1] % bs + ((ch >> 1) & 1),
                           cells[p, 2] % bs + (ch & 1)] = vals[p * 8 + ch]
        rescue = np.zeros(n * 8, dtype=np.bool_)
        for p in prange(n):
            for ch in range(8):
                val = vals[p * 8 + ch]
                if not (valid[p * 8 + ch] and val > -0.5 and val <= 0.0):
                    continue
                a = cells[p, 0] + (ch >> 2)
                b = cells[p, 1] + ((ch >> 1) & 1)
                c = cells[p, 2] + (ch & 1)
                near = ((a > 0 and _block_get(index, values, bs, a - 1, b, c) > 0)
                        or (a + 1 < nx and _block_get(index, values, bs, a + 1, b, c) > 0)
                        or (b > 0 and _block_get(index, values, bs, a, b - 1, c) > 0)
                        or (b + 1 < ny and _block_get(index, values, bs, a, b + 1, c) > 0)
                        or (c > 0 and _block_get(index, values, bs, a, b, c - 1) > 0)
                        or (c + 1 < nz and _block_get(index, values, bs, a, b, c + 1) > 0))
                rescue[p * 8 + ch] = keep_thin and not near
        count = 0
        for p in prange(n):
            row = index[cells[p, 0] // bs, cells[p, 1] // bs, cells[p, 2] // bs]
            for ch in range(8):
                if not valid[p * 8 + ch]:
                    continue
                a = cells[p, 0] % bs + (ch >> 2)
                b = cells[p, 1] % bs + ((ch >> 1) & 1)
                c = cells[p, 2] % bs + (ch & 1)
                if rescue[p * 8 + ch]:
                    values[row, a, b, c] = thin_value
                    count += 1
                elif values[row, a, b, c] == 0:
                    values[row, a, b, c] = -1e-3
        return count

    # ------------------------------------------------------------------ groups of 8 siblings
    # The 8 children of a split cell share their parent's list of ambiguous views:
    # they are tested together, from the projection of the parent's centre plus
    # the rotated half-offsets (3 additions per child instead of a matrix product).
    # A chunk of parents is processed view-major (lists are in the global view
    # order), so one view's table is read for neighbouring cells in a row.  Per view,
    # the children of the parents that take it are projected in one branch-free loop
    # that the compiler vectorises (8 divisions at once), their 4 table values read in
    # a second loop and their values formed in a third (session 6: scalar, the voxels
    # cost 33-41 ns per test on the captured 256^3 input, in passes 17-22 ns).

    @njit(cache=True)
    def _block(lo, hi, tree):
        return Block(lo, hi, tree.start[lo:hi].copy(), np.zeros(hi - lo, np.int32))

    @njit(cache=True)
    def _passes(n, n_parents):
        # The scratch of the passes for n children of n_parents parents.
        return Passes(np.empty(n), np.empty(n), np.empty(n), np.empty(n, dtype=np.int64),
                      np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32),
                      np.empty(n, dtype=SD_DTYPE), np.empty(n, dtype=SD_DTYPE),
                      np.empty(n, dtype=SD_DTYPE), np.empty(n, dtype=SD_DTYPE),
                      np.empty(n, dtype=np.int8), np.empty(n), np.empty(n, dtype=np.bool_),
                      np.empty(n), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.float32),
                      np.empty(n_parents, dtype=np.int64))

    @njit(cache=True, inline="always")
    def _children_in_view(vr, j, offs, centres, tree, block, buf):
        # The parents of the block whose list holds view j (next, in the global view
        # order) and that have live children: their indices in buf.SEL[:ns], their 8
        # children's centres (camera frame, ``offs`` from the parent's) in buf.X, Y,
        # Z[:8 ns].  Returns ns and the number of live children among them (the tests
        # counted).
        lo, cursor, alive = block.lo, block.cursor, block.alive
        start, views = tree.start, tree.views
        X, Y, Z, SEL = buf.X, buf.Y, buf.Z, buf.SEL
        ns = 0
        count = 0
        for i in range(lo, block.hi):
            if not _takes_view(cursor, i - lo, start, views, i, j) or alive[i - lo] == 0:
                continue
            count += alive[i - lo]
            xc0, yc0, zc0 = _cam(vr, centres[i, 0], centres[i, 1], centres[i, 2])
            for ch in range(8):
                X[ns * 8 + ch] = xc0 + offs[ch, 0]
                Y[ns * 8 + ch] = yc0 + offs[ch, 1]
                Z[ns * 8 + ch] = zc0 + offs[ch, 2]
            SEL[ns] = i
            ns += 1
        return ns, count

    @njit(cache=True, inline="always")
    def _in_table(vr, lu, lv):
        # Whether a point at (lu, lv) relative to the table's corner reads the table.
        return (lu >= -0.5) & (lu <= vr.tw - 0.5) & (lv >= -0.5) & (lv <= vr.th - 0.5)

    # ------------------------------------------------------------------ cells, in passes
    @njit(cache=True, error_model="numpy")
    def _project_cells(n, buf, vr, rho, cc):
        # The geometry of ``_cell_test`` for the cells centred at buf.X, Y, Z[:n] (camera
        # frame), branch-free: RES CELL_OFF / CELL_EDGE when decided without the table,
        # else -1 and the margin and table reading to decide it (``_cell_outcomes``):
        # bilinear at the centre for small footprints, else the nearest pixel, which is
        # the bilinear formula with zero fractions on one corner (the same value).
        # Returns how many nearest readings fall beyond the table (the box bound:
        # ``_cells_beyond_table``).
        X, Y, Z, RES, MARGIN, IDX, BIL, FX, FY = (buf.X, buf.Y, buf.Z, buf.RES, buf.MARGIN,
                                                   buf.IDX, buf.BIL, buf.FX, buf.FY)
        voxel_size, lip, slack, bil_r = cc.voxel_size, cc.lip, cc.slack, cc.bil_r
        w = vr.tw
        h = vr.th
        x_max = w - 2 if w > 1 else 0
        y_max = h - 2 if h > 1 else 0
        n_beyond = 0
        for t in range(n):
            zc = Z[t]
            near = zc - rho
            zs = zc if zc > 0.0 else 1.0  # behind: decided below, any finite pixel
            u, v = _radial(vr, X[t], Y[t], zs)
            ns = near if near > 0.0 else 1.0
            r = rho * (vr.gain / ns)
            off_img = (u + r < -0.5) | (u - r > vr.u_hi) | (v + r < -0.5) | (v - r > vr.v_hi)
            in_img = (u - r >= -0.5) & (u + r <= vr.u_hi) & (v - r >= -0.5) & (v + r <= vr.v_hi)
            behind = zc + rho <= 0
            off = behind | ((near > 0.0) & off_img)
            edge = ~behind & ((near <= 0.0) | (~off_img & ~in_img))
            read = ~off & ~edge
            one_voxel = voxel_size * vr.f / ns
            lu = u - vr.u0
            lv = v - vr.v0
            bil = ((r < bil_r) & (lu - r >= -0.5) & (lu + r <= w - 0.5) & (lv - r >= -0.5)
                   & (lv + r <= h - 0.5))
            n_beyond += read & ~bil & ~_in_table(vr, lu, lv)
            MARGIN[t] = (lip * _SQRT2 * r + _SD_STEP + one_voxel if bil
                         else lip * r + one_voxel + slack)
            RES[t] = CELL_OFF if off else (CELL_EDGE if edge else -1)
            # Unread cells read the table's first pixel (any in-bounds index; unused).
            lu = min(max(lu, 0.0), w - 1.0) if read else 0.0
            lv = min(max(lv, 0.0), h - 1.0) if read else 0.0
            x0 = min(int(np.floor(lu)), x_max)
            y0 = min(int(np.floor(lv)), y_max)
            iu = min(max(int(np.rint(lu)), 0), w - 1)
            iv = min(max(int(np.rint(lv)), 0), h - 1)
            IDX[t] = vr.off + (y0 * w + x0 if bil else iv * w + iu)
            BIL[t] = bil
            FX[t] = np.float32(lu - x0) if bil else np.float32(0.0)
            FY[t] = np.float32(lv - y0) if bil else np.float32(0.0)
        return n_beyond

    @njit(cache=True, error_model="numpy")
    def _cell_outcomes(n, tables, buf, dx1, dy1):
        # The table readings of the cells with RES -1 and their outcomes.
        IDX, BIL, FX, FY, MARGIN, RES = buf.IDX, buf.BIL, buf.FX, buf.FY, buf.MARGIN, buf.RES
        A, B, C, D = buf.A, buf.B, buf.C, buf.D
        for t in range(n):
            q = IDX[t]
            A[t] = tables[q]
            dx = dx1 if BIL[t] else 0  # the nearest pixel: all 4 corners on it
            dy = dy1 if BIL[t] else 0
            B[t] = tables[q + dx]
            C[t] = tables[q + dy]
            D[t] = tables[q + dy + dx]
        for t in range(n):
            sd = _lerp2(A[t], B[t], C[t], D[t], FX[t], FY[t]) * _SD_STEP
            m = MARGIN[t]
            res = CELL_OUT if sd < -m else (CELL_IN if sd > m else CELL_AMB)
            RES[t] = res if RES[t] < 0 else RES[t]

    @njit(cache=True)
    def _cells_beyond_table(n, buf, vr):
        # The cells read at a nearest pixel beyond the table (rare): the box bound.
        X, Y, Z, RES, BIL, MARGIN = buf.X, buf.Y, buf.Z, buf.RES, buf.BIL, buf.MARGIN
        for t in range(n):
            if RES[t] <= CELL_EDGE or BIL[t]:
                continue
            u, v = _pixel(vr, X[t], Y[t], Z[t])  # as in ``_project_cells``
            if not _in_table(vr, u - vr.u0, v - vr.v0):
                sd = _box_bound(vr, u, v)
                RES[t] = CELL_OUT if sd < -MARGIN[t] else (CELL_IN if sd > MARGIN[t] else CELL_AMB)

    # Per child of a block: the counts of its views' outcomes, whether it lies in the grid
    # (live_ok), and which of its parent's listed views it found ambiguous: bit q of
    # ambig[q // 64, child] for list position q.  One row per 64 positions, so a view's
    # updates write one contiguous row (writing the lists view by view touched one cache
    # line per child: 20 % of the time); the lists are written at the end.
    Siblings = namedtuple("Siblings", ["n_out", "n_in", "n_off", "n_on_amb", "na", "live_ok",
                                       "ambig"])

    @njit(cache=True)
    def _siblings(block, valid, tree, k, max_off):
        # The children's counts start as their parent's; ``block.alive`` their live ones.
        n = (block.hi - block.lo) * 8
        longest = 0
        for i in range(block.lo, block.hi):
            longest = max(longest, tree.start[i + 1] - tree.start[i])
        sib = Siblings(np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.int32),
                       np.zeros(n, np.int32), np.zeros(n, np.int32), np.empty(n, np.bool_),
                       np.zeros(((longest + 63) // 64, n), np.uint64))
        n_out, n_in, n_off, live_ok = sib.n_out, sib.n_in, sib.n_off, sib.live_ok
        alive = block.alive
        for i in range(block.lo, block.hi):
            for ch in range(8):
                f = (i - block.lo) * 8 + ch
                n_out[f] = tree.n_out[i]
                n_in[f] = tree.n_in[i]
                n_off[f] = tree.n_off[i]
                live_ok[f] = valid[i * 8 + ch]
                alive[i - block.lo] += live_ok[f] and not _removed(n_out[f], n_off[f], k, max_off)
        return sib

    @njit(cache=True, inline="always")
    def _count_outcomes(ns, block, tree, sib, buf, k, max_off):
        # Adds the outcomes in buf.RES of the children of the ns parents buf.SEL to their
        # counts; a removed child is still counted with its siblings (it stays removed:
        # its counts only grow) but no longer counted as live.
        lo, cursor, alive, start, SEL, RES = (block.lo, block.cursor, block.alive, tree.start,
                                              buf.SEL, buf.RES)
        n_out, n_in, n_off, n_on_amb, na, live_ok, ambig = sib
        for s in range(ns):
            i = SEL[s]
            a = 0
            q = cursor[i - lo] - 1 - start[i]  # the view's place in the parent's list
            row = q >> 6
            bit = np.uint64(1) << np.uint64(q & 63)
            for ch in range(8):
                f = (i - lo) * 8 + ch
                res = RES[s * 8 + ch]
                n_off[f] += res == CELL_OFF
                n_out[f] += res == CELL_OUT
                n_in[f] += res == CELL_IN
                is_amb = (res == CELL_EDGE) | (res == CELL_AMB)
                ambig[row, f] |= bit if is_amb else np.uint64(0)
                na[f] += is_amb
                n_on_amb[f] += res == CELL_AMB
                a += live_ok[f] and not _removed(n_out[f], n_off[f], k, max_off)
            alive[i - lo] = a

    @njit(cache=True)
    def _write_cells(block, valid, tree, sib, max_off, cc, out):
        # The children's decisions and counts into ``out``; the split children's lists of
        # ambiguous views (in the global view order), for their own children: the
        # siblings' lists are written in one walk of the parent's list (each slot
        # written, kept if its bit is set: a list never outgrows the walk).  Other
        # children's lists are not read.
        n_out, n_in, n_off, n_on_amb, na, _, ambig = sib
        decision, c_out, c_in, c_off, c_amb, amb, amb_start = out
        start, views, lo = tree.start, tree.views, block.lo
        w = np.empty(8, np.int64)
        for i in range(lo, block.hi):
            any_split = False
            for ch in range(8):
                f = (i - lo) * 8 + ch
                g = i * 8 + ch
                if not valid[g]:
                    continue  # beyond the grid: decision REMOVED
                c_out[g] = n_out[f]
                c_in[g] = n_in[f]
                c_off[g] = n_off[f]
                c_amb[g] = na[f]
                decision[g] = _decide(n_out[f], n_in[f], n_off[f], na[f], n_on_amb[f], max_off,
                                      cc)
                any_split |= decision[g] == SPLIT
            if not any_split:
                continue
            for ch in range(8):
                w[ch] = amb_start[i * 8 + ch]
            p0 = start[i]
            for q in range(start[i + 1] - p0):
                view = views[p0 + q]
                row = q >> 6
                shift = np.uint64(q & 63)
                for ch in range(8):
                    amb[w[ch]] = view
                    w[ch] += np.int64((ambig[row, (i - lo) * 8 + ch] >> shift) & np.uint64(1))

    @njit(cache=True)
    def _classify_range(lo, hi, centres, valid, tree, cc, packed, out):
        # Serial body of ``_steal`` for sibling groups: parents lo..hi, view-major: for each
        # view (lists are in the global view order) the children of the parents whose
        # list holds it are projected and decided in vectorised passes, then counted.
        params, tables = packed.params, packed.tables
        rho = (cc.half_size - 0.5 * cc.voxel_size) * np.sqrt(3.0)  # voxel centres: see carve
        max_off = params.shape[0] - cc.min_seen
        block = _block(lo, hi, tree)
        sib = _siblings(block, valid, tree, cc.k, max_off)
        buf = _passes((hi - lo) * 8, hi - lo)
        offs = np.empty((8, 3))
        count = 0
        for j in range(params.shape[0]):
            vr = _row(params, j)
            _child_offsets(vr, cc.half_size, offs)
            ns, tested = _children_in_view(vr, j, offs, centres, tree, block, buf)
            count += tested
            n_beyond = _project_cells(ns * 8, buf, vr, rho, cc)
            _cell_outcomes(ns * 8, tables, buf, 1 if vr.tw > 1 else 0,
                           vr.tw if vr.th > 1 else 0)
            if n_beyond:
                _cells_beyond_table(ns * 8, buf, vr)
            _count_outcomes(ns, block, tree, sib, buf, cc.k, max_off)
        _write_cells(block, valid, tree, sib, max_off, cc, out)
        return count

    # ------------------------------------------------------------------ fine voxels, in passes
    # Each voxel keeps its k+1 smallest values sorted in kept[p, :, ch] (kept[p, k, ch] is
    # the (k+1)-th smallest), updated without branches, the 8 siblings at once
    # (vectorised min / max).  Same field to the bit and same test counts as the scalar
    # ``_voxel_test`` and ``_keep_smallest`` view by view (the reference in the tests).

    @njit(cache=True, error_model="numpy")
    def _project_children(n, buf, vr, fs):
        # Camera-frame points buf.X, Y, Z[:n] -> their depth / (f voxel) ZF, whether seen
        # ON and, for ``_bilinear_row``'s in-table branch, the table index of the upper-left
        # neighbour IDX and fractions FX, FY (same arithmetic as ``_pixel`` and
        # ``_bilinear_row``).  Returns how many seen points fall beyond the table (their
        # bilinear value is the box bound: ``_voxels_beyond_table``).
        X, Y, Z, ZF, IDX, FX, FY, ON = buf.X, buf.Y, buf.Z, buf.ZF, buf.IDX, buf.FX, buf.FY, buf.ON
        w = vr.tw
        h = vr.th
        x_max = w - 2 if w > 1 else 0
        y_max = h - 2 if h > 1 else 0
        n_off = 0
        for t in range(n):
            zc = Z[t]
            zs = zc if zc > 0.0 else 1.0  # behind the camera: not seen, any finite pixel
            u, v = _radial(vr, X[t], Y[t], zs)
            on = (zc > 0.0) & (u >= -0.5) & (u <= vr.u_hi) & (v >= -0.5) & (v <= vr.v_hi)
            lu = u - vr.u0
            lv = v - vr.v0
            n_off += on & ~_in_table(vr, lu, lv)
            # Unseen points read the table's first pixel (any in-bounds index; unused).
            lu = min(max(lu, 0.0), w - 1.0) if on else 0.0
            lv = min(max(lv, 0.0), h - 1.0) if on else 0.0
            x0 = min(int(np.floor(lu)), x_max)
            y0 = min(int(np.floor(lv)), y_max)
            FX[t] = np.float32(lu - x0)
            FY[t] = np.float32(lv - y0)
            IDX[t] = vr.off + y0 * w + x0
            ZF[t] = zc / fs
            ON[t] = on
        return n_off

    @njit(cache=True, error_model="numpy")
    def _read_corners(n, tables, buf, dx, dy):
        # The 4 table values around each point (a separate loop: the loads are what it
        # waits for; the arithmetic after it vectorises).
        IDX, A, B, C, D = buf.IDX, buf.A, buf.B, buf.C, buf.D
        for t in range(n):
            q = IDX[t]
            A[t] = tables[q]
            B[t] = tables[q + dx]
            C[t] = tables[q + dy]
            D[t] = tables[q + dy + dx]

    @njit(cache=True, error_model="numpy")
    def _bilinear_values(n, buf):
        # DD: field value (voxels, float32) of each seen point, +inf for the unseen (as
        # ``_bilinear_row`` then ``_voxel_test``).
        A, B, C, D, FX, FY, ZF, ON, DD = (buf.A, buf.B, buf.C, buf.D, buf.FX, buf.FY, buf.ZF,
                                          buf.ON, buf.DD)
        for t in range(n):
            val = np.float32(_lerp2(A[t], B[t], C[t], D[t], FX[t], FY[t]) * _SD_STEP * ZF[t])
            DD[t] = val if ON[t] else np.float32(np.inf)

    @njit(cache=True, error_model="numpy")
    def _voxels_beyond_table(n, buf, vr):
        # Seen points beyond the table (rare): the box bound, as ``_bilinear_row``.
        X, Y, Z, ON, ZF, DD = buf.X, buf.Y, buf.Z, buf.ON, buf.ZF, buf.DD
        for t in range(n):
            if not ON[t]:
                continue
            u, v = _pixel(vr, X[t], Y[t], Z[t])  # as in ``_project_children``
            if not _in_table(vr, u - vr.u0, v - vr.v0):
                DD[t] = np.float32(_box_bound(vr, u, v) * ZF[t])

    # Per voxel of a block (parent p, child ch): its k+1 smallest values kept[p, :, ch]
    # sorted, the views that saw it, whether it lies in the grid; x: scratch of 8 values.
    Voxels = namedtuple("Voxels", ["kept", "seen", "live_ok", "x"])

    @njit(cache=True)
    def _voxels(block, valid, tree, k):
        # The decided views of each parent start its voxels' values: out -> -1, in -> +1
        # after clamping; ``block.alive`` counts the live ones.  Returns them and that count.
        npl = block.hi - block.lo
        vox = Voxels(np.empty((npl, k + 1, 8), dtype=np.float32),
                     np.empty((npl, 8), dtype=np.int32), np.empty((npl, 8), dtype=np.bool_),
                     np.empty(8, dtype=np.float32))
        kept, seen, live_ok, alive = vox.kept, vox.seen, vox.live_ok, block.alive
        total = 0
        for i in range(block.lo, block.hi):
            p = i - block.lo
            n_out = min(tree.n_out[i], k + 1)
            n_in = min(tree.n_in[i], k + 1 - n_out)
            for ch in range(8):
                for q in range(k + 1):
                    kept[p, q, ch] = (np.float32(-1.0) if q < n_out else np.float32(1.0)
                                      if q < n_out + n_in else np.float32(np.inf))
                seen[p, ch] = tree.n_out[i] + tree.n_in[i]
                live_ok[p, ch] = valid[i * 8 + ch]
                alive[p] += live_ok[p, ch] and kept[p, k, ch] > -1.0
            total += alive[p]
        return vox, total

    @njit(cache=True, inline="always")
    def _keep_values(ns, block, vox, buf):
        # Inserts each child's value buf.DD into its sorted k+1 smallest, dropping the
        # largest; a value at or above the largest (or unseen: +inf) changes nothing.
        # Same multiset as ``_keep_smallest``.  A dead voxel (<= -1) is still updated with
        # its siblings (its clamped value stays -1) but no longer live.  Returns how many
        # voxels died.
        kept, seen, live_ok, x = vox
        lo, alive, SEL, DD, ON = block.lo, block.alive, buf.SEL, buf.DD, buf.ON
        k = kept.shape[1] - 1
        died = 0
        for s in range(ns):
            p = SEL[s] - lo
            for ch in range(8):
                x[ch] = min(DD[s * 8 + ch], kept[p, k, ch])
                seen[p, ch] += ON[s * 8 + ch]
            for q in range(k, 0, -1):
                for ch in range(8):
                    kept[p, q, ch] = max(kept[p, q - 1, ch], min(kept[p, q, ch], x[ch]))
            for ch in range(8):
                kept[p, 0, ch] = min(kept[p, 0, ch], x[ch])
            a = 0
            for ch in range(8):
                a += live_ok[p, ch] and kept[p, k, ch] > -1.0
            died += alive[p] - a
            alive[p] = a
        return died

    @njit(cache=True, error_model="numpy")
    def _voxel_range(lo, hi, centres, valid, tree, cc, packed, out):
        # Serial body of ``_steal`` for the fine voxels: parents lo..hi, view-major as
        # ``_classify_range``; a parent whose voxels are all dead is skipped.
        params, tables, k = packed.params, packed.tables, cc.k
        block = _block(lo, hi, tree)
        vox, total = _voxels(block, valid, tree, k)
        buf = _passes((hi - lo) * 8, hi - lo)
        offs = np.empty((8, 3))
        count = 0
        for j in range(params.shape[0]):
            if total == 0:
                break
            vr = _row(params, j)
            fs = vr.f * cc.voxel_size
            _child_offsets(vr, 0.5 * cc.voxel_size, offs)
            ns, tested = _children_in_view(vr, j, offs, centres, tree, block, buf)
            count += tested
            n = ns * 8
            n_off = _project_children(n, buf, vr, fs)
            _read_corners(n, tables, buf, 1 if vr.tw > 1 else 0, vr.tw if vr.th > 1 else 0)
            _bilinear_values(n, buf)
            if n_off:
                _voxels_beyond_table(n, buf, vr)
            total -= _keep_values(ns, block, vox, buf)
        kept, seen, min_seen = vox.kept, vox.seen, cc.min_seen
        for i in range(lo, hi):
            for ch in range(8):
                if valid[i * 8 + ch]:
                    out[i * 8 + ch] = _final_value(kept[i - lo, k, ch], seen[i - lo, ch], min_seen)
        return count

    # ------------------------------------------------------------------ work stealing
    # The parallel kernels steal work: each of ``workers`` threads takes the next chunk
    # of ``chunk`` points or parents (``_take``) until none is left, so both cores stay
    # busy to the end of a level however unevenly the work lies (a static split into
    # halves leaves one core idle while the other finishes the leafy half).  Each chunk
    # writes its own outputs and test count: the same field and counts in any order.
    # The loop is written once (``_steal``); its serial body is picked by the types of
    # the arguments when it is compiled (``_chunk``), as the three bodies share one
    # argument list.  A body passed as an argument, or closed over by a factory, would
    # be recompiled in every process (numba keys its cache on the dispatcher object).

    def _chunk(lo, hi, centres, sel, tree, cc, packed, out):  # pragma: no cover - typing only
        raise NotImplementedError("compiled only: the body of ``_steal`` (overloaded)")

    @overload(_chunk, jit_options={"cache": True})
    def _chunk_body(lo, hi, centres, sel, tree, cc, packed, out):
        if isinstance(out, types.Array):  # (P * 8,) float32 voxel values
            return lambda lo, hi, centres, sel, tree, cc, packed, out: _voxel_range(
                lo, hi, centres, sel, tree, cc, packed, out)
        if isinstance(sel.dtype, types.Boolean):  # ``valid`` children of split parents
            return lambda lo, hi, centres, sel, tree, cc, packed, out: _classify_range(
                lo, hi, centres, sel, tree, cc, packed, out)
        return lambda lo, hi, centres, sel, tree, cc, packed, out: _tree_range(  # ``parent``
            lo, hi, centres, sel, tree, cc, packed, out)

    @njit(cache=True, parallel=True)
    def _steal(chunk, workers, centres, sel, tree, cc, packed, out):
        # ``_chunk`` on lo..hi for every chunk of the cells or parents ``centres``; total tests.
        n = centres.shape[0]
        nchunks = (n + chunk - 1) // chunk
        tests = np.zeros(nchunks, dtype=np.int64)
        counter = np.zeros(1, np.int64)
        for _ in prange(workers):
            c = _take(counter)
            while c < nchunks:
                tests[c] = _chunk(c * chunk, min(n, (c + 1) * chunk), centres, sel, tree, cc,
                                  packed, out)
                c = _take(counter)
        return tests.sum()

    # ------------------------------------------------------------------ distance tables
    @njit(cache=True, nogil=True)
    def _distance_table(d_in, d_out, m, out):
        # ``views.signed_distance_table``'s combination in one pass, the float32
        # operations of OpenCV's ``subtract`` then ``addWeighted`` (32-bit working
        # type: 32 a and 32 b are exact and one of them is 0, so one rounding of
        # 32 a - 32 b + 16; then round half to even and saturate, as ``saturate_cast``).
        h, w = out.shape
        for i in range(h):
            for j in range(w):
                a = d_in[i, j] - np.float32(m[i, j])
                y = (a * np.float32(32.0) + d_out[i, j] * np.float32(-32.0)) + np.float32(16.0)
                out[i, j] = np.int16(min(max(np.rint(y), np.float32(-32768.0)),
                                         np.float32(32767.0)))

    # ------------------------------------------------------------------ mesh topology
    @njit(cache=True)
    def _nonmanifold_vertices(faces, n_vertices):
        # A vertex is manifold when its incident faces form one fan: the link edges
        # (b, c) of its faces (a, b, c) make one connected chain.  Per vertex, a tiny
        # union-find over its link vertices counts the chains.
        counts = np.zeros(n_vertices + 1, dtype=np.int64)
        for f in range(faces.shape[0]):
            for q in range(3):
                counts[faces[f, q] + 1] += 1
        for v in range(n_vertices):
            counts[v + 1] += counts[v]
        fill = counts[:-1].copy()
        inc = np.empty(counts[-1], dtype=np.int64)
        for f in range(faces.shape[0]):
            for q in range(3):
                a = faces[f, q]
                inc[fill[a]] = f * 3 + q
                fill[a] += 1
        bad = 0
        nodes = np.empty(64, dtype=np.int64)
        root = np.empty(64, dtype=np.int64)
        for v in range(n_vertices):
            n = counts[v + 1] - counts[v]
            if n == 0:
                continue
            if 2 * n > nodes.shape[0]:
                nodes = np.empty(4 * n, dtype=np.int64)
                root = np.empty(4 * n, dtype=np.int64)
            m = 0
            comps = 0
            for t in range(counts[v], counts[v + 1]):
                f = inc[t] // 3
                q = inc[t] % 3
                ends = (faces[f, (q + 1) % 3], faces[f, (q + 2) % 3])
                ids = np.empty(2, dtype=np.int64)
                for e in range(2):
                    x = ends[e]
                    pos = -1
                    for r in range(m):
                        if nodes[r] == x:
                            pos = r
                            break
                    if pos < 0:
                        nodes[m] = x
                        root[m] = m
                        pos = m
                        m += 1
                        comps += 1
                    ids[e] = pos
                ra = ids[0]
                while root[ra] != ra:
                    ra = root[ra]
                rb = ids[1]
                while root[rb] != rb:
                    rb = root[rb]
                if ra != rb:
                    root[rb] = ra
                    comps -= 1
            if comps > 1:
                bad += 1
        return bad


    # ------------------------------------------------------------------ components
    @njit(cache=True)
    def _find(parent, a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    @njit(cache=True)
    def _component_sizes(idx, nx, ny, nz):
        # 26-connected components of the voxels with sorted linear indices ``idx``
        # (C order): for each of the 13 "forward" offsets a second pointer sweeps
        # ``idx`` in step (both increase), then a union-find.  Returns each voxel's
        # component size.
        n = idx.shape[0]
        parent = np.arange(n)
        for di in range(0, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    if di == 0 and (dj < 0 or (dj == 0 and dk <= 0)):
                        continue  # the mirrored offsets: each pair once
                    d = (di * ny + dj) * nz + dk
                    q = 0
                    for p in range(n):
                        lin = idx[p]
                        k = lin % nz
                        j = (lin // nz) % ny
                        i = lin // (ny * nz)
                        if (i + di >= nx or j + dj < 0 or j + dj >= ny or k + dk < 0
                                or k + dk >= nz):
                            continue
                        target = lin + d
                        while q < n and idx[q] < target:
                            q += 1
                        if q < n and idx[q] == target:
                            ra = _find(parent, p)
                            rb = _find(parent, q)
                            if ra != rb:
                                parent[max(ra, rb)] = min(ra, rb)
        size = np.zeros(n, dtype=np.int64)
        for p in range(n):
            size[_find(parent, p)] += 1
        out = np.empty(n, dtype=np.int64)
        for p in range(n):
            out[p] = size[parent[p]]
        return out


def voxel_field(packed: Packed, points: np.ndarray, consts: CarveConsts,
                stats=None) -> np.ndarray:
    """Compiled ``carve.voxel_field`` (``packed`` from ``pack``)."""
    out, tests = _voxel_field(np.ascontiguousarray(points, dtype=np.float64), packed, consts,
                              CHUNK)
    if stats is not None:
        stats.voxel_view_tests += int(tests)
    return out


def distance_table(d_in: np.ndarray, d_out: np.ndarray, m: np.ndarray, out: np.ndarray) -> bool:
    """Compiled combination of ``views.signed_distance_table`` into ``out``; False
    (nothing written) without numba or when ``SD_STEP`` is not the kernel's 1/32 px."""
    if not HAVE_NUMBA or SD_STEP != 1.0 / 32.0 or SD_DTYPE != np.int16:
        return False
    _distance_table(d_in, d_out, m, out)
    return True


def minus_ones(shape: tuple[int, ...]) -> np.ndarray:
    """A new float32 array of ``shape`` filled with -1 (on every thread when large)."""
    out = np.empty(shape, dtype=np.float32)
    if HAVE_NUMBA and out.size > 1 << 20:
        _fill_minus_one(out.reshape(-1))
    else:
        out.fill(-1.0)
    return out


def threads() -> int:
    return int(numba.get_num_threads()) if HAVE_NUMBA else 1


def cell_counts(m: int, amb_start: np.ndarray) -> CellCounts:
    """Zeroed ``CellCounts`` of m cells, their scratch lists laid out by ``amb_start``."""
    return CellCounts(np.zeros(m, np.int8), np.zeros(m, np.int32), np.zeros(m, np.int32),
                      np.zeros(m, np.int32), np.zeros(m, np.int32),
                      np.empty(int(amb_start[m]), np.int16), amb_start)


def _offsets(lengths: np.ndarray) -> np.ndarray:
    """CSR offsets (len + 1,) int64 of segments of ``lengths``."""
    out = np.zeros(len(lengths) + 1, dtype=np.int64)
    np.cumsum(lengths, out=out[1:])
    return out


def _split_tree(counts: CellCounts) -> Tree:
    """The ``Tree`` of the cells with decision SPLIT, their lists gathered from the scratch."""
    sel = np.flatnonzero(counts.decision == SPLIT)
    start = _offsets(counts.n_amb[sel])
    return Tree(start, _gather_lists(sel, counts, start), counts.n_out[sel], counts.n_in[sel],
                counts.n_off[sel])


def classify_tree(packed: Packed, tree: Tree, parent: np.ndarray, centres: np.ndarray,
                  consts: CarveConsts, stats=None) -> tuple[np.ndarray, Tree]:
    """Decide cells (``centres`` (M, 3), mm) testing only their parent's ambiguous views.

    Returns the decision (REMOVED, FULL, SPLIT) and the ``Tree`` of the cells to
    split (in the order of ``np.flatnonzero(decision == SPLIT)``).
    """
    counts = cell_counts(len(centres), _offsets(np.diff(tree.start)[parent]))
    tests = _steal(CHUNK, threads(), np.ascontiguousarray(centres, dtype=np.float64),
                   parent, tree, consts, packed, counts)
    if stats is not None:
        stats.cell_view_tests += int(tests)
    return counts.decision, _split_tree(counts)


def classify_group(packed: Packed, tree: Tree, centres: np.ndarray, valid: np.ndarray,
                   consts: CarveConsts, stats=None) -> tuple[np.ndarray, Tree]:
    """Decide the 8 children of every split cell (``centres`` (P, 3): the parents').

    Children are ordered as ``carve._children``; ``valid`` (P * 8,) bool marks
    those inside the grid.  Returns the (P * 8,) decision (REMOVED, FULL, SPLIT)
    and the ``Tree`` of the children to split.
    """
    centres = np.ascontiguousarray(centres, dtype=np.float64)
    n_par = len(centres)
    decision = np.empty(n_par * 8, dtype=np.int8)
    parts = []
    for b0 in range(0, max(n_par, 1), GROUP_BATCH):
        b1 = min(n_par, b0 + GROUP_BATCH)
        sub = _sub_tree(tree, b0, b1)
        counts = cell_counts(8 * (b1 - b0), _offsets(np.repeat(np.diff(sub.start), 8)))
        tests = _steal(GROUP_CHUNK, threads(), centres[b0:b1], valid[8 * b0:8 * b1],
                       sub, consts, packed, counts)
        decision[8 * b0:8 * b1] = counts.decision
        parts.append(_split_tree(counts))
        if stats is not None:
            stats.cell_view_tests += int(tests)
    return decision, _concat_trees(parts)


def _sub_tree(tree: Tree, a: int, b: int) -> Tree:
    """Cells ``a:b`` of ``tree`` (views shared, not copied)."""
    return Tree(tree.start[a:b + 1] - tree.start[a], tree.views[tree.start[a]:tree.start[b]],
                tree.n_out[a:b], tree.n_in[a:b], tree.n_off[a:b])


def _concat_trees(parts: list[Tree]) -> Tree:
    """One ``Tree`` of the cells of ``parts`` in order; each part is freed once copied."""
    if len(parts) == 1:
        return parts[0]
    start = _offsets(np.concatenate([np.diff(p.start) for p in parts]))
    counts = [np.concatenate([getattr(p, name) for p in parts])
              for name in ("n_out", "n_in", "n_off")]
    # np.empty maps pages as they are written, so the copy and the parts do not add up.
    views = np.empty(int(start[-1]), dtype=np.int16)
    pos = 0
    parts.reverse()
    while parts:
        part_views = parts.pop().views
        views[pos:pos + len(part_views)] = part_views
        pos += len(part_views)
        del part_views
    return Tree(start, views, *counts)


def voxel_group(packed: Packed, tree: Tree, centres: np.ndarray, valid: np.ndarray,
                consts: CarveConsts, stats=None) -> np.ndarray:
    """Clamped field of the 8 voxels of every split 2-voxel cell (``centres``: the cells')."""
    out = minus_ones((len(centres) * 8,))  # voxels of invalid children stay -1
    tests = _steal(GROUP_CHUNK, threads(),
                   np.ascontiguousarray(centres, dtype=np.float64), valid, tree, consts, packed,
                   out)
    if stats is not None:
        stats.voxel_view_tests += int(tests)
    return out


def nonmanifold_vertices(faces: np.ndarray, n_vertices: int) -> int:
    """Vertices whose incident faces do not form a single fan (compiled)."""
    return int(_nonmanifold_vertices(np.ascontiguousarray(faces, dtype=np.int64),
                                     int(n_vertices)))


def component_sizes(idx: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Size of the 26-connected component of each voxel (``idx``: sorted linear indices)."""
    return _component_sizes(np.ascontiguousarray(idx, dtype=np.int64), *map(int, shape))

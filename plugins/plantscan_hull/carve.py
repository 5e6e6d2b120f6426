"""Visual hull carving: the plain full grid (reference) and the octree.

The field handed on is, per voxel, the (k+1)-th smallest signed distance to
the silhouette cones over the views that see the voxel, in voxels, clamped
to [-1, 1].  A voxel is *outside* in a view where that distance is < 0; it is
removed when it is outside in more than ``k`` views, i.e. when the (k+1)-th
smallest distance is < 0.  Views that do not see the voxel (its centre
projects off the image or behind the camera) do not count.  Because the
field is a distance and not 0/1, marching cubes puts the surface between
voxels where the silhouettes put it.

A leaf thinner than a voxel has no voxel centre inside it in the views that
see it edge-on, so its field is negative everywhere; ``rescue_thin`` keeps a
voxel whose distance is > -0.5 voxel (the leaf passes through the voxel's
inscribed ball in all but k views) when no 6-neighbour is inside, with a
small positive value: marching cubes then draws a thin closed sheet through
the voxel centres instead of losing the leaf or fattening it by a voxel.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from plantscan_core.data import FIELD_BLOCK, BlockField
from plantscan_hull.views import (
    DISTANCE_LIPSCHITZ,
    SD_STEP,
    ViewField,
    project,
    sample_bilinear,
    sample_nearest,
)

# Slack (px) of the conservative cell tests: the cell test reads the pixel nearest
# the projected centre (<= 0.71 px away), a voxel's value interpolates pixels
# <= 0.71 px from its projection, and the pixel distances are 1-Lipschitz.
CELL_SLACK_PX = 1.5
# Largest projected radius (px) of a cell's voxel centres at which the cell test reads
# its centre bilinearly: below it, lip * sqrt(2) * r + SD_STEP < lip * r + CELL_SLACK_PX
# (``classify_cells``; in practice the 2- and 4-voxel cells).  Any value gives the same
# field (both margins are valid); 0 reads the nearest pixel always (as before session 4).
CELL_BILINEAR_MAX_PX = (CELL_SLACK_PX - SD_STEP) / (DISTANCE_LIPSCHITZ * (math.sqrt(2.0) - 1.0))
# Views processed between two compactions of the still-undecided points.
COMPACT_EVERY = 8


@dataclass
class Grid:
    """A regular voxel grid in the turntable frame.

    Attributes
    ----------
    origin : (3,) float64 array, mm
        Centre of voxel (0, 0, 0).
    voxel_size : float, mm
    shape : (3,) tuple of int
    """

    origin: np.ndarray
    voxel_size: float
    shape: tuple[int, int, int]

    @classmethod
    def from_box(cls, lo: Sequence[float], hi: Sequence[float], resolution: int) -> Grid:
        """Grid over the box ``[lo, hi]`` (mm) with ``resolution`` voxels on its longest side."""
        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        extent = hi - lo
        if np.any(extent <= 0):
            raise ValueError(f"empty bounding box {lo.tolist()} .. {hi.tolist()}")
        size = float(extent.max()) / resolution
        shape = tuple(int(max(1, math.ceil(e / size - 1e-9))) for e in extent)
        return cls(lo + size / 2, size, shape)  # type: ignore[arg-type]

    def centres(self, idx: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(idx, dtype=float) * self.voxel_size

    @property
    def lo(self) -> np.ndarray:
        return self.origin - self.voxel_size / 2

    @property
    def hi(self) -> np.ndarray:
        return self.origin + (np.asarray(self.shape) - 0.5) * self.voxel_size


@dataclass
class CarveStats:
    """Work counts of one carve (tests assert these, not times)."""

    voxel_view_tests: int = 0
    cell_view_tests: int = 0
    cells_per_level: dict[int, int] = field(default_factory=dict)
    # Mean number of views the split cells of a level left ambiguous (numba path).
    split_views_per_level: dict[int, float] = field(default_factory=dict)
    seconds_per_level: dict[int, float] = field(default_factory=dict)
    fine_voxels: int = 0
    rescued_voxels: int = 0
    seconds: float = 0.0
    backend: str = "numpy"

    def as_dict(self) -> dict:
        return {"voxel_view_tests": self.voxel_view_tests,
                "cell_view_tests": self.cell_view_tests,
                "cells_per_level": {str(k): v for k, v in self.cells_per_level.items()},
                "split_views_per_level": {str(k): round(v, 1)
                                          for k, v in self.split_views_per_level.items()},
                "seconds_per_level": {str(k): round(v, 3)
                                      for k, v in self.seconds_per_level.items()},
                "fine_voxels": self.fine_voxels, "rescued_voxels": self.rescued_voxels,
                "carve_seconds": self.seconds, "backend": self.backend}


# --------------------------------------------------------------------------- fine voxels
def voxel_field(views: Sequence[ViewField], points: np.ndarray, voxel_size: float, k: int,
                stats: CarveStats | None = None, min_seen: int = 0) -> np.ndarray:
    """Clamped (k+1)-th smallest cone distance, in voxels, at ``points``.

    Parameters
    ----------
    views : prepared silhouettes
    points : (N, 3) float64 array, mm, turntable frame (voxel centres)
    voxel_size : float, mm
    k : int
        Outside tolerance: a voxel outside in at most ``k`` views is kept.
    min_seen : int
        A voxel seen by fewer views is removed (nothing supports it: without
        this, space that few views see could never be carved).

    Returns
    -------
    (N,) float32 array in [-1, 1], voxels; > 0 inside.
    """
    n = len(points)
    kept = np.full((n, k + 1), np.inf, dtype=np.float32)
    seen_count = np.zeros(n, dtype=np.int32)
    active = np.arange(n)
    pts = points
    tests = 0
    for i, view in enumerate(views):
        if active.size == 0:
            break
        uv, z = project(view, pts)
        tests += len(pts)
        seen = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= view.width - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] <= view.height - 0.5)
        seen_count[active] += seen
        sd = sample_bilinear(view, uv)
        dist = np.where(seen, sd * (z / (view.focal * voxel_size)), np.inf).astype(np.float32)
        kk = kept[active]
        worst = np.argmax(kk, axis=1)
        rows = np.arange(len(kk))
        better = dist < kk[rows, worst]
        kk[rows[better], worst[better]] = dist[better]
        kept[active] = kk
        if (i + 1) % COMPACT_EVERY == 0:
            # A voxel whose k+1 smallest are all <= -1 is final (-1 after clamping).
            undecided = kk.max(axis=1) > -1.0
            active = active[undecided]
            pts = points[active]
    if stats is not None:
        stats.voxel_view_tests += tests
    out = np.clip(kept.max(axis=1), -1.0, 1.0).astype(np.float32)
    out[seen_count < min_seen] = -1.0
    return out


# --------------------------------------------------------------------------- octree cells
def centre_radius(half_size: float, voxel_size: float) -> float:
    """Radius (mm) of the ball around a cell's centre holding its voxel centres.

    The field lives at voxel centres only, so a cell test must bound those, not
    the whole cube: a cell of ``n`` voxels a side has its outermost voxel
    centres ``(n - 1) / 2`` voxels from its centre on each axis.  For the
    2-voxel cells this is half the cube's half-diagonal (which the tests used
    before session 4), so fewer views are left ambiguous (same field).
    """
    return (half_size - 0.5 * voxel_size) * math.sqrt(3.0)


def classify_cells(views: Sequence[ViewField], centres: np.ndarray, half_size: float,
                   voxel_size: float, k: int, stats: CarveStats | None = None,
                   min_seen: int = 0) -> np.ndarray:
    """Conservative per-cell decision: 0 removed, 1 full, 2 subdivide.

    A cell is *out* in a view when its whole projected footprint is on the
    image and ``sd(centre) < -(r + one voxel + slack)``, *in* when
    ``sd(centre) > r + one voxel + slack`` (every voxel then has a cone
    distance beyond +-1 voxel, the clamp), ignored when its footprint is off
    the image, ambiguous otherwise.  Removed: out in more than ``k`` views;
    full: out or ambiguous in at most ``k`` views and wholly on at least
    ``min_seen`` images (removed too when off more than ``V - min_seen``
    images).  So the clamped field of
    every voxel of a decided cell is exactly what ``voxel_field`` would give.

    ``r`` bounds the projected distance from the centre to the cell's voxel
    centres (``centre_radius``).  ``slack`` covers reading the nearest pixel
    at the centre and interpolating at the voxels.  When the footprint is
    small (``r`` < 3.5 px) and inside the table, the centre is read
    bilinearly instead: the table's steps between neighbouring pixels are
    <= 1 px, so its bilinear interpolant changes by at most
    ``|du| + |dv| <= sqrt(2) r`` between two points, plus one table step for
    the rounding of the two readings: margin ``1.02 sqrt(2) r + SD_STEP``.

    Parameters
    ----------
    centres : (M, 3) float64 array, mm
    half_size : float, mm (half the cell's side)
    """
    m = len(centres)
    rho = centre_radius(half_size, voxel_size)
    n_out = np.zeros(m, dtype=np.int32)
    n_amb = np.zeros(m, dtype=np.int32)
    n_on = np.zeros(m, dtype=np.int32)
    n_off = np.zeros(m, dtype=np.int32)
    max_off = len(views) - min_seen
    active = np.arange(m)
    pts = centres
    tests = 0
    for i, view in enumerate(views):
        if active.size == 0:
            break
        uv, z = project(view, pts)
        tests += len(pts)
        near = z - rho
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(near > 0, view.gain / near, np.inf)
        r = rho * inv
        # One voxel in px at the nearest depth (the field is sd * z / (f * voxel)).
        with np.errstate(divide="ignore", invalid="ignore"):
            one_voxel = np.where(near > 0, voxel_size * view.focal / near, np.inf)
        margin = DISTANCE_LIPSCHITZ * r + one_voxel + CELL_SLACK_PX
        u = np.nan_to_num(uv[:, 0], nan=-1e9)
        v = np.nan_to_num(uv[:, 1], nan=-1e9)
        lo_u, hi_u = -0.5, view.width - 0.5
        lo_v, hi_v = -0.5, view.height - 0.5
        finite = np.isfinite(r)
        on_image = finite & (u - r >= lo_u) & (u + r <= hi_u) & (v - r >= lo_v) & (v + r <= hi_v)
        off_image = (z + rho <= 0) | (finite & ((u + r < lo_u) | (u - r > hi_u)
                                               | (v + r < lo_v) | (v - r > hi_v)))
        sd = sample_nearest(view, uv)
        # Small footprints: the bilinear value at the centre bounds the voxels' within
        # lip * sqrt(2) * r + one table step (see the docstring), tighter than the
        # nearest pixel's lip * r + slack when r < 3.5 px.
        tight = DISTANCE_LIPSCHITZ * math.sqrt(2.0) * r + SD_STEP
        h, w = view.sd.shape
        lu, lv = u - view.u0, v - view.v0
        use = (finite & (r < CELL_BILINEAR_MAX_PX) & (lu - r >= -0.5)
               & (lu + r <= w - 0.5) & (lv - r >= -0.5) & (lv + r <= h - 0.5))
        if use.any():
            sd[use] = sample_bilinear(view, uv[use])
            margin[use] = tight[use] + one_voxel[use]
        out = on_image & (sd < -margin)
        inside = on_image & (sd > margin)
        amb = ~(out | inside | off_image)
        n_out[active] += out
        n_amb[active] += amb
        n_on[active] += on_image
        n_off[active] += off_image
        if (i + 1) % COMPACT_EVERY == 0:
            alive = (n_out[active] <= k) & (n_off[active] <= max_off)
            active = active[alive]
            pts = centres[active]
    if stats is not None:
        stats.cell_view_tests += tests
    decision = np.full(m, 2, dtype=np.int8)
    decision[(n_out + n_amb <= k) & (n_on >= min_seen)] = 1
    decision[(n_out > k) | (n_off > max_off)] = 0
    return decision


def interleaved(views: Sequence[ViewField]) -> list[ViewField]:
    """Views in bit-reversed order: the first few look from very different directions.

    The result is order-independent (a (k+1)-th smallest and counts); the order
    only decides how soon a point's fate is sealed and its tests stop.
    """
    n = len(views)
    bits = max(1, (n - 1).bit_length())
    keys = [int(format(i, f"0{bits}b")[::-1], 2) for i in range(n)]
    return [views[i] for i in sorted(range(n), key=keys.__getitem__)]


# --------------------------------------------------------------------------- backends
BACKENDS = ("auto", "numpy", "numba")


class _Kernels:
    """The views and the voxel loop, from numpy (reference) or numba (compiled).

    The compiled path classifies cells with inherited view decisions (``_carve_tree``);
    ``classify_cells`` is the numpy path's.
    """

    def __init__(self, views: Sequence[ViewField], backend: str, min_seen: int = 0):
        from plantscan_hull import kernels

        if backend not in BACKENDS:
            raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
        if backend == "numba" and not kernels.supported(views):
            raise ValueError("backend 'numba' needs numba installed and the seed's camera "
                             "model (CameraModel) for every view")
        use_numba = backend == "numba" or (backend == "auto" and kernels.supported(views))
        self.name = "numba" if use_numba else "numpy"
        views = interleaved(views)
        self.views = views
        self.min_seen = int(min_seen)
        self._kernels = kernels
        self._packed = kernels.pack(views) if use_numba else None

    def voxel_field(self, points, voxel_size, k, stats):
        if self._packed is not None:
            return self._kernels.voxel_field(
                self._packed, points, self._kernels.carve_consts(voxel_size, k, self.min_seen),
                stats)
        return voxel_field(self.views, points, voxel_size, k, stats, self.min_seen)

    def cell_consts(self, half_size: float, voxel_size: float, k: int):
        """The compiled cell kernels' constants of a level of cells of half-side ``half_size``."""
        return self._kernels.carve_consts(voxel_size, k, self.min_seen, half_size,
                                          CELL_SLACK_PX, DISTANCE_LIPSCHITZ, CELL_BILINEAR_MAX_PX)


# --------------------------------------------------------------------------- thin parts
def rescue_thin(phi: np.ndarray, value: float) -> int:
    """Keep sub-voxel parts (thin leaves) in place: see the module docstring.

    Modifies ``phi`` (clamped field, voxels) in place; returns the number of
    voxels rescued.
    """
    cand = (phi > -0.5) & (phi <= 0.0)
    if not cand.any():
        return 0
    pos = phi > 0
    near_inside = np.zeros_like(pos)
    near_inside[1:] |= pos[:-1]
    near_inside[:-1] |= pos[1:]
    near_inside[:, 1:] |= pos[:, :-1]
    near_inside[:, :-1] |= pos[:, 1:]
    near_inside[:, :, 1:] |= pos[:, :, :-1]
    near_inside[:, :, :-1] |= pos[:, :, 1:]
    rescue = cand & ~near_inside
    phi[rescue] = value
    return int(rescue.sum())


# --------------------------------------------------------------------------- carvers
def _finish(phi: np.ndarray, stats: CarveStats, keep_thin: bool, thin_value: float,
            t0: float) -> np.ndarray:
    if keep_thin:
        stats.rescued_voxels = rescue_thin(phi, thin_value)
    # Exact zeros would put marching-cubes vertices on voxel centres (degenerate faces).
    phi[phi == 0] = -1e-3
    stats.seconds = time.perf_counter() - t0
    return phi


def carve_dense(views: Sequence[ViewField], grid: Grid, k: int, keep_thin: bool = True,
                thin_value: float = 0.15, chunk: int = 1 << 20, backend: str = "numpy",
                min_seen: int = 0) -> tuple[np.ndarray, CarveStats]:
    """Full-grid reference: ``voxel_field`` at every voxel centre.

    Returns
    -------
    phi : (NX, NY, NZ) float32 array, voxels, > 0 inside
    stats : CarveStats
    """
    t0 = time.perf_counter()
    stats = CarveStats()
    kern = _Kernels(views, backend, min_seen)
    stats.backend = kern.name
    nx, ny, nz = grid.shape
    phi = np.empty(nx * ny * nz, dtype=np.float32)
    total = nx * ny * nz
    for start in range(0, total, chunk):
        flat = np.arange(start, min(total, start + chunk))
        idx = np.stack(np.unravel_index(flat, grid.shape), axis=1)
        phi[flat] = kern.voxel_field(grid.centres(idx), grid.voxel_size, k, stats)
    stats.fine_voxels = total
    phi = phi.reshape(grid.shape)
    return _finish(phi, stats, keep_thin, thin_value, t0), stats


def _children(cells: np.ndarray, size: int) -> np.ndarray:
    """Corner indices of the 8 children (side ``size // 2``) of cells with corner ``cells``."""
    h = size // 2
    offs = np.array([[i, j, kk] for i in (0, h) for j in (0, h) for kk in (0, h)], dtype=np.int64)
    return (cells[:, None, :] + offs[None, :, :]).reshape(-1, 3)


def carve_octree(views: Sequence[ViewField], grid: Grid, k: int, top_cell: int = 32,
                 keep_thin: bool = True, thin_value: float = 0.15, backend: str = "numpy",
                 min_seen: int = 0, blocks: bool = False
                 ) -> tuple[np.ndarray | BlockField, CarveStats]:
    """Coarse-to-fine carving; same field as ``carve_dense`` with far fewer tests.

    Cells of ``top_cell`` voxels (a power of two) are classified with
    ``classify_cells``; undecided ones are split in 8 down to single voxels,
    whose field is computed by ``voxel_field``.  With ``blocks`` the field is
    returned as a ``BlockField`` (the compiled path fills it so, without ever
    holding the dense grid), else as the dense ``(NX, NY, NZ)`` array.
    """
    if top_cell < 1 or top_cell & (top_cell - 1):
        raise ValueError(f"top_cell must be a power of two, got {top_cell}")
    t0 = time.perf_counter()
    stats = CarveStats()
    kern = _Kernels(views, backend, min_seen)
    stats.backend = kern.name
    if kern.name == "numba" and top_cell > 1:  # top_cell 1 is the dense grid (below)
        field, stats = _carve_tree(kern, grid, k, top_cell, keep_thin, thin_value, stats, t0)
        return (field if blocks else field.dense()), stats
    shape = np.array(grid.shape)
    s = grid.voxel_size
    padded = -(-shape // top_cell) * top_cell
    phi = np.full(tuple(padded), -1.0, dtype=np.float32)
    ranges = [np.arange(0, p, top_cell) for p in padded]
    cells = np.stack(np.meshgrid(*ranges, indexing="ij"), axis=-1).reshape(-1, 3)
    size = top_cell
    while size > 1 and len(cells):
        # Cells entirely in the padding beyond the grid are dropped.
        cells = cells[np.all(cells < shape, axis=1)]
        stats.cells_per_level[size] = len(cells)
        centres = grid.centres(cells + (size - 1) / 2.0)
        decision = classify_cells(kern.views, centres, size * s / 2.0, s, k, stats,
                                  kern.min_seen)
        full = cells[decision == 1]
        if len(full):
            r = np.arange(size)
            block = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
            for part in np.array_split(full, max(1, len(full) * size**3 // (1 << 22))):
                vox = (part[:, None, :] + block[None]).reshape(-1, 3)
                phi[vox[:, 0], vox[:, 1], vox[:, 2]] = 1.0
        cells = _children(cells[decision == 2], size)
        size //= 2
    if len(cells):
        cells = cells[np.all(cells < shape, axis=1)]
        stats.cells_per_level[1] = len(cells)
        stats.fine_voxels = len(cells)
        phi[cells[:, 0], cells[:, 1], cells[:, 2]] = kern.voxel_field(
            grid.centres(cells), s, k, stats)
    phi = np.ascontiguousarray(phi[: shape[0], : shape[1], : shape[2]])
    phi = _finish(phi, stats, keep_thin, thin_value, t0)
    return (BlockField.from_dense(phi) if blocks else phi), stats


class _Blocks:
    """The compiled carve's field as it is filled, block by block (``BlockField``).

    Decided cells of a block's side or larger make their blocks implicit (wholly
    inside; never-touched blocks are wholly outside); the split cells of a block's
    side become the mixed blocks, whose rows start at -1 and take every smaller
    decided cell and fine voxel.  When the top cells are smaller than a block, every
    block holding a cell that is not removed is mixed from the start.
    """

    def __init__(self, shape: tuple[int, int, int], block: int):
        self.shape = tuple(int(n) for n in shape)
        self.block = block
        self.index = np.full(tuple(-(-np.array(self.shape) // block)), BlockField.OUTSIDE,
                             dtype=np.int32)
        self.values: np.ndarray | None = None

    def _materialise(self, blocks: np.ndarray) -> None:
        from plantscan_hull import kernels

        self.index[tuple(blocks.T)] = np.arange(len(blocks), dtype=np.int32)
        self.values = kernels.minus_ones((len(blocks),) + (self.block,) * 3)

    def level(self, cells: np.ndarray, size: int, decision: np.ndarray) -> None:
        """Write a level's decided cells (corners ``cells`` (C, 3), side ``size``)."""
        from plantscan_hull import kernels

        B = self.block
        full = cells[decision == kernels.FULL]
        if self.values is None and size <= B:
            if size == B:
                blocks = cells[decision == kernels.SPLIT] // B
            else:  # top cells smaller than a block
                blocks = np.unique(cells[decision != kernels.REMOVED] // B, axis=0)
            self._materialise(blocks.reshape(-1, 3))
        if size >= B:
            n = size // B
            for off in np.ndindex(n, n, n):
                at = full // B + np.array(off)
                at = at[np.all(at < self.index.shape, axis=1)]
                self.index[tuple(at.T)] = BlockField.INSIDE
        elif len(full):
            kernels._fill_blocked(self.index, self.values, self.shape, np.ascontiguousarray(full),
                                  size, np.float32(1.0))

    def field(self) -> BlockField:
        values = self.values if self.values is not None else np.zeros(
            (0,) + (self.block,) * 3, np.float32)
        return BlockField(self.shape, self.block, self.index, values)


def _carve_tree(kern: _Kernels, grid: Grid, k: int, top_cell: int, keep_thin: bool,
                thin_value: float, stats: CarveStats, t0: float
                ) -> tuple[BlockField, CarveStats]:
    """``carve_octree`` with the compiled kernels and inherited view decisions.

    A cell's conservative test in a view holds for all of its points, so its
    children test only the views it left ambiguous (``kernels.classify_tree``,
    ``classify_group``: the 8 siblings together); the field equals
    ``carve_dense``'s (tested).  The field is filled block by block
    (``_Blocks``): only the blocks the surface crosses hold values, and the
    thin-part rescue visits only the fine voxels.
    """
    from plantscan_hull import kernels

    shape = np.array(grid.shape)
    s = grid.voxel_size
    out = _Blocks(grid.shape, FIELD_BLOCK)
    padded = -(-shape // top_cell) * top_cell
    ranges = [np.arange(0, p, top_cell) for p in padded]
    cells = np.stack(np.meshgrid(*ranges, indexing="ij"), axis=-1).reshape(-1, 3)
    size = top_cell
    t_level = time.perf_counter()
    stats.cells_per_level[size] = len(cells)
    decision, tree = kernels.classify_tree(
        kern._packed, kernels.root_tree(len(kern.views)), np.zeros(len(cells), dtype=np.int64),
        grid.centres(cells + (size - 1) / 2.0), kern.cell_consts(size * s / 2.0, s, k), stats)
    voxel_consts = kernels.carve_consts(s, k, kern.min_seen)
    while True:
        out.level(cells, size, decision)
        split = cells[decision == 2]  # (P, 3) corners, in the order of ``tree``
        stats.split_views_per_level[size] = float(np.diff(tree.start).mean()) if len(
            split) else 0.0
        stats.seconds_per_level[size] = time.perf_counter() - t_level
        t_level = time.perf_counter()
        if size == 1 or not len(split):
            return _done(out.field(), stats, t0)
        centres = grid.centres(split + (size - 1) / 2.0)
        if size == 2:  # top_cell == 2: the voxels of the split cells, in one go
            valid = _fine_valid(split, shape)
            stats.cells_per_level[1] = stats.fine_voxels = int(valid.sum())
            values = kernels.voxel_group(kern._packed, tree, centres, valid, voxel_consts, stats)
            del tree
            return _scatter(out, split, values, valid, keep_thin, thin_value, stats, t_level, t0)
        if size == 4:
            break
        cells = _children(split, size)
        valid = np.all(cells < shape, axis=1)  # the top level is padded
        size //= 2
        stats.cells_per_level[size] = int(valid.sum())
        decision, tree = kernels.classify_group(
            kern._packed, tree, centres, valid, kern.cell_consts(size * s / 2.0, s, k), stats)
    # The split 4-voxel cells: their children (2-voxel cells) are classified and the
    # voxels of the split ones carved batch by batch, so the view lists of the last split
    # level exist for one batch at a time (the whole level's: 1.6-2.1 GB at 1024^3).
    # Same tests in the same order within each chunk of parents: same field and counts.
    splits, values, valids = [], [], []
    n_cells = n_split = n_listed = 0
    t_cells = t_voxels = 0.0
    for b0 in range(0, len(split), kernels.GROUP_BATCH):
        b1 = min(len(split), b0 + kernels.GROUP_BATCH)
        t1 = time.perf_counter()
        cells = _children(split[b0:b1], 4)
        valid = np.all(cells < shape, axis=1)
        n_cells += int(valid.sum())
        decision, sub = kernels.classify_group(
            kern._packed, kernels._sub_tree(tree, b0, b1), centres[b0:b1], valid,
            kern.cell_consts(s, s, k), stats)
        out.level(cells, 2, decision)
        split_2 = cells[decision == 2]
        n_split += len(split_2)
        n_listed += int(sub.start[-1])
        t2 = time.perf_counter()
        t_cells += t2 - t1
        if len(split_2):
            fine_valid = _fine_valid(split_2, shape)
            values.append(kernels.voxel_group(kern._packed, sub, grid.centres(split_2 + 0.5),
                                              fine_valid, voxel_consts, stats))
            splits.append(split_2)
            valids.append(fine_valid)
        del sub
        t_voxels += time.perf_counter() - t2
    del tree
    stats.cells_per_level[2] = n_cells
    stats.split_views_per_level[2] = n_listed / n_split if n_split else 0.0
    stats.seconds_per_level[2] = t_cells
    if not n_split:
        return _done(out.field(), stats, t0)
    split = np.concatenate(splits)
    valid = np.concatenate(valids)
    stats.cells_per_level[1] = stats.fine_voxels = int(valid.sum())
    return _scatter(out, split, np.concatenate(values), valid, keep_thin, thin_value, stats,
                    time.perf_counter() - t_voxels, t0)


def _fine_valid(split: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(P * 8,) bool: which voxels of the 2-voxel cells with corners ``split`` are in the grid.

    Without their (P * 8, 3) indices: child ``ch`` is at corner + (ch >> 2, ch >> 1 & 1,
    ch & 1).
    """
    room = split + 1 < shape  # (P, 3): the upper child fits along each axis
    valid = np.ones((len(split), 8), dtype=bool)
    for ch in range(8):
        for axis, bit in enumerate((4, 2, 1)):
            if ch & bit:
                valid[:, ch] &= room[:, axis]
    return valid.ravel()


def _scatter(out: _Blocks, split: np.ndarray, values: np.ndarray, valid: np.ndarray,
             keep_thin: bool, thin_value: float, stats: CarveStats, t_level: float,
             t0: float) -> tuple[BlockField, CarveStats]:
    """Writes the fine voxels' values (and the thin-part rescue) into ``out``."""
    from plantscan_hull import kernels

    stats.rescued_voxels = int(kernels._scatter_fine_blocked(
        out.index, out.values, out.shape, np.ascontiguousarray(split), values, valid,
        np.float32(thin_value), keep_thin))
    stats.seconds_per_level[1] = time.perf_counter() - t_level
    return _done(out.field(), stats, t0)


def _done(phi: np.ndarray | BlockField, stats: CarveStats, t0: float
          ) -> tuple[np.ndarray | BlockField, CarveStats]:
    stats.seconds = time.perf_counter() - t0
    return phi, stats

"""Surface extraction: marching cubes (scikit-image) and mesh checks."""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np

from plantscan_core.data import Mesh
from plantscan_hull.fields import (
    Field,
    chunk_max,
    inside_indices,
    read_box,
    set_voxels,
    values_at,
)

log = logging.getLogger(__name__)


def drop_small_components(field: Field, min_voxels: int, in_place: bool = False,
                          undo: list | None = None) -> tuple[Field, int]:
    """Set inside components smaller than ``min_voxels`` (26-connected) to outside.

    Works on the inside voxels only (the cost follows the hull, not the grid):
    a compiled union-find when numba is installed, else a graph of their
    26-neighbour pairs (``scipy.sparse.csgraph``).

    Returns the field (``field`` itself when ``in_place`` or nothing was
    dropped, else a modified copy) and the number of components dropped.
    With ``in_place`` and ``undo`` (a list), the edits are recorded in ``undo``
    (see :func:`restore`).  ``field`` is a dense array or a ``BlockField``.
    """
    from plantscan_hull import kernels

    if min_voxels <= 1:
        return field, 0
    idx = inside_indices(field)
    if idx.size == 0:
        return field, 0
    if kernels.HAVE_NUMBA:
        sizes = kernels.component_sizes(idx, field.shape)
    else:
        sizes = _component_sizes_scipy(idx, field.shape)
    small = sizes < min_voxels
    if not small.any():
        return field, 0
    # Each component of size s contributes s voxels of size s.
    dropped = int(np.sum(1.0 / sizes[small]).round())
    out = field if in_place else _copy(field)
    set_voxels(out, idx[small], -1.0, undo if in_place else None)
    return out, dropped


def _copy(field: Field) -> Field:
    if isinstance(field, np.ndarray):
        return field.copy()
    from plantscan_core.data import BlockField

    return BlockField(field.shape, field.block, field.index.copy(), field.values.copy())


def _component_sizes_scipy(idx: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``kernels.component_sizes`` with scipy (no numba)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    dims = np.array(shape)
    ijk = np.stack(np.unravel_index(idx, shape), axis=1)
    rows, cols = [], []
    # Half of the 26 neighbour offsets: each pair is found once.
    for off in np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                         if (a, b, c) > (0, 0, 0)]):
        nb = ijk + off
        ok = np.all((nb >= 0) & (nb < dims), axis=1)
        lin = np.ravel_multi_index(nb[ok].T, shape)
        pos = np.minimum(np.searchsorted(idx, lin), idx.size - 1)
        hit = idx[pos] == lin
        rows.append(np.flatnonzero(ok)[hit])
        cols.append(pos[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(idx.size, idx.size))
    n, labels = connected_components(graph, directed=False)
    return np.bincount(labels, minlength=n)[labels]


# Field values closer than this to the level (voxels) are moved to +-LEVEL_GAP: every
# marching-cubes vertex is then >= LEVEL_GAP / 2 voxel from a grid point, so no two
# vertices on different grid edges coincide (coincident vertices make zero-area
# triangles, and removing or merging them leaves non-manifold edges).
LEVEL_GAP = 1e-3
# Cubes per block side of the blocked marching cubes.
MC_BLOCK = 32


def _surface_blocks(field: Field, block: int) -> np.ndarray:
    """Indices ``(K, 3)`` of the blocks whose samples hold an inside voxel (C order).

    Block ``b`` (along each axis) samples voxels ``b * block - 1 .. b * block +
    block - 1`` (its cubes' corners; index -1 is the outside layer), i.e. the
    last voxel of chunk ``b - 1`` and chunk ``b``, where chunk ``c`` is voxels
    ``[c * block, (c + 1) * block)``.  A block without an inside sample has no
    surface.  The chunks' maxima take one read of the field (``reduceat``),
    instead of copying every block out of the grid to look at it (on a
    ``BlockField`` of the same block side, the blocks' own maxima).
    """
    n = np.array(field.shape)
    n_blocks = -(-(n + 1) // block)
    maxima = chunk_max(field, block)
    pad = np.zeros(tuple(n_blocks + 1), bool)
    pad[tuple(slice(1, 1 + c) for c in maxima.shape)] = maxima > 0
    hit = np.zeros(tuple(n_blocks), bool)
    for shift in np.ndindex(2, 2, 2):
        hit |= pad[tuple(slice(s, s + nb) for s, nb in zip(shift, n_blocks, strict=True))]
    return np.argwhere(hit)


def marching_cubes(field: Field, origin: np.ndarray, voxel_size: float,
                   block: int = MC_BLOCK, thin_rims: bool | Literal["measure"] = False
                   ) -> Mesh:
    """Closed surface of ``field > 0`` (0 level, linear interpolation between voxels).

    scikit-image's marching cubes runs on the blocks of ``block``
    cubes that the surface crosses (the field outside the grid is -1, so every
    surface closes); a cube belongs to exactly one block, so the triangles are
    those of one call on the whole grid, and the vertices of neighbouring blocks
    are merged by the grid edge they lie on.  Only blocks holding an inside
    voxel are copied out (:func:`_surface_blocks`).  The classic table
    (``method="lorensen"``), not Lewiner's: the clamped field has many exact
    +-1 values, whose tied face tests make scikit-image's Lewiner tables emit
    duplicate faces (non-manifold edges; scikit-image issue #8109).  The
    table runs on ``-field`` so that inside voxels sharing only an edge stay
    connected (a thin leaf sheet stepping diagonally is not cut apart).

    Parameters
    ----------
    field : (NX, NY, NZ) float array or BlockField, > 0 inside
    origin : (3,) mm, centre of voxel (0, 0, 0)
    voxel_size : mm
    thin_rims : True moves the rims of one-voxel-thick parts out (:func:`_thin_rims`);
        ``"measure"`` leaves the vertices where interpolation puts them and gives the
        moved ones as ``rim_vertices`` (same faces).

    Returns
    -------
    Mesh with faces counter-clockwise seen from outside (outward normals).
    """
    from skimage.measure import marching_cubes as sk_marching_cubes

    if isinstance(field, np.ndarray):
        field = np.asarray(field, dtype=np.float32)
    # Padded grid: index g = voxel index + 1, one outside layer all round.
    n_cubes = np.array(field.shape) + 1
    stride = np.array([(n_cubes[1] + 1) * (n_cubes[2] + 1), n_cubes[2] + 1, 1])
    verts, faces, keys, count, volume6 = [], [], [], 0, 0.0
    for bi in _surface_blocks(field, block):
        lo = bi * block
        hi = np.minimum(lo + block, n_cubes) + 1  # samples of the block's cubes
        sub = read_box(field, lo - 1, hi - 1)
        if not (sub.max() > 0 and sub.min() <= 0):
            continue  # no surface in this block
        near = np.abs(sub) < LEVEL_GAP
        sub[near] = np.where(sub[near] > 0, LEVEL_GAP, -LEVEL_GAP)
        # On -field: the table joins the *lower* side across an ambiguous cube face, so
        # the inside is then 18-connected (a leaf sheet one voxel thick stays one surface
        # where it steps diagonally); on +field it would be cut at every such step.
        np.negative(sub, out=sub)
        v, f, _, _ = sk_marching_cubes(sub, level=0.0, allow_degenerate=True, method="lorensen")
        v = v.astype(np.float64) + lo
        # A vertex on a grid edge is named by the edge's lower end and axis (a vertex
        # inside a cube, which some tables add, belongs to that cube alone: own name).
        # Per block: the arrays stay in cache.
        low = np.floor(v)
        frac = v - low
        il = low.astype(np.int64)
        on = frac > 1e-6
        # Column by column: numpy's reductions over a length-3 axis are slow.  A vertex
        # with one fractional coordinate lies on an edge along that axis; any other is
        # "inner" and named by its own index below.
        key = (il[:, 0] * stride[0] + il[:, 1] * stride[1] + il[:, 2]) * 3 + np.where(
            on[:, 0], 0, np.where(on[:, 1], 1, 2))
        inner = (on[:, 0].view(np.uint8) + on[:, 1] + on[:, 2]) != 1
        key[inner] = -1 - (count + np.flatnonzero(inner))
        # Six times the signed volume (grid units), summed block by block: the pieces
        # together are the closed surface, so the sum is its volume.
        p0, p1, p2 = v[f[:, 0]].T, v[f[:, 1]].T, v[f[:, 2]].T
        volume6 += float(np.sum(p0[0] * (p1[1] * p2[2] - p1[2] * p2[1])
                                + p0[1] * (p1[2] * p2[0] - p1[0] * p2[2])
                                + p0[2] * (p1[0] * p2[1] - p1[1] * p2[0])))
        verts.append(v)
        faces.append(f.astype(np.int64) + count)
        keys.append(key)
        count += len(v)
    if not verts:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    verts = np.concatenate(verts)
    faces = np.concatenate(faces)
    key = np.concatenate(keys)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    verts = verts[first]
    rim = None
    if thin_rims:
        low = np.floor(verts)
        frac = verts - low
        rim = _thin_rims(verts, low.astype(np.int64), np.argmax(frac, axis=1),
                         (frac > 1e-6).sum(axis=1) == 1, field)
        if thin_rims != "measure":
            verts, rim = rim, None
    shift = np.asarray(origin, dtype=float) - voxel_size
    verts = verts * voxel_size + shift
    faces = inverse.reshape(-1)[faces]
    if volume6 < 0:
        faces = faces[:, ::-1].copy()
    return Mesh(verts, faces, None if rim is None else rim * voxel_size + shift)


def _thin_rims(verts: np.ndarray, low: np.ndarray, axis: np.ndarray, on_edge: np.ndarray,
               field: Field) -> np.ndarray:
    """Move vertices on grid edges leaving a one-voxel-thick part out to its rim.

    ``verts`` are padded-grid coordinates (voxel index + 1); ``low``, ``axis``
    the lower end and axis of each one's grid edge, ``on_edge`` False for
    vertices inside a cube (left in place).

    Along an edge from an inside voxel A to an outside one B, a 1-Lipschitz
    field puts the surface at least ``f_A`` from A and at least ``|f_B|``
    from B; linear interpolation picks ``f_A / (f_A - f_B)``.  Where
    A is a slab one voxel thick (its two neighbours across some other axis are
    outside) its value is capped by the slab's half thickness, not by the
    distance to the rim along the edge, so the interpolated rim falls short;
    the far end ``1 - |f_B|`` is B's own distance (from the views that see
    the rim) and is used instead.  Vertices only move outwards within the
    edge, so the mesh's topology is unchanged.
    """
    frac = verts - low

    def value(idx):  # field at padded-grid points, -1 outside the grid
        return values_at(field, idx - 1)

    rows = np.arange(len(verts))
    step = np.eye(3, dtype=np.int64)[axis]
    f0, f1 = value(low), value(low + step)
    a_is_low = f0 > 0
    f_b = np.where(a_is_low, f1, f0)
    # Distance of the rim from A along the edge, and its upper bound from B.
    t = np.where(a_is_low, frac[rows, axis], 1 - frac[rows, axis])
    far = 1.0 + f_b  # f_b in (-1, 0]
    # Only the vertices that would move need the thinness test (6 reads each).
    cand = np.flatnonzero(on_edge & (f_b > -1) & (far > t))
    a = np.where(a_is_low[cand, None], low[cand], low[cand] + step[cand])
    thin = np.zeros(len(cand), bool)
    for other in range(3):
        across = np.zeros(3, np.int64)
        across[other] = 1
        thin |= (axis[cand] != other) & (value(a + across) <= 0) & (value(a - across) <= 0)
    move = cand[thin]
    out = verts.copy()
    ax = axis[move]
    t_new = far[move] - LEVEL_GAP
    out[move, ax] = np.where(a_is_low[move], low[move, ax] + t_new, low[move, ax] + 1 - t_new)
    return out


def signed_volume(mesh: Mesh) -> float:
    """Enclosed volume (mm^3), positive when faces are counter-clockwise from outside."""
    v = mesh.vertices[mesh.faces]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def topology_report(mesh: Mesh) -> dict:
    """Watertight / manifold checks of a triangle mesh.

    Returns
    -------
    dict with ``boundary_edges`` (edges in one face), ``nonmanifold_edges``
    (edges in more than two faces), ``misoriented_edges`` (directed edges used
    twice), ``nonmanifold_vertices`` (incident faces not one fan: Open3D's
    test, compiled when numba is installed), ``degenerate_faces``,
    ``watertight`` and ``manifold`` (bool).
    """
    f = mesh.faces
    if len(f) == 0:
        return {"boundary_edges": 0, "nonmanifold_edges": 0, "misoriented_edges": 0,
                "nonmanifold_vertices": 0, "degenerate_faces": 0, "watertight": False,
                "manifold": False}
    n = np.int64(max(len(mesh.vertices), 1))
    # Edge (a, b) of each face; int32 when the vertices fit (half the bytes: each 3F-long
    # int64 temporary of a 3 M-face mesh is 76 MB of fresh pages).
    ends = np.int32 if n < 2**31 else np.int64
    a = np.ascontiguousarray(f.T, dtype=ends).reshape(-1)
    b = np.roll(a.reshape(3, -1), -1, axis=0).reshape(-1)
    # One sorted int64 key per directed edge: the undirected edge, then its direction.
    # Stable (radix/tim) sort: marching-cubes order is nearly sorted, 2x faster than quicksort.
    keys = np.minimum(a, b).astype(np.int64)
    keys *= n
    keys += np.maximum(a, b)
    keys *= 2
    keys += a < b
    del a, b
    keys.sort(kind="stable")
    # Runs of equal keys counted with boolean masks (no index or count arrays): keys i and
    # i + 1 are the same undirected edge when they differ in the direction bit at most.
    # A run starts where the edge changes; it is one face long when the next key differs
    # too, more than two long when the next two keys equal it.
    same = np.empty(keys.size - 1, bool)
    dsame = np.empty(keys.size - 1, bool)
    for i in range(0, keys.size - 1, 1 << 20):  # int64 xor in pieces: no 3F-long temporary
        j = min(i + (1 << 20), keys.size - 1)
        step = keys[i + 1:j + 1] ^ keys[i:j]
        np.less(step, 2, out=same[i:j])
        np.equal(step, 0, out=dsame[i:j])
    if same.size > 1:
        boundary = int(np.count_nonzero(~(same[:-1] | same[1:]))) + int(not same[0]) + int(
            not same[-1])
        nonmanifold = int(np.count_nonzero(~same[:-2] & same[1:-1] & same[2:])) + int(
            same[0] and same[1])
        misoriented = int(np.count_nonzero(dsame[1:] & ~dsame[:-1])) + int(dsame[0])
    else:  # pragma: no cover - a single face has 3 distinct edges
        boundary, nonmanifold, misoriented = keys.size, 0, 0
    degenerate = int(np.sum((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])))
    from plantscan_hull import kernels

    if kernels.HAVE_NUMBA:  # same test as Open3D's, without its import (~4 s) and 5x faster
        nm_vertices = kernels.nonmanifold_vertices(f, len(mesh.vertices))
    else:
        nm_vertices = len(np.asarray(mesh.to_open3d().get_non_manifold_vertices()))
    rep = {
        "boundary_edges": boundary,
        "nonmanifold_edges": nonmanifold,
        "misoriented_edges": misoriented,
        "nonmanifold_vertices": int(nm_vertices),
        "degenerate_faces": degenerate,
    }
    rep["manifold"] = (rep["nonmanifold_edges"] == 0 and nm_vertices == 0 and degenerate == 0
                       and rep["misoriented_edges"] == 0)
    rep["watertight"] = rep["manifold"] and rep["boundary_edges"] == 0
    return rep


def postprocess(mesh: Mesh, smooth_iterations: int, target_faces: int | None) -> Mesh:
    """Optional Taubin smoothing and quadric decimation with pymeshlab.

    The result is kept only if it is still watertight and manifold (both
    filters can pinch thin sheets); otherwise the input is returned and a
    warning logged.
    """
    if smooth_iterations <= 0 and not target_faces:
        return mesh
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.vertices,
                               face_matrix=mesh.faces.astype(np.int32)))
    if smooth_iterations > 0:
        ms.apply_coord_taubin_smoothing(stepsmoothnum=int(smooth_iterations))
    if target_faces and target_faces < len(mesh.faces):
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(target_faces), preservetopology=True, preservenormal=True,
            qualitythr=0.3)
        ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    out = Mesh(m.vertex_matrix(), m.face_matrix())
    if not topology_report(out)["watertight"]:
        log.warning("marching-cubes: smoothing/decimation broke watertightness; kept the raw mesh")
        return mesh
    return out

"""Scale-free geometric features of a plant surface, per sample cell.

A visual-hull plant surface has a million faces at 512³; an organ classifier does
not need a decision per face.  The faces are grouped into **samples**: cubic cells
of ``SAMPLE_CELL_UNITS`` mesh units (the unit ``u`` is the median edge length, about
a voxel for a marching-cubes mesh), each holding the bits of surface inside it
(both sides of a thin leaf slab fall into the same cells).  Every feature is a
pure number — lengths over ``u`` or over the block size, curvatures times their
smoothing scale, positions over the plant's extent — so the same plant modelled
in centimetres, or scanned at another voxel size, gives the same features:

* per scale ``s`` in ``BLOCK_SCALES`` (cells of ``s u``, read over their 3x3x3
  block): the spread of the normals (eigenvalues of the area-weighted normal
  tensor over the largest: 0 for a flat slab, 1/2 for a tube, 1 for a blob), the
  extent of the surface (square roots of the position covariance's eigenvalues
  over the block's size: a sheet, a rod or a lump), how vertical the sheet axis
  is, how much surface the block holds (layers of fused organs hold more) and how
  well the sample's own normals agree with the block's (inner product of the two
  normal tensors);
* the surface's most concave and its mean curvature across the edges of the
  sample's faces, smoothed at ``CURVATURE_UNITS`` u, times that scale (bends at
  larger scales show in the blocks' normal spread);
* the thickness by an inward ray (where a ray from the face along its inward
  normal leaves the plant), over ``u`` and over the plant's median thickness;
* where the sample sits on the plant: height over the plant's height, distance
  from the plant's axis over its 90th-percentile radius, and the geodesic distance
  over the surface from the plant's base over the largest such distance.

``sample_graph`` holds the pairs of samples that share a mesh edge: instances are
grown over it (``plantscan_leaves.organs``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import dijkstra

from plantscan_core.data import Mesh
from plantscan_leaves import geometry as geo

SAMPLE_CELL_UNITS = 2.0  # a sample: a cell of 2 mesh edges, both sides of a thin slab in it
BLOCK_SCALES = (2.0, 4.0, 8.0, 16.0)  # cell sizes (u) of the neighbourhoods, read as 3x3x3 blocks
CURVATURE_UNITS = 1.5  # smoothing (u) of the edge curvature: creases a voxel or two wide
BASE_BAND = 0.02  # samples within this share of the plant's height above its lowest point: base
GRID_OFFSET = 0.382  # of a unit: an irrational-ish shift of every cell grid
AXIS_BAND = 0.05  # the plant's axis: the mean xy of the samples in this lowest share of height

FEATURE_NAMES = (
    [f"{name}_s{int(s)}" for s in BLOCK_SCALES
     for name in ("normal_mid", "normal_low", "extent_major", "extent_mid", "extent_minor",
                  "axis_vertical", "density", "on_sheet")]
    + ["concave_curvature", "mean_curvature"]
    + ["thickness_units", "thickness_relative", "normal_vertical", "height", "radius",
       "geodesic_from_base"]
)


@dataclass
class SurfaceSamples:
    """The samples of one plant surface and their features.

    Attributes
    ----------
    unit_mm : float
        The mesh unit ``u`` (median edge length), mm.
    face_sample : (F,) int64
        Sample of each face.
    centroid : (S, 3) float64, mm
        Area-weighted centroid of each sample's faces.
    area : (S,) float64, mm²
        Surface area of each sample (both sides of a slab).
    features : (S, len(FEATURE_NAMES)) float32
    pairs : (P, 2) int64
        Samples sharing a mesh edge, each pair once.
    thickness_mm : (S,) float64
        Inward thickness at each sample (NaN where the ray left through nothing).
    moments : (S, 16) float64
        Area moments of each sample's faces (``_moments``: area, normal tensor, first
        and second moments of position); sums, so the moments of a group of samples
        are the sums of theirs.
    """

    unit_mm: float
    face_sample: np.ndarray
    centroid: np.ndarray
    area: np.ndarray
    features: np.ndarray
    pairs: np.ndarray
    thickness_mm: np.ndarray
    moments: np.ndarray

    @property
    def n(self) -> int:
        return len(self.area)


def _cells(points: np.ndarray, lo: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray,
                                                                         np.ndarray]:
    """Cell keys of ``points`` on a grid of ``cell`` mm from ``lo``: (keys, index of each point's
    cell, dims); every occupied cell has a free cell on each side."""
    ijk = np.floor((points - lo) / cell).astype(np.int64) + 1
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    keys, inv = geo.unique_inverse(key, int(np.prod(dims)))
    return keys, inv, dims


def _block_sums(keys: np.ndarray, dims: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(C, m) sums of ``values`` (C, m) over each cell's 3x3x3 block of cells."""
    nc = len(keys)
    ext = np.vstack([values, np.zeros((1, values.shape[1]))])
    acc = np.zeros_like(values)
    for d in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T:
        qk = keys + int((d[0] * dims[1] + d[1]) * dims[2] + d[2])
        pos = np.minimum(np.searchsorted(keys, qk), nc - 1)
        acc += ext[np.where(keys[pos] == qk, pos, nc)]
    return acc


_PAIRS = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def moment_shape(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Shape of groups from their summed moments (G, 16): unit sheet normal (G, 3) (the
    normal tensor's principal axis), its eigenvalues (G, 3, ascending, over the area),
    the principal axis of position (G, 3) and the position covariance's eigenvalues (G, 3)."""
    total = np.maximum(moments[:, :1], 1e-12)
    ev_n, vec_n = np.linalg.eigh(_sym(moments[:, 1:7] / total))
    mean = moments[:, 7:10] / total
    cov = _sym(moments[:, 10:16] / total) - mean[:, :, None] * mean[:, None, :]
    ev_c, vec_c = np.linalg.eigh(cov)
    return vec_n[:, :, 2], ev_n, vec_c[:, :, 2], np.maximum(ev_c, 0.0)


def _sym(flat: np.ndarray) -> np.ndarray:
    m = np.empty((len(flat), 3, 3))
    for c, (a, b) in enumerate(_PAIRS):
        m[:, a, b] = m[:, b, a] = flat[:, c]
    return m


def _moments(centroids: np.ndarray, normals: np.ndarray, areas: np.ndarray, group: np.ndarray,
             n: int) -> np.ndarray:
    """(n, 16) area moments of the faces of each group: area, normal tensor (6), first (3) and
    second (6) moments of position; sums, so groups of groups add up."""
    w = areas
    cols = [w] + [w * normals[:, a] * normals[:, b] for a, b in _PAIRS]
    cols += [w * centroids[:, a] for a in range(3)]
    cols += [w * centroids[:, a] * centroids[:, b] for a, b in _PAIRS]
    return np.stack([np.bincount(group, c, n) for c in cols], axis=1)


def _block_features(moments: np.ndarray, centroid: np.ndarray, lo: np.ndarray,
                    cell: float) -> np.ndarray:
    """(S, 8) features of the 3x3x3 block of ``cell`` mm cells around each sample, from the
    samples' ``moments`` (S, 16) and ``centroid`` (S, 3)."""
    keys, inv, dims = _cells(centroid, lo, cell)
    nc = len(keys)
    per_cell = np.stack([np.bincount(inv, moments[:, c], nc) for c in range(16)], axis=1)
    block = _block_sums(keys, dims, per_cell)
    total = np.maximum(block[:, 0], 1e-12)
    ev_n, vec_n = np.linalg.eigh(_sym(block[:, 1:7] / total[:, None]))  # ascending
    mean = block[:, 7:10] / total[:, None]
    cov = _sym(block[:, 10:16] / total[:, None]) - mean[:, :, None] * mean[:, None, :]
    ev_c = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0.0)) / (3.0 * cell)
    top = np.maximum(ev_n[:, 2], 1e-12)
    # how well the sample's own normals agree with the block's: the inner product of the two
    # normal tensors (trace 1 each; 1 when both are one sheet, 1/3 for a sample of a blob), a
    # smooth function of both, free of the arbitrary eigenvector of a tube's equal eigenvalues
    own = moments[:, 1:7] / np.maximum(moments[:, :1], 1e-12)
    blk = block[inv, 1:7] / total[inv, None]
    weights = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])  # off-diagonal terms count twice
    on_sheet = np.sqrt(np.maximum((own * blk) @ weights, 0.0))
    cell_feats = np.stack([
        ev_n[:, 1] / top, ev_n[:, 0] / top,
        ev_c[:, 2], ev_c[:, 1], ev_c[:, 0],
        np.abs(vec_n[:, 2, 2]),
        block[:, 0] / (3.0 * cell) ** 2,
    ], axis=1)
    return np.hstack([cell_feats[inv], on_sheet[:, None]])


def inward_thickness(mesh: Mesh, faces: np.ndarray) -> np.ndarray:
    """(N,) how far a ray from each of ``faces`` (face indices) along its inward normal runs
    inside the closed surface, mm; NaN where it leaves through nothing."""
    v, f = mesh.vertices, mesh.faces
    scene = geo.raycasting_scene(v, f)
    fn, _ = geo.face_normals_areas(v, f[faces])
    centre = geo.face_centroids(v, f[faces])
    eps = 1e-3 * float(np.median(geo.row_norm(v[f[faces, 0]] - v[f[faces, 1]])))  # off the face
    rays = np.hstack([centre - eps * fn, -fn]).astype(np.float32)
    t = scene.t_hit(rays).astype(float) + eps
    t[~np.isfinite(t)] = np.nan
    return t


def surface_samples(mesh: Mesh, topo: geo.MeshTopology | None = None) -> SurfaceSamples:
    """The samples of ``mesh`` (a closed plant surface, any unit) and their features."""
    topo = topo or geo.topology(mesh.faces)
    u = geo.mesh_unit(mesh.vertices, mesh.faces)
    v, f = mesh.vertices, mesh.faces
    normals, areas = geo.face_normals_areas(v, f)
    centroids = geo.face_centroids(v, f)
    # the grids start off the lattice of marching-cubes centroids (thirds of a voxel), so no
    # centroid sits on a cell wall where float rounding of another unit could flip its cell
    lo = centroids.min(axis=0) - (max(BLOCK_SCALES) + GRID_OFFSET) * u
    # samples
    _, face_sample, _ = _cells(centroids, lo, SAMPLE_CELL_UNITS * u)
    ns = int(face_sample.max()) + 1
    moments = _moments(centroids, normals, areas, face_sample, ns)
    s_area = moments[:, 0]
    safe = np.maximum(s_area, 1e-12)[:, None]
    s_centroid = moments[:, 7:10] / safe

    def per_sample(x: np.ndarray) -> np.ndarray:
        return np.bincount(face_sample, areas * x, ns) / safe[:, 0]

    feats = []
    for s in BLOCK_SCALES:
        block = _block_features(moments, s_centroid, lo, s * u)
        feats += list(block.T)
    kf = geo.face_curvature(mesh, topo, CURVATURE_UNITS * u) * (CURVATURE_UNITS * u)
    concave = np.full(ns, np.inf)
    np.minimum.at(concave, face_sample, kf)
    feats += [concave, per_sample(kf)]
    # one face per sample casts the thickness ray: its first in mesh order (an index, not a
    # size, chooses it: the same face in any unit)
    order = np.argsort(face_sample, kind="stable")
    first = order[np.r_[True, face_sample[order][1:] != face_sample[order][:-1]]]
    thick = inward_thickness(mesh, first)
    median = float(np.nanmedian(thick)) if np.isfinite(thick).any() else u
    thick_filled = np.where(np.isfinite(thick), thick, median)
    feats += [thick_filled / u, thick_filled / max(median, 1e-9)]
    feats.append(per_sample(np.abs(normals[:, 2])))
    # where on the plant
    z = s_centroid[:, 2]
    z0, height = float(z.min()), max(float(np.ptp(z)), 1e-9)
    low = z < z0 + AXIS_BAND * height
    axis_xy = np.average(s_centroid[low, :2], axis=0, weights=s_area[low])
    radius = geo.row_norm(np.c_[s_centroid[:, :2] - axis_xy, np.zeros(ns)])
    feats += [(z - z0) / height, radius / max(float(np.percentile(radius, 90)), 1e-9)]
    # sample adjacency over shared mesh edges, and the geodesic distance from the base
    a, b = face_sample[topo.face_pairs[:, 0]], face_sample[topo.face_pairs[:, 1]]
    cross = a != b
    key = np.unique(np.minimum(a[cross], b[cross]) * ns + np.maximum(a[cross], b[cross]))
    pairs = np.stack([key // ns, key % ns], axis=1)
    feats.append(_geodesic_from_base(s_centroid, pairs, z < z0 + BASE_BAND * height))
    x = np.stack(feats, axis=1).astype(np.float32)
    return SurfaceSamples(u, face_sample, s_centroid, s_area, x, pairs, thick, moments)


def _geodesic_from_base(centroid: np.ndarray, pairs: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(S,) surface distance of each sample from the ``base`` samples over the largest finite
    one (1 where a sample is not connected to the base)."""
    ns = len(centroid)
    w = geo.row_norm(centroid[pairs[:, 0]] - centroid[pairs[:, 1]]) + 1e-9
    g = sparse.csr_matrix((np.r_[w, w], (np.r_[pairs[:, 0], pairs[:, 1]],
                                        np.r_[pairs[:, 1], pairs[:, 0]])), shape=(ns, ns))
    d = dijkstra(g, directed=True, indices=np.flatnonzero(base), min_only=True)
    finite = np.isfinite(d)
    top = float(d[finite].max()) if finite.any() else 1.0
    return np.where(finite, d / max(top, 1e-9), 1.0)

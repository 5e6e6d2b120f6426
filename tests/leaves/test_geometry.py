"""Fast mesh helpers against their plain numpy references."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import phantoms as ph
from plantscan_leaves.geometry import sort_keys, topology, triangle_union_mask, unique_inverse


@pytest.mark.parametrize("n, bound", [(0, 4), (1, 4), (20_000, 50), (20_000, 80_000),
                                      (20_000, 2**61)])
def test_packed_sort_matches_numpy(n, bound):
    # the packed sort is used below 2**62 / n, argsort above, a table of the keys (compiled)
    # when the range is at most DENSE_KEYS_PER_ITEM x n: all must agree with numpy
    key = np.random.default_rng(n).integers(0, bound, n, dtype=np.int64)
    order, ks = sort_keys(key, bound)
    assert np.array_equal(ks, np.sort(key)) and np.array_equal(key[order], ks)
    u, inv = unique_inverse(key, bound)
    u_ref, inv_ref = np.unique(key, return_inverse=True)
    assert np.array_equal(u, u_ref) and np.array_equal(inv, inv_ref.reshape(-1))


def test_topology_of_a_closed_slab():
    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    t = topology(mesh.faces)
    f = mesh.faces
    half = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2), 1)
    assert np.array_equal(t.edges, np.unique(half, axis=0))
    assert np.array_equal(t.edges[t.face_edges.reshape(-1)], half)
    # closed and manifold: every edge has two faces, one pair each, sharing that edge
    assert t.border_edges == 0 and t.non_manifold_edges == 0
    assert len(t.face_pairs) == len(t.edges)
    assert np.all(np.any(t.face_edges[t.face_pairs[:, 0]] == t.pair_edge[:, None], axis=1))
    assert np.all(np.any(t.face_edges[t.face_pairs[:, 1]] == t.pair_edge[:, None], axis=1))


def test_smoothing_a_vanishing_polyline_neither_explodes_nor_moves_it():
    """A 1e-7 mm crest piece (seen on a 640x427 demo hull) once asked scipy for a
    1e15-sample Gaussian kernel; it must come back as a curve no longer than itself."""
    from plantscan_leaves.geometry import polyline_length, smooth_polyline

    tiny = np.array([[0.0, 0.0, 0.0], [1e-7, 0.0, 0.0], [2e-7, 1e-7, 0.0]])
    assert polyline_length(smooth_polyline(tiny, 1.0)) <= polyline_length(tiny)
    coincident = np.zeros((4, 3))
    assert np.array_equal(smooth_polyline(coincident, 1.0), coincident)


@pytest.mark.parametrize("a, b, sigma", [(30.0, 30.0, 5.0), (60.0, 30.0, 5.0), (60.0, 30.0, 2.0)])
def test_smoothing_shrinkage_gives_back_what_smoothing_took(a, b, sigma):
    from plantscan_leaves.geometry import polyline_length, smooth_polyline, smoothing_shrinkage

    s = np.linspace(0.0, 2.0 * np.pi, 3000, endpoint=False)
    loop = np.stack([a * np.cos(s), b * np.sin(s), 0.0 * s], axis=1)
    closed = np.concatenate([loop, loop[:1]])

    def smoothed(sig):
        sm = smooth_polyline(closed, sig, closed=True)
        return np.concatenate([sm, sm[:1]])

    truth = ph.ellipse_perimeter(a, b)
    raw = polyline_length(smoothed(sigma))
    fixed = raw + smoothing_shrinkage(smoothed(2.0 * sigma), sigma, closed=True,
                                      curve_sigma_mm=2.0 * sigma)
    # the outline smoothing of leaf-geometry loses 0.15-1.4 % of these ellipses (radius of
    # curvature 15-30 mm vs sigma 2-5 mm); the circle model gives it back to 0.1 % (the
    # curvature read at 2 sigma is a little low at the ellipse's tips)
    assert raw < truth * (1 - 0.001)
    assert abs(fixed / truth - 1.0) < 0.001


def test_smoothing_shrinkage_ignores_specks():
    from plantscan_leaves.geometry import smooth_polyline, smoothing_shrinkage

    # a loop far smaller than sigma is a speck smoothing is meant to remove, not a circle
    speck = np.random.default_rng(0).normal(0.0, 0.3, (6, 3))
    sm = smooth_polyline(np.concatenate([speck, speck[:1]]), 10.0, closed=True)
    assert smoothing_shrinkage(np.concatenate([sm, sm[:1]]), 5.0, closed=True,
                               curve_sigma_mm=10.0) == 0.0


def test_smoothing_shrinkage_of_a_straight_line_is_zero():
    from plantscan_leaves.geometry import smoothing_shrinkage

    # exactly collinear samples turn by 0: nothing lost, and no division by that 0
    line = np.stack([np.linspace(0.0, 50.0, 200), np.zeros(200), np.zeros(200)], axis=1)
    with np.errstate(all="raise"):
        assert smoothing_shrinkage(line, 5.0, curve_sigma_mm=10.0) == 0.0


def _union_reference(triangles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Every pixel centre tested against every triangle (edge functions, edges included)."""
    r, c = np.mgrid[: shape[0], : shape[1]]
    out = np.zeros(shape, bool)
    for t in triangles:
        s = np.sign((t[1, 0] - t[0, 0]) * (t[2, 1] - t[0, 1])
                    - (t[1, 1] - t[0, 1]) * (t[2, 0] - t[0, 0]))
        if s == 0:
            continue
        inside = np.ones(shape, bool)
        for a, b in ((0, 1), (1, 2), (2, 0)):
            e = (t[b, 0] - t[a, 0]) * (r - t[a, 1]) - (t[b, 1] - t[a, 1]) * (c - t[a, 0])
            inside &= s * e >= -1e-9
        out |= inside
    return out


@pytest.mark.parametrize("seed", range(4))
def test_triangle_union_matches_brute_force(seed):
    # overlapping triangles of both orientations, some reaching past the image's edges
    rng = np.random.default_rng(seed)
    tri = rng.uniform(-4.0, 36.0, (40, 3, 2))
    tri[:5] = tri[:5].round()  # vertices and edges exactly on pixel centres
    assert np.array_equal(triangle_union_mask(tri, (30, 33)), _union_reference(tri, (30, 33)))


def test_triangle_union_counts_an_overlap_once():
    # two triangles covering one square: cv2.fillPoly of both (parity) leaves it empty
    square = np.array([[[2, 2], [20, 2], [20, 20]], [[2, 2], [20, 20], [2, 20]]], float)
    both = np.concatenate([square, square[:, ::-1]])
    assert triangle_union_mask(both, (24, 24)).sum() == 19 * 19


def test_per_mesh_caches_key_on_content():
    # the segmenter's judge and the measurer share one scene and unit per surface: by its
    # content, so a copy hits and an edited copy does not
    from plantscan_leaves.geometry import forget_meshes, mesh_unit, raycasting_scene

    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    v, f = mesh.vertices, mesh.faces
    forget_meshes()
    scene = raycasting_scene(v, f)
    assert raycasting_scene(v.copy(), f.copy()) is scene
    assert mesh_unit(v.copy(), f) == mesh_unit(v, f)
    moved = v * 2.0
    assert raycasting_scene(moved, f) is not scene
    assert mesh_unit(moved, f) == pytest.approx(2.0 * mesh_unit(v, f))
    forget_meshes()
    assert raycasting_scene(v, f) is not scene


def test_shared_topology_is_the_topology_and_read_only():
    # the segmenter and the trust features share one topology per surface (its faces):
    # the same arrays as ``topology``, and nobody may edit what the other reads
    from plantscan_leaves.geometry import forget_meshes, mesh_topology, topology

    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    forget_meshes()
    shared, plain = mesh_topology(mesh.faces), topology(mesh.faces)
    assert mesh_topology(mesh.faces.copy()) is shared  # a copy of the faces hits
    for name in ("edges", "face_edges", "edge_face_count", "face_pairs", "pair_edge"):
        np.testing.assert_array_equal(getattr(shared, name), getattr(plain, name))
        with pytest.raises(ValueError):
            getattr(shared, name)[0] = 0
    assert mesh_topology(mesh.faces[::-1].copy()) is not shared


@pytest.mark.parametrize("case", ["slab", "open", "non-manifold", "shuffled"])
def test_compiled_topology_matches_the_reference(case):
    # the same arrays, in the same order, as the numpy reference: every pass downstream
    # (region growing, smoothing sums) then gives the same labels to the bit
    from plantscan_leaves.geometry import HAVE_NUMBA, topology_reference

    if not HAVE_NUMBA:
        pytest.skip("numba not installed: topology is the reference")
    f = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5).faces
    if case == "open":  # borders: edges of one face
        f = f[: len(f) // 2]
    elif case == "non-manifold":  # an edge of three and four faces, a duplicated face
        f = np.vstack([f, [[f[0, 0], f[0, 1], f.max() + 1]], f[:1], f[5:6, ::-1]])
    elif case == "shuffled":
        f = np.random.default_rng(3).permutation(f)
        f = np.roll(f, 1, axis=1)
    got, want = topology(f), topology_reference(f)
    for name in ("edges", "face_edges", "edge_face_count", "face_pairs", "pair_edge"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name


@pytest.mark.parametrize("case", ["faces", "vertices", "repeated"])
def test_compiled_averaging_operator_matches_the_reference(case):
    # the same CSR arrays (each row's columns in scipy's product order): smoothing sums
    # every row in the same order, so curvature and smoothed slabs are the same to the bit
    from plantscan_leaves.geometry import (
        HAVE_NUMBA,
        averaging_operator,
        averaging_operator_reference,
    )

    if not HAVE_NUMBA:
        pytest.skip("numba not installed: the operator is the reference")
    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    t = topology(mesh.faces)
    n, links = {"faces": (len(mesh.faces), t.face_pairs),
                "vertices": (len(mesh.vertices), t.edges),
                "repeated": (6, np.array([[0, 1], [1, 2], [0, 1], [3, 3], [5, 2]]))}[case]
    got, want = averaging_operator(n, links), averaging_operator_reference(n, links)
    for name in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    x = np.random.default_rng(1).normal(size=(n, 3))
    assert np.array_equal(got @ x, want @ x)


@pytest.mark.parametrize("seed", range(6))
def test_compiled_triangle_union_matches_the_reference(seed):
    # the same spans from the same float expressions: the same pixels, also for vertices on
    # pixel centres, horizontal edges and triangles of no height
    from plantscan_leaves.geometry import HAVE_NUMBA, triangle_union_mask_reference

    if not HAVE_NUMBA:
        pytest.skip("numba not installed: the mask is the reference")
    rng = np.random.default_rng(seed)
    tri = rng.uniform(-4.0, 36.0, (80, 3, 2))
    tri[:10] = tri[:10].round()
    tri[10:14, 1, 1] = tri[10:14, 0, 1]
    tri[14, :, 1] = tri[14, 0, 1]
    assert np.array_equal(triangle_union_mask(tri, (30, 33)),
                          triangle_union_mask_reference(tri, (30, 33)))


@pytest.mark.parametrize("seed", range(5))
def test_compiled_components_match_the_reference(seed):
    # the same component numbers as scipy's (in the order of their lowest node, nodes off
    # `keep` counted alone): every region and piece id downstream stays the same
    from plantscan_leaves.geometry import HAVE_NUMBA, components, components_reference

    if not HAVE_NUMBA:
        pytest.skip("numba not installed: components are the reference")
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 400))
    pairs = rng.integers(0, n, (int(rng.integers(0, 2 * n)), 2))
    keep = rng.random(n) < rng.uniform(0.3, 1.0)
    assert np.array_equal(components(n, pairs, keep), components_reference(n, pairs, keep))


def _bumpy_slab():
    """A closed slab with its vertices jittered: faces of every orientation and size."""
    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    v = mesh.vertices + np.random.default_rng(7).normal(0.0, 0.05, mesh.vertices.shape)
    return v, mesh.faces


def test_compiled_face_loops_match_the_references_to_the_bit():
    # cross products, normals, areas, edge lengths and the curvature across edges summed in
    # the references' (einsum's) order: every threshold downstream sees the same numbers,
    # so the labels and traits stay the same to the last digit
    from plantscan_leaves import geometry as geo

    if not geo.HAVE_NUMBA:
        pytest.skip("numba not installed: the loops are the references")
    v, f = _bumpy_slab()
    t = topology(f)
    cross = geo.face_cross_reference(v, f)
    assert np.array_equal(geo.face_cross(v, f), cross)
    normals, areas = geo.face_normals_areas(v, f)
    norm = geo.row_norm(cross)
    assert np.array_equal(areas, 0.5 * norm)
    assert np.array_equal(normals, cross / np.maximum(norm, 1e-300)[:, None])
    a, b = t.edges[:, 0], t.edges[:, 1]
    assert np.array_equal(geo.segment_lengths(v, a, b), geo.row_norm(v[a] - v[b]))
    c = geo.face_centroids(v, f)
    assert np.array_equal(c, geo.face_centroids_reference(v, f))
    got = geo._edge_curvature_kernel(normals, c, t.face_pairs, len(f))
    assert np.array_equal(got, geo.edge_curvature_reference(normals, c, t.face_pairs, len(f)))
    assert np.isfinite(got).all() and (got < 0).any() and (got > 0).any()  # a real surface


@pytest.mark.parametrize("floor", [None, 1e-12])
def test_compiled_label_moments_match_the_reference_to_the_bit(floor):
    # per-label sums of the same products in the same face order as np.bincount's, also
    # for labels no face carries (their rows stay zero)
    from plantscan_leaves import geometry as geo

    if not geo.HAVE_NUMBA:
        pytest.skip("numba not installed: the moments are the reference")
    v, f = _bumpy_slab()
    normals, areas = geo.face_normals_areas(v, f)
    lab = np.random.default_rng(2).integers(0, 40, len(f))
    lab[lab == 7] = 8  # label 7 empty
    x = geo.face_centroids(v, f) if floor else normals
    got = geo.label_moments(lab, 41, areas, x, floor)
    want = geo.label_moments_reference(lab, 41, areas, x, floor)
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
    assert not got[2][7].any() and got[0][8] > 0


@pytest.mark.parametrize("seed", range(4))
def test_compiled_pair_graph_matches_the_reference(seed):
    # the same canonical CSR arrays as scipy's (columns ascending per row) and the same
    # pair behind every entry: the measurer's shortest paths then take the same
    # predecessors on ties, so the same midrib and length to the bit
    from plantscan_leaves import geometry as geo
    from scipy.spatial import cKDTree

    if not geo.HAVE_NUMBA:
        pytest.skip("numba not installed: the graph is the reference")
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.0, 10.0, (int(rng.integers(1, 600)), 3)).round(1)  # ties on a lattice
    pairs = cKDTree(q).query_pairs(1.0, output_type="ndarray")
    got, got_of = geo.pair_graph(len(q), pairs)
    want, want_of = geo.pair_graph_reference(len(q), pairs)
    assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
    assert np.array_equal(got_of, want_of)
    assert got.has_sorted_indices and got.nnz == 2 * len(pairs)


@pytest.mark.parametrize("cell", [0.7, 1.3, 4.0])
def test_compiled_cell_normal_tensors_match_the_reference(cell):
    # the cell keys, the per-cell tensors and their 3x3x3 block sums added in the same order
    # as the numpy lines they replace: the same bits
    from plantscan_leaves import geometry as geo

    if not geo.HAVE_NUMBA:
        pytest.skip("numba not installed: the tensors are the reference")
    v, f = _bumpy_slab()
    n, w = geo.face_normals_areas(v, f)
    c = geo.face_centroids(v, f)
    keys, m, inv, grid = geo.cell_normal_tensors(c, n, w, cell)
    lo = c.min(axis=0) - cell
    ijk = np.floor((c - lo) / cell).astype(np.int64)
    dims = ijk.max(axis=0) + 3
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    want_keys, want_inv = np.unique(key, return_inverse=True)
    assert np.array_equal(keys, want_keys) and np.array_equal(inv, want_inv)
    assert np.array_equal(grid, np.concatenate([lo, dims.astype(float)]))
    comps = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    t = np.stack([np.bincount(inv, w * n[:, a] * n[:, b], len(keys)) for a, b in comps], 1)
    offsets = np.array([int((d[0] * dims[1] + d[1]) * dims[2] + d[2]) for d in
                        np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T])
    acc = geo.block_sums_reference(keys, t, offsets)
    assert np.array_equal(np.stack([m[:, a, b] for a, b in comps], 1), acc)
    # what a block sums: unit normals, so each block's trace is the area of its 27 cells' faces
    i = np.asarray(ijk[0])
    near = np.all(np.abs(ijk - i) <= 1, axis=1)
    assert np.isclose(np.trace(m[inv[0]]), w[near].sum())


@pytest.mark.parametrize("seed", range(4))
def test_compiled_shortest_paths_match_scipy(seed):
    # distances and predecessors as scipy's dijkstra gives them, with impassable (inf) edges
    # and a distance limit, as the measurer's side graphs have them
    from plantscan_leaves import geometry as geo
    from scipy.spatial import cKDTree

    if not geo.HAVE_NUMBA:
        pytest.skip("numba not installed: scipy's dijkstra is used")
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.0, 10.0, (800, 3))
    pairs = cKDTree(q).query_pairs(1.6, output_type="ndarray")  # ~13 neighbours a point
    g, pair_of = geo.pair_graph(len(q), pairs)
    w = geo.segment_lengths(q, pairs[:, 0], pairs[:, 1])
    w[rng.random(len(w)) < 0.2] = np.inf  # the other side's edges
    g.data = w[pair_of]
    for limit in (np.inf, 6.0):
        dist, pred = geo.shortest_paths(g, 0, limit)
        want_dist, want_pred = geo.shortest_paths_reference(g, 0, limit)
        assert np.array_equal(dist, want_dist) and np.array_equal(pred, want_pred)
        assert np.isfinite(dist).sum() > 10
        if np.isfinite(limit):
            assert (~np.isfinite(dist)).any()  # the limit leaves some out

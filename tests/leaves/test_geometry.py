"""Fast mesh helpers against their plain numpy references."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import phantoms as ph
from plantscan_leaves.geometry import sort_keys, topology, unique_inverse


@pytest.mark.parametrize("n, bound", [(0, 4), (1, 4), (20_000, 50), (20_000, 2**61)])
def test_packed_sort_matches_numpy(n, bound):
    # the packed sort is used below 2**62 / n, argsort above: both must agree with numpy
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

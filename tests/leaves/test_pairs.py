"""The pair judge: two halves of one leaf are merged, two touching leaves are not."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from plantscan_leaves import geometry as geo
from plantscan_leaves import pairs as pr
from plantscan_leaves import phantoms as ph
from plantscan_leaves import pieces as pc
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

from plantscan_core.data import Mesh


def _surface(mesh: Mesh) -> pc.PieceSurface:
    return pc.surface_of(mesh)


def _touching_leaves():
    """Two 1.5 mm slabs, the second tilted 35 deg over the first one's tip: one surface, two
    leaves meeting along a crease; each face's leaf (1, 2)."""
    mesh, parts = ph.touching_slabs()
    return mesh, parts + 1


def _halved(mock_plant, cut):
    """The mock plant's true labels with leaf 3 cut in two: ``cut`` "along" its midrib (as a
    crease along the midrib of a folded leaf cuts it: each half looks like a whole narrow
    leaf) or "across" it, a third of the way from its tip; the cut-off half is leaf 6."""
    plant, mesh, part = mock_plant
    labels = np.where(part >= 0, part + 1, 0)
    c = geo.face_centroids(mesh.vertices, mesh.faces)
    leaf = labels == 3
    d = c[leaf] - c[leaf].mean(axis=0)
    axes = np.linalg.svd(d, full_matrices=False)[2]  # long axis, across, normal
    if cut == "along":
        half = d @ axes[1] > 0
    else:
        s = d @ axes[0]
        half = s > np.percentile(s, 67)
        if np.abs(c[leaf][half, :2]).sum() < np.abs(c[leaf][~half, :2]).sum():
            half = ~half  # the piece farther from the stem is the tip
    labels[np.flatnonzero(leaf)[half]] = 6
    return mesh, labels


@pytest.mark.parametrize("cut", ["along", "across"])
def test_two_halves_of_a_leaf_are_one_leaf(mock_plant, cut):
    mesh, labels = _halved(mock_plant, cut)
    found = pr.pair_features(_surface(mesh), labels, 6)
    assert found.pairs.tolist() in ([[3, 6]], [[6, 3]])  # the other leaves touch none
    prob = pr.load_model().probabilities(found)
    assert prob[0] >= pr.MERGE_PROBABILITY, prob
    out, n, merged, _ = pr.merge_pairs(labels, 6, found, prob)
    assert n == 5 and np.array_equal(out, np.where(labels == 6, 3, labels))
    assert merged[3][0] == 2  # the merged leaf says it was two (the trust's "rejoined")


def test_two_touching_leaves_stay_two():
    mesh, labels = _touching_leaves()
    found = pr.pair_features(_surface(mesh), labels, 2)
    assert len(found.pairs) == 1  # they share a border
    prob = pr.load_model().probabilities(found)
    assert prob[0] < pr.MERGE_PROBABILITY, prob


@pytest.mark.parametrize("scale", [0.2, 3.0])
def test_pair_features_are_scale_free(scale):
    mesh, labels = _touching_leaves()
    ref = pr.pair_features(_surface(mesh), labels, 2).features
    scaled = pr.pair_features(_surface(Mesh(mesh.vertices * scale, mesh.faces)), labels, 2)
    # float32 features of float64 geometry: equal to 1e-4 relative
    np.testing.assert_allclose(scaled.features, ref, rtol=1e-4, atol=1e-5)


def test_merge_rules():
    # leaves 1-2 and 2-3 likely one (a chain: one leaf of three), 3-4 not; debris (5) stays
    # debris, renumbered after the leaves
    labels = np.array([0, 1, 2, 3, 4, 5, 1])
    found = pr.Pairs(np.array([[1, 2], [2, 3], [3, 4]]), np.zeros((3, len(pr.FEATURE_NAMES))))
    out, n, merged, new_of_old = pr.merge_pairs(labels, 4, found, np.array([0.9, 0.6, 0.4]))
    assert n == 2
    assert out.tolist() == [0, 1, 1, 1, 2, 3, 1]
    assert merged == {1: (3, pytest.approx(0.6))}
    assert new_of_old[1:5].tolist() == [1, 1, 1, 2]
    # 1 and 2 were one leaf before a tentative split (parent 7): their merge undoes it, not
    # a join; the leaf is two pieces (leaf 7 and leaf 3) and its one join is 2-3's 0.6
    parent = np.array([0, 7, 7, 3, 4])
    _, _, merged, _ = pr.merge_pairs(labels, 4, found, np.array([0.9, 0.6, 0.4]), parent=parent)
    assert merged == {1: (2, pytest.approx(0.6))}
    _, _, merged, _ = pr.merge_pairs(labels, 4, found, np.array([0.6, 0.9, 0.4]), parent=parent)
    assert merged == {1: (2, pytest.approx(0.9))}  # the uncertain merge was the undo
    # only the undo: one piece, nothing joined
    _, _, merged, _ = pr.merge_pairs(labels, 4, found, np.array([0.6, 0.4, 0.4]), parent=parent)
    assert merged == {1: (1, 1.0)}


def test_the_judge_merges_in_the_segmenter_and_says_so():
    # the segmenter with judge_pairs on a leaf the rules cut in two (labels as the pass sees
    # them, the model a stand-in at our own interface): one leaf, with its evidence
    class Always:
        def probabilities(self, found):
            return np.ones(len(found.pairs))

    mesh, _ = _touching_leaves()
    plain, _ = segment_leaves(mesh)
    assert len(plain.leaf_labels) == 2
    judged, report = segment_leaves(mesh, CurvatureRegionsParams(judge_pairs=True),
                                    pair_model=Always())
    assert judged.leaf_labels == [1] and report.counts["pairs_merged"] == 1
    assert judged.evidence[1]["fragments"] == 2


def test_the_shipped_model_is_what_the_training_script_trains():
    path = pc.__file__.replace("plugins/plantscan_leaves/pieces.py",
                               "scripts/train_pair_model.py")
    spec = importlib.util.spec_from_file_location("train_pair_model", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    model = pr.load_model()
    plants = script.SHIPPED[pr.MODEL_FILE]
    assert model.config == script.training_config(plants)
    assert all(s < 1000 for seeds in plants.values() for s in seeds)  # development only


def test_merges_are_the_components_of_the_likely_pairs():
    # against a plain reference: whatever the order, merging every pair at the threshold or
    # more gives the connected components of those pairs (scipy), numbered in the order of
    # their lowest leaf, debris kept last
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    @settings(max_examples=200, deadline=None)
    @given(st.integers(2, 12), st.data())
    def check(n, data):
        k = data.draw(st.integers(0, 20))
        a = np.array(data.draw(st.lists(st.integers(1, n), min_size=k, max_size=k)), np.int64)
        b = np.array(data.draw(st.lists(st.integers(1, n), min_size=k, max_size=k)), np.int64)
        keep = a != b
        pairs = np.stack([a[keep], b[keep]], 1).reshape(-1, 2)
        prob = np.array(data.draw(st.lists(st.floats(0, 1), min_size=len(pairs),
                                           max_size=len(pairs))))
        labels = np.arange(n + 2)  # stem, every leaf, debris
        found = pr.Pairs(pairs, np.zeros((len(pairs), len(pr.FEATURE_NAMES))))
        out, n_new, merged, _ = pr.merge_pairs(labels, n, found, prob)
        hit = pairs[prob >= pr.MERGE_PROBABILITY] - 1
        graph = coo_matrix((np.ones(len(hit)), (hit[:, 0], hit[:, 1])), shape=(n, n))
        count, comp = connected_components(graph, directed=False)
        first = {}
        ref = [first.setdefault(c, len(first) + 1) for c in comp]
        assert n_new == count
        assert out.tolist() == [0, *ref, count + 1]
        sizes = np.bincount(comp)
        assert {k: v[0] for k, v in merged.items()} == {
            ref[int(np.flatnonzero(comp == c)[0])]: int(sizes[c])
            for c in range(count) if sizes[c] > 1}

    check()

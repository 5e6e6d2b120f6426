"""``learned-organs``: the shipped organ model on analytic phantoms (not its training data)."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import organs as org
from plantscan_leaves import phantoms as ph
from plantscan_leaves.features import surface_samples
from plantscan_leaves.organs import segment_organs

from plantscan_core.data import LabelledMesh, Mesh


def _purity(labelled: LabelledMesh, part: np.ndarray) -> dict[int, tuple[int, float]]:
    """Leaf label -> (truth part holding most of its faces, that share of its faces)."""
    out = {}
    for label in labelled.leaf_labels:
        counts = np.bincount(part[labelled.face_labels == label] + 1)
        out[label] = (int(counts.argmax()) - 1, float(counts.max() / counts.sum()))
    return out


@pytest.fixture(scope="module")
def mock_organs(mock_plant):
    _, mesh, _ = mock_plant
    return segment_organs(mesh)


def test_every_leaf_of_the_mock_plant_is_one_label(mock_plant, mock_organs):
    plant, mesh, part = mock_plant
    labelled, info = mock_organs
    purity = _purity(labelled, part)
    # one label per leaf, each almost all one leaf: the 1-2 % are faces where the blade meets
    # its petiole, which the truth splits by the larger field value, the model by samples
    assert sorted(p for p, _ in purity.values()) == list(range(len(plant.leaves)))
    assert min(share for _, share in purity.values()) > 0.97
    for leaf in range(len(plant.leaves)):  # and almost all of each leaf is in its label
        label = next(lab for lab, (p, _) in purity.items() if p == leaf)
        assert np.mean(labelled.face_labels[part == leaf] == label) > 0.95
    assert info.counts["leaves"] == len(plant.leaves)


def test_features_and_labels_are_the_same_in_centimetres(mock_plant, mock_organs):
    _, mesh, _ = mock_plant
    cm = Mesh(mesh.vertices / 10.0, mesh.faces)
    a, b = surface_samples(mesh), surface_samples(cm)
    assert np.array_equal(a.face_sample, b.face_sample)
    # every feature is a ratio of lengths: float32 rounding of the ratios only
    assert np.allclose(a.features, b.features, rtol=1e-4, atol=1e-5)
    labelled_cm, _ = segment_organs(cm)
    assert np.array_equal(mock_organs[0].face_labels, labelled_cm.face_labels)


def test_a_leaf_broken_in_two_is_one_leaf(mock_plant):
    plant, mesh, part = mock_plant
    # cut leaf 1 across its midrib at mid-length by a 1.6 mm gap (two voxels): the hull of a
    # leaf whose middle the views lost, or a blade the hull broke where it narrows
    pts = mesh.vertices[mesh.faces[part == 1]].reshape(-1, 3)
    centre = pts.mean(axis=0)
    axis = np.linalg.svd(pts - centre, full_matrices=False)[2][0]

    def broken(p: np.ndarray) -> np.ndarray:
        value = plant.field(p)
        in_gap = np.abs((p - centre) @ axis) < 0.8
        return np.where(in_gap & (plant.part_of(p) == 1), -1.0, value)

    cut = ph.MockPlant(broken, plant.leaves, plant.lo, plant.hi, plant.parts, plant.boxes)
    m = cut.mesh(voxel_mm=0.8)
    side = np.sign((m.vertices[m.faces].mean(axis=1) - centre) @ axis)
    truth = plant.part_of(m.vertices[m.faces].mean(axis=1))
    labelled, info = segment_organs(m)
    labels = labelled.face_labels
    halves = [np.bincount(labels[(truth == 1) & (side == s)]).argmax() for s in (-1.0, 1.0)]
    assert halves[0] == halves[1] and halves[0] in labelled.leaf_labels
    assert info.counts["leaves"] == len(plant.leaves)


def _one_pair_at_a_time(frags: org.Fragments, merge_probability, threshold: float = 0.5):
    """Reference for ``agglomerate``: merge the single most likely pair, score again, repeat."""
    moments = frags.moments.copy()
    prob = frags.prob * frags.moments[:, :1]
    log_thick = frags.log_thick * frags.moments[:, 0]
    stem_border = frags.stem_border.astype(float).copy()
    links = {k: list(v) for k, v in frags.links.items()}
    root = np.arange(frags.n)

    def score(keys):
        area = np.maximum(moments[:, :1], 1e-12)
        x = org.pair_features(org._View(frags, links), keys, moments, prob / area,
                              log_thick / area[:, 0], stem_border)
        return dict(zip(keys, merge_probability(x))) if keys else {}

    p = score(sorted(links))
    while p and max(p.values()) >= threshold:
        f, g = max(p, key=lambda k: (p[k], (-k[0], -k[1])))
        root[root == g] = f
        for arr in (moments, prob):
            arr[f] += arr[g]
            arr[g] = 0.0
        log_thick[f] += log_thick[g]
        stem_border[f] += stem_border[g]
        p.pop((f, g))
        links.pop((f, g))
        for key in [k for k in links if g in k]:
            other = key[0] if key[1] == g else key[1]
            old = links.pop(key)
            p.pop(key, None)
            new = (min(f, other), max(f, other))
            cur = links.get(new)
            links[new] = old if cur is None else [cur[0] + old[0], cur[1] + old[1],
                                                  min(cur[2], old[2]), min(cur[3], old[3])]
        p.update(score(sorted(k for k in links if f in k)))
    return root


def test_merging_in_rounds_joins_what_one_pair_at_a_time_joins(mock_plant):
    _, mesh, _ = mock_plant
    model = org.load_model()
    s = surface_samples(mesh)
    frags = org.leaf_fragments(s, np.asarray(model.organ.predict(s.features)),
                               org.InstanceParams())
    calls = []

    def merge_probability(x):
        calls.append(len(x))
        return model.merge.predict(x)

    rounds = org.agglomerate(frags, merge_probability)
    n_rounds = len(calls)
    reference = _one_pair_at_a_time(frags, merge_probability)
    merges = frags.n - len(np.unique(reference))
    assert merges >= 2  # the mock plant's leaves come in pieces: something to merge
    # the same partition of the fragments (labels may differ: compare who is with whom)
    assert np.array_equal(rounds[:, None] == rounds[None, :],
                          reference[:, None] == reference[None, :])
    assert n_rounds <= merges  # a model call per round, not per merge


def test_another_model_folder_without_the_model_names_the_file(tmp_path):
    from plantscan_core.errors import DataError

    with pytest.raises(DataError, match=str(tmp_path)):
        org.load_model(str(tmp_path))

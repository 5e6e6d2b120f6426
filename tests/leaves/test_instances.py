"""Instance-level evaluation on hand-built cases: merged, split, missed, extra, debris."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plantscan_leaves.evaluate import evaluate_traits

from plantscan_core.data import LabelledMesh, LeafTraits, Mesh, Traits


def _plate(x0: float, y0: float, z: float, size: float = 40.0, step: float = 2.0):
    """A flat square of triangles (vertices, faces) in the plane z, corner at (x0, y0)."""
    n = int(size / step) + 1
    xs, ys = np.meshgrid(x0 + np.arange(n) * step, y0 + np.arange(n) * step, indexing="ij")
    v = np.stack([xs.ravel(), ys.ravel(), np.full(n * n, z)], 1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    f = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return v, f


def _join(parts):
    vs, fs, labels, off = [], [], [], 0
    for (v, f), label in parts:
        vs.append(v)
        fs.append(f + off)
        labels.append(np.full(len(f), label))
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(labels)


@pytest.fixture
def case(tmp_path):
    # truth: four 40 mm leaves (ids 0-3) and a stem strip (-1)
    leaf_at = {0: (0.0, 0.0), 1: (45.0, 0.0), 2: (0.0, 60.0), 3: (60.0, 60.0)}
    truth_parts = [(_plate(x, y, 100.0), tid) for tid, (x, y) in leaf_at.items()]
    truth_parts.append((_plate(-30.0, -30.0, 100.0, size=10.0), -1))
    tv, tf, tid = _join(truth_parts)
    truth = tmp_path / "truth"
    truth.mkdir()
    np.savez(truth / "plant.npz", vertices=tv, faces=tf, face_leaf_id=tid)
    Traits([LeafTraits(t, 40.0, 40.0, 1600.0, 160.0) for t in leaf_at],
           {"height_mm": 100.0, "leaf_count": 4, "total_leaf_area_mm2": 6400.0}).save(
        truth / "traits.csv", truth / "plant_traits.json")

    # measured: the same surfaces 0.3 mm higher (a hull around the leaf), labelled as a
    # segmentation might: leaves 0 and 1 in one label (merged), leaf 2 cut 24/16 mm into
    # two labels (split), leaf 3 right, the stem strip called a leaf, and a piece 30 mm
    # away from every organ (phantom volume)
    measured_parts = [
        (_plate(0.0, 0.0, 100.3), 10), (_plate(45.0, 0.0, 100.3), 10),
        (_plate(0.0, 60.0, 100.3, size=40.0), None),  # relabelled below
        (_plate(60.0, 60.0, 100.3), 30),
        (_plate(-30.0, -30.0, 100.3, size=10.0), 40),
        (_plate(150.0, 150.0, 130.0, size=10.0), 50),
    ]
    v2, f2 = measured_parts[2][0]
    centre_x = v2[f2].mean(axis=1)[:, 0]
    mv, mf, labels = _join([(p, 0 if lab is None else lab) for p, lab in measured_parts])
    first = sum(len(p[0][1]) for p in measured_parts[:2])
    labels[first:first + len(f2)] = np.where(centre_x < 24.0, 20, 21)
    labelled = LabelledMesh(Mesh(mv, mf), labels, {k: "leaf" for k in (10, 20, 21, 30, 40, 50)})
    run = tmp_path / "run"
    run.mkdir()
    labelled.save(run / "labelled.npz")
    measured = Traits([LeafTraits(10, 85.0, 40.0, 3200.0, 250.0),
                       LeafTraits(20, 24.0, 40.0, 960.0, 128.0),
                       LeafTraits(21, 16.0, 40.0, 640.0, 112.0),
                       LeafTraits(30, 40.0, 40.0, 1600.0, 160.0),
                       LeafTraits(40, 10.0, 10.0, 100.0, 40.0),
                       LeafTraits(50, 10.0, 10.0, 100.0, 40.0)],
                      {"height_mm": 130.3, "leaf_count": 6, "total_leaf_area_mm2": 6600.0})
    measured.save(run / "traits.csv", run / "plant_traits.json")
    return run, truth


def test_the_matching_rule_gives_the_documented_counts(case):
    run, truth = case
    section = evaluate_traits(run, truth)["traits"]
    json.dumps(section)
    inst = section["instances"]
    # one of the two merged leaves is found through the merged label, the other missed
    assert inst["truth"] == 4 and inst["measured"] == 6
    assert inst["found"] == 3 and inst["missed"] == 1
    assert inst["missed_ids"][0] in (0, 1)
    assert inst["merged"] == 1 and inst["merged_ids"] == [10]
    # leaf 2 is found (its 60 % piece) and split; its 40 % piece is no extra leaf
    assert inst["split"] == 1 and inst["split_ids"] == {"2": [20, 21]}
    assert inst["split_pieces"] == 1
    pairs = {p["truth_id"]: p["measured_id"] for p in section["pairs"]}
    assert pairs[2] == 20 and pairs[3] == 30
    # extra: the stem strip and the off-plant piece, with where each lies
    extra = {e["measured_id"]: e for e in inst["extra_pieces"]}
    assert inst["extra"] == 2 and set(extra) == {40, 50}
    assert extra[40]["stem"] == pytest.approx(1.0) and extra[50]["off_plant"] == pytest.approx(1.0)
    # debris: the extra leaves' measured area, and its share of all measured leaf area
    assert inst["debris_area_mm2"] == pytest.approx(200.0)
    assert inst["debris_share"] == pytest.approx(200.0 / 6600.0)
    assert inst["recall"] == pytest.approx(3 / 4) and inst["precision"] == pytest.approx(3 / 6)
    # plant-level errors against the truth
    plant = section["plant"]
    assert plant["leaf_count"]["error"] == 2
    assert plant["total_leaf_area_mm2"]["relative_error"] == pytest.approx(200.0 / 6400.0)


def test_a_perfect_segmentation_counts_nothing_extra(case):
    run, truth = case
    with np.load(truth / "plant.npz") as z:
        tv, tf, tid = z["vertices"], z["faces"], z["face_leaf_id"]
    labels = np.where(tid >= 0, tid + 1, 0)
    LabelledMesh(Mesh(tv + [0.0, 0.0, 0.3], tf), labels,
                 {0: "stem", 1: "leaf", 2: "leaf", 3: "leaf", 4: "leaf"}).save(run / "labelled.npz")
    Traits([LeafTraits(k, 40.0, 40.0, 1600.0, 160.0) for k in (1, 2, 3, 4)]).save(
        run / "traits.csv")
    inst = evaluate_traits(run, truth)["traits"]["instances"]
    assert (inst["found"], inst["missed"], inst["merged"], inst["split"], inst["extra"]) == (
        4, 0, 0, 0, 0)
    assert inst["debris_area_mm2"] == 0.0 and inst["precision"] == 1.0

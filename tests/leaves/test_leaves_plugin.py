"""The stages through the plugin manager, and the ``traits`` section of ``plantscan evaluate``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from plantscan_leaves import plugin as leaves_plugin

from plantscan_core.data import LabelledMesh, Traits
from plantscan_core.plugins import new_manager


@pytest.fixture
def manager():
    pm = new_manager()
    pm.register(leaves_plugin, name="leaves")
    try:
        yield pm
    finally:
        pm.unregister(leaves_plugin)


def _truth_dir(tmp: Path, plant, mesh, part) -> Path:
    truth = tmp / "ground_truth"
    truth.mkdir()
    np.savez(truth / "plant.npz", vertices=mesh.vertices, faces=mesh.faces, face_leaf_id=part)
    rows = "".join(f"{i},{lf.length_mm},{lf.width_mm},{lf.area_mm2},{lf.perimeter_mm}\n"
                   for i, lf in enumerate(plant.leaves))
    (truth / "traits.csv").write_text("leaf_id,length_mm,width_mm,area_mm2,perimeter_mm\n" + rows)
    return truth


def test_stages_registered_and_run(manager, mock_plant, tmp_path):
    plant, mesh, part = mock_plant
    seg = manager.build("mesh_segmenter", "curvature-regions", {"smoothing_mm": 1.5})
    meas = manager.build("measurer", "leaf-geometry", {})
    labelled = seg.segment(mesh)
    traits = meas.measure(labelled)
    assert len(traits.leaves) == len(plant.leaves)
    assert set(traits.plant) >= {"height_mm", "total_leaf_area_mm2", "leaf_count",
                                 "convex_hull_volume_mm3", "projected_area_mm2"}
    with pytest.raises(ValueError, match="no_such"):
        manager.build("measurer", "leaf-geometry", {"no_such": 1})


def test_evaluate_matches_and_scores(manager, mock_plant, mock_plant_measured, tmp_path):
    plant, mesh, part = mock_plant
    truth = _truth_dir(tmp_path, plant, mesh, part)
    run = tmp_path / "run"
    run.mkdir()
    assert manager.evaluate(run, truth) == {}  # nothing measured yet: no section
    labelled, traits = mock_plant_measured
    labelled.save(run / "labelled.npz")
    traits.save(run / "traits.csv", run / "plant_traits.json")
    section = manager.evaluate(run, truth)["traits"]
    json.dumps(section)  # plain JSON
    assert section["leaves_found"] == section["leaves_truth"] == len(plant.leaves)
    assert section["leaves_merged"] == section["leaves_missed"] == 0
    err = section["mean_relative_error"]
    assert set(err) == {"length", "width", "area", "perimeter", "all"}
    # same 4 % as test_mock_plant_traits (petiole cut known to ~2 mm), as a mean
    assert all(0 <= e < 0.04 for e in err.values())
    # the truth value is compared to the measured one of the matched leaf, not by id
    t0 = Traits.load(truth / "traits.csv").leaves[0]
    row = next(r for r in section["per_leaf"] if r["truth_id"] == 0)
    assert row["area_truth"] == pytest.approx(t0.area_mm2)
    # no leaf of the mock plant sits in thick volume: nothing warned, the same ε
    assert all(r["thick_share"] < 0.05 for r in section["per_leaf"])
    assert section["leaves_warned"] == 0
    assert section["mean_relative_error_unwarned"] == pytest.approx(err)
    # a leaf the measurer warned about (measured 20 % long here) is left out of the
    # second figure only
    bad = row["measured_id"]
    warned = Traits([dataclasses.replace(lf, length_mm=1.2 * lf.length_mm, thick_share=0.3)
                     if lf.leaf_id == bad else lf for lf in traits.leaves], traits.plant)
    warned.save(run / "traits.csv", run / "plant_traits.json")  # the fixture stays as it was
    rows = section["per_leaf"]
    section = manager.evaluate(run, truth)["traits"]
    assert section["leaves_warned"] == 1
    rel = [abs(r["length_measured"] / r["length_truth"] - 1) for r in rows
           if r["measured_id"] != bad]
    assert section["mean_relative_error_unwarned"]["length"] == pytest.approx(np.mean(rel))
    # traits.csv holds 4 decimals: 1.2 x a rounded length is not the rounded 1.2 x length
    assert section["mean_relative_error"]["length"] == pytest.approx(
        (sum(rel) + abs(1.2 * row["length_measured"] / row["length_truth"] - 1)) / len(rows),
        abs=1e-4 / row["length_truth"])


def test_evaluate_counts_merged_and_missed(mock_plant, tmp_path):
    plant, mesh, part = mock_plant
    truth = _truth_dir(tmp_path, plant, mesh, part)
    run = tmp_path / "run"
    run.mkdir()
    # a segmentation that put truth leaves 0 and 1 into one label
    labels = np.where(part == 1, 0, part) + 1  # stem -> 0, leaves 0 and 1 -> 1, leaf i -> i + 1
    kinds = {0: "stem", **{int(k): "leaf" for k in np.unique(labels) if k > 0}}
    lm = LabelledMesh(mesh, labels, kinds)
    lm.save(run / "labelled.npz")
    leaves_plugin.LeafGeometry().measure(lm).save(run / "traits.csv")
    section = leaves_plugin.plantscan_evaluate(run, truth)["traits"]
    assert section["leaves_merged"] == 1
    assert section["leaves_missed"] == 1
    assert section["leaves_found"] == len(plant.leaves) - 1


def test_evaluate_finds_the_turntable_gauge(mock_plant, mock_plant_measured, tmp_path):
    # a calibration fixes the world frame up to a turn about the axis and a shift along it
    from plantscan_core.data import Mesh, rotation_z

    plant, mesh, part = mock_plant
    truth = _truth_dir(tmp_path, plant, mesh, part)
    labelled, traits = mock_plant_measured
    run = tmp_path / "run"
    run.mkdir()
    moved = Mesh(mesh.vertices @ rotation_z(90.0).T + [0.0, 0.0, 80.0], mesh.faces)
    LabelledMesh(moved, labelled.face_labels, labelled.kinds).save(run / "labelled.npz")
    traits.save(run / "traits.csv")
    section = leaves_plugin.plantscan_evaluate(run, truth)["traits"]
    assert section["leaves_found"] == len(plant.leaves) and section["leaves_merged"] == 0
    align = section["frame_alignment"]
    assert align["yaw_deg"] == pytest.approx(-90.0, abs=1.0)
    assert align["translation_mm"][2] == pytest.approx(-80.0, abs=1.0)
    assert align["median_distance_mm"] < 0.5


def test_evaluate_says_where_each_truth_leaf_went(mock_plant, tmp_path):
    # a segmentation that gave the base third of leaf 0 to the stem and a third of leaf 1 to
    # leaf 2: the evaluation names both losses, in shares of the truth leaf's area
    plant, mesh, part = mock_plant
    truth = _truth_dir(tmp_path, plant, mesh, part)
    run = tmp_path / "run"
    run.mkdir()
    centres = mesh.vertices[mesh.faces].mean(axis=1)
    areas = mesh.face_areas()
    labels = part + 1  # stem -> 0, truth leaf i -> i + 1
    r = np.hypot(centres[:, 0], centres[:, 1])
    leaf0, leaf1 = part == 0, part == 1
    base0 = leaf0 & (r < np.percentile(r[leaf0], 33))
    third1 = leaf1 & (centres[:, 2] < np.percentile(centres[leaf1, 2], 33))
    labels[base0] = 0
    labels[third1] = 3
    kinds = {0: "stem", **{int(k): "leaf" for k in np.unique(labels) if k > 0}}
    lm = LabelledMesh(mesh, labels, kinds)
    lm.save(run / "labelled.npz")
    leaves_plugin.LeafGeometry().measure(lm).save(run / "traits.csv")
    shares = {row["truth_id"]: row
              for row in leaves_plugin.plantscan_evaluate(run, truth)["traits"]["area_shares"]}
    assert len(shares) == len(plant.leaves)
    # the measured mesh is the truth mesh, so each truth face's nearest face is itself and
    # the shares are the moved areas exactly (up to float sums)
    assert shares[0]["stem"] == pytest.approx(areas[base0].sum() / areas[leaf0].sum(), abs=1e-4)
    assert shares[0]["own"] == pytest.approx(1.0 - shares[0]["stem"], abs=1e-4)
    assert shares[1]["other_leaves"] == pytest.approx(areas[third1].sum() / areas[leaf1].sum(),
                                                      abs=1e-4)
    assert shares[1]["stem"] == 0.0
    for t in range(2, len(plant.leaves)):
        assert shares[t]["own"] == pytest.approx(1.0) and shares[t]["measured_id"] == t + 1


def test_the_model_files_a_leaf_stage_reads_are_in_its_cache_key(manager, tmp_path):
    # A judge or trust model retrained under its old name must not leave a run folder's
    # cached labels or traits in place (the pipeline hashes the content of input_files).
    import shutil

    from plantscan_leaves import pairs, pieces, stem_parts

    own = tmp_path / "my_piece_model.json.gz"
    shutil.copy(pieces.model_location(None, pieces.MODEL_FILE), own)
    seg = manager.build("mesh_segmenter", "curvature-regions",
                        {"judge_pieces": True, "piece_model": str(own),
                         "judge_stem_parts": True, "judge_pairs": True})
    files = seg.input_files(None)
    assert files[0] == own
    assert files[1] == Path(str(pieces.model_location(None, stem_parts.MODEL_FILE)))
    assert files[2] == Path(str(pieces.model_location(None, pairs.MODEL_FILE)))
    assert all(f.is_file() for f in files)
    assert manager.build("mesh_segmenter", "curvature-regions", {}).input_files(None) == []
    meas = manager.build("measurer", "leaf-geometry", {"trust_model": "trust_model_grass.json.gz"})
    (trust,) = meas.input_files(None)
    assert trust.name == "trust_model_grass.json.gz" and trust.is_file()
    assert manager.build("measurer", "leaf-geometry", {}).input_files(None) == []
    organs = manager.build("mesh_segmenter", "learned-organs", {}).input_files(None)
    assert organs and all(f.is_file() for f in organs)

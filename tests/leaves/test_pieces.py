"""The piece judge of ``curvature-regions`` (``judge_pieces``) on small virtual plants."""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest
from plantscan_leaves import geometry as geo
from plantscan_leaves import phantoms as ph
from plantscan_leaves import pieces as pc
from plantscan_leaves.evaluate import match_leaves
from plantscan_leaves.measure import measure_plant
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

from plantscan_core.data import Mesh
from plantscan_core.errors import DataError

LUMP_RADIUS_MM = 10.0  # a ball of phantom volume on the stem's top: 630 mm² one side, a
#                        "leaf" to the rules (min_leaf_area_mm2 500)


def _surface(mesh: Mesh) -> pc.PieceSurface:
    return pc.surface_of(mesh)


@pytest.fixture(scope="module")
def lumpy_plant():
    """The mock plant (5 leaves on petioles, 0.8 mm voxels) with a ball of phantom volume
    fused to the top of its stem (hull volume no view carved, as over a plant's apex); and
    each face's true part (-1 stem, petioles and lump; 0.. leaves)."""
    plant = ph.mock_plant(5, thickness=2.0, petiole_mm=20.0)
    top = plant.boxes[0][1][2]
    centre = np.array([0.0, 0.0, top + 0.5 * LUMP_RADIUS_MM])

    def lump(p):
        return LUMP_RADIUS_MM - np.linalg.norm(p - centre, axis=-1)

    box = (centre - LUMP_RADIUS_MM, centre + LUMP_RADIUS_MM)
    lumpy = dataclasses.replace(plant, parts=[*plant.parts, lump],
                                boxes=[*plant.boxes, box],
                                hi=np.maximum(plant.hi, box[1] + 2.0))
    mesh = lumpy.mesh(voxel_mm=0.8)
    c = geo.face_centroids(mesh.vertices, mesh.faces)
    in_lump = np.linalg.norm(c - centre, axis=1) < LUMP_RADIUS_MM + 1.0
    return plant, mesh, plant.part_of(c), in_lump


def _training_script():
    spec = importlib.util.spec_from_file_location(
        "train_piece_model", pc.__file__.replace("plugins/plantscan_leaves/pieces.py",
                                                 "scripts/train_piece_model.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_shipped_models_are_what_the_training_script_trains():
    # every model in the package records the configuration it was trained with (plants,
    # label rules, booster parameters, features); it must be the script's for that file, so
    # retraining with the script (--model FILE) gives back the shipped model
    script = _training_script()
    assert pc.MODEL_FILE in script.SHIPPED
    for name, plants in script.SHIPPED.items():
        model = pc.load_model(None if name == pc.MODEL_FILE else name)
        config = script.training_config(plants)
        assert model.config == config, name
        assert model.config_sha256 == pc.config_sha256(config), name
        seeds = script.trained_seeds(model.config)
        assert seeds == plants and all(s < 1000 for v in seeds.values() for s in v), name


def test_the_recipes_judge_with_a_shipped_model():
    # a family recipe with the judge on names a model the package ships (piece_model: a
    # file name in plantscan_leaves/models, or none: the dicot model), trained on that
    # family's development plants among others
    from plantscan_core.recipe import read_recipe_file

    script = _training_script()
    judged = {}
    for recipe in sorted((script.REPO / "recipes").glob("*.yaml")):
        params = read_recipe_file(recipe).get("segment_mesh", {}).get("params") or {}
        if params.get("judge_pieces"):
            judged[recipe.stem] = params.get("piece_model") or pc.MODEL_FILE
    assert judged.get("dicot") == pc.MODEL_FILE  # the session-12 model, unchanged
    for family, name in judged.items():
        assert name in script.SHIPPED, (family, name)
        model = pc.load_model(None if name == pc.MODEL_FILE else name)
        assert model.config == script.training_config(script.SHIPPED[name]), family
        if family in ("dicot", "branched", "grass"):  # the population families
            assert family in script.trained_seeds(model.config), (family, name)


def test_a_model_for_other_features_is_refused(tmp_path):
    import gzip
    import json

    path = tmp_path / "old.json.gz"
    path.write_bytes(gzip.compress(json.dumps({"feature_names": ["area"], "booster": "",
                                               "config": {}, "config_sha256": ""}).encode()))
    with pytest.raises(DataError, match="other features"):
        pc.load_model(str(path))


def test_a_leaf_cut_in_two_is_rejoined(mock_plant):
    # the true labels of the mock plant, with one leaf cut across its midrib a third of the
    # way from its tip (as a crease through a leaf cuts it): the judge joins the two pieces
    # (either to the other: they are each other's partner), and every leaf is whole again
    plant, mesh, part = mock_plant
    labels = np.where(part >= 0, part + 1, 0)
    c = geo.face_centroids(mesh.vertices, mesh.faces)
    leaf = labels == 3
    d = c[leaf] - c[leaf].mean(axis=0)
    axis = np.linalg.svd(d, full_matrices=False)[2][0]
    s = d @ axis
    out = np.where(s > np.percentile(s, 67), 6, 3)
    if np.abs(c[leaf][out == 6, :2]).sum() < np.abs(c[leaf][out == 3, :2]).sum():
        out = np.where(out == 6, 3, 6)  # the piece farther from the stem is the tip
    labels[np.flatnonzero(leaf)] = out
    verdict, _, prob = pc.judge(_surface(mesh), labels, 6, pc.load_model())
    assert pc.JOIN in verdict.verdict[[2, 5]], prob.round(3)
    assert verdict.n_leaves == len(plant.leaves) and not verdict.debris
    m = match_leaves(pc.verdict_labelled(mesh, verdict), mesh.vertices, mesh.faces, part)
    assert len(m["pairs"]) == len(plant.leaves) and not m["split"] and not m["extra"]
    # the rejoined leaf says so (the trust's "rejoined" evidence)
    (joined,) = verdict.joined
    assert verdict.joined[joined][0] == 2


def test_a_lump_of_phantom_volume_is_debris_and_not_counted(lumpy_plant):
    plant, mesh, part, in_lump = lumpy_plant
    rules, _ = segment_leaves(mesh)
    judged, report = segment_leaves(mesh, CurvatureRegionsParams(judge_pieces=True))
    # the rules count the lump as a leaf, the judge as debris
    assert len(rules.leaf_labels) == len(plant.leaves) + 1
    assert len(judged.leaf_labels) == len(plant.leaves)
    (debris,) = [k for k, v in judged.kinds.items() if v == "debris"]
    # most of the lump is debris (its foot, fused with the stem, may stay stem: 80 %)
    assert np.mean(judged.face_labels[in_lump] == debris) > 0.8
    assert report.counts["pieces_debris"] == 1
    m = match_leaves(judged, mesh.vertices, mesh.faces, part)
    assert len(m["pairs"]) == len(plant.leaves) and not m["extra"] and not m["merged"]
    traits, _, _ = measure_plant(judged)
    leaf_area = sum(lf.area_mm2 for lf in traits.leaves)
    assert traits.plant["leaf_count"] == len(plant.leaves) == len(traits.leaves)
    assert traits.plant["total_leaf_area_mm2"] == pytest.approx(leaf_area)
    assert traits.plant["debris_area_mm2"] > 0  # kept, and said


def test_the_judge_is_off_by_default(mock_plant):
    _, mesh, _ = mock_plant
    assert not CurvatureRegionsParams().judge_pieces
    labelled, report = segment_leaves(mesh)
    assert "pieces_leaf" not in report.counts
    assert "debris" not in labelled.kinds.values()


@pytest.mark.parametrize("scale", [0.1, 0.2, 3.0])
def test_piece_features_are_scale_free(lumpy_plant, scale):
    # the same labels on the plant in centimetres (x 0.1) and scaled x 0.2 and x 3 with its
    # voxel: the features agree to 1e-4 relative (the thickness rays are cast in float32 by
    # Open3D: 5e-6 measured; everything else to 1e-9), and so do the judge's verdicts
    _, mesh, part, in_lump = lumpy_plant
    labels = np.where(part >= 0, part + 1, 0)
    labels[in_lump] = 6
    a = pc.piece_features(_surface(mesh), labels, 6)
    b = pc.piece_features(_surface(Mesh(mesh.vertices * scale, mesh.faces)), labels, 6)
    np.testing.assert_allclose(b.features, a.features, rtol=1e-4, atol=1e-9)
    assert np.array_equal(a.partner, b.partner)
    model = pc.load_model()
    assert np.array_equal(model.probabilities(a).argmax(1), model.probabilities(b).argmax(1))


@pytest.mark.parametrize("scale", [0.1, 0.2, 3.0])
def test_judged_labels_are_the_same_in_centimetres_and_scaled(lumpy_plant, scale):
    # with reference_unit_mm the rules and the judge see the plant at the reference unit
    # (docs/leaves.md, "Scale-free segmentation"): the labels are the same face for face
    _, mesh, _, _ = lumpy_plant
    p = CurvatureRegionsParams(reference_unit_mm=geo.mesh_unit(mesh.vertices, mesh.faces),
                               judge_pieces=True)
    mm, _ = segment_leaves(mesh, p)
    scaled, _ = segment_leaves(Mesh(mesh.vertices * scale, mesh.faces), p)
    assert np.array_equal(scaled.face_labels, mm.face_labels)
    assert scaled.kinds == mm.kinds and "debris" in mm.kinds.values()


def _pieces(area, partner):
    return pc.Pieces(np.zeros((len(area), len(pc.FEATURE_NAMES)), np.float32),
                     np.asarray(partner), np.asarray(area, float))


def test_verdict_rules():
    labels = np.array([0, 1, 1, 2, 3, 4, 4, 5])
    prob = np.array([[0.1, 0.1, 0.8],  # largest: a leaf whatever the model says
                     [0.1, 0.8, 0.1],  # joins leaf 3
                     [0.9, 0.05, 0.05],
                     [0.2, 0.7, 0.1],  # its partner (5) is debris: leaf (0.2 > 0.1)
                     [0.1, 0.1, 0.8]])
    v = pc.apply_verdict(labels, _pieces([10, 2, 5, 3, 1], [0, 3, 0, 5, 0]), prob)
    assert v.verdict.tolist() == [pc.LEAF, pc.JOIN, pc.LEAF, pc.LEAF, pc.DEBRIS]
    # leaves numbered by their lowest piece: 1 | 2 + 3 | 4; debris after them
    assert v.labels.tolist() == [0, 1, 1, 2, 2, 3, 3, 4]
    assert v.n_leaves == 3 and v.debris
    assert v.joined == {2: (2, pytest.approx(0.8))}
    # pieces 2 and 3 were one leaf before a tentative split: the join undoes it (one piece)
    v = pc.apply_verdict(labels, _pieces([10, 2, 5, 3, 1], [0, 3, 0, 5, 0]), prob,
                         parent=np.array([0, 1, 3, 3, 4, 5]))
    assert v.labels.tolist() == [0, 1, 1, 2, 2, 3, 3, 4] and v.joined == {}


def test_one_ray_scene_serves_the_judge_and_the_measurer(mock_plant, monkeypatch):
    # with reference_unit_mm the segmenter works on the plant scaled; the piece judge still
    # casts its thickness rays at the plant as given, so the measurer (thick shares) reuses
    # that ray scene instead of building a second (about 1 s at 1.7 M faces)
    from plantscan_leaves import geometry as geo

    _, mesh, _ = mock_plant
    geo.forget_meshes()
    made = []
    real_get = geo._SCENES.get

    def get(vertices, faces, make):
        return real_get(vertices, faces, lambda: made.append(1) or make())

    monkeypatch.setattr(geo._SCENES, "get", get)
    labelled, _ = segment_leaves(mesh, CurvatureRegionsParams(reference_unit_mm=0.5,
                                                              judge_pieces=True))
    assert made == [1]
    measure_plant(labelled)
    assert made == [1]


@pytest.mark.parametrize("seed", range(6))
def test_nearest_pieces_are_those_of_one_tree_of_all_the_others(seed):
    # the pruned search (each piece's own tree, nearest box first) finds the distance and
    # piece that a tree of every other piece's points gives (the plain way)
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, (12, 3))
    points = [c + rng.normal(0, rng.uniform(1, 8), (rng.integers(1, 300), 3)) for c in centres]
    points[3] = np.zeros((0, 3))  # a piece without points has no gap and is no neighbour
    which = [0, 2, 3, 5, 11]
    gap, label = pc._nearest_pieces(points, which)
    for w, i in enumerate(which):
        others = [j for j in range(len(points)) if j != i and len(points[j])]
        if not len(points[i]):
            assert gap[w] == np.inf and label[w] == 0
            continue
        allp = np.vstack([points[j] for j in others])
        owner = np.concatenate([[j + 1] * len(points[j]) for j in others])
        d, k = cKDTree(allp).query(points[i])
        assert gap[w] == d.min()  # the same pair's distance, to the bit
        assert label[w] == owner[k[int(np.argmin(d))]]

"""The learned trust model of the measurer (``measure``'s ``trust_model``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plantscan_leaves import trust_model as tm
from plantscan_leaves.measure import LeafGeometryParams, measure_plant
from plantscan_leaves.trust import LOW_CONFIDENCE, Trust, leaf_trust, model_trust, reason_text
from pydantic import ValidationError

from plantscan_core.data import LabelledMesh, Mesh

SHIPPED = "trust_model_grass.json.gz"


@pytest.fixture(scope="module")
def measured(mock_plant_measured):
    labelled, _ = mock_plant_measured
    traits, measurements, _ = measure_plant(labelled)
    return labelled, traits, measurements


def _features(labelled, traits, measurements):
    from plantscan_leaves import geometry as geo

    unit = geo.mesh_unit(labelled.mesh.vertices, labelled.mesh.faces)
    return tm.leaf_features(traits, measurements, labelled, unit)


def test_features_are_scale_free(measured):
    # the same plant modelled in centimetres (every coordinate / 10) must look the same to
    # the model: a recipe's model then serves a seedling and a grass alike
    labelled, traits, measurements = measured
    x_mm = _features(labelled, traits, measurements)
    cm = LabelledMesh(Mesh(labelled.mesh.vertices / 10.0, labelled.mesh.faces),
                      labelled.face_labels, labelled.kinds, labelled.evidence)
    t_cm, m_cm, _ = measure_plant(cm)
    x_cm = _features(cm, t_cm, m_cm)
    assert x_mm.shape == (len(measurements), len(tm.FEATURE_NAMES)) == x_cm.shape
    assert np.isfinite(x_mm).all()
    # the measurer works in mesh units, so only float rounding differs between the two:
    # points binned into cells fall on the other side of a cell border now and then, which
    # moves one leaf's width and outline by up to 0.07 % (measured); 0.5 % is far below
    # any step the model's trees could take on these ratios
    np.testing.assert_allclose(x_cm, x_mm, rtol=5e-3, atol=1e-6)


def test_a_context_worked_out_beforehand_gives_the_same_features(measured):
    # the measurer works out the labels' part of the features (plant_context) while the
    # leaves are measured, for every leaf label, measured or not: the same numbers
    from plantscan_leaves import geometry as geo

    labelled, traits, measurements = measured
    unit = geo.mesh_unit(labelled.mesh.vertices, labelled.mesh.faces)
    context = tm.plant_context(labelled, labelled.leaf_labels)
    some = measurements[1:]  # one measured leaf fewer than the context knows
    with_context = tm.leaf_features(traits, some, labelled, unit, context)
    assert with_context.tobytes() == tm.leaf_features(traits, some, labelled, unit).tobytes()


def test_one_stem_tree_serves_the_base_hints_and_the_plant_context(measured, monkeypatch):
    # the measurer's base hints and the trust model's plant context both look up the stem's
    # vertices: one k-d tree per plant (0.2 s at 2.9 M faces), built before the first leaf
    from plantscan_leaves import measure as ms

    labelled, traits, _ = measured
    built = []
    real = ms.stem_faces_and_tree
    monkeypatch.setattr(ms, "stem_faces_and_tree", lambda lab: built.append(1) or real(lab))
    again, _, _ = measure_plant(labelled, LeafGeometryParams(trust_model=SHIPPED))
    assert built == [1]
    assert [(lf.length_mm, lf.area_mm2) for lf in again.leaves] == [
        (lf.length_mm, lf.area_mm2) for lf in traits.leaves]


def test_edge_contact_shares(measured):
    # the mock plant's leaves sit on petioles labelled stem: each leaf's edge touches the
    # stem and nothing else, so its three contact shares are (1, 0, 0)
    labelled, traits, measurements = measured
    x = _features(labelled, traits, measurements)
    c = [tm.FEATURE_NAMES.index(f) for f in ("contact_stem", "contact_leaf", "contact_debris")]
    np.testing.assert_allclose(x[:, c].sum(axis=1), 1.0)
    assert (x[:, c[0]] > 0.9).all()


def test_shipped_models_are_trained_on_development_seeds_only():
    from importlib import resources

    names = sorted(f.name for f in (resources.files("plantscan_leaves") / "models").iterdir()
                   if f.name.startswith("trust_model_"))
    assert SHIPPED in names and "trust_model_all.json.gz" in names
    for name in names:
        model = tm.load_model(name)
        seeds = [s for ss in model.config["plants"].values() for s in ss]
        assert seeds and max(seeds) < 1000, name  # validation seeds (>= 1000): never
        assert model.config["features"] == list(tm.FEATURE_NAMES), name


def test_every_family_recipe_names_a_shipped_trust_model():
    # one model per family recipe (each family's own; the all-family one is a new species'
    # start), read when the recipe is checked
    from plantscan_core.recipe import read_recipe_file

    recipes = sorted((Path(__file__).parents[2] / "recipes").glob("*.yaml"))
    families = ("dicot", "grass", "branched", "rosette", "seedling")
    named = {r.stem: (read_recipe_file(r)["measure"].get("params") or {}).get("trust_model")
             for r in recipes if r.stem in families}
    assert set(named) == set(families)
    for family, name in named.items():
        assert name is not None, family
        LeafGeometryParams(trust_model=name)  # found (the validator names a missing one)


def test_each_model_carries_its_cut_and_doubt_puts_it_at_one_half():
    # the low-confidence cut on p_bad is chosen per model on its development plants
    # (scripts/train_trust_model.py choose_cut); doubt maps it onto the confidence's 0.5
    for name in ("trust_model_dicot.json.gz", "trust_model_grass.json.gz",
                 "trust_model_branched.json.gz", "trust_model_seedling.json.gz",
                 "trust_model_all.json.gz"):
        model = tm.load_model(name)
        assert 0.05 <= model.cut <= 0.5, name
        assert "cut_rule" in model.config, name
    model = tm.load_model("trust_model_dicot.json.gz")
    assert model.cut < 0.5  # its development plants need a lower cut (docs/leaves.md)
    p = np.array([0.0, model.cut / 2, model.cut, 0.7, 1.0])

    class Fixed(tm.TrustModel):
        def p_bad(self, x):
            return p

    d = Fixed(model.booster, model.config, model.config_sha256).doubt(np.zeros((5, 1)))
    np.testing.assert_allclose(d, [0.0, 0.25, 0.5, 0.5 + 0.5 * (0.7 - model.cut)
                                   / (1 - model.cut), 1.0])
    assert (np.diff(d) > 0).all()


def test_model_adds_doubt_never_removes_it():
    ruled = Trust(0.3, ["phantom"])
    assert model_trust(ruled, 0.1, []).confidence == 0.3  # the rules' doubt stays
    assert model_trust(ruled, 0.1, []).reasons == ["phantom"]
    t = model_trust(Trust(1.0), 0.8, ["contact_stem", "aspect"])
    assert t.confidence == pytest.approx(0.2) and t.low and t.reasons == ["model"]
    words = reason_text("model", t)
    assert "touches the stem" in words and "width for its length" in words
    assert not model_trust(Trust(1.0), 0.2, ["aspect"]).low


@pytest.mark.parametrize("name", [SHIPPED, "trust_model_dicot.json.gz"])
def test_measure_with_the_shipped_model(measured, name):
    # grass's cut is 0.5, the dicot's lower (chosen on its development plants)
    labelled, _, _ = measured
    traits, measurements, report = measure_plant(labelled,
                                                 LeafGeometryParams(trust_model=name))
    model = tm.load_model(name)
    x = _features(labelled, traits, measurements)
    p_bad, doubt = model.p_bad(x), model.doubt(x)
    assert ((p_bad >= 0) & (p_bad <= 1)).all()
    for leaf, pb, d in zip(traits.leaves, p_bad, doubt):
        rules = leaf_trust(leaf, labelled.evidence.get(leaf.leaf_id))
        # the lower of the two confidences, and the model named when it is the doubt:
        # when its p_bad reaches the model's cut (to the confidence's 3 decimals)
        assert leaf.confidence == pytest.approx(min(rules.confidence, round(1 - d, 3)))
        assert ("model" in leaf.confidence_reasons.split(";")) == (round(1 - d, 3)
                                                                   < LOW_CONFIDENCE)
        if abs(pb - model.cut) > 0.002:
            assert ("model" in leaf.confidence_reasons.split(";")) == (pb >= model.cut)
        assert leaf.quality_flag == ("check" if leaf.confidence < LOW_CONFIDENCE else "ok")
    for w in report.warnings_about(code="low-confidence"):
        leaf = next(lf for lf in traits.leaves if lf.leaf_id == w.leaf)
        if "model" in leaf.confidence_reasons:
            assert "trust model" in w.message


def test_a_missing_model_is_named_when_the_recipe_is_read():
    with pytest.raises(ValidationError, match="no_such_model.json.gz.*train_trust_model"):
        LeafGeometryParams(trust_model="no_such_model.json.gz")
    from plantscan_leaves.segment import CurvatureRegionsParams

    with pytest.raises(ValidationError, match="nope.json.gz.*train_piece_model"):
        CurvatureRegionsParams(piece_model="nope.json.gz")
    with pytest.raises(ValidationError, match="/tmp/absent/m.json.gz.*train_stem_part_model"):
        CurvatureRegionsParams(stem_part_model="/tmp/absent/m.json.gz")

"""The stem-part judge of ``curvature-regions`` (``judge_stem_parts``) on a grass phantom."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from plantscan_leaves import geometry as geo
from plantscan_leaves import phantoms as ph
from plantscan_leaves import pieces as pc
from plantscan_leaves import stem_parts as sp

from plantscan_core.data import rotation_about_axis
from plantscan_core.errors import DataError


@pytest.fixture(scope="module")
def tufted():
    """Two 3 mm culms 170 mm tall (x 0 and 30), a broad blade (120 x 16 mm) and a narrow
    one (100 x 5 mm, 2 mm thick: as thick as a 512³ hull makes a narrow blade) leaving the
    first culm at 45°, 0.6 mm voxels; the labels as the rules give a grass whose narrow
    blade is a tube to them: the broad blade leaf 1, everything else stem (0)."""
    up45 = rotation_about_axis((0.0, 1.0, 0.0), -45.0)  # x -> (cos 45°, 0, sin 45°)
    along = up45 @ np.array([1.0, 0.0, 0.0])
    narrow_base = np.array([-3.0, 0.0, 90.0])
    narrow_dir = np.array([-along[0], 0.0, along[2]])  # up and away from the second culm
    flip = rotation_about_axis((0.0, 0.0, 1.0), 180.0) @ up45
    field = ph.union(ph.cylinder_field(3.0, 0.0, 170.0),
                     ph.cylinder_field(3.0, 0.0, 170.0, (30.0, 0.0)),
                     ph.placed(ph.ellipse_slab_field(60.0, 8.0, 1.5), up45,
                               np.array([33.0, 0.0, 60.0]) + 60.0 * along),
                     ph.placed(ph.ellipse_slab_field(50.0, 2.5, 2.0), flip,
                               narrow_base + 50.0 * narrow_dir))
    mesh = ph.mesh_field(field, (-80, -12, -2), (125, 12, 172), 0.6)
    c = geo.face_centroids(mesh.vertices, mesh.faces)
    on_culm = (np.hypot(c[:, 0], c[:, 1]) < 4.0) | (np.hypot(c[:, 0] - 30.0, c[:, 1]) < 4.0)
    broad = (c[:, 0] > 34.0) & ~on_culm
    narrow = (c[:, 0] < -4.0) & ~on_culm
    labels = np.where(broad, 1, 0).astype(np.int32)
    return mesh, c, labels, on_culm, narrow


def _surface(mesh) -> pc.PieceSurface:
    topo = geo.topology(mesh.faces)
    normals, areas = geo.face_normals_areas(mesh.vertices, mesh.faces)
    return pc.PieceSurface(mesh.vertices, mesh.faces,
                           geo.face_centroids(mesh.vertices, mesh.faces), normals, areas,
                           topo.face_pairs, geo.face_curvature(mesh, topo, 1.5),
                           geo.mesh_unit(mesh.vertices, mesh.faces))


def test_the_narrow_blade_is_one_part_and_the_culms_none(tufted):
    mesh, c, labels, on_culm, narrow = tufted
    parts = sp.stem_parts(_surface(mesh), labels, 1, ground_z=12.0)
    assert parts.features.shape == (parts.m, len(sp.FEATURE_NAMES))
    # the RANSAC finds both culms; their faces (within radius + margin) are in no part
    assert parts.features[0, sp.FEATURE_NAMES.index("found_culms")] == 2
    core = (np.hypot(c[:, 0], c[:, 1]) < 3.5) | (np.hypot(c[:, 0] - 30.0, c[:, 1]) < 3.5)
    assert (parts.part[core] == -1).all()
    # the narrow blade's faces off the culm are one part (its base within the culm's
    # radius + 1.5 mm stays with the culm: a few per cent of the blade)
    k = np.bincount(parts.part[narrow & (parts.part >= 0)]).argmax()
    _, areas = geo.face_normals_areas(mesh.vertices, mesh.faces)
    assert areas[narrow & (parts.part == k)].sum() > 0.9 * areas[narrow].sum()
    assert not (parts.part[~narrow] == k).any()
    # the broad blade (a leaf already) is no part of the stem
    assert (parts.part[labels == 1] == -1).all()


def test_a_part_judged_blade_becomes_a_leaf_and_debris_moves_up(tufted):
    mesh, c, labels, on_culm, narrow = tufted
    parts = sp.stem_parts(_surface(mesh), labels, 1, ground_z=12.0)
    k = np.bincount(parts.part[narrow & (parts.part >= 0)]).argmax()
    prob = np.zeros(parts.m)
    prob[k] = 0.9
    with_debris = labels.copy()
    with_debris[on_culm & (c[:, 2] > 160.0)] = 2  # label 2 = n + 1: debris
    out, n, made = sp.blades_from_stem(with_debris, 1, parts, prob)
    assert (n, made) == (2, 1)
    assert (out[parts.part == k] == 2).all() and (out[with_debris == 2] == 3).all()
    assert (out[with_debris == 1] == 1).all()
    # nothing called a blade: the labels as they were
    same, n0, none = sp.blades_from_stem(with_debris, 1, parts, np.zeros(parts.m))
    assert (n0, none) == (1, 0) and np.array_equal(same, with_debris)


def test_the_pass_is_off_by_default_and_its_counts_are_reported(tufted):
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    mesh = tufted[0]

    class Everything:  # calls every part a blade
        def probabilities(self, parts):
            return np.ones(parts.m)

    off, report_off = segment_leaves(mesh, CurvatureRegionsParams())
    on, report = segment_leaves(mesh, CurvatureRegionsParams(judge_stem_parts=True),
                                stem_part_model=Everything())
    assert "stem_parts" not in report_off.counts
    assert report.counts["stem_parts_to_leaf"] == report.counts["stem_parts"]
    assert len(on.leaf_labels) == len(off.leaf_labels) + report.counts["stem_parts"]


def _training_script():
    spec = importlib.util.spec_from_file_location(
        "train_stem_part_model",
        sp.__file__.replace("plugins/plantscan_leaves/stem_parts.py",
                            "scripts/train_stem_part_model.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_shipped_model_is_what_the_training_script_trains():
    # the model records the configuration it was trained with; it must be the script's,
    # on development seeds only, so the script retrains the shipped model
    script = _training_script()
    model = sp.load_model()
    assert model.config == script.training_config(script.SHIPPED)
    assert model.config_sha256 == pc.config_sha256(model.config)
    assert all(s < 1000 for seeds in model.config["plants"].values() for s in seeds)


def test_the_recipes_that_judge_stem_parts_use_the_shipped_model():
    from plantscan_core.recipe import read_recipe_file

    script = _training_script()
    judged = [r.stem for r in sorted((script.REPO / "recipes").glob("*.yaml"))
              if (read_recipe_file(r).get("segment_mesh", {}).get("params") or {}
                  ).get("judge_stem_parts")]
    for family in judged:  # judged only by a model trained on that family's plants
        assert family in script.SHIPPED, family


def test_a_model_for_other_features_is_refused(tmp_path):
    import gzip
    import json

    path = tmp_path / "old.json.gz"
    path.write_bytes(gzip.compress(json.dumps({"feature_names": ["area"], "booster": "",
                                               "config": {}, "config_sha256": ""}).encode()))
    with pytest.raises(DataError, match="other features"):
        sp.load_model(str(path))

"""Flat-leaf truth of the procedural plants (no rendering)."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_sim.families import FAMILIES
from plantscan_sim.geometry import LeafPlacement, leaf_outline, leaf_surface, mesh_area
from plantscan_sim.plants import PLASTIC_DICOT_LEAVES, build_plant


@pytest.fixture(scope="module")
def dicot():
    return build_plant("plastic-dicot", seed=3, soil_z=142.0)


def test_plastic_dicot_matches_the_seed_table(dicot):
    # Seed's table of dissected leaves.  Length and width within 0.5 % and area within 1 %
    # (the tolerances); perimeter within 3.5 % because the seed's perimeters are
    # shorter than any outline with their length, width and area can have.
    counts = {}
    for leaf in dicot.leaves:
        ref = PLASTIC_DICOT_LEAVES[leaf.kind]
        t = leaf.traits()
        counts[leaf.kind] = counts.get(leaf.kind, 0) + 1
        assert abs(t.length_mm / ref["length"] - 1) < 0.005
        assert abs(t.width_mm / ref["width"] - 1) < 0.005
        assert abs(t.area_mm2 / ref["area"] - 1) < 0.01
        assert abs(t.perimeter_mm / ref["perimeter"] - 1) < 0.035
    assert counts == {k: v["count"] for k, v in PLASTIC_DICOT_LEAVES.items()}


def _boundary_length(v, rows, across):
    g = v.reshape(rows, across, 3)
    sides = [g[:, 0], g[:, -1]]
    return sum(float(np.linalg.norm(np.diff(s, axis=0), axis=1).sum()) for s in sides)


def _assert_keeps_flat_traits(o, placement):
    # The bent blade (mid-surface, in 3D) must keep the flat outline's area, boundary
    # length, midrib length and width: 0.5 % (the bound; chords of the bent
    # polyline are the only loss).
    v, f = leaf_surface(o, placement, across=9)
    rows = len(o.x)
    assert mesh_area(v, f) == pytest.approx(o.area, rel=0.005)
    assert _boundary_length(v, rows, 9) == pytest.approx(o.perimeter, rel=0.005)
    mid = v.reshape(rows, 9, 3)[:, 4]
    assert float(np.linalg.norm(np.diff(mid, axis=0), axis=1).sum()) == pytest.approx(
        o.length, rel=0.005)
    g = v.reshape(rows, 9, 3)
    assert float(np.linalg.norm(g[:, -1] - g[:, 0], axis=1).max()) == pytest.approx(
        o.width, rel=0.005)


@pytest.mark.parametrize("preset", ["plastic-dicot", "wheat", "sorghum", *FAMILIES])
def test_bending_preserves_flat_traits(preset):
    plant = build_plant(preset, seed=1, soil_z=142.0)
    for leaf in plant.leaves:
        _assert_keeps_flat_traits(leaf.outline, leaf.placement)


@pytest.mark.parametrize("twist", [0.0, 15.0, -30.0])
def test_a_twisted_bent_blade_keeps_its_flat_traits(twist):
    # Wrapped on a cylinder, a blade is developable whatever the twist.
    o = leaf_outline(300.0, 20.0, 0.72 * 300.0 * 20.0, p=4.0, warp=0.7)
    place = LeafPlacement.with_total_bend([0.0, 0.0, 150.0], 30.0, 60.0, o.length, 130.0, 5.0,
                                          twist_deg=twist)
    _assert_keeps_flat_traits(o, place)
    # a twisted blade is not planar-bent: its normal turns about the midrib
    _, n = place.midrib(np.array([0.0, o.length]))
    _, _, e3 = place.frame()
    assert (abs(float(n[1] @ e3)) > 0.1) == (twist != 0.0)


@pytest.mark.parametrize("preset", ["plastic-dicot", "wheat", "sorghum"])
def test_rendered_leaf_solids_carry_the_truth_area(preset):
    # Each leaf is a closed 0.5 mm solid: its surface is two blades plus a rim of
    # perimeter x thickness.  Checks the mesh that is rendered against traits.csv's
    # numbers within 0.5 %.
    plant = build_plant(preset, seed=2, soil_z=142.0)
    traits = {t.leaf_id: t for t in plant.traits().leaves}
    for lid, t in traits.items():
        faces = plant.mesh.faces[plant.mesh.face_attr == lid]
        expected = 2 * t.area_mm2 + 0.5 * t.perimeter_mm
        assert mesh_area(plant.mesh.vertices, faces) == pytest.approx(expected, rel=0.005)


def test_presets_are_seeded():
    a = build_plant("wheat", seed=5, soil_z=142.0)
    b = build_plant("wheat", seed=5, soil_z=142.0)
    c = build_plant("wheat", seed=6, soil_z=142.0)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert a.mesh.vertices.shape != c.mesh.vertices.shape or not np.allclose(
        a.mesh.vertices, c.mesh.vertices)


def test_leaves_do_not_cross_each_other():
    # Leaves passing through each other would make the truth mesh non-physical: cast
    # every blade edge of one leaf against the others.
    import open3d as o3d

    plant = build_plant("plastic-dicot", seed=0, soil_z=142.0)
    crossings = 0
    for leaf in plant.leaves:
        others = plant.mesh.face_attr >= 0
        others &= plant.mesh.face_attr != leaf.leaf_id
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(plant.mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(plant.mesh.faces[others].astype(np.uint32)))
        v, _ = leaf_surface(leaf.outline, leaf.placement, across=9)
        g = v.reshape(len(leaf.outline.x), 9, 3)
        a, b = g[:-1].reshape(-1, 3), g[1:].reshape(-1, 3)
        rays = np.concatenate([a, b - a], axis=1).astype(np.float32)
        hit = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
        crossings += int(hit.sum())
    assert crossings == 0

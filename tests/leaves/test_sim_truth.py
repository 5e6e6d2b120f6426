"""Segmentation + measurement of the virtual scanner's truth plants (exact meshes, no hull).

The truth mesh is the plant the virtual scanner renders: leaves are closed 0.5 mm
solids on petioles/stems (separate, interpenetrating shells).  This checks the
leaf stages alone; the full chain is in benchmarks/leaves.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from plantscan_core.data import Mesh

plants = pytest.importorskip("plantscan_sim.plants")

from plantscan_leaves.evaluate import match_leaves, trait_errors  # noqa: E402
from plantscan_leaves.measure import measure_plant  # noqa: E402
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves  # noqa: E402

# the grass settings of docs/leaves.md (blades fused with their stem, chains of crumbs)
# the grass recipes' segmentation parameters (recipes/wheat.yaml, recipes/sorghum.yaml)
GRASS = CurvatureRegionsParams(stem_sheet_ratio=0.25, crumb_merge_rounds=20, stem_scale_mm=None,
                               tips_to_leaf=True, petiole_within_leaf=True)


def _run(preset: str, seed: int = 1, params: CurvatureRegionsParams | None = None):
    plant = plants.build_plant(preset, seed, 0.0)
    tm = plant.mesh
    labelled, _ = segment_leaves(Mesh(tm.vertices, tm.faces), params)
    traits, _, _ = measure_plant(labelled)
    m = match_leaves(labelled, tm.vertices, tm.faces, tm.face_attr)
    return plant, m, trait_errors(plant.traits(), traits, m["pairs"])["mean_relative_error"]


def test_plastic_dicot_truth_mesh():
    plant, m, err = _run("plastic-dicot")
    assert len(m["truth_ids"]) == 12
    assert len(m["pairs"]) == 12 and not m["merged"] and not m["missed"] and not m["extra"]
    # exact surfaces (3.8 mm triangles, 0.5 mm thick): 1 % per trait, the paper-360
    # target for the whole chain, so the leaf stages alone must do at least that well
    for name in ("length", "width", "area", "perimeter"):
        assert err[name] < 0.01, (name, err)


@pytest.mark.parametrize("grass_params", [False, True], ids=["defaults", "grass-params"])
@pytest.mark.parametrize("preset", ["wheat", "sorghum"])
def test_grass_truth_mesh(preset, grass_params):
    plant, m, err = _run(preset, params=GRASS if grass_params else None)
    assert len(m["pairs"]) == len(m["truth_ids"]) and not m["merged"]
    # the grass targets (length 3 %, area 5 %) for the chain, met by the stages alone
    assert err["length"] < 0.03 and err["area"] < 0.05, err


@pytest.mark.slow
def test_plastic_dicot_voxelised_truth():
    # the truth plant as a hull would mesh it: slabs 0.5 + 2 x 0.75 mm thick, 1.25 mm voxels
    from plantscan_leaves.phantoms import voxelise_mesh

    from plantscan_core.data import LeafTraits, Traits

    offset = 0.75
    plant = plants.build_plant("plastic-dicot", 1, 0.0)
    tm = plant.mesh
    mesh = voxelise_mesh(tm.vertices, tm.faces, 1.25, offset)
    labelled, _ = segment_leaves(mesh)
    traits, _, _ = measure_plant(labelled)
    m = match_leaves(labelled, tm.vertices, tm.faces, tm.face_attr)
    assert len(m["pairs"]) == 12 and not m["merged"] and not m["extra"]
    # the slab's outline is the leaf's grown by the offset (phantoms.voxelise_mesh)
    grown = Traits([LeafTraits(t.leaf_id, t.length_mm + 2 * offset, t.width_mm + 2 * offset,
                               t.area_mm2 + t.perimeter_mm * offset + np.pi * offset**2,
                               t.perimeter_mm + 2 * np.pi * offset)
                    for t in plant.traits().leaves])
    err = trait_errors(grown, traits, m["pairs"])["mean_relative_error"]
    # 1.25 mm voxels blur the outline by ~half a voxel (0.3-0.8 % of these leaves): the
    # issue's 1.5 % chain target must hold for the leaf stages on a hull-like mesh
    for name in ("length", "width", "area", "perimeter"):
        assert err[name] < 0.015, (name, err)

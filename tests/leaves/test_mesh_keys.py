"""Mesh digests (the per-mesh caches' key) taken once per leaf stage."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import geometry as geo


@pytest.fixture(autouse=True)
def _fresh_caches():
    geo.forget_meshes()
    yield
    geo.forget_meshes()


def _arrays(seed: int = 0):  # a mesh's two arrays (the digest reads only their bytes)
    rng = np.random.default_rng(seed)
    return rng.normal(size=(30, 3)), rng.integers(0, 30, (40, 3))


def test_digests_are_taken_once_per_array_pair_inside_a_stage(monkeypatch):
    v, f = _arrays(2)
    outside = geo.mesh_key(v, f)
    count = []
    digest = geo._digest
    monkeypatch.setattr(geo, "_digest", lambda a, b: count.append(1) or digest(a, b))
    with geo.meshes_unchanged():
        keys = {geo.mesh_key(v, f) for _ in range(5)}
        other = geo.mesh_key(v * 2.0, f)  # another vertex array: its own digest
    assert keys == {outside} and other != outside
    assert len(count) == 2
    v[0, 0] += 1.0  # outside a stage arrays may change: digested every time
    assert geo.mesh_key(v, f) != outside and len(count) == 3
    assert not geo._KNOWN_KEYS  # nothing held once the last stage ended


def test_each_leaf_stage_digests_its_plant_once(mock_plant, monkeypatch):
    """The segmenter (unit, topology, the judge's scene) and the measurer (unit, scene,
    topology for the trust features) each digest the plant's arrays once, not per ask."""
    from plantscan_leaves.measure import measure_plant
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    _, mesh, _ = mock_plant
    seen = []
    digest = geo._digest
    monkeypatch.setattr(geo, "_digest", lambda a, b: seen.append((id(a), id(b))) or digest(a, b))
    labelled, _ = segment_leaves(mesh, CurvatureRegionsParams(judge_pieces=True))
    in_segment = list(seen)
    measure_plant(labelled)
    in_measure = seen[len(in_segment):]
    assert len(in_segment) == len(set(in_segment)) and len(in_measure) == len(set(in_measure))
    assert (id(mesh.vertices), id(mesh.faces)) in in_segment  # the plant as given: once

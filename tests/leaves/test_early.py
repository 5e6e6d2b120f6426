"""Work begun early for a later stage, and mesh digests taken once per stage."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from plantscan_leaves import geometry as geo
from plantscan_leaves import measure as ms
from plantscan_leaves import segment as sg


@pytest.fixture(autouse=True)
def _fresh_caches():
    geo.forget_meshes()
    yield
    geo.forget_meshes()


def _arrays(seed: int = 0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(30, 3)), rng.integers(0, 30, (40, 3))


def test_early_work_is_taken_once_and_else_computed_where_asked():
    v, f = _arrays()
    calls = []
    gate = threading.Event()

    def work():
        gate.wait(5)
        calls.append(threading.current_thread().name)
        return "early"

    geo.start_early("w", v, f, work)
    geo.start_early("w", v, f, work)  # started once per name and mesh
    gate.set()
    assert geo.early_result("w", v, f, lambda: "now") == "early"
    assert len(calls) == 1 and calls[0].startswith("plantscan-early")
    # taken: the next ask computes; a copy of the arrays is the same mesh (content digest)
    geo.start_early("w", v.copy(), f.copy(), lambda: "again")
    assert geo.early_result("w", v, f, lambda: "now") == "again"
    assert geo.early_result("w", v, f, lambda: "now") == "now"


def test_an_error_in_early_work_reaches_whoever_asks():
    v, f = _arrays(1)

    def broken():
        raise ValueError("no hull")

    geo.start_early("w", v, f, broken)
    with pytest.raises(ValueError, match="no hull"):
        geo.early_result("w", v, f, lambda: "now")


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


def test_the_segmenter_begins_the_measurers_plant_geometry(mock_plant, monkeypatch):
    """Both stages together compute the plant's geometry once, the same as alone."""
    _, mesh, _ = mock_plant
    alone = ms.plant_geometry(mesh)
    calls = []
    real = ms.plant_geometry
    monkeypatch.setattr(ms, "plant_geometry",
                        lambda *a, **k: calls.append(threading.current_thread().name)
                        or real(*a, **k))
    monkeypatch.setattr(sg, "EARLY_MIN_FACES", 0)  # the mock plant is small
    labelled, _ = sg.segment_leaves(mesh)
    traits, _, _ = ms.measure_plant(labelled)
    assert len(calls) == 1 and calls[0].startswith("plantscan-early")  # begun by the segmenter
    for name, value in alone.items():
        assert traits.plant[name] == value  # the same numbers, to the bit

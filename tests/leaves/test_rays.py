"""The ray-casting scene built in a helper process answers as the one built in-process."""

from __future__ import annotations

import numpy as np
import pytest
from plantscan_leaves import geometry as geo
from plantscan_leaves import phantoms as ph
from plantscan_leaves import rays


@pytest.fixture(scope="module")
def slab_and_rays():
    mesh = ph.ellipse_slab_mesh(20.0, 10.0, 2.0, voxel_mm=0.5)
    v, f = mesh.vertices, mesh.faces
    normals, _ = geo.face_normals_areas(v, f)
    centres = geo.face_centroids(v, f)
    # inward rays from every face (the judge's and the measurer's kind), and a few that
    # start outside and miss (inf)
    inward = np.hstack([centres - 1e-3 * normals, -normals])
    outward = np.hstack([centres[:50] + 1e-3 * normals[:50], normals[:50]])
    return v, f, np.vstack([inward, outward]).astype(np.float32)


def test_the_helper_hits_as_the_scene_here_to_the_bit(slab_and_rays):
    v, f, r = slab_and_rays
    here = rays.LocalScene(v, f).t_hit(r)
    helper = rays.HelperScene(v, f)
    try:
        there = helper.t_hit(r)
        again = helper.t_hit(r[::7])  # a second conversation with the same helper
    finally:
        helper.close()
    assert np.isfinite(here).sum() >= len(f) - 5  # inward rays leave through the far side
    assert np.isinf(here[-50:]).all()
    assert there.dtype == np.float32 and there.tobytes() == here.tobytes()
    assert again.tobytes() == here[::7].tobytes()
    assert helper._proc.poll() is not None  # closed: the helper has ended


def test_a_dead_helper_falls_back_to_a_scene_here(slab_and_rays):
    v, f, r = slab_and_rays
    helper = rays.HelperScene(v, f)
    helper._proc.kill()
    try:
        t = helper.t_hit(r)
    finally:
        helper.close()
    assert t.tobytes() == rays.LocalScene(v, f).t_hit(r).tobytes()


def test_a_helper_that_never_answers_is_not_waited_for(slab_and_rays, monkeypatch):
    # a helper that hangs (here: a Python that sleeps) costs READY_TIMEOUT_S, then the
    # scene is built in this process and answers as ever
    import sys

    v, f, r = slab_and_rays
    monkeypatch.setattr(rays, "_helper_command",
                        lambda: [sys.executable, "-c", "import time; time.sleep(60)"])
    monkeypatch.setattr(rays, "READY_TIMEOUT_S", 0.5)
    helper = rays.HelperScene(v, f)
    try:
        t = helper.t_hit(r)
    finally:
        helper.close()
    assert t.tobytes() == rays.LocalScene(v, f).t_hit(r).tobytes()
    assert helper._proc.poll() is not None  # the sleeper was ended


def test_large_meshes_get_a_helper_and_forgetting_ends_it(slab_and_rays, monkeypatch):
    v, f, r = slab_and_rays
    geo.forget_meshes()
    monkeypatch.setattr(rays, "HELPER_MIN_FACES", len(f))
    scene = geo.raycasting_scene(v, f)
    assert isinstance(scene, rays.HelperScene)
    scene.t_hit(r[:10])
    geo.forget_meshes()
    assert scene._proc.poll() is not None
    monkeypatch.setenv("PLANTSCAN_RAY_HELPER", "0")  # the batch's workers: in-process
    assert isinstance(geo.raycasting_scene(v, f), rays.LocalScene)
    geo.forget_meshes()

"""The compiled octree's field, pinned to the bit at 256^3 and 512^3.

The kernels were restructured (issue #20: records instead of positional scalars, dead
paths deleted) without changing their arithmetic; these digests were taken with the
kernels before that change (commit ef60aad) and every later change must keep them, or
say why the field moved and record new ones.  The dense grid cannot check this size
(134 M voxels x 36 views); tests/hull/test_carve.py checks the octree against it on
small grids.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from hull_phantoms import Box, Cylinder, Sphere, ring_calibration, views
from plantscan_hull import kernels
from plantscan_hull.carve import Grid, carve_octree
from plantscan_hull.views import prepare_views

from plantscan_core.data import Silhouette, rotation_x, rotation_z

ELEVATIONS = (0.0, 30.0, 60.0)
# (sha256 of the float32 field, voxel-view tests, cell-view tests, voxels inside)
PINNED = {
    256: ("60a17fb0b79820023e8bd3fa99249972683f3ea0bfcca0732d0e165e52160c4a",
          4499956, 1627182, 675824),
    512: ("3a5c8e3ed00087a6c5a942c8c9d209e5ad5c3d465b607a09ff13aa32e048016a",
          18405230, 6562669, 5368628),
}


def _solid_points() -> np.ndarray:
    """Points 0.4 mm apart filling a sphere, a tapered cylinder and a 0.8 mm leaf, mm."""
    solids = [(Sphere((0.0, 10.0, 30.0), 15.0), (-15, -5, 15), (15, 25, 45)),
              (Box((10.0, 0.0, 20.0), (rotation_z(20) @ rotation_x(30)).T, (30.0, 10.0, 0.4)),
               (-25, -35, 0), (45, 35, 40)),
              (Cylinder(-40.0, -20.0, 25.0, 30.0), (-30, -30, -40), (30, 30, -20))]
    out = []
    for solid, lo, hi in solids:
        axes = [np.arange(a, b, 0.4) for a, b in zip(lo, hi)]
        p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        out.append(p[solid.contains(p)])
    return np.concatenate(out)


@pytest.fixture(scope="module")
def views_36():
    """36 views (3 tilts x 12 angles) of 960 x 720 px: masks splatted from the solids'
    points (fast, deterministic; their exact shape does not matter here)."""
    cal = ring_calibration(f=1400.0, size=(960, 720), elevations=ELEVATIONS)
    pts = _solid_points()
    sils = []
    for v in views(12, ELEVATIONS):
        cam = cal.camera_for_view(v)
        uv = np.rint(cam.project(pts)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < 960) & (uv[:, 1] >= 0) & (uv[:, 1] < 720)
        mask = np.zeros((720, 960), bool)
        mask[uv[ok, 1], uv[ok, 0]] = True
        sils.append(Silhouette(v, mask))
    return prepare_views(sils, cal)


@pytest.mark.slow
@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the compiled kernels' field")
@pytest.mark.parametrize("resolution", [256, 512])
def test_octree_field_is_the_pinned_one(views_36, resolution):
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), resolution)
    phi, stats = carve_octree(views_36, grid, 3, top_cell=32, backend="numba", min_seen=18)
    got = (hashlib.sha256(np.ascontiguousarray(phi).tobytes()).hexdigest(),
           stats.voxel_view_tests, stats.cell_view_tests, int((phi > 0).sum()))
    assert got == PINNED[resolution]

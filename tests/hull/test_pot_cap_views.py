"""The cap over the pot's opening is bounded by the cone the cameras cannot carve."""

from __future__ import annotations

import numpy as np
import pytest
from hull_phantoms import Box, Cylinder, render, ring_calibration, views
from plantscan_hull.pot import TaperedCylinder, views_cone
from plantscan_hull.stages import MarchingCubesMesher, OctreeHull

from plantscan_core.data import CarvingViews

ELEVATIONS = (10.0, 45.0)  # deg above the aim point (0, 0, 0), 400 mm away
POT = Cylinder(-70.0, -30.0, 26.0, 32.0)


def _cone_height(rim_z: float, rim_r: float) -> float:
    """Height of the cone no camera of the lower ring carves over a rim (parallel-free
    geometry: the far rim seen from the camera's centre)."""
    e = np.radians(ELEVATIONS[0])
    return rim_r * (400.0 * np.sin(e) - rim_z) / (400.0 * np.cos(e) + rim_r)


@pytest.fixture(scope="module")
def rosette():
    """Eight flat leaves (1.2 mm thick) lying 1.3 cone heights over the rim, from the axis
    to past the rim: the hull's slices under them stay solid above the cone."""
    height = _cone_height(POT.z1, POT.r1)
    leaves = []
    for a in np.radians(np.arange(0.0, 360.0, 45.0)):
        u, w = np.array([np.cos(a), np.sin(a), 0.0]), np.array([-np.sin(a), np.cos(a), 0.0])
        leaves.append(Box(tuple(20.0 * u + [0.0, 0.0, POT.z1 + 1.3 * height]),
                          np.array([u, w, [0.0, 0.0, 1.0]]), (20.0, 5.0, 0.6)))
    cal = ring_calibration(elevations=ELEVATIONS)
    sils = render(cal, views(12, ELEVATIONS), [POT, *leaves])
    hull = OctreeHull(OctreeHull.Params(resolution=96, floor_z_mm=None))
    volume = hull.reconstruct(sils, cal)
    return volume, CarvingViews.of(sils, cal, hull.k), leaves


def _leaf_points_in_cap(leaves, cap: dict, margin: float, keep_axis: float) -> int:
    """Sample points of the leaves that the cap (grown by the mesher's margin, less the
    stem's column it keeps) removes."""
    g = np.linspace(-1.0, 1.0, 21)
    pts = []
    for leaf in leaves:
        q = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
        pts.append(np.asarray(leaf.centre) + (q * leaf.half) @ np.asarray(leaf.axes))
    p = np.concatenate(pts)
    rho = np.hypot(p[:, 0] - cap["centre_xy_mm"][0], p[:, 1] - cap["centre_xy_mm"][1])
    inside = TaperedCylinder(**cap).inside_distance(rho, p[:, 2], margin) > 0
    return int(np.count_nonzero(inside & (rho > keep_axis)))


def test_the_views_cone_is_the_geometric_one():
    # One ring of cameras 10 deg up and one 45 deg up: the cone is the low ring's,
    # r_rim (h_cam - z_rim) / (d_cam + r_rim) over the rim; with k views allowed to see a
    # point outside it is a little taller (k = 3 of the 12 low views: up to a few tenths
    # of the height), never lower.
    rim = TaperedCylinder(z_bottom_mm=-70.0, z_top_mm=-30.0, r_bottom_mm=26.0, r_top_mm=32.0)
    cal = ring_calibration(elevations=ELEVATIONS)
    vl = views(12, ELEVATIONS)
    centres = np.array([cal.camera_for_view(v).pose.centre for v in vl])
    height = _cone_height(-30.0, 32.0)
    exact = views_cone(CarvingViews(centres, 0), [rim], 0.5)
    # k = 0: for a ring of views the region is the straight cone; the edge is found by
    # bisection to 0.5 / 64 mm, a few hundredths of a mm in height at this slope (4.3)
    exact_h = exact.z_top_mm - exact.z_bottom_mm
    assert exact_h == pytest.approx(height, abs=0.05)
    # k = 3: a point seen outside by 3 views stays, so the region only grows (off the axis;
    # on it all 12 low views lose the rim at once)
    tolerant = views_cone(CarvingViews(centres, 3), [rim], 0.5)
    assert exact_h - 0.05 <= tolerant.z_top_mm - tolerant.z_bottom_mm < 1.3 * height
    # A camera level with the rim sees every point over it against the background.
    level = centres.copy()
    level[:, 2] = -30.0
    assert views_cone(CarvingViews(level, 0), [rim], 0.5) is None


def test_the_cap_under_low_leaves_stays_within_the_views_cone(rosette):
    volume, carving, leaves = rosette
    s = volume.voxel_size
    unbounded = MarchingCubesMesher(MarchingCubesMesher.Params(cap_fit="hull"))
    unbounded.mesh(volume, carving)
    bounded = MarchingCubesMesher(MarchingCubesMesher.Params(cap_fit="bounded"))
    bounded.mesh(volume, carving)
    f = bounded.report.figures
    cap, bound, pot = f["cap"], f["cap_views_bound"], f["pot"][-1]
    free = unbounded.report.figures["cap"]
    # the hull's slices under the leaves keep the walk going: the fit alone overshoots the
    # cone (the test's premise; the rosette family's validation seed 1001: 12.9 vs 6.5 mm)
    cone = _cone_height(pot["z_top_mm"], pot["r_top_mm"])
    assert free["z_top_mm"] - pot["z_top_mm"] > 1.5 * cone
    # bounded: no taller than the views' cone over the fitted rim (k = 3 of 12 low views:
    # a few tenths taller than the k = 0 geometry, test above), recorded in the report
    assert bound["z_top_mm"] - pot["z_top_mm"] < 1.3 * cone
    assert cap["z_top_mm"] <= bound["z_top_mm"] + 1e-9
    assert cap["r_bottom_mm"] <= bound["r_bottom_mm"] + 1e-9
    assert bounded.report.counts["cap_voxels_removed"] < unbounded.report.counts[
        "cap_voxels_removed"]
    # what a user cares about: the leaves lying over the opening are not cut away
    margin = f["pot_margin_mm"]
    taken_free = _leaf_points_in_cap(leaves, free, margin, free["r_top_mm"] + s)
    taken = _leaf_points_in_cap(leaves, cap, margin, cap["r_top_mm"] + s)
    assert taken_free > 0.4 * 8 * 21 * 21  # the unbounded cap takes the leaves' inner parts
    # The bound stands on the fitted rim, which the solid hull under the leaves lifts by
    # about 3 voxels at this resolution (3 mm; the rosettes' 0.24 mm voxels: 0.8 mm), so
    # the cap grown by the mesher's margin still reaches the leaves' undersides near the
    # axis: a fraction of what the unbounded cap takes.
    assert taken < 0.4 * taken_free


def test_without_views_the_cap_is_the_hulls_fit(rosette):
    volume, carving, _ = rosette
    alone = MarchingCubesMesher(MarchingCubesMesher.Params(cap_fit="bounded"))
    alone.mesh(volume)
    hull = MarchingCubesMesher(MarchingCubesMesher.Params(cap_fit="hull"))
    hull.mesh(volume, carving)
    assert alone.report.figures["cap"] == hull.report.figures["cap"]
    assert alone.report.figures["cap_views_bound"] is None

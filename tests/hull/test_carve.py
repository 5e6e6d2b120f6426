"""Visual hull carving against analytic phantoms with exact silhouettes."""

from __future__ import annotations

import numpy as np
import pytest
from hull_phantoms import Box, Cylinder, Sphere, render, ring_calibration, views
from plantscan_hull import kernels
from plantscan_hull.carve import Grid, carve_dense, carve_octree
from plantscan_hull.meshing import marching_cubes, signed_volume
from plantscan_hull.stages import OctreeHull
from plantscan_hull.views import prepare_views

from plantscan_core.data import Silhouettes, rotation_x, rotation_z

ELEVATIONS = (0.0, 30.0)
SPHERE = Sphere((5.0, -3.0, 10.0), 40.0)
# A leaf 0.5 mm thick, 60 x 20 mm, tilted 30 deg: much thinner than the ~1.5 mm voxels below.
LEAF = Box((10.0, 0.0, 20.0), (rotation_z(20) @ rotation_x(30)).T, (30.0, 10.0, 0.25))


@pytest.fixture(scope="module")
def rig():
    return ring_calibration(elevations=ELEVATIONS), views(12, ELEVATIONS)


@pytest.fixture(scope="module")
def sphere_sils(rig):
    cal, vl = rig
    return render(cal, vl, [SPHERE])


@pytest.fixture(scope="module")
def mixed_sils(rig):
    cal, vl = rig
    cyl = Cylinder(-40.0, -20.0, 25.0, 30.0)
    return render(cal, vl, [Sphere((0.0, 10.0, 30.0), 15.0), LEAF, cyl])


BACKENDS = ["numpy"] + (["numba"] if kernels.HAVE_NUMBA else [])


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [0, 3])
@pytest.mark.parametrize("which", ["sphere", "mixed"])
def test_octree_equals_dense(rig, sphere_sils, mixed_sils, k, which, backend):
    # The octree's cell tests are conservative, so every voxel it decides at a coarse
    # level must get exactly the clamped field the full grid computes: no tolerance.
    # numba: children test only the views their parent left ambiguous (inheritance).
    cal, _ = rig
    sils = sphere_sils if which == "sphere" else mixed_sils
    vf = prepare_views(list(sils), cal)
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), 40)
    dense, sd = carve_dense(vf, grid, k, backend=backend)
    octree, so = carve_octree(vf, grid, k, top_cell=16, backend=backend)
    assert np.array_equal(dense > 0, octree > 0)
    assert np.array_equal(dense, octree)
    assert (dense > 0).sum() > 100  # something was kept
    assert so.voxel_view_tests + so.cell_view_tests < sd.voxel_view_tests


def _exact_sphere_hull(cal, vl, sphere: Sphere, points: np.ndarray) -> np.ndarray:
    """Points inside the continuous visual hull of a sphere (no pixels involved)."""
    inside = np.ones(len(points), dtype=bool)
    c = np.asarray(sphere.centre)
    for v in vl:
        cam = cal.camera_for_view(v)
        o = cam.pose.centre
        d = points - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        oc = c - o
        along = d @ oc
        dist2 = oc @ oc - along**2
        inside &= (dist2 <= sphere.radius**2) & (along > 0)
    return inside


def test_sphere_hull_volume(rig, sphere_sils):
    cal, vl = rig
    hull = OctreeHull(OctreeHull.Params(resolution=80, k=0, floor_z_mm=None))
    vol = hull.reconstruct(sphere_sils, cal)
    mesh = marching_cubes(vol.field, vol.origin, vol.voxel_size)
    # Exact hull volume by sampling a 1 mm lattice (sampling error ~0.3 %).
    ax = [np.arange(c - 50, c + 50, 1.0) for c in SPHERE.centre]
    pts = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)
    exact = _exact_sphere_hull(cal, vl, SPHERE, pts).sum() * 1.0
    sphere_volume = 4 / 3 * np.pi * SPHERE.radius**3
    assert exact > sphere_volume  # the hull of 24 views is a polyhedron around the sphere
    # The masks put the boundary to the nearest pixel: on a ~40 px radius that is an
    # unbiased +-0.5 px, plus marching cubes' chords on ~1.4 mm voxels: 1.5 % covers both.
    assert signed_volume(mesh) == pytest.approx(exact, rel=0.015)


def test_sphere_occupancy_matches_exact_hull(rig, sphere_sils):
    cal, vl = rig
    vf = prepare_views(list(sphere_sils), cal)
    grid = Grid.from_box((-50, -50, -40), (60, 60, 60), 64)
    phi, _ = carve_octree(vf, grid, 0, keep_thin=False)
    idx = np.argwhere(np.ones(grid.shape, dtype=bool))
    exact = _exact_sphere_hull(cal, vl, SPHERE, grid.centres(idx)).reshape(grid.shape)
    wrong = (phi > 0) != exact
    # Disagreement only from the masks' pixel quantisation: a voxel within 0.5 px
    # (~0.5 mm here, a third of a voxel) of the hull surface; that shell is < 2 % of it.
    assert wrong.sum() < 0.02 * exact.sum()
    # and never deep: every wrong voxel has a 6-neighbour on the other side of the truth.
    e = exact
    border = np.zeros_like(e)
    for ax in range(3):
        border |= np.roll(e, 1, ax) != e
        border |= np.roll(e, -1, ax) != e
    assert not (wrong & ~border).any()


@pytest.mark.parametrize("k", [0, 3])
def test_more_views_never_add_voxels(rig, mixed_sils, k):
    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), 40)
    previous = None
    # Nested view sets: every 4th view of ring 0, every 2nd, all of ring 0, both rings.
    for subset in (vf[0:12:4], vf[0:12:2], vf[0:12], vf):
        occ = carve_octree(subset, grid, k, keep_thin=False)[0] > 0
        if previous is not None:
            assert not (occ & ~previous).any()
            assert occ.sum() <= previous.sum()
        previous = occ


def _leaf_points() -> np.ndarray:
    """(N, 3) points of the leaf's mid-plane on a 1 mm lattice, mm."""
    grid = np.stack(np.meshgrid(np.linspace(-29, 29, 59), np.linspace(-9, 9, 19), [0.0],
                                indexing="ij"), -1).reshape(-1, 3)
    return grid @ np.asarray(LEAF.axes) + np.asarray(LEAF.centre)


def _outside_distance(mesh, pts: np.ndarray) -> np.ndarray:
    """Distance (mm) from each point to the closed mesh, 0 for points inside it."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh.to_open3d()))
    q = o3d.core.Tensor(pts.astype(np.float32))
    d = scene.compute_distance(q).numpy()
    return np.where(scene.compute_occupancy(q).numpy() > 0, 0.0, d)


def _exact_leaf_hull_volumes(cal, vl) -> dict[int, float]:
    """Volume (mm^3) of the continuous k-tolerant visual hull of LEAF for k = 0, 3.

    Ray geometry only: a point is outside a view when the ray through it misses the box.
    """
    step = np.array([1.0, 1.0, 0.2])  # fine across the leaf, where the hull is thin
    g = np.stack(np.meshgrid(np.arange(-34, 34, step[0]), np.arange(-14, 14, step[1]),
                             np.arange(-5, 5, step[2]), indexing="ij"), -1).reshape(-1, 3)
    pts = g @ np.asarray(LEAF.axes) + np.asarray(LEAF.centre)
    n_out = np.zeros(len(pts), dtype=int)
    for v in vl:
        o = cal.camera_for_view(v).pose.centre
        d = pts - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        n_out += ~LEAF.hit(np.broadcast_to(o, d.shape).copy(), d)
    assert not ((n_out <= 3) & (np.abs(g[:, 2]) >= 4.8)).any()  # the lattice holds the hull
    return {k: float((n_out <= k).sum() * step.prod()) for k in (0, 3)}


@pytest.fixture(scope="module")
def leaf_sils(rig):
    cal, vl = rig
    return render(cal, vl, [LEAF])


@pytest.fixture(scope="module")
def leaf_hull_volumes(rig):
    return _exact_leaf_hull_volumes(*rig)


@pytest.mark.parametrize("k", [0, 3])
def test_thin_leaf_survives(rig, leaf_sils, leaf_hull_volumes, k):
    cal, vl = rig
    sils = leaf_sils
    vol = OctreeHull(OctreeHull.Params(resolution=64, k=k, floor_z_mm=None)).reconstruct(sils, cal)
    s = vol.voxel_size
    assert s > 2 * 0.5  # the leaf is less than half a voxel thick
    mesh = marching_cubes(vol.field, vol.origin, vol.voxel_size)
    d = _outside_distance(mesh, _leaf_points()) / s
    # Not lost: a voxel centre is within half a voxel of the leaf plane and the kept
    # sheet passes through it, so the leaf is within a voxel of (or inside) the mesh;
    # near the leaf's outline the outline itself is only known to a voxel, hence 1.5.
    assert np.mean(d < 1.0) >= 0.99, k
    assert d.max() < 1.5, (k, d.max())
    # Not fattened: no more volume than the exact k-tolerant hull of the leaf (+10 % for
    # pixel quantisation); a whole-footprint test gives 1.7-2.8 times that.
    assert signed_volume(mesh) <= 1.1 * leaf_hull_volumes[k]


def test_thin_leaf_lost_without_rescue(rig, leaf_sils):
    # The failure the rescue exists for: centre tests at k = 0 leave holes in the leaf.
    cal, vl = rig
    sils = leaf_sils
    hull = OctreeHull(OctreeHull.Params(resolution=64, k=0, keep_thin=False, floor_z_mm=None))
    vol = hull.reconstruct(sils, cal)
    mesh = marching_cubes(vol.field, vol.origin, vol.voxel_size)
    d = _outside_distance(mesh, _leaf_points()) / vol.voxel_size
    assert d.max() > 1.5 or np.mean(d < 1.0) < 0.99


def test_views_that_miss_a_voxel_do_not_carve_it(rig):
    # Some images end at column 170 (a narrower sensor): the part of the sphere beyond
    # that column is unseen by them and must not be carved by them.
    from dataclasses import replace

    from plantscan_hull.views import prepare_view

    from plantscan_core.data import Camera, Silhouette

    cal, vl = rig
    sils = render(cal, vl, [SPHERE])
    vf = []
    for s in sils:
        cam = cal.camera_for_view(s.view)
        if s.view.tilt_index == 0 and s.view.angle_index % 3 == 0:
            narrow = Camera(replace(cam.model, width=170), cam.pose)
            assert s.mask[:, 170:].any()  # the sphere really crosses the cut
            vf.append(prepare_view(Silhouette(s.view, s.mask[:, :170]), narrow))
        else:
            vf.append(prepare_view(s, cam))
    grid = Grid.from_box((-50, -50, -40), (60, 60, 60), 40)
    phi = carve_octree(vf, grid, 0, keep_thin=False)[0]
    idx = np.argwhere(np.ones(grid.shape, dtype=bool))
    depth = SPHERE.radius - np.linalg.norm(grid.centres(idx) - SPHERE.centre, axis=1)
    deep = (depth > grid.voxel_size).reshape(grid.shape)
    assert deep.sum() > 1000
    assert (phi[deep] > 0).all()


def test_silhouettes_container_roundtrip(sphere_sils):
    assert isinstance(sphere_sils, Silhouettes) and len(sphere_sils) == 24


def test_distance_table_is_signed_distance_in_fixed_point():
    # The int16 table is the float signed distance rounded to SD_STEP: within half a
    # step (the cell tests' slack assumes it) and never of the other sign (the bounding
    # box reads the mask back from it).
    from plantscan_hull.views import SD_STEP, signed_distance, signed_distance_table

    rng = np.random.default_rng(3)
    for _ in range(5):
        mask = rng.random((60, 80)) < 0.3
        mask[20:40, 30:60] = True
        exact = signed_distance(mask)
        table = signed_distance_table(mask)
        assert table.dtype == np.int16
        assert np.abs(table * SD_STEP - exact).max() <= SD_STEP / 2 + 1e-4
        assert np.array_equal(table > 0, mask)


def test_distance_table_from_a_placed_crop_equals_the_full_mask():
    # prepare_views writes each silhouette's crop straight into the thread's scratch
    # mask at its place in the region of interest; the scratch holds the previous view's
    # mask, so everything outside the crop must be cleared: same table as the full mask.
    from plantscan_hull.views import signed_distance_table

    rng = np.random.default_rng(5)
    signed_distance_table(np.ones((70, 90), bool))  # a dirty scratch, larger than below
    for v, u in [(0, 0), (7, 11), (20, 50)]:
        crop = rng.random((40, 30)) < 0.4
        full = np.zeros((60, 80), bool)
        ch, cw = crop[:60 - v, :80 - u].shape
        full[v:v + ch, u:u + cw] = crop[:ch, :cw]
        out = np.empty(full.shape, np.int16)
        signed_distance_table(crop[:ch, :cw], out, at=(v, u))
        assert np.array_equal(out, signed_distance_table(full))


def test_distance_table_saturates_towards_zero():
    # Beyond the int16 range (1024 px at 1/32 px) values saturate towards 0: a cell
    # test then decides less, never wrongly (|stored| <= |true|, same sign).
    from plantscan_hull.views import SD_STEP, signed_distance, signed_distance_table

    mask = np.zeros((8, 2400), dtype=bool)
    mask[2:6, :4] = True
    exact = signed_distance(mask)
    table = signed_distance_table(mask).astype(float) * SD_STEP
    assert exact.min() < -2000  # the far end is beyond the range
    assert np.all(np.abs(table) <= np.abs(exact) + SD_STEP / 2)
    assert np.array_equal(table > 0, exact > 0)
    assert table.min() == pytest.approx(-1024.0, abs=SD_STEP)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the compiled combination needs numba")
def test_compiled_distance_table_equals_the_opencv_combination(monkeypatch):
    # The compiled one-pass combination against OpenCV's subtract + addWeighted (the
    # path without numba), to the bit: random masks, a placed crop, values beyond the
    # int16 range and a mask touching the image edges.
    from plantscan_hull.views import signed_distance_table

    rng = np.random.default_rng(11)
    masks = [rng.random((90, 120)) < p for p in (0.05, 0.3, 0.7)]
    far = np.zeros((8, 2400), bool)
    far[2:6, :4] = True
    edge = np.zeros((50, 60), bool)
    edge[:, :3] = edge[0, :] = True
    cases = [(m, None) for m in (*masks, far, edge)] + [(masks[1][10:50, 20:70], (5, 9))]
    for mask, at in cases:
        shape = (70, 90) if at is not None else mask.shape
        compiled = signed_distance_table(mask, np.empty(shape, np.int16), at=at)
        with monkeypatch.context() as mp:
            mp.setattr(kernels, "distance_table", lambda *a: False)
            plain = signed_distance_table(mask, np.empty(shape, np.int16), at=at)
        assert np.array_equal(compiled, plain)
        if mask is far:
            assert plain.min() == -32768  # saturated (the far end is ~2400 px out)


def test_tables_in_one_buffer_never_copied(rig, sphere_sils):
    # Memory: every view's table is a slice of one int16 buffer of exactly the regions
    # of interest, and the compiled carve reads that buffer as it is (no second copy,
    # whatever the subset or order of views).
    cal, _ = rig
    vf = prepare_views(list(sphere_sils), cal)
    buf = vf[0].sd.base
    assert buf is not None and buf.dtype == np.int16
    assert all(v.sd.base is buf for v in vf)
    assert buf.nbytes == sum(v.sd.nbytes for v in vf) == 2 * sum(v.sd.size for v in vf)
    params, tables = kernels.pack(vf[::-3])
    assert tables is buf
    assert params.shape[0] == len(vf[::-3])


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the batches are the compiled path's")
def test_sibling_batches_change_nothing(rig, mixed_sils, monkeypatch):
    # classify_group works through the parents in batches (memory: one batch's scratch
    # lists at a time); tiny batches must give the same field and the same work.
    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), 40)
    whole, s_whole = carve_octree(vf, grid, 3, top_cell=16, backend="numba")
    monkeypatch.setattr(kernels, "GROUP_BATCH", 3)
    batched, s_batched = carve_octree(vf, grid, 3, top_cell=16, backend="numba")
    assert s_whole.cells_per_level[2] > 3 * 8  # several batches at the last split level
    assert np.array_equal(whole, batched)
    assert s_batched.cell_view_tests == s_whole.cell_view_tests
    assert s_batched.voxel_view_tests == s_whole.voxel_view_tests


@pytest.mark.parametrize("backend", BACKENDS)
def test_tighter_cell_tests_do_less_work_for_the_same_field(rig, mixed_sils, backend,
                                                            monkeypatch):
    # Session 4: a cell test bounds the cell's voxel centres ((n - 1) / 2 voxels from its
    # centre on each axis, not the cube's corners) and, for small footprints, reads its
    # centre bilinearly (margin 1.02 sqrt(2) r + 1/32 px instead of 1.02 r + 1.5 px).
    # Both tighten a conservative bound: the field stays exactly the dense one, and
    # fewer views are left ambiguous, so fewer cells are split and fewer voxels tested.
    import math

    from plantscan_hull import carve

    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), 64)
    dense, _ = carve_dense(vf, grid, 3, backend=backend)
    now, s_now = carve_octree(vf, grid, 3, top_cell=16, backend=backend)
    monkeypatch.setattr(carve, "CELL_BILINEAR_MAX_PX", 0.0)
    if backend == "numpy":  # the compiled kernels compute the radius inline
        monkeypatch.setattr(carve, "centre_radius", lambda half, s: half * math.sqrt(3.0))
    before, s_before = carve_octree(vf, grid, 3, top_cell=16, backend=backend)
    assert np.array_equal(now, dense)
    assert np.array_equal(before, dense)
    assert s_now.cell_view_tests < s_before.cell_view_tests
    assert s_now.voxel_view_tests < s_before.voxel_view_tests
    assert s_now.fine_voxels < s_before.fine_voxels


@pytest.mark.parametrize("backend", BACKENDS)
def test_octree_equals_dense_for_every_top_cell(rig, mixed_sils, backend):
    # An odd grid (37 voxels: padded top cells, partial 2-voxel cells) and every top
    # cell size, down to 1 (the dense grid) and 2 and 4 (the last levels' batches start
    # at once): no tolerance.  top_cell 1 on the compiled path used to leave every
    # voxel at -1 (found in session 4).
    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    grid = Grid.from_box((-60, -60, -50), (60, 60, 70), 37)
    dense, _ = carve_dense(vf, grid, 3, backend=backend)
    assert (dense > 0).sum() > 100
    for top in (1, 2, 4, 32):
        octree, _ = carve_octree(vf, grid, 3, top_cell=top, backend=backend)
        assert np.array_equal(octree, dense), top


def _random_parents(vf, n_par: int, seed: int):
    """Inputs of the sibling kernels: (P, 3) parent centres (half around the objects, half
    anywhere within 1.2 camera distances: behind cameras, off the images, beyond the
    tables), the ``Tree`` of their lists (each of ~80 % of the views, with decided out /
    in / off counts) and which children lie in the grid."""
    rng = np.random.default_rng(seed)
    dist = np.linalg.norm(vf[0].camera.pose.t)  # camera distance from the origin (mm)
    centres = rng.uniform(-1.2 * dist, 1.2 * dist, (n_par, 3))
    centres[: n_par // 2] = rng.uniform(-50, 50, (n_par // 2, 3))
    lists = [np.flatnonzero(rng.random(len(vf)) < 0.8) for _ in range(n_par)]
    start = np.concatenate([[0], np.cumsum([len(v) for v in lists])]).astype(np.int64)
    views = np.concatenate(lists).astype(np.int16)
    counts = [rng.integers(0, 3, n_par).astype(np.int32) for _ in range(3)]
    return centres, kernels.Tree(start, views, *counts), rng.random(n_par * 8) < 0.9


if kernels.HAVE_NUMBA:
    from numba import njit

    @njit(cache=True)
    def _scalar_voxels(centres, valid, tree, cc, packed):
        # The reference of ``kernels._voxel_range``: each voxel of each parent, view by
        # view with the scalar ``_voxel_test`` and ``_keep_smallest``, stopping once it
        # is final (<= -1: the kernel's test count).
        params, tables, k = packed.params, packed.tables, cc.k
        n_par = centres.shape[0]
        out = np.full(n_par * 8, np.float32(-1.0))
        kept = np.empty((1, k + 1), dtype=np.float32)
        offs = np.empty((8, 3))
        tests = 0
        for i in range(n_par):
            for ch in range(8):
                if not valid[i * 8 + ch]:
                    continue
                # Decided views of the parent: out -> -1, in -> +1 after clamping.
                filled = 0
                for q in range(k + 1):
                    kept[0, q] = np.inf
                for _ in range(min(tree.n_out[i], k + 1)):
                    kept[0, filled] = -1.0
                    filled += 1
                for _ in range(min(tree.n_in[i], k + 1 - filled)):
                    kept[0, filled] = 1.0
                    filled += 1
                mx = kept[0].max()
                seen = tree.n_out[i] + tree.n_in[i]
                for t in range(tree.start[i], tree.start[i + 1]):
                    if mx <= -1.0:
                        break
                    vr = kernels._row(params, tree.views[t])
                    kernels._child_offsets(vr, 0.5 * cc.voxel_size, offs)
                    x0, y0, z0 = kernels._cam(vr, centres[i, 0], centres[i, 1], centres[i, 2])
                    tests += 1
                    on, d = kernels._voxel_test(vr, tables, x0 + offs[ch, 0], y0 + offs[ch, 1],
                                                z0 + offs[ch, 2], vr.f * cc.voxel_size)
                    seen += on
                    if on and d < mx:
                        mx = kernels._keep_smallest(kept, 0, k, d)
                out[i * 8 + ch] = kernels._final_value(mx, seen, cc.min_seen)
        return out, tests


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the compiled kernels' test")
def test_fine_voxel_passes_equal_the_scalar_kernel(rig, mixed_sils):
    # Session 6: the fine voxels' kernel runs in passes (vectorised projection, table
    # reads, branch-free sorted insertion).  It must give the scalar kernel's values to
    # the bit and the same test count, also where the scalar one branches: voxels beyond
    # the tables (box bound), off the image, behind a camera, parents with views already
    # decided out / in, voxels beyond the grid.
    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    packed = kernels.pack(vf)
    n_par, s = 300, 8.0  # coarse voxels: fewer values clamped at +-1
    centres, tree, valid = _random_parents(vf, n_par, 6)
    beyond = behind = 0  # the inputs do reach the scalar kernel's branches
    for v in vf:
        front = centres @ v.camera.pose.R[2] + v.camera.pose.t[2] > 0
        behind += (~front).sum()
        u, w = v.camera.project(centres[front]).T
        on = (u >= -0.5) & (u <= v.width - 0.5) & (w >= -0.5) & (w <= v.height - 0.5)
        lu, lv = u - v.u0, w - v.v0
        beyond += (on & ~((lu >= -0.5) & (lu <= v.sd.shape[1] - 0.5) & (lv >= -0.5)
                          & (lv <= v.sd.shape[0] - 0.5))).sum()
    assert beyond > 0 and behind > 0
    for k, min_seen in ((3, 4), (0, 1), (3, 0)):
        cc = kernels.carve_consts(s, k, min_seen)
        new = np.full(n_par * 8, np.float32(-1.0))
        n_new = kernels._voxel_range(0, n_par, centres, valid, tree, cc, packed, new)
        old, n_old = _scalar_voxels(centres, valid, tree, cc, packed)
        assert np.array_equal(new.view(np.int32), old.view(np.int32)), k
        assert n_new == n_old
        assert len(np.unique(new)) > 20  # not all clamped: real field values compared


if kernels.HAVE_NUMBA:

    @njit(cache=True)
    def _scalar_cells(centres, valid, tree, cc, packed):
        # The reference of ``kernels._classify_range``: each child of each parent, view by
        # view with the scalar ``_cell_test``, stopping once removed (the kernel's counts).
        params, tables, half, k = packed.params, packed.tables, cc.half_size, cc.k
        n_par = centres.shape[0]
        rho = (half - 0.5 * cc.voxel_size) * np.sqrt(3.0)
        max_off = params.shape[0] - cc.min_seen
        decision = np.zeros(n_par * 8, np.int8)
        counts = np.zeros((n_par * 8, 4), np.int64)  # out, in, off, ambiguous
        amb = np.full(tree.views.shape[0] * 8, -1, np.int16)
        tests = 0
        offs = np.empty((8, 3))
        for i in range(n_par):
            a, b = tree.start[i], tree.start[i + 1]
            for ch in range(8):
                g = i * 8 + ch
                if not valid[g]:
                    continue
                n_out, n_in, n_off, na, n_on_amb = tree.n_out[i], tree.n_in[i], tree.n_off[i], 0, 0
                for t in range(a, b):
                    if n_out > k or n_off > max_off:
                        break
                    vr = kernels._row(params, tree.views[t])
                    kernels._child_offsets(vr, half, offs)
                    x0, y0, z0 = kernels._cam(vr, centres[i, 0], centres[i, 1], centres[i, 2])
                    tests += 1
                    res = kernels._cell_test(vr, tables, x0 + offs[ch, 0], y0 + offs[ch, 1],
                                             z0 + offs[ch, 2], rho, cc)
                    if res == kernels.CELL_OFF:
                        n_off += 1
                    elif res == kernels.CELL_OUT:
                        n_out += 1
                    elif res == kernels.CELL_IN:
                        n_in += 1
                    else:
                        amb[a * 8 + ch * (b - a) + na] = tree.views[t]
                        na += 1
                        n_on_amb += res == kernels.CELL_AMB
                counts[g] = n_out, n_in, n_off, na
                if n_out > k or n_off > max_off:
                    decision[g] = 0
                elif n_out + na <= k and n_out + n_in + n_on_amb >= cc.min_seen:
                    decision[g] = 1
                else:
                    decision[g] = 2
        return decision, counts, amb, tests


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="the compiled kernels' test")
def test_cell_passes_equal_the_scalar_cell_test(rig, mixed_sils):
    # Session 6: sibling cells are classified in passes.  Each child's decision, counts
    # and list of ambiguous views must be those of the scalar ``_cell_test`` applied
    # view by view (child by child here), also beyond the tables (nearest pixel: box
    # bound), off the image, behind a camera and for the bilinear small footprints.
    cal, _ = rig
    vf = prepare_views(list(mixed_sils), cal)
    packed = kernels.pack(vf)
    n_par = 400
    centres, tree, valid = _random_parents(vf, n_par, 7)
    amb_start = kernels._offsets(np.repeat(np.diff(tree.start), 8))
    for half, s, k, min_seen in ((1.0, 1.0, 3, 4), (2.0, 1.0, 3, 4), (4.0, 2.0, 0, 0)):
        cc = kernels.carve_consts(s, k, min_seen, half, 1.5, 1.02, 3.48)
        out = kernels.cell_counts(n_par * 8, amb_start)
        tests = kernels._classify_range(0, n_par, centres, valid, tree, cc, packed, out)
        ref, counts, ref_amb, ref_tests = _scalar_cells(centres, valid, tree, cc, packed)
        assert np.array_equal(out.decision, ref) and tests == ref_tests, half
        kept = out.decision > 0  # removed cells' counts are never read
        mine = np.stack([out.n_out, out.n_in, out.n_off, out.n_amb], 1)
        assert np.array_equal(mine[kept], counts[kept]), half
        split = np.flatnonzero(out.decision == 2)  # only split cells' lists are read
        for g in split:
            na = counts[g, 3]
            assert np.array_equal(out.amb[amb_start[g]:amb_start[g] + na],
                                  ref_amb[amb_start[g]:amb_start[g] + na]), g
        assert len(np.unique(ref)) == 3 and (counts[split, 3] > 0).any()

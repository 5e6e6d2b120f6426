"""Mesher (pot removal, marching cubes), numba kernels, bad input, registration."""

from __future__ import annotations

import numpy as np
import pytest
from hull_phantoms import Box, Cylinder, Sphere, render, ring_calibration, views
from plantscan_hull import kernels
from plantscan_hull.bbox import BoundingBoxError
from plantscan_hull.carve import Grid, carve_dense, carve_octree
from plantscan_hull.meshing import (
    inside_indices,
    marching_cubes,
    signed_volume,
    topology_report,
)
from plantscan_hull.pot import TaperedCylinder, fit_pot
from plantscan_hull.stages import DenseHull, MarchingCubesMesher, OctreeHull
from plantscan_hull.views import prepare_views

from plantscan_core.data import Silhouette, Silhouettes, Volume
from plantscan_core.errors import DataError

ELEVATIONS = (0.0, 35.0)
POT = Cylinder(-60.0, -20.0, 22.0, 28.0)  # tapered pot, wider at the top
PLANT = [Sphere((0.0, 0.0, 5.0), 12.0), Box((0.0, 0.0, -8.0), np.eye(3), (2.0, 2.0, 12.0)),
         # a thin leaf drooping over the rim, outside the pot
         Box((34.0, 0.0, -22.0), np.eye(3), (3.0, 8.0, 6.0))]


@pytest.fixture(scope="module")
def rig():
    return ring_calibration(elevations=ELEVATIONS), views(12, ELEVATIONS)


@pytest.fixture(scope="module")
def potted(rig):
    cal, vl = rig
    return render(cal, vl, [POT, *PLANT])


@pytest.fixture(scope="module")
def potted_volume(rig, potted):
    cal, _ = rig
    return OctreeHull(OctreeHull.Params(resolution=72, floor_z_mm=None)).reconstruct(potted, cal)


def test_mesh_is_watertight_and_manifold(potted_volume):
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="none"))
    mesh = mesher.mesh(potted_volume)
    rep = topology_report(mesh)
    assert rep["watertight"] and rep["manifold"], rep
    assert signed_volume(mesh) > 0  # faces wind counter-clockwise seen from outside


def test_topology_report_detects_a_hole():
    field = -np.ones((12, 12, 12), np.float32)
    field[3:9, 3:9, 3:9] = 1.0
    mesh = marching_cubes(field, np.zeros(3), 1.0)
    assert topology_report(mesh)["watertight"]
    holed = type(mesh)(mesh.vertices, mesh.faces[1:])
    rep = topology_report(holed)
    assert not rep["watertight"] and rep["boundary_edges"] == 3


@pytest.mark.parametrize("seed", range(6))
def test_fields_with_ties_and_near_zero_values_mesh_watertight(seed):
    # The carved field is full of exact +-1 (decided cells, clamps) and of values within
    # float noise of 0 (the batch benchmark's 2-6 non-manifold edges at hull 256 came from
    # these): tied face tests in scikit-image's Lewiner tables give duplicate faces, and
    # vertices on grid points coincide.  Random fields of such values are the worst case.
    rng = np.random.default_rng(seed)
    values = np.array([-1.0, -1e-7, 0.0, 1e-7, 0.15, 1.0, -0.3], np.float32)
    field = rng.choice(values, size=(14, 13, 12)).astype(np.float32)
    rep = topology_report(marching_cubes(field, np.zeros(3), 1.0))
    assert rep["watertight"] and rep["manifold"], rep


def test_blocked_marching_cubes_equals_one_block(potted_volume):
    # Blocks only where the surface is: same surface as one call on the whole grid.
    field = potted_volume.field
    one = marching_cubes(field, potted_volume.origin, potted_volume.voxel_size, block=1024)
    small = marching_cubes(field, potted_volume.origin, potted_volume.voxel_size, block=8)
    assert len(small.faces) == len(one.faces) and len(small.vertices) == len(one.vertices)
    from scipy.spatial import cKDTree

    # scikit-image places vertices in float32 block coordinates: equal to ~1e-6 voxel.
    d, _ = cKDTree(one.vertices).query(small.vertices)
    assert d.max() < 1e-4 * potted_volume.voxel_size
    assert topology_report(small)["watertight"]
    assert signed_volume(small) == pytest.approx(signed_volume(one), rel=1e-6)


def _face_set(faces: np.ndarray) -> set:
    return {tuple(np.roll(f, -int(np.argmin(f)))) for f in faces}


@pytest.mark.parametrize("seam", [7, 8, 15])
def test_marching_cubes_finds_surface_on_block_seams(seam):
    # Only blocks holding an inside sample are meshed; a block's samples reach one voxel
    # back into the previous chunk (its cubes' low corners), so a speck sitting exactly
    # on that seam (voxel 7 or 15 with blocks of 8) must still be found by both blocks.
    # The unblocked call is the reference.
    field = -np.ones((20, 17, 19), np.float32)
    field[seam, 9, 4] = 0.7
    field[3:6, seam:seam + 2, 16:18] = 0.4
    one = marching_cubes(field, np.zeros(3), 1.0, block=1024)
    small = marching_cubes(field, np.zeros(3), 1.0, block=8)
    for centre in ([seam, 9, 4], [4, seam + 0.5, 16.5]):  # both specks are meshed
        assert np.linalg.norm(one.vertices - centre, axis=1).min() < 1.5
    # Same triangles (block order differs; each rolled to start at its lowest vertex,
    # keeping its orientation).
    assert _face_set(small.faces) == _face_set(one.faces)
    assert np.abs(small.vertices - one.vertices).max() < 1e-5  # float32 block offsets
    assert topology_report(small)["watertight"]


def _edge_counts_reference(faces: np.ndarray) -> tuple[int, int, int]:
    """Boundary, non-manifold and misoriented edge counts by ``np.unique`` (plain)."""
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    directed, dcount = np.unique(np.stack([a, b], 1), axis=0, return_counts=True)
    undirected, ucount = np.unique(np.sort(np.stack([a, b], 1), axis=1), axis=0,
                                   return_counts=True)
    return int(np.sum(ucount == 1)), int(np.sum(ucount > 2)), int(np.sum(dcount > 1))


def test_topology_report_counts_edges_like_a_plain_count():
    field = -np.ones((12, 12, 12), np.float32)
    field[3:9, 3:9, 3:9] = 1.0
    field[4:6, 4:6, 10] = 0.5
    mesh = marching_cubes(field, np.zeros(3), 1.0)
    rng = np.random.default_rng(3)
    f = mesh.faces
    cases = [f, f[rng.permutation(len(f))[:-7]],  # holes
             np.concatenate([f, f[:5], f[5:9, ::-1]]),  # doubled faces, flipped copies
             rng.integers(0, 30, (200, 3))]  # garbage
    for faces in cases:
        rep = topology_report(type(mesh)(mesh.vertices, faces))
        assert (rep["boundary_edges"], rep["nonmanifold_edges"],
                rep["misoriented_edges"]) == _edge_counts_reference(faces)
    assert topology_report(type(mesh)(mesh.vertices, cases[2]))["nonmanifold_edges"] > 0


def _thin_slab_field(half_x: float, half_y: float, half_t: float) -> np.ndarray:
    """Field (voxels, clamped) of a flat slab centred in a 40 x 30 x 9 grid of 1 mm voxels:
    inside, the distance to its nearest face; outside, minus the distance to the slab."""
    idx = np.indices((40, 30, 9)).astype(float)
    x, y, z = idx[0] - 19.5, idx[1] - 14.5, idx[2] - 4
    out = np.stack([np.abs(x) - half_x, np.abs(y) - half_y, np.abs(z) - half_t])
    inside = -out.max(axis=0)
    outside = -np.sqrt((np.clip(out, 0, None) ** 2).sum(axis=0))
    return np.clip(np.where(inside > 0, inside, outside), -1, 1).astype(np.float32)


@pytest.mark.parametrize("half_x, plain_short", [(10.0, 2 * (0.5 - 0.25 / 0.75)),
                                                  (10.3, 2 * (0.8 - 0.25 / 0.45)),
                                                  (9.8, 2 * (0.3 - 0.25 / 0.95))])
def test_thin_rims_put_a_thin_slabs_outline_in_place(half_x, plain_short):
    """A 0.5 mm leaf slab is one voxel thick: its inside values (0.25) are the half
    thickness, so linear interpolation pulls the outline in (a third of a voxel per side
    at a mid-voxel rim); ``thin_rims`` puts it where the outside field says, within 0.01
    voxel (LEVEL_GAP and float32), keeping the mesh watertight."""
    field = _thin_slab_field(half_x, 8.0, 0.25)
    plain = marching_cubes(field, np.zeros(3), 1.0)
    snapped = marching_cubes(field, np.zeros(3), 1.0, thin_rims=True)
    true_extent = 2 * half_x
    # Voxel centres sit at half-integers: the linear rim is short by the computed amount.
    assert np.ptp(plain.vertices[:, 0]) == pytest.approx(true_extent - plain_short, abs=0.01)
    assert np.ptp(snapped.vertices[:, 0]) == pytest.approx(true_extent, abs=0.01)
    assert np.ptp(snapped.vertices[:, 1]) == pytest.approx(16.0, abs=0.01)
    # Across the slab nothing moves: still 0.5 mm thick.
    assert np.ptp(snapped.vertices[:, 2]) == pytest.approx(0.5, abs=0.01)
    assert topology_report(snapped)["watertight"]
    assert len(snapped.faces) == len(plain.faces)


def _mesh_components(mesh) -> int:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.faces
    rows, cols = np.concatenate([f[:, 0], f[:, 1]]), np.concatenate([f[:, 1], f[:, 2]])
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def test_a_sheet_stepping_diagonally_stays_one_surface():
    """A one-voxel leaf sheet whose voxels step diagonally (sharing only an edge) must mesh
    as one closed surface, not a piece per step: the leaf stages cannot join pieces that
    the mesh cut apart (wheat blades fell apart into thousands of pieces)."""
    field = -np.ones((12, 12, 5), np.float32)
    for i in range(1, 11):  # a staircase in x-y, one voxel thick, three voxels tall
        field[i, i, 1:4] = 0.3
    mesh = marching_cubes(field, np.zeros(3), 1.0)
    assert _mesh_components(mesh) == 1
    assert topology_report(mesh)["watertight"] and topology_report(mesh)["manifold"]


def test_thin_rims_for_measuring_keep_the_mesh_and_carry_the_rims(tmp_path):
    """``thin_rims: measure``: the segmenter gets the interpolated mesh (thin rims move
    vertices, and on grass blades that broke blades into pieces), the measurer the rims put
    out; both on the same faces, and both kept by the run cache's mesh file."""
    from plantscan_core.data import LabelledMesh, Mesh

    field = _thin_slab_field(10.0, 8.0, 0.25)
    plain = marching_cubes(field, np.zeros(3), 1.0)
    snapped = marching_cubes(field, np.zeros(3), 1.0, thin_rims=True)
    both = marching_cubes(field, np.zeros(3), 1.0, thin_rims="measure")
    np.testing.assert_array_equal(both.vertices, plain.vertices)
    np.testing.assert_array_equal(both.faces, plain.faces)
    np.testing.assert_array_equal(both.rim_vertices, snapped.vertices)
    np.testing.assert_array_equal(both.measured().vertices, snapped.vertices)
    assert plain.rim_vertices is None and plain.measured() is plain
    both.save(tmp_path / "mesh.npz")
    np.testing.assert_array_equal(Mesh.load(tmp_path / "mesh.npz").rim_vertices,
                                  snapped.vertices)
    labelled = LabelledMesh(both, np.zeros(len(both.faces)), {0: "leaf"})
    labelled.save(tmp_path / "labelled.npz")
    np.testing.assert_array_equal(LabelledMesh.load(tmp_path / "labelled.npz").mesh.rim_vertices,
                                  snapped.vertices)
    # the pot's rim, where the plant's height starts, is kept by both files too
    both.base_z_mm = 3.25
    both.save(tmp_path / "mesh.npz")
    assert Mesh.load(tmp_path / "mesh.npz").base_z_mm == 3.25
    assert both.measured().base_z_mm == 3.25
    LabelledMesh(both, np.zeros(len(both.faces)), {0: "leaf"}).save(tmp_path / "labelled.npz")
    assert LabelledMesh.load(tmp_path / "labelled.npz").mesh.base_z_mm == 3.25
    with pytest.raises(ValueError, match="rim_vertices has 3 rows"):
        Mesh(plain.vertices, plain.faces, plain.vertices[:3])


def test_thin_rims_for_measuring_refuse_smoothing():
    with pytest.raises(ValueError, match="smooth_iterations"):
        MarchingCubesMesher.Params(thin_rims="measure", smooth_iterations=2)


def test_thin_rims_leave_thick_parts_alone():
    """A slab 4 voxels thick has exact distances inside: no vertex moves."""
    field = _thin_slab_field(10.5, 8.5, 2.0)
    plain = marching_cubes(field, np.zeros(3), 1.0)
    snapped = marching_cubes(field, np.zeros(3), 1.0, thin_rims=True)
    np.testing.assert_array_equal(plain.vertices, snapped.vertices)


def test_small_components_are_dropped():
    from plantscan_hull.meshing import drop_small_components

    field = -np.ones((20, 20, 20), np.float32)
    field[2:8, 2:8, 2:8] = 1.0  # 216 voxels: kept
    field[12, 12, 12] = field[13, 13, 13] = 0.5  # 2 voxels, diagonal (26-connected)
    field[17, 2, 2] = field[19, 2, 2] = 0.2  # two single voxels
    out, n = drop_small_components(field, 8)
    assert n == 3
    assert (out > 0).sum() == 216 and (out[2:8, 2:8, 2:8] > 0).all()
    field[12:15, 12:15, 12:15] = 1.0  # 27 voxels now: kept
    out, n = drop_small_components(field, 8)
    assert n == 2 and (out[12:15, 12:15, 12:15] > 0).all()


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")
@pytest.mark.parametrize("slab", [1, 30, 1 << 23])
def test_inside_indices_slab_by_slab_equal_flatnonzero(slab):
    field = np.random.default_rng(4).uniform(-1, 1, (9, 5, 6)).astype(np.float32)
    assert np.array_equal(inside_indices(field, slab), np.flatnonzero(field > 0))


def test_compiled_component_sizes_match_scipy():
    from plantscan_hull.meshing import _component_sizes_scipy
    from scipy import ndimage

    occ = np.random.default_rng(3).random((23, 17, 19)) < 0.3
    idx = np.flatnonzero(occ)
    labels, _ = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    truth = np.bincount(labels.ravel())[labels.ravel()[idx]]
    assert np.array_equal(kernels.component_sizes(idx, occ.shape), truth)
    assert np.array_equal(_component_sizes_scipy(idx, occ.shape), truth)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")
def test_nonmanifold_vertex_check_matches_open3d():
    # Two cubes touching at one corner: a vertex whose faces form two fans.
    field = -np.ones((8, 8, 8), np.float32)
    field[1:4, 1:4, 1:4] = 1.0
    field[4:7, 4:7, 4:7] = 1.0
    field[3, 3, 3] = field[4, 4, 4] = 0.1  # a sub-voxel pinch between the cubes
    for mesh in (marching_cubes(field, np.zeros(3), 1.0),
                 marching_cubes(field[:4, :4, :4], np.zeros(3), 1.0)):
        o3 = len(np.asarray(mesh.to_open3d().get_non_manifold_vertices()))
        assert kernels.nonmanifold_vertices(mesh.faces, len(mesh.vertices)) == o3
    # Glue two closed meshes at one vertex: that vertex is non-manifold.
    a = marching_cubes(field[:4, :4, :4], np.zeros(3), 1.0)
    b_faces = a.faces + len(a.vertices)
    b_faces[b_faces == len(a.vertices)] = 0
    glued_faces = np.concatenate([a.faces, b_faces])
    glued = type(a)(np.concatenate([a.vertices, a.vertices + 10]), glued_faces)
    assert kernels.nonmanifold_vertices(glued.faces, len(glued.vertices)) == 1
    assert len(np.asarray(glued.to_open3d().get_non_manifold_vertices())) == 1


def test_auto_pot_fit_and_removal(potted_volume):
    cyl = fit_pot(potted_volume)
    assert len(cyl) == 1
    c = cyl[0]
    s = potted_volume.voxel_size
    # Rim height and radius from the hull: within 1.5 voxels (the rim is known to a voxel,
    # and the hull of a circle from 12 azimuths is a polygon ~1-3 % larger).
    assert c.z_top_mm == pytest.approx(POT.z1, abs=1.5 * s)
    assert c.r_top_mm == pytest.approx(POT.r1, abs=1.5 * s + 0.04 * POT.r1)
    assert c.r_bottom_mm == pytest.approx(POT.r0, abs=1.5 * s + 0.04 * POT.r0)
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="auto"))
    mesh = mesher.mesh(potted_volume)
    assert not mesher.report.warnings_about(code="no-pot")
    # the plant's base, for its height, is the rim (the leaf over the rim droops below it)
    assert mesh.base_z_mm == pytest.approx(POT.z1, abs=1.5 * s)
    assert mesh.vertices[:, 2].min() < mesh.base_z_mm - 5.0
    assert topology_report(mesh)["watertight"]
    v = mesh.vertices
    rho = np.hypot(v[:, 0], v[:, 1])
    # No pot left: no vertex within the pot wall's region below its rim.
    in_pot = (v[:, 2] < POT.z1 - s) & (v[:, 2] > POT.z0 - s) & (rho < POT.r1 + 0.5 * s) & (
        rho > 5.0)
    assert not in_pot.any()
    # The plant stays: the sphere and the leaf over the rim are still meshed.
    sphere_top = v[:, 2].max()
    assert sphere_top == pytest.approx(17.0, abs=1.5 * s)
    leaf = (v[:, 0] > 30) & (v[:, 2] < -10)
    assert leaf.sum() > 20


def test_auto_pot_finding_no_pot_says_so():
    # A hull with no pot at its bottom (a slab 30 x 10 x 10 mm: no slice is disc-like):
    # nothing is removed, and the user is told that a pot, if there is one, stays in the mesh
    # (its height, perhaps a leaf), and how to give it or to say there is none.
    xs = np.arange(-20.0, 21.0)
    x, y, z = np.meshgrid(xs, xs, xs, indexing="ij")
    inside = np.minimum(np.minimum(15.0 - np.abs(x), 5.0 - np.abs(y)), 5.0 - np.abs(z))
    slab = Volume(np.clip(inside, -1, 1).astype(np.float32), np.full(3, -20.0), 1.0)
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="auto"))
    mesher.mesh(slab)
    (w,) = mesher.report.warnings_about(code="no-pot")
    assert "pot: none" in w.message and "height" in w.message
    quiet = MarchingCubesMesher(MarchingCubesMesher.Params(pot="none"))
    assert quiet.mesh(slab).base_z_mm is None  # no pot removed: no base, height = extent
    assert not quiet.report.warnings


def test_auto_pot_fit_survives_speckled_silhouettes(potted_volume):
    # A pot in the leaves' shade read as shadow in some views: scattered holes inside the pot's
    # hull (measured on a 5-tilt 18 MP scan: 20-30 % of the voxels of a slice). The fit on the
    # slices' outlines must still find the rim and radius (same tolerances as above).
    field = potted_volume.field.copy()
    s = potted_volume.voxel_size
    idx = np.stack(np.nonzero(field > 0), axis=1)
    p = potted_volume.origin + idx * s
    rho = np.hypot(p[:, 0], p[:, 1])
    interior = (p[:, 2] < POT.z1 - 2 * s) & (rho < POT.r0 - 2 * s)
    rng = np.random.default_rng(5)
    holes = idx[interior & (rng.random(len(idx)) < 0.3)]
    field[tuple(holes.T)] = -1.0
    speckled = Volume(field, potted_volume.origin, s)
    cyl = fit_pot(speckled)
    assert len(cyl) == 1, cyl
    c = cyl[0]
    assert c.z_top_mm == pytest.approx(POT.z1, abs=1.5 * s)
    assert c.r_top_mm == pytest.approx(POT.r1, abs=1.5 * s + 0.04 * POT.r1)


def test_mesher_leaves_the_volume_as_it_was(potted_volume):
    # Pot and specks are cut in the volume's own field (no copy of the grid) and put
    # back afterwards: the caller's volume is unchanged, and the mesh is the one the
    # copying path (taken for a read-only field) gives.
    field = potted_volume.field.copy()
    field[0, 0, 0] = 0.5  # a speck in a corner: dropped
    before = field.copy()
    pot = [TaperedCylinder(z_bottom_mm=POT.z0, z_top_mm=POT.z1, r_bottom_mm=POT.r0,
                           r_top_mm=POT.r1)]
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot=pot))
    mesh = mesher.mesh(Volume(field, potted_volume.origin, potted_volume.voxel_size))
    assert np.array_equal(field, before)
    assert mesher.report.counts["pot_voxels_removed"] > 0
    assert mesher.report.counts["components_dropped"] >= 1
    before.flags.writeable = False
    copied = mesher.mesh(Volume(before, potted_volume.origin, potted_volume.voxel_size))
    assert np.array_equal(mesh.vertices, copied.vertices)
    assert np.array_equal(mesh.faces, copied.faces)


@pytest.mark.parametrize("pot", ["auto", "given"])
def test_mesher_on_blocks_equals_the_dense_field_and_leaves_them(potted_volume, pot):
    # The octree hull's volume holds its field in blocks; pot removal, speck removal and
    # marching cubes read and edit them block by block.  Same mesh to the bit as on the
    # dense field, and the blocks are as they were afterwards.
    from plantscan_core.data import BlockField

    field = potted_volume.field.copy()
    # A speck inside the highest wholly-outside block (an implicit block before,
    # given a row by the cut; high, so the pot fit's lowest slices do not see it): dropped.
    empty = np.argwhere(BlockField.from_dense(field, 32).index == BlockField.OUTSIDE)
    assert len(empty), "the phantom has no wholly-outside block"
    corner = empty[np.argmax(empty[:, 2])] * 32
    field[tuple(np.minimum(corner + 8, np.array(field.shape) - 1))] = 0.5
    blocks = BlockField.from_dense(field, 32)
    index, values = blocks.index.copy(), blocks.values.copy()
    cyl = pot if pot == "auto" else [TaperedCylinder(z_bottom_mm=POT.z0, z_top_mm=POT.z1,
                                                     r_bottom_mm=POT.r0, r_top_mm=POT.r1)]
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot=cyl))
    on_blocks = mesher.mesh(Volume(blocks, potted_volume.origin, potted_volume.voxel_size))
    reference = MarchingCubesMesher(MarchingCubesMesher.Params(pot=cyl))  # counts add up
    dense = reference.mesh(Volume(field, potted_volume.origin, potted_volume.voxel_size))
    counts = mesher.report.counts
    assert counts == reference.report.counts and counts["pot_voxels_removed"] > 0
    assert counts["components_dropped"] >= 1
    assert np.array_equal(on_blocks.vertices, dense.vertices)
    assert np.array_equal(on_blocks.faces, dense.faces)
    assert np.array_equal(blocks.index, index) and np.array_equal(blocks.values, values)


def test_octree_hull_volume_is_held_in_blocks(potted_volume, rig, potted):
    # The reconstructor hands on the field in blocks (never the dense grid); its dense
    # view equals the dense reconstructor's field.
    cal, _ = rig
    assert potted_volume.blocks is not None
    dense = DenseHull(DenseHull.Params(resolution=72, floor_z_mm=None)).reconstruct(potted, cal)
    assert dense.blocks is None
    assert np.array_equal(potted_volume.field, dense.field)


def test_given_pot_is_removed(potted_volume):
    pot = [TaperedCylinder(z_bottom_mm=POT.z0, z_top_mm=POT.z1, r_bottom_mm=POT.r0,
                           r_top_mm=POT.r1)]
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot=pot))
    mesh = mesher.mesh(potted_volume)
    v = mesh.vertices
    rho = np.hypot(v[:, 0], v[:, 1])
    assert not ((v[:, 2] < POT.z1 - 2) & (v[:, 2] > POT.z0) & (rho < POT.r0 - 2)
                & (rho > 5)).any()


def test_the_cone_no_view_carves_over_the_pot_is_removed():
    # Cameras 10 and 45 deg above the aim point, 400 mm away: the lower ones look down on the
    # rim, so every view sees a point over the opening lower than
    # r_rim (h_cam - z_rim) / (d_cam + r_rim) = 7.5 mm against the pot (the masks are pot +
    # plant): the carved hull keeps that cone (the virtual scanner's rigs: 13 mm over the
    # dicot's pot, 17 mm over the branched family's).  The mesher cuts it; the leaf over the
    # rim and the stem above the cone stay.
    elevations = (10.0, 45.0)
    pot = Cylinder(-70.0, -30.0, 26.0, 32.0)
    stem = Box((0.0, 0.0, -10.0), np.eye(3), (2.0, 2.0, 20.0))  # from the soil to z = 10
    leaf = Box((26.0, 0.0, -16.0), np.eye(3), (24.0, 8.0, 1.2))  # 14 mm over the rim
    cal = ring_calibration(elevations=elevations)
    sils = render(cal, views(12, elevations), [pot, stem, leaf])
    volume = OctreeHull(OctreeHull.Params(resolution=96, floor_z_mm=None)).reconstruct(sils, cal)
    s = volume.voxel_size
    e = np.radians(elevations[0])
    height = pot.r1 * (400.0 * np.sin(e) - pot.z1) / (400.0 * np.cos(e) + pot.r1)

    def inside_cone(v):  # the geometric cone, less a fifth of its radius (its outline's
        # voxels), outside the stem's column (2.8 mm to its corners, plus 2 voxels)
        h = v[:, 2] - pot.z1
        rho = np.hypot(v[:, 0], v[:, 1])
        return (h > 0) & (rho < 0.8 * pot.r1 * (1.0 - h / height)) & (rho > 2.9 + 2 * s)

    mesher = MarchingCubesMesher(MarchingCubesMesher.Params())
    v = mesher.mesh(volume).vertices
    cap = mesher.report.figures["cap"]
    # Apex from the hull's own slices: the geometric height, plus up to 3 voxels (the fitted
    # rim is up to 1.5 voxels high, and with k = 3 a point needs 4 of the 12 low views to
    # see it outside: the hull's cone is a little taller than the geometric one).
    assert pot.z1 + height - s < cap["z_top_mm"] < pot.z1 + height + 3 * s, (cap, height)
    assert not inside_cone(v).any()
    on_leaf = (v[:, 2] > -18.0) & (v[:, 2] < -14.0) & (v[:, 0] > 10.0)
    assert v[on_leaf, 0].max() == pytest.approx(50.0, abs=1.5 * s)  # the leaf's tip stays
    stem_above = (np.hypot(v[:, 0], v[:, 1]) < 4.0) & (v[:, 2] > -12.0) & (v[:, 2] < 8.0)
    assert stem_above.sum() > 20
    # The stem's column is kept through the cap (the plant's height is the mesh's extent):
    # the mesh still reaches down to the pot cut (rim + margin + a voxel, the fitted rim is
    # up to 1.5 voxels high).
    margin = mesher.report.figures["pot_margin_mm"]
    assert v[:, 2].min() < pot.z1 + margin + 2.5 * s
    # Without the cap the cone is meshed (what the virtual experiment measured as a leaf).
    plain = MarchingCubesMesher(MarchingCubesMesher.Params(pot_cap=False)).mesh(volume)
    assert inside_cone(plain.vertices).sum() > 100


def test_no_pot_found_on_a_plant_without_pot(rig):
    cal, vl = rig
    sils = render(cal, vl, [Sphere((0.0, 0.0, 0.0), 5.0),
                            Box((0.0, 0.0, 0.0), np.eye(3), (30.0, 6.0, 0.5))])
    vol = OctreeHull(OctreeHull.Params(resolution=48, floor_z_mm=None)).reconstruct(sils, cal)
    assert fit_pot(vol) == []


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")
@pytest.mark.parametrize("k", [0, 3])
def test_numba_matches_numpy_and_dense(rig, potted, k):
    cal, _ = rig
    vf = prepare_views(list(potted), cal)
    grid = Grid.from_box((-40, -40, -70), (45, 40, 25), 40)
    ref, _ = carve_dense(vf, grid, k, backend="numpy")
    fast_dense, _ = carve_dense(vf, grid, k, backend="numba")
    fast_oct, st = carve_octree(vf, grid, k, top_cell=16, backend="numba")
    assert st.backend == "numba"
    # Same arithmetic, different summation order in the projection: float32 rounding only.
    assert np.abs(fast_dense - ref).max() < 1e-4
    assert np.array_equal(fast_oct, fast_dense)
    differs = (ref > 0) != (fast_dense > 0)
    assert np.all(np.abs(ref[differs]) < 1e-4)


def test_dense_and_octree_stages_agree(rig, potted):
    cal, _ = rig
    a = OctreeHull(OctreeHull.Params(resolution=40, bbox=[-40, -40, -70, 45, 40, 25],
                                     floor_z_mm=None))
    b = DenseHull(DenseHull.Params(resolution=40, bbox=[-40, -40, -70, 45, 40, 25],
                                  floor_z_mm=None))
    va, vb = a.reconstruct(potted, cal), b.reconstruct(potted, cal)
    assert np.array_equal(va.field > 0, vb.field > 0)
    assert a.report.counts["voxel_view_tests"] < b.report.counts["voxel_view_tests"]


# --------------------------------------------------------------------------- bad input
def test_mask_size_mismatch_names_the_view(rig, potted):
    cal, _ = rig
    bad = list(potted)
    bad[5] = Silhouette(bad[5].view, bad[5].mask[:, :-10])
    with pytest.raises(DataError, match=r"view 5 .*do not match the calibration"):
        OctreeHull().reconstruct(Silhouettes(bad), cal)


@pytest.mark.parametrize("fill, word", [(False, "empty"), (True, "all foreground")])
def test_empty_or_full_silhouette_names_the_view(rig, potted, fill, word):
    cal, _ = rig
    bad = list(potted)
    bad[3] = Silhouette(bad[3].view, np.full_like(bad[3].mask, fill))
    with pytest.raises(DataError, match=rf"view 3 .*{word}"):
        OctreeHull().reconstruct(Silhouettes(bad), cal)


def test_clipping_box_is_reported(rig, potted):
    cal, _ = rig
    hull = OctreeHull(OctreeHull.Params(resolution=32, bbox=[-40, -40, -40, 40, 40, 10],
                                         floor_z_mm=None))
    with pytest.raises(BoundingBoxError, match=r"z-.*reconstruct.params.bbox.*clips the plant"):
        hull.reconstruct(potted, cal)


def test_too_few_views_for_k(rig, potted):
    cal, _ = rig
    with pytest.raises(DataError, match="lower reconstruct.params.k"):
        OctreeHull(OctreeHull.Params(k=3)).reconstruct(Silhouettes(list(potted)[:3]), cal)


def test_auto_k_grows_with_the_views(rig, potted):
    """k "auto": 2.5 % of the views, at least 3 (the 72-view protocol keeps the seed's 3,
    360 views carve with 9); the hull records the k it used."""
    from plantscan_hull.stages import resolve_k

    assert [resolve_k("auto", n) for n in (4, 72, 360)] == [3, 3, 9]
    assert resolve_k(5, 360) == 5
    cal, _ = rig
    hull = OctreeHull(OctreeHull.Params(resolution=32, floor_z_mm=None))
    hull.reconstruct(potted, cal)
    assert hull.report.counts["k"] == resolve_k("auto", len(potted)) == 3


def test_a_frame_whose_floor_is_not_the_plate_is_reported(rig, potted):
    # this rig's pot stands 20-60 mm below z = 0 (like a calibration imported from a rig
    # whose z = 0 is the camera's height): the default floor (a plantscan plate at z = 0)
    # would cut it off silently; the error names the parameter that fixes it
    cal, _ = rig
    with pytest.raises(BoundingBoxError, match=r"z = -\d+ mm.*reconstruct.params.floor_z_mm"):
        OctreeHull(OctreeHull.Params(resolution=32)).reconstruct(potted, cal)


def test_bad_params_are_rejected():
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        OctreeHull.Params(top_cell=24)
    with pytest.raises(ValidationError):
        OctreeHull.Params(k=-1)
    with pytest.raises(ValidationError):
        OctreeHull.Params(bbox=[0, 0, 0, -1, 1, 1])
    with pytest.raises(ValidationError):
        MarchingCubesMesher.Params(pot="guess")


def test_empty_volume_is_an_error():
    vol = Volume(-np.ones((8, 8, 8), np.float32), np.zeros(3), 1.0)
    with pytest.raises(DataError, match="nothing left to mesh"):
        MarchingCubesMesher(MarchingCubesMesher.Params(pot="none")).mesh(vol)


def test_plugin_registers_its_stages():
    from plantscan_hull import plugin

    from plantscan_core.plugins import new_manager

    manager = new_manager()
    manager.register(plugin, name="hull")
    try:
        assert "octree-hull" in manager.registry.names("reconstructor")
        assert "dense-hull" in manager.registry.names("reconstructor")
        hull = manager.build("reconstructor", "octree-hull", {"resolution": 64, "k": 2})
        assert hull.params.resolution == 64
        assert manager.build("mesher", "marching-cubes", {"pot": "none"}).params.pot == "none"
    finally:
        manager.unregister(plugin)

"""Analytic leaf phantoms meshed the way a visual hull is meshed.

A visual hull leaf is a thin closed slab a few voxels thick with rounded
edges.  These phantoms are built the same way: an inside/outside field of
the leaf is sampled on a voxel grid (optionally binarised and blurred like a
carved occupancy grid, optionally with noise) and meshed with
``skimage.measure.marching_cubes``.  Their flat-leaf truth is analytic: an
ellipse of semi-axes ``a``, ``b`` has area ``pi a b``, length ``2 a``, width
``2 b`` and Ramanujan's perimeter.

Every field is a callable ``field(points) -> values`` on ``(..., 3)`` points
in mm, > 0 inside.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from plantscan_core.data import Mesh, rotation_about_axis

Field = Callable[[np.ndarray], np.ndarray]


def ellipse_perimeter(a: float, b: float) -> float:
    """Ramanujan's second approximation (relative error < 1e-9 for leaf shapes), mm."""
    h = ((a - b) / (a + b)) ** 2
    return math.pi * (a + b) * (1.0 + 3.0 * h / (10.0 + math.sqrt(4.0 - 3.0 * h)))


@dataclass(frozen=True)
class EllipseLeaf:
    """Flat-leaf truth of an elliptical leaf (semi-axes ``a`` along the midrib, ``b`` across)."""

    a: float
    b: float

    @property
    def length_mm(self) -> float:
        return 2.0 * self.a

    @property
    def width_mm(self) -> float:
        return 2.0 * self.b

    @property
    def area_mm2(self) -> float:
        return math.pi * self.a * self.b

    @property
    def perimeter_mm(self) -> float:
        return ellipse_perimeter(self.a, self.b)


def ellipse_slab_field(a: float, b: float, thickness: float) -> Field:
    """Rounded slab whose rim crest is the ellipse ``(x/a)^2 + (y/b)^2 = 1`` in z = 0.

    The flat inset ellipse (semi-axes ``a - t/2``, ``b - t/2``) is offset by
    ``t/2`` in 3D, so the slab is ``t`` thick with semicircular edges and its
    outline is (to first order in ``t/a``) the ellipse itself, as the
    silhouettes of a thin leaf bound a visual hull.
    """
    r = thickness / 2.0
    ai, bi = a - r, b - r

    def field(p: np.ndarray) -> np.ndarray:
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        f = (x / ai) ** 2 + (y / bi) ** 2 - 1.0
        grad = 2.0 * np.sqrt((x / ai**2) ** 2 + (y / bi**2) ** 2) + 1e-12
        d2 = np.maximum(f / grad, 0.0)  # first-order distance to the inset ellipse
        return r - np.sqrt(d2 * d2 + z * z)

    return field


def bent(field: Field, radius: float) -> Field:
    """Bend a leaf lying in z = 0 isometrically around a cylinder of ``radius`` (axis // y).

    The flat point ``(x, y, z)`` goes to ``((R + z) sin(x/R), y, (R + z) cos(x/R) - R)``:
    the mid-surface ``z = 0`` keeps every length and area.
    """

    def out(p: np.ndarray) -> np.ndarray:
        X, Y, Z = p[..., 0], p[..., 1], p[..., 2]
        rr = np.sqrt(X * X + (Z + radius) ** 2)
        theta = np.arctan2(X, Z + radius)
        q = np.stack([radius * theta, Y, rr - radius], axis=-1)
        return field(q)

    return out


def placed(field: Field, rotation: np.ndarray, translation: Sequence[float]) -> Field:
    """The leaf moved rigidly: ``x_world = rotation @ x_leaf + translation``."""
    rot = np.asarray(rotation, float)
    t = np.asarray(translation, float)

    def out(p: np.ndarray) -> np.ndarray:
        return field((p - t) @ rot)  # (R^T (p - t)) for row vectors

    return out


def touching_slabs(a: float = 40.0, b: float = 18.0, thickness: float = 1.5,
                   tilt_deg: float = 35.0, overlap_mm: float = 4.0,
                   voxel_mm: float = 0.5) -> tuple[Mesh, np.ndarray]:
    """Two elliptical slabs, the second tilted ``tilt_deg`` and overlapping the first one's
    tip by ``overlap_mm``: one connected surface whose two leaves meet along a concave
    crease; and each face's leaf (0, 1)."""
    leaf1 = ellipse_slab_field(a, b, thickness)
    rot = rotation_about_axis((0, 1, 0), -tilt_deg)
    leaf2 = placed(ellipse_slab_field(a, b, thickness), rot,
                   np.array([a - overlap_mm, 0.0, 0.0]) + rot @ np.array([a, 0.0, 0.0]))
    t = math.radians(tilt_deg)
    box1 = (np.array([-a, -b, -2.0]), np.array([a, b, 2.0]))
    box2 = (np.array([a - overlap_mm - 2.0, -b, -2.0]),
            np.array([a + 2 * a * math.cos(t) + 2.0, b, 2 * a * math.sin(t) + 2.0]))
    mesh = mesh_field(None, box1[0], box2[1], voxel_mm, parts=[(leaf1, box1), (leaf2, box2)])
    c = mesh.vertices[mesh.faces].mean(axis=1)
    return mesh, np.argmax(np.stack([leaf1(c), leaf2(c)]), 0)


def cylinder_field(radius: float, z0: float, z1: float, centre=(0.0, 0.0)) -> Field:
    """Vertical cylinder (a stem) of ``radius`` from ``z0`` to ``z1``."""

    def field(p: np.ndarray) -> np.ndarray:
        rho = np.hypot(p[..., 0] - centre[0], p[..., 1] - centre[1])
        return np.minimum(radius - rho, np.minimum(p[..., 2] - z0, z1 - p[..., 2]))

    return field


def capsule_field(p0: Sequence[float], p1: Sequence[float], radius: float) -> Field:
    """Tube of ``radius`` around the segment ``p0``-``p1`` with round ends (a petiole)."""
    a = np.asarray(p0, float)
    d = np.asarray(p1, float) - a
    dd = float(d @ d)

    def field(p: np.ndarray) -> np.ndarray:
        t = np.clip(((p - a) @ d) / dd, 0.0, 1.0)
        return radius - np.linalg.norm(p - a - t[..., None] * d, axis=-1)

    return field


def union(*fields: Field) -> Field:
    def out(p: np.ndarray) -> np.ndarray:
        return np.max(np.stack([f(p) for f in fields]), axis=0)

    return out


def mesh_field(
    field: Field,
    lo: Sequence[float],
    hi: Sequence[float],
    voxel_mm: float,
    *,
    binary: bool = True,
    blur_voxels: float = 0.7,
    noise_mm: float = 0.0,
    seed: int = 0,
    parts: list | None = None,
) -> Mesh:
    """Sample ``field`` on a grid, mesh its 0 level set with marching cubes.

    Parameters
    ----------
    field : callable, (..., 3) mm -> (...) values, > 0 inside
    lo, hi : (3,) mm, bounds of the grid (world frame)
    voxel_mm : float, mm
    binary : bool
        Binarise the field first (as a carved occupancy grid is), then blur
        it by ``blur_voxels`` (Gaussian sigma in voxels) so marching cubes
        sees a smooth 0.5 level: the staircase of a voxel hull, softened.
    noise_mm : float
        Standard deviation of a random displacement of every vertex, mm.
    parts : list of (field, (lo, hi)), optional
        Sample these fields, each only inside its box, and mesh their union
        (instead of ``field`` over the whole grid).
    """
    from scipy import ndimage
    from skimage.measure import marching_cubes

    lo = np.asarray(lo, float) - 2 * voxel_mm
    hi = np.asarray(hi, float) + 2 * voxel_mm
    n = np.ceil((hi - lo) / voxel_mm).astype(int) + 1
    axes = [lo[i] + voxel_mm * np.arange(n[i]) for i in range(3)]
    values = np.full(tuple(n), -1.0, np.float32)
    for part, (plo, phi) in (parts if parts is not None else [(field, (lo, hi))]):
        # each part is sampled only inside its own box (a plant's grid is mostly air)
        i0 = np.clip(np.floor((np.asarray(plo) - lo) / voxel_mm).astype(int) - 1, 0, n - 1)
        i1 = np.clip(np.ceil((np.asarray(phi) - lo) / voxel_mm).astype(int) + 2, 1, n)
        yy, zz = np.meshgrid(axes[1][i0[1]:i1[1]], axes[2][i0[2]:i1[2]], indexing="ij")
        for i in range(i0[0], i1[0]):  # slice by slice: a plant grid does not fit in memory
            pts = np.stack([np.full_like(yy, axes[0][i]), yy, zz], axis=-1)
            sl = values[i, i0[1]:i1[1], i0[2]:i1[2]]
            np.maximum(sl, part(pts).astype(np.float32), out=sl)
    if binary:
        occ = (values > 0).astype(np.float32)
        if blur_voxels > 0:
            occ = ndimage.gaussian_filter(occ, blur_voxels)
        values, level = occ, 0.5
    else:
        level = 0.0
    if values.max() <= level:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    verts, faces, _, _ = marching_cubes(values, level, spacing=(voxel_mm,) * 3)
    verts = verts + lo
    # marching_cubes orients faces by the gradient (towards larger values = inside);
    # the plantscan convention is counter-clockwise seen from outside.
    faces = faces[:, ::-1]
    if noise_mm > 0:
        rng = np.random.default_rng(seed)
        verts = verts + rng.normal(0.0, noise_mm, verts.shape)
    return Mesh(verts, faces)


def ellipse_slab_mesh(a: float, b: float, thickness: float, voxel_mm: float = 0.5,
                      bend_radius: float | None = None, **kwargs) -> Mesh:
    """Mesh of one elliptical slab (optionally bent), centred on the origin, in z = 0."""
    f = ellipse_slab_field(a, b, thickness)
    lo, hi = np.array([-a, -b, -thickness]), np.array([a, b, thickness])
    if bend_radius is not None:
        f = bent(f, bend_radius)
        sag = bend_radius * (1.0 - math.cos(min(a / bend_radius, math.pi)))
        lo[2] -= sag + thickness
        lo[0] = -bend_radius * math.sin(min(a / bend_radius, math.pi / 2)) - thickness
        hi[0] = -lo[0]
    return mesh_field(f, lo, hi, voxel_mm, **kwargs)


@dataclass
class MockPlant:
    """A stem cylinder with elliptical leaves attached, and each leaf's truth."""

    field: Field
    leaves: list[EllipseLeaf]
    lo: np.ndarray
    hi: np.ndarray
    parts: list[Field]
    boxes: list[tuple[np.ndarray, np.ndarray]]

    def part_of(self, points: np.ndarray) -> np.ndarray:
        """(N,) truth part of points near the surface: -1 stem, i for leaf i (largest field)."""
        values = np.stack([f(points) for f in self.parts])
        part = np.argmax(values, axis=0) - 1
        part[part >= len(self.leaves)] = -1  # petioles are stem
        return part

    def mesh(self, voxel_mm: float = 0.6, **kwargs) -> Mesh:
        return mesh_field(self.field, self.lo, self.hi, voxel_mm,
                          parts=list(zip(self.parts, self.boxes)), **kwargs)


def mock_plant(n_leaves: int = 5, stem_radius: float = 3.0, thickness: float = 1.5,
               seed: int = 1, petiole_mm: float = 0.0, petiole_radius: float = 1.5) -> MockPlant:
    """Stem + ``n_leaves`` elliptical leaves in a spiral, their bases sunk into the stem.

    Each leaf points outwards and upwards (20–35 deg) from a node on the stem;
    leaves are 60–90 mm long, 30–45 mm wide.  A leaf starts half a stem
    radius from the axis, so its first ``stem_radius / 2`` mm are inside the
    stem (visible length ``2 a - stem_radius / 2``).  With ``petiole_mm`` > 0
    each blade sits instead at the end of a petiole (a tube, part of the stem
    in the truth) that long from the stem surface, and its whole ``2 a`` shows.
    Parts: ``parts[0]`` stem, ``parts[1 + i]`` leaf i, then the petioles.
    """
    rng = np.random.default_rng(seed)
    height = 40.0 + 25.0 * n_leaves
    fields = [cylinder_field(stem_radius, 0.0, height)]
    boxes = [(np.array([-stem_radius, -stem_radius, 0.0]),
              np.array([stem_radius, stem_radius, height]))]
    leaves = []
    petioles = []
    for i in range(n_leaves):
        a = rng.uniform(30.0, 45.0)
        b = rng.uniform(15.0, 22.0)
        leaves.append(EllipseLeaf(a, b))
        azimuth = i * 137.5  # phyllotaxis
        elevation = rng.uniform(20.0, 35.0)
        roll = rng.uniform(-20.0, 20.0)
        z = 30.0 + 25.0 * i
        # leaf frame: x along the midrib (outwards), y across, z normal
        rot = (rotation_about_axis((0, 0, 1), azimuth)
               @ rotation_about_axis((0, 1, 0), -elevation)
               @ rotation_about_axis((1, 0, 0), roll))
        x0 = stem_radius * 0.5 if petiole_mm <= 0 else stem_radius + petiole_mm
        centre = np.array([x0 + a, 0.0, 0.0])
        t = rot @ centre + np.array([0.0, 0.0, z])
        if petiole_mm > 0:
            # from the stem axis to 1 mm into the blade's base
            ends = np.array([[0.0, 0.0, 0.0], [x0 + 1.0, 0.0, 0.0]]) @ rot.T + [0.0, 0.0, z]
            box = (ends.min(axis=0) - petiole_radius, ends.max(axis=0) + petiole_radius)
            petioles.append((capsule_field(ends[0], ends[1], petiole_radius), box))
        fields.append(placed(ellipse_slab_field(a, b, thickness), rot, t))
        corners = np.array(np.meshgrid([-a, a], [-b, b], [-thickness, thickness])).reshape(3, -1).T
        world = corners @ rot.T + t
        boxes.append((world.min(axis=0), world.max(axis=0)))
    for field, box in petioles:
        fields.append(field)
        boxes.append(box)
    reach = 2 * 45.0 + stem_radius + 5 + petiole_mm
    lo = np.array([-reach, -reach, -1.0])
    hi = np.array([reach, reach, height + 60.0])
    return MockPlant(union(*fields), leaves, lo, hi, fields, boxes)


def voxelise_mesh(vertices: np.ndarray, faces: np.ndarray, voxel_mm: float, offset_mm: float,
                  sigma_noise_mm: float = 0.0, seed: int = 0) -> Mesh:
    """A marching-cubes surface at ``offset_mm`` around a (thin) mesh: a hull-like slab.

    The unsigned distance to the mesh is computed (Open3D ray-casting scene) in
    a narrow band of voxels around its surface; the 0 level of
    ``offset_mm - distance`` is meshed.  A 0.5 mm leaf becomes a
    ``0.5 + 2 offset`` mm slab with rounded edges whose outline lies
    ``offset_mm`` outside the leaf's (so its flat-leaf traits are those of
    the leaf grown by ``offset_mm``: length and width ``+ 2 offset``,
    perimeter ``+ 2 pi offset``, area ``+ perimeter x offset + pi offset^2``).
    """
    import open3d as o3d
    from scipy import ndimage
    from skimage.measure import marching_cubes

    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    lo = v.min(axis=0) - offset_mm - 3 * voxel_mm
    n = np.ceil((v.max(axis=0) + offset_mm + 3 * voxel_mm - lo) / voxel_mm).astype(int) + 1
    # narrow band: voxels near points sampled on every triangle at < voxel spacing
    tri = v[f]
    edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    k = np.maximum(np.ceil(edge / (0.5 * voxel_mm)).astype(int), 1)
    near = np.zeros(tuple(n), bool)
    for kk in np.unique(k):
        sel = tri[k == kk]
        u, w = np.meshgrid(np.arange(kk + 1), np.arange(kk + 1), indexing="ij")
        keep = (u + w) <= kk
        bary = np.stack([u[keep], w[keep]], axis=1) / kk
        pts = (sel[:, None, 0] + bary[None, :, 0, None] * (sel[:, None, 1] - sel[:, None, 0])
               + bary[None, :, 1, None] * (sel[:, None, 2] - sel[:, None, 0])).reshape(-1, 3)
        ijk = np.clip(np.round((pts - lo) / voxel_mm).astype(np.int64), 0, n - 1)
        near[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    # every voxel within the offset (+1 voxel) of a sampled point: a dilation of the grid
    reach = int(np.ceil(offset_mm / voxel_mm)) + 1
    near = ndimage.binary_dilation(near, np.ones((2 * reach + 1,) * 3, bool))
    cand = np.argwhere(near)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                        o3d.core.Tensor(f.astype(np.uint32)))
    d = scene.compute_distance(o3d.core.Tensor((lo + cand * voxel_mm).astype(np.float32))).numpy()
    field = np.full(tuple(n), -voxel_mm, np.float32)
    field[cand[:, 0], cand[:, 1], cand[:, 2]] = np.maximum(offset_mm - d, -voxel_mm)
    verts, tris, _, _ = marching_cubes(field, 0.0, spacing=(voxel_mm,) * 3)
    verts = verts + lo
    if sigma_noise_mm > 0:
        verts = verts + np.random.default_rng(seed).normal(0.0, sigma_noise_mm, verts.shape)
    return Mesh(verts, tris[:, ::-1])

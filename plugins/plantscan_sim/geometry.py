"""Triangle-mesh primitives and isometrically bent leaves for the virtual scanner.

All lengths in mm.  Meshes are ``(V, 3) float64`` vertices and ``(F, 3) int64``
faces, counter-clockwise seen from outside (outward normals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar


# --------------------------------------------------------------------------- mesh helpers
@dataclass
class TriMesh:
    """A mesh plus one integer attribute per face (material or leaf id)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_attr: np.ndarray

    @staticmethod
    def concat(parts: list[TriMesh]) -> TriMesh:
        vs, fs, attrs, off = [], [], [], 0
        for p in parts:
            vs.append(p.vertices)
            fs.append(p.faces + off)
            attrs.append(p.face_attr)
            off += len(p.vertices)
        if not parts:
            return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
        return TriMesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(attrs))

    def with_attr(self, value: int) -> TriMesh:
        return TriMesh(self.vertices, self.faces, np.full(len(self.faces), value, np.int64))

    def transformed(self, rotation: np.ndarray, translation=(0.0, 0.0, 0.0)) -> TriMesh:
        return TriMesh(self.vertices @ np.asarray(rotation).T + np.asarray(translation),
                       self.faces, self.face_attr)


def _mesh(v, f, attr: int = 0) -> TriMesh:
    v = np.asarray(v, dtype=float)
    f = np.asarray(f, dtype=np.int64)
    return TriMesh(v, f, np.full(len(f), attr, np.int64))


def grid_faces(rows: int, cols: int, flip: bool = False) -> np.ndarray:
    """Faces of a ``rows x cols`` vertex grid (row-major), two triangles per cell."""
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (i * cols + j).ravel()
    b, c, d = a + 1, a + cols, a + cols + 1
    f = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return f[:, ::-1].copy() if flip else f


def revolve(profile_rz: np.ndarray, n: int = 96, attr: int = 0) -> TriMesh:
    """Surface of revolution about +Z of an (r, z) polyline (outward when z rises with index
    on the outside, i.e. the profile goes bottom -> top along the outer wall)."""
    prof = np.asarray(profile_rz, dtype=float)
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    ca, sa = np.cos(a), np.sin(a)
    z = np.broadcast_to(prof[:, 1:2], (len(prof), n))
    v = np.stack([prof[:, 0:1] * ca, prof[:, 0:1] * sa, z], axis=-1).reshape(-1, 3)
    rows, cols = len(prof), n
    faces = []
    for i in range(rows - 1):
        for j in range(cols):
            p, q = i * cols + j, i * cols + (j + 1) % cols
            r, s = p + cols, q + cols
            faces += [(p, q, s), (p, s, r)]
    return _mesh(v, faces, attr)


def frustum(z0: float, z1: float, r0: float, r1: float, n: int = 96, attr: int = 0) -> TriMesh:
    """Closed tapered cylinder between heights ``z0 < z1`` with radii ``r0``, ``r1``."""
    return revolve(np.array([[0.0, z0], [r0, z0], [r1, z1], [0.0, z1]]), n, attr)


MIN_STEP_MM = 1e-4  # points of a polyline closer than this are one point (tube tangents)


def tube(points: np.ndarray, radii, n: int = 10, attr: int = 0) -> TriMesh:
    """Closed tube along a polyline ``(N, 3)`` with radius per point (stems, petioles)."""
    pts = np.asarray(points, dtype=float)
    radii = np.broadcast_to(np.asarray(radii, dtype=float), (len(pts),))
    # A growing plant's organs start at zero length (an internode not yet elongated, a
    # sessile petiole): repeated points have no tangent, so they are dropped, and a tube
    # with no length left is no mesh at all.
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > MIN_STEP_MM])
    pts, radii = pts[keep], radii[keep]
    if len(pts) < 2:
        return _mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), attr)
    tang = np.gradient(pts, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    u = np.cross(tang, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(tang, u)
    rings = pts[:, None, :] + radii[:, None, None] * (
        np.cos(a)[None, :, None] * u[:, None, :] + np.sin(a)[None, :, None] * w[:, None, :])
    v = np.concatenate([rings.reshape(-1, 3), pts[:1], pts[-1:]])
    m = len(pts)
    i, j = np.meshgrid(np.arange(m - 1), np.arange(n), indexing="ij")
    p_ = (i * n + j).ravel()
    q = (i * n + (j + 1) % n).ravel()
    side = np.stack([np.stack([p_, q, q + n], 1), np.stack([p_, q + n, p_ + n], 1)], 1)
    c0, c1 = m * n, m * n + 1
    jj = np.arange(n)
    caps = np.stack([np.stack([np.full(n, c0), (jj + 1) % n, jj], 1),
                     np.stack([np.full(n, c1), (m - 1) * n + jj, (m - 1) * n + (jj + 1) % n], 1)],
                    1)
    return _mesh(v, np.concatenate([side.reshape(-1, 3), caps.reshape(-1, 3)]), attr)


def box(centre, ex, ey, ez, half_sizes, attr: int = 0) -> TriMesh:
    """Closed box with axes ``ex, ey, ez`` (orthonormal) and half sizes (hx, hy, hz)."""
    c = np.asarray(centre, float)
    axes = [np.asarray(e, float) * h for e, h in zip((ex, ey, ez), half_sizes, strict=True)]
    v = np.array([c + sx * axes[0] + sy * axes[1] + sz * axes[2]
                  for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    # vertex index = 4*ix + 2*iy + iz
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, c_, d in quads:
        faces += [(a, b, c_), (a, c_, d)]
    m = _mesh(v, faces, attr)
    # Orient outward whatever the handedness of (ex, ey, ez).
    tri = m.vertices[m.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.einsum("ij,ij->i", n, tri.mean(1) - c) < 0
    m.faces[out] = m.faces[out][:, ::-1]
    return m


# --------------------------------------------------------------------------- leaf outlines
@dataclass
class LeafOutline:
    """A flat, symmetric leaf blade: midrib along +x from base (0) to tip (``length``).

    The blade is ``|y| <= half_width(x)``; its outline polygon runs base -> tip along
    ``+y`` and back along ``-y``.  ``length``, ``width``, ``area`` and ``perimeter``
    are the exact measurements of that polygon (the truth traits).
    """

    x: np.ndarray            # (N,) mm, 0 .. length, increasing
    half_width: np.ndarray   # (N,) mm, 0 at both ends
    shape: dict

    @property
    def length(self) -> float:
        return float(self.x[-1] - self.x[0])

    @property
    def width(self) -> float:
        return float(2.0 * self.half_width.max())

    @property
    def area(self) -> float:
        return float(2.0 * np.trapezoid(self.half_width, self.x))

    @property
    def perimeter(self) -> float:
        return float(2.0 * np.sum(np.hypot(np.diff(self.x), np.diff(self.half_width))))

    def polygon(self) -> np.ndarray:
        """(2N-2, 2) closed outline, counter-clockwise."""
        lower = np.stack([self.x, -self.half_width], 1)
        upper = np.stack([self.x[::-1], self.half_width[::-1]], 1)
        return np.concatenate([lower, upper[1:-1]])


def _profile(n: int, length: float, width: float, p: float, q: float, warp: float):
    s = np.linspace(0.0, 1.0, n)
    x = 0.5 * (1.0 - np.cos(np.pi * s))  # dense at base and tip where the outline turns
    x_max = 0.5 ** (1.0 / warp)          # position of the widest point (t = 0)
    x = np.unique(np.concatenate([x, [x_max]]))
    t = 2.0 * x**warp - 1.0
    h = 0.5 * width * np.clip(1.0 - np.abs(t) ** p, 0.0, 1.0) ** q
    h[0] = h[-1] = 0.0
    return x * length, h


def leaf_outline(length: float, width: float, area: float, *, p: float | None = None,
                 warp: float = 1.0, n: int = 121) -> LeafOutline:
    """Outline with exactly ``length`` and ``width`` and area ``area`` (to < 1e-6 relative).

    Family ``h = W/2 (1 - |t|^p)^q`` with ``t = 2 (x/L)^warp - 1``; ``q`` is solved for
    the area.  With ``p=None`` the exponent ``p`` is chosen to make the perimeter as
    short as this family allows (the seed's perimeters are shorter than any outline
    with their length, width and area can have, see docs/virtual-scanner.md).
    """
    fill = area / (length * width)
    if not 0.05 < fill < 0.98:
        raise ValueError(f"leaf area {area} mm² impossible for {length} x {width} mm "
                         f"(fill {fill:.3f} not in (0.05, 0.98))")

    def solve_q(pp: float) -> float:
        def f(q):
            x, h = _profile(n, length, width, pp, q, warp)
            return 2.0 * np.trapezoid(h, x) - area
        return brentq(f, 1e-3, 60.0, xtol=1e-12)

    def perim(pp: float) -> float:
        x, h = _profile(n, length, width, pp, solve_q(pp), warp)
        return float(2.0 * np.sum(np.hypot(np.diff(x), np.diff(h))))

    if p is None:
        p = float(minimize_scalar(perim, bounds=(1.2, 8.0), method="bounded",
                                  options={"xatol": 1e-3}).x)
    q = solve_q(p)
    x, h = _profile(n, length, width, p, q, warp)
    return LeafOutline(x, h, {"p": p, "q": q, "warp": warp, "samples": len(x)})


# --------------------------------------------------------------------------- bent leaves
@dataclass
class LeafPlacement:
    """Where and how a flat blade is put on the plant.

    The midrib leaves ``base`` in direction ``e1 = cos(incl) radial + sin(incl) z``
    (``radial`` horizontal at ``azimuth_deg``); ``e2`` is the blade's upper normal
    there and ``e3 = e1 x e2`` its across direction, both rolled by ``roll_deg``
    about ``e1``.  The blade is wrapped, without stretching, on a cylinder whose
    cross-section bends downwards with curvature ``kappa(sigma) = k0 + k1 sigma``
    (1/mm, ``sigma`` the arc length of the cross-section).  With ``twist_deg = 0``
    the cylinder's generators run across the blade (``e3``): the midrib bends in
    one plane.  With ``twist_deg = b`` the midrib crosses the cross-sections at
    ``b`` degrees, so it winds as a helix-like curve and the blade's normal turns
    about it (a twisted, drooping blade).  A blade wrapped on a cylinder is a
    developable surface: flat length, width, area and perimeter are preserved
    exactly whatever the bend, roll and twist.
    """

    base: np.ndarray
    azimuth_deg: float
    inclination_deg: float
    k0: float
    k1: float
    roll_deg: float = 0.0
    twist_deg: float = 0.0
    fine_samples: int = 4001  # grid of the exact tangent integral (601 is exact to 1e-5 mm)

    @staticmethod
    def with_total_bend(base, azimuth_deg, inclination_deg, length, bend_deg, roll_deg=0.0,
                        tip_share=0.7, twist_deg=0.0) -> LeafPlacement:
        """The cylinder's cross-section turns by ``bend_deg`` over the blade, ``tip_share``
        of it from the linear term (with no twist: the midrib turns by ``bend_deg``)."""
        total = math.radians(bend_deg)
        span = length * math.cos(math.radians(twist_deg))  # cross-section arc under the blade
        k0 = (1.0 - tip_share) * total / span
        k1 = 2.0 * tip_share * total / span**2
        return LeafPlacement(np.asarray(base, float), azimuth_deg, inclination_deg, k0, k1,
                             roll_deg, twist_deg)

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, i = math.radians(self.azimuth_deg), math.radians(self.inclination_deg)
        radial = np.array([math.cos(a), math.sin(a), 0.0])
        e1 = math.cos(i) * radial + math.sin(i) * np.array([0.0, 0.0, 1.0])
        e2 = -math.sin(i) * radial + math.cos(i) * np.array([0.0, 0.0, 1.0])  # "up" of the blade
        e3 = np.cross(e1, e2)
        r = math.radians(self.roll_deg)
        e2, e3 = math.cos(r) * e2 + math.sin(r) * e3, -math.sin(r) * e2 + math.cos(r) * e3
        return e1, e2, e3

    def surface(self, x: np.ndarray, y: np.ndarray, offset: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(N, 3)`` mm and unit normals of the blade at flat coordinates.

        ``x`` (mm along the flat midrib from the base) and ``y`` (mm across it,
        towards ``e3``) are broadcast together; points lie ``offset`` mm along
        the upper normal.
        """
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        e1, e2, e3 = self.frame()
        b = math.radians(self.twist_deg)
        u = math.cos(b) * e1 - math.sin(b) * e3   # cross-section direction at the base
        axis = math.cos(b) * e3 + math.sin(b) * e1  # the cylinder's generators
        sigma = math.cos(b) * x - math.sin(b) * y
        along = math.sin(b) * x + math.cos(b) * y
        # Exact integral of the cross-section's unit tangent on a fine grid (it is smooth).
        lo, hi = (min(0.0, float(sigma.min())), float(sigma.max())) if sigma.size else (0.0, 0.0)
        fine = np.linspace(lo, hi, self.fine_samples)
        th = -(self.k0 * fine + 0.5 * self.k1 * fine * fine)
        ca, sa = np.cos(th), np.sin(th)
        ds = np.diff(fine)
        ga = np.concatenate([[0.0], np.cumsum(0.5 * (ca[1:] + ca[:-1]) * ds)])
        gb = np.concatenate([[0.0], np.cumsum(0.5 * (sa[1:] + sa[:-1]) * ds)])
        zero = np.interp(0.0, fine, ga), np.interp(0.0, fine, gb)
        ga, gb = np.interp(sigma, fine, ga) - zero[0], np.interp(sigma, fine, gb) - zero[1]
        theta = -(self.k0 * sigma + 0.5 * self.k1 * sigma * sigma)
        normal = -np.sin(theta)[..., None] * u + np.cos(theta)[..., None] * e2
        pts = (self.base + ga[..., None] * u + gb[..., None] * e2 + along[..., None] * axis
               + offset * normal)
        return pts, normal

    def midrib(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Midrib points ``(N, 3)`` and blade normals ``(N, 3)`` at arc lengths ``s`` (mm)."""
        s = np.asarray(s, dtype=float)
        return self.surface(s, np.zeros_like(s))


def leaf_surface(outline: LeafOutline, place: LeafPlacement, across: int = 9,
                 offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(N*across, 3)`` and faces of the bent blade, offset along its normal."""
    sj = np.linspace(-1.0, 1.0, across)
    y = outline.half_width[:, None] * sj[None, :]
    v, _ = place.surface(np.broadcast_to(outline.x[:, None], y.shape), y, offset)
    return v.reshape(-1, 3), grid_faces(len(outline.x), across)


def leaf_solid(outline: LeafOutline, place: LeafPlacement, thickness: float = 0.5,
               across: int = 9, attr: int = 0) -> TriMesh:
    """Closed thin solid of the bent blade: two faces ``thickness`` apart plus the rim."""
    top_v, f = leaf_surface(outline, place, across, +0.5 * thickness)
    bot_v, _ = leaf_surface(outline, place, across, -0.5 * thickness)
    n = len(top_v)
    rows = len(outline.x)
    # Orient the top face along +normal: grid (i along x, j across -> e3); e1 x e3 = -e2.
    top_f = f[:, ::-1]
    bot_f = f + n
    # Boundary loop of the grid: j=0 edge base->tip, then j=across-1 edge tip->base.
    loop = np.concatenate([np.arange(rows) * across,
                           (np.arange(rows)[::-1]) * across + across - 1])
    rim = []
    for a, b in zip(loop, np.roll(loop, -1), strict=True):
        rim += [(a, b, b + n), (a, b + n, a + n)]
    faces = np.concatenate([top_f, bot_f, np.asarray(rim, np.int64)])
    m = TriMesh(np.concatenate([top_v, bot_v]), faces, np.full(len(faces), attr, np.int64))
    return _orient_outward(m)


def _orient_outward(m: TriMesh) -> TriMesh:
    """Flip the whole mesh if its signed volume is negative (closed meshes only)."""
    tri = m.vertices[m.faces]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if vol < 0:
        m = TriMesh(m.vertices, m.faces[:, ::-1].copy(), m.face_attr)
    return m


def mesh_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    t = vertices[faces]
    return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


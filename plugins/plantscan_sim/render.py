"""CPU ray-cast renderer of the virtual scanner (Open3D ``RaycastingScene``).

Every sample gets its own ray through the exact lens model
(``CameraModel.unproject``: the distortion is inverted per sample, not
approximated by a warp), ``ss x ss`` samples per pixel are box-filtered so thin
leaf edges cover partial pixels.  Shading: diffuse albedo x (ambient + key light
x visibility) with a hard shadow ray per sample towards a point key light fixed
in the lab, then an sRGB-like gamma, sensor noise and 8-bit quantisation.

Two ray-casting scenes are used per role: objects attached to the turntable
(plate, carrier, pot, plant, calibration board) in the world frame, and the
studio backdrop fixed in the lab frame.  A camera ray is cast in both frames
(the lab frame is the world frame turned by the true turntable angle) and the
nearer hit wins, so neither scene is rebuilt when the turntable moves.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from plantscan_core.data import Camera, CameraModel, rotation_z
from plantscan_sim.geometry import TriMesh

CLASS_BACKGROUND, CLASS_PLANT, CLASS_POT, CLASS_BOARD = 0, 1, 2, 3
MAX_RAYS_PER_BAND = 2_000_000  # bounds memory (~0.4 GB peak) at 18 MP
MAX_CACHED_RAYS = 20_000_000  # one 18 MP lens: 18 M unit rays, 215 MB float32


@dataclass
class Material:
    albedo: tuple[float, float, float]  # linear RGB, 0..1
    klass: int = CLASS_BACKGROUND


@dataclass
class BoardTexture:
    """Pattern on the calibration board's front face, in board coordinates (mm).

    ``origin`` is the outer corner of square (0, 0); ``ex`` runs along rows,
    ``ey`` down the columns (``ex x ey`` points into the board).
    """

    origin: np.ndarray
    ex: np.ndarray
    ey: np.ndarray
    squares: tuple[int, int]
    square_mm: float
    image: np.ndarray | None = None  # (H, W) float32 albedo for ChArUco; None = chessboard
    px_per_mm: float = 1.0
    black: float = 0.03
    white: float = 0.82

    def albedo(self, p_world: np.ndarray) -> np.ndarray:
        d = p_world - self.origin
        u, v = d @ self.ex, d @ self.ey
        nx, ny = self.squares
        s = self.square_mm
        out = np.full(len(u), self.white, dtype=np.float32)
        if self.image is None:
            inside = (u >= 0) & (u < nx * s) & (v >= 0) & (v < ny * s)
            black = ((np.floor(u / s) + np.floor(v / s)) % 2 == 0) & inside
            out[black] = self.black
        else:
            h, w = self.image.shape
            col = np.floor(u * self.px_per_mm).astype(np.int64)
            row = np.floor(v * self.px_per_mm).astype(np.int64)
            ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
            out[ok] = self.image[row[ok], col[ok]]
        return out


@dataclass
class Lighting:
    key_position_lab: np.ndarray  # (3,) mm, lab frame
    key: float = 0.8
    ambient: float = 0.3
    miss_colour: tuple[float, float, float] = (0.04, 0.04, 0.045)
    gamma: float = 2.2  # tone curve of the camera: 8-bit value = 255 * radiance ** (1/gamma)


def _raycasting_scene(mesh: TriMesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    if len(mesh.faces):
        scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene


@dataclass
class _Layer:
    mesh: TriMesh
    scene: object
    face_material: np.ndarray


def _room(mesh: TriMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Triangles (T, 3, 3), unit normals (T, 3) turned towards the room, materials (T,)
    of a lab mesh that bounds a convex room (the studio sweep), else None.

    Seen from inside such a room a ray leaves through exactly one plane, so the
    fast path intersects it analytically instead of casting into Open3D.
    """
    if not len(mesh.faces):
        return None
    v = np.asarray(mesh.vertices, dtype=float)
    tri = v[mesh.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    if np.any(norm <= 1e-12):
        return None
    n /= norm[:, None]
    side = np.einsum("tk,vk->tv", n, v) - np.einsum("tk,tk->t", n, tri[:, 0])[:, None]
    eps = 1e-6 * float(np.ptp(v, axis=0).max())
    behind, ahead = (side <= eps).all(1), (side >= -eps).all(1)
    if not (behind | ahead).all():
        return None
    # A convex room lies on the side of each face where the rest of the mesh is.
    n[~ahead] *= -1.0
    offset = -np.einsum("tk,tk->t", n, tri[:, 0])
    key = np.round(np.column_stack([n, offset / max(1.0, float(np.ptp(v, axis=0).max()))]), 9)
    _, plane_of, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    plane_of = plane_of.ravel()
    planes = np.zeros((len(counts), 4))
    plane_tris = np.full((len(counts), int(counts.max())), -1, dtype=np.int64)
    fill = np.zeros(len(counts), dtype=np.int64)
    for j, k in enumerate(plane_of):
        planes[k] = [*n[j], offset[j]]
        plane_tris[k, fill[k]] = j
        fill[k] += 1
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    a11, a12, a22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    det = (a11 * a22 - a12 * a12)[:, None]
    dual = np.stack([(a22[:, None] * e1 - a12[:, None] * e2) / det,
                     (a11[:, None] * e2 - a12[:, None] * e1) / det], 1)
    return _Room(tri, dual, planes, plane_tris, np.asarray(mesh.face_attr, dtype=np.int64))


SHADOW_MAP = 2048  # texels per side of the light's culling map
TONE_LUT = 16384  # entries of the interpolated tone curve


@dataclass
class _Cull:
    """Per-view culling of the fast path (``Renderer._culling``)."""

    room: _Room | None           # the backdrop as a convex room, or None: cast it
    foot: np.ndarray             # (H, W) bool: pixels whose ray may meet the turntable scene
    basis: np.ndarray | None     # (3, 3) light camera axes (rows), world frame
    window: np.ndarray | None    # (3,) x0, y0, texels per unit of x/z
    shadow_map: np.ndarray | None  # (M, M) bool: texels an occluder may cover


@dataclass
class _Room:
    tri: np.ndarray         # (T, 3, 3) lab frame, mm
    dual: np.ndarray        # (T, 2, 3): barycentric (u, v) = dual . (p - tri[:, 0])
    planes: np.ndarray      # (P, 4): unit normal towards the room, offset
    plane_tris: np.ndarray  # (P, k) triangle indices per plane, -1 padded
    attr: np.ndarray        # (T,) material


@dataclass
class Renderer:
    """Renders the roles of one virtual scene.

    Parameters
    ----------
    world : dict role -> TriMesh
        Turntable-attached geometry of each role, world frame; ``face_attr`` is a
        material index.
    lab : TriMesh
        Lab-fixed geometry (backdrop), lab frame.
    materials : list of Material
    lighting : Lighting
    board : BoardTexture or None
    """

    world: dict[str, TriMesh]
    lab: TriMesh
    materials: list[Material]
    lighting: Lighting
    board: BoardTexture | None = None
    board_material: int = -1
    moving: dict[str, TriMesh] = field(default_factory=dict)
    # material -> .albedo(p) (N,); p in the world frame, or the lab's if .lab_frame
    textures: dict[int, object] = field(default_factory=dict)
    _layers: dict = field(default_factory=dict, init=False)
    _lab: _Layer | None = field(default=None, init=False)
    _moving: dict = field(default_factory=dict, init=False)
    _cache: dict = field(default_factory=dict, init=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False)
    fast: bool = True
    rays_cast: int = field(default=0, init=False)
    rays_analytic: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self._albedo = np.array([m.albedo for m in self.materials], dtype=np.float32)
        self._klass = np.array([m.klass for m in self.materials], dtype=np.int8)
        for role, mesh in self.world.items():
            self._layers[role] = _Layer(mesh, _raycasting_scene(mesh), mesh.face_attr)
        self._lab = _Layer(self.lab, _raycasting_scene(self.lab), self.lab.face_attr)
        for role, mesh in self.moving.items():
            self._moving[role] = _Layer(mesh, _raycasting_scene(mesh), mesh.face_attr)
        # A printed backdrop is shaded per point: it goes through the cast path.
        lab_printed = any(getattr(t, "lab_frame", False) for t in self.textures.values())
        self._room = _room(self.lab) if HAVE_NUMBA and not lab_printed else None

    def _textured(self) -> list[tuple[int, object]]:
        """(material, texture) pairs: the board's pattern and any other printed surface."""
        out = list(self.textures.items())
        if self.board is not None and self.board_material >= 0:
            out.append((self.board_material, self.board))
        return out

    # ------------------------------------------------------------------ rays
    def _centre_bands(self, model: CameraModel):
        """Camera-frame unit ray directions through pixel centres, per band of rows."""
        cached = self._cache.get(model)
        if cached is not None:
            return cached
        w, h = model.width, model.height
        rows = max(1, MAX_RAYS_PER_BAND // w)
        bands = []
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(r0, r1, dtype=float))
            bands.append((r0, r1, self._unproject(model, np.stack([uu.ravel(), vv.ravel()], 1))))
        if w * h <= MAX_CACHED_RAYS:
            with self._lock:
                if len(self._cache) > 8:
                    self._cache.clear()
                self._cache[model] = bands
        return bands

    # ------------------------------------------------------------------ render
    def render(self, role: str, camera: Camera, angle_deg: float, ss: int = 3,
               noise_sigma: float = 0.0, rng: np.random.Generator | None = None,
               want_coverage: bool = False, adaptive: bool = True,
               sway: tuple[np.ndarray, np.ndarray] | None = None,
               fast: bool | None = None,
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """Render ``role`` seen by ``camera`` (world frame, turntable at ``angle_deg``).

        Adaptive anti-aliasing: one ray through every pixel centre first; every
        pixel whose 3 x 3 neighbourhood is not uniform (another surface, a shadow
        edge or a board square edge) is rendered again with ``ss x ss`` rays and
        box-filtered.  Uniform pixels are exact with one ray.  ``adaptive=False``
        casts ``ss x ss`` rays through every pixel (the plain reference).
        ``sway = (S, pivot)`` displaces the role's moving geometry (the plant) by
        the rotation ``S`` (3, 3) about ``pivot`` (3,) mm, world frame.
        ``fast`` (default ``self.fast``) culls rays that cannot hit the turntable
        scene or be shadowed and intersects the backdrop analytically (same hits,
        see ``_trace``); ``fast=False`` is the plain Open3D path (``_shade``).

        Returns
        -------
        image : (H, W, 3) uint8, BGR
        coverage : (H, W) float32 in [0, 1] or None
            Fraction of each pixel's samples whose first hit is plant or pot.
        """
        model = camera.model
        w, h = model.width, model.height
        fast = (self.fast if fast is None else fast) and HAVE_NUMBA
        layer = self._layers[role]
        moving = None
        if role in self._moving:
            s_rot, pivot = sway if sway is not None else (np.eye(3), np.zeros(3))
            moving = (self._moving[role], np.asarray(s_rot, np.float32),
                      np.asarray(pivot, np.float32))
        rz = rotation_z(angle_deg).astype(np.float32)
        rot = camera.pose.R.astype(np.float32)
        centre = camera.pose.centre.astype(np.float32)
        light_w = (rz.T @ self.lighting.key_position_lab.astype(np.float32)).astype(np.float32)
        cull = self._culling(layer, moving, camera, light_w, rz) if fast else None
        radiance = np.empty((h, w, 3), dtype=np.float32)
        fg = np.empty((h, w), dtype=np.float32)
        key = np.empty((h, w), dtype=np.int32)
        if adaptive or ss == 1:
            for r0, r1, dirs_cam in self._centre_bands(model):
                if fast:
                    self._primary_band(layer, centre, dirs_cam, rot, rz, light_w, moving, cull,
                                       radiance[r0:r1].reshape(-1, 3), fg[r0:r1].reshape(-1),
                                       key[r0:r1].reshape(-1), cull.foot[r0:r1].reshape(-1))
                    continue
                rad, cls, k = self._shade(layer, centre, _mul3(dirs_cam, rot), rz, light_w,
                                          moving)
                radiance[r0:r1] = rad.reshape(r1 - r0, w, 3)
                fg[r0:r1] = ((cls == CLASS_PLANT) | (cls == CLASS_POT)).reshape(r1 - r0, w)
                key[r0:r1] = k.reshape(r1 - r0, w)
        if ss > 1:
            if adaptive:
                edge = np.empty((h, w), dtype=bool)
                if fast:
                    _edges(key, edge)
                else:
                    from scipy.ndimage import maximum_filter, minimum_filter

                    edge = maximum_filter(key, size=3, mode="nearest") != minimum_filter(
                        key, size=3, mode="nearest")
            else:
                edge = np.ones((h, w), dtype=bool)
            rows, cols = np.nonzero(edge)
            offs = (np.arange(ss) + 0.5) / ss - 0.5
            du, dv = (a.ravel() for a in np.meshgrid(offs, offs))
            n_ss = ss * ss
            chunk = max(1, MAX_RAYS_PER_BAND // n_ss)
            for i in range(0, len(rows), chunk):
                r, c = rows[i:i + chunk], cols[i:i + chunk]
                uv = np.stack([(c[:, None] + du).ravel(), (r[:, None] + dv).ravel()], 1)
                d_w = _mul3(self._unproject(model, uv), rot)
                if fast:  # a sample is within half a pixel of its centre: the grown foot holds
                    rad, cls, _ = self._trace(layer, centre, d_w, rz, light_w, moving, cull,
                                              np.repeat(cull.foot[r, c], n_ss))
                else:
                    rad, cls, _ = self._shade(layer, centre, d_w, rz, light_w, moving)
                radiance[r, c] = rad.reshape(len(r), n_ss, 3).mean(axis=1)
                fg[r, c] = ((cls == CLASS_PLANT) | (cls == CLASS_POT)).reshape(
                    len(r), n_ss).mean(axis=1)
            self.last_edge_fraction = float(edge.mean())
        if fast:
            img = np.empty((h, w, 3), dtype=np.uint8)
            rows_per_band = max(1, MAX_RAYS_PER_BAND // w)
            none = np.zeros((0, 0, 3), dtype=np.float32)
            if noise_sigma > 0:
                rng = rng if rng is not None else np.random.default_rng(0)
            lut = 255.0 * np.linspace(0.0, 1.0, TONE_LUT + 1) ** (1.0 / self.lighting.gamma)
            for r0 in range(0, h, rows_per_band):
                r1 = min(h, r0 + rows_per_band)
                # float32 draws, band by band (a third of the cost of float64 normals)
                noise = rng.standard_normal((r1 - r0, w, 3), dtype=np.float32) \
                    if noise_sigma > 0 else none
                _tone(radiance[r0:r1], np.float32(1.0 / self.lighting.gamma), lut, noise,
                      np.float32(noise_sigma), img[r0:r1])
            return img, (fg if want_coverage else None)
        img = 255.0 * np.power(np.clip(radiance, 0.0, 1.0), 1.0 / self.lighting.gamma)
        if noise_sigma > 0:
            rng = rng if rng is not None else np.random.default_rng(0)
            img += rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return img[:, :, ::-1].copy(), (fg if want_coverage else None)

    @staticmethod
    def _unproject(model: CameraModel, uv: np.ndarray) -> np.ndarray:
        """(N, 3) float32 unit camera rays through pixel positions ``uv`` (N, 2)
        (``model.unproject`` compiled; a subclass may have another lens model)."""
        if not (HAVE_NUMBA and type(model) is CameraModel):
            return model.unproject(uv).astype(np.float32)
        out = np.empty((len(uv), 3), dtype=np.float32)
        _unproject_uv(np.ascontiguousarray(uv, dtype=float), float(model.f), float(model.fy),
                      float(model.cu), float(model.cv), float(model.d1), float(model.d2), 20,
                      out)
        return out

    def _primary_band(self, layer, centre, dirs_cam, rot, rz, light_w, moving, cull, rad, fg,
                      key, foot) -> None:
        """Pixel-centre rays of one band into ``rad`` (N, 3), ``fg`` (N,), ``key`` (N,).

        ``_primary`` finishes the pixels that see only the backdrop with a free shadow
        ray; the rest (turntable footprint, possible shadow) go through ``_trace``.
        """
        room = cull.room
        if room is not None:
            todo = np.empty(len(foot), dtype=bool)
            _primary(dirs_cam, rot.astype(float), centre.astype(float), rz.astype(float),
                     room.planes, room.plane_tris, room.tri, room.dual, room.attr, foot,
                     light_w.astype(float), cull.basis, cull.window, cull.shadow_map,
                     self._albedo, self._klass, np.float32(self.lighting.ambient),
                     np.float32(self.lighting.key),
                     np.asarray(self.lighting.miss_colour, dtype=np.float32), rad, fg, key, todo)
            self.rays_analytic += len(foot)
            ti = np.flatnonzero(todo)
        else:
            ti = np.arange(len(foot))
        if not len(ti):
            return
        r, cls, k = self._trace(layer, centre, _mul3(dirs_cam[ti], rot), rz, light_w, moving,
                                cull, foot[ti])
        rad[ti] = r
        fg[ti] = (cls == CLASS_PLANT) | (cls == CLASS_POT)
        key[ti] = k

    def _culling(self, layer: _Layer, moving, camera: Camera, light_w, rz) -> _Cull:
        """What the fast path may skip in this view (see ``_trace``)."""
        model = camera.model
        shape = (model.height, model.width)
        verts, faces = [layer.mesh.vertices], [layer.mesh.faces]
        if moving is not None:
            lay, m, piv = moving
            # rest frame -> world: x = pivot + (X - pivot) @ S.T
            verts.append(piv + (lay.mesh.vertices - piv) @ m.T.astype(float))
            faces.append(lay.mesh.faces + len(verts[0]))
        verts = np.concatenate(verts).astype(float)
        faces = np.concatenate(faces).astype(np.int64)
        room = self._room
        if room is not None:
            ol = rz.astype(float) @ camera.pose.centre
            if not np.all(room.planes[:, :3] @ ol + room.planes[:, 3] > 0):
                room = None  # the camera is outside the room: cast the backdrop
        if not len(faces):
            return _Cull(room, np.zeros(shape, dtype=bool), np.eye(3),
                         np.array([0.0, 0.0, 0.0]), np.zeros((1, 1), dtype=bool))
        # Camera footprint: pixels within a margin of a projected triangle.  Edges bend
        # under the lens distortion by about their midpoint's offset from the chord.
        foot = np.ones(shape, dtype=bool)
        if np.all(camera.depth(verts) > 1.0):
            uv = camera.project(verts)
            a_i, b_i = faces.T[[0, 1, 2]], faces.T[[1, 2, 0]]
            mid = camera.project(0.5 * (verts[a_i.ravel()] + verts[b_i.ravel()]))
            bend = np.abs(mid - 0.5 * (uv[a_i.ravel()] + uv[b_i.ravel()])).max(1)
            bend = bend.reshape(3, -1).max(0)  # per triangle, px
            if np.all(np.isfinite(uv)) and np.all(np.isfinite(bend)):
                raster = np.zeros(shape, dtype=np.uint8)
                _raster_triangles(uv[faces], 2.0 + 2.0 * bend, raster)
                foot = raster.view(bool)
        # Shadow map: a pinhole at the light looking at the occluders.
        fwd = verts.mean(0) - light_w
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0] if abs(fwd[2]) < 0.9 else [1.0, 0.0, 0.0])
        right /= np.linalg.norm(right)
        basis = np.stack([right, np.cross(fwd, right), fwd])
        v = (verts - light_w) @ basis.T
        if np.any(v[:, 2] <= 1.0):  # the light is among the occluders: test every ray
            return _Cull(room, foot, basis, np.array([-1e9, -1e9, 0.0]),
                         np.ones((1, 1), dtype=bool))
        xy = v[:, :2] / v[:, 2:]
        lo = xy.min(0)
        scale = (SHADOW_MAP - 8) / float(max((xy.max(0) - lo).max(), 1e-9))
        origin = lo - 4.0 / scale
        shadow_map = np.zeros((SHADOW_MAP, SHADOW_MAP), dtype=np.uint8)
        # texel (cx, cy) covers [cx, cx + 1) x [cy, cy + 1): shift by half a texel so the
        # rasteriser's integer sample points are texel centres
        _raster_triangles(((xy - origin) * scale - 0.5)[faces], np.full(len(faces), 2.0),
                          shadow_map)
        return _Cull(room, foot, basis, np.array([origin[0], origin[1], scale]),
                     shadow_map.view(bool))

    def _trace(self, layer: _Layer, centre, d_w, rz, light_w, moving, cull: _Cull,
               foot: np.ndarray):
        """``_shade``'s radiance, class and key, casting only rays that can matter.

        The backdrop is hit analytically when it bounds a convex room around the
        camera (else cast as in ``_shade``); a camera ray enters Open3D's turntable
        scene only inside the view's footprint of that scene's triangles (``foot``
        (N,)), and a shadow ray is cast only where the occluders' triangles cover its
        texel in the light's shadow map.  Culled rays are rays that would miss, so the hits
        and the image are those of ``_shade``.
        """
        n_rays = len(d_w)
        c64 = centre.astype(float)
        t = np.empty(n_rays, dtype=np.float32)
        mat = np.empty(n_rays, dtype=np.int64)
        normal = np.empty((n_rays, 3), dtype=np.float32)
        room = cull.room
        if room is not None:
            _camera_rays(d_w, c64, rz.astype(float), room.planes, room.plane_tris, room.tri,
                         room.dual, room.attr, t, mat, normal)
            self.rays_analytic += n_rays
            cast_lab = np.zeros(0, dtype=np.int64)
        else:
            t[:] = np.inf
            mat[:] = -1
            normal[:] = 0.0
            cast_lab = np.arange(n_rays)
        idx = np.flatnonzero(foot)
        cands = [(self._lab, rz.T, None, cast_lab), (layer, None, None, idx)]
        if moving is not None:
            cands.append((*moving, idx))
        for lay, m, piv, sel_rays in cands:
            if not len(sel_rays):
                continue
            o, d = _into_layer(centre, d_w[sel_rays], m, piv)
            hc = self._cast(lay.scene, o.astype(np.float32), d)
            closer = hc["t_hit"] < t[sel_rays]
            if not closer.any():
                continue
            sel = sel_rays[closer]
            t[sel] = hc["t_hit"][closer]
            mat[sel] = lay.face_material[hc["primitive_ids"][closer].astype(np.int64)]
            nn = hc["primitive_normals"][closer]
            normal[sel] = nn if m is None else _mul3(nn, m.T)
        board_albedo = np.full(n_rays, -1.0, dtype=np.float32)
        for m_tex, tex in self._textured():
            ob = np.flatnonzero(mat == m_tex)
            if len(ob):
                p = centre + t[ob, None] * d_w[ob]
                if getattr(tex, "lab_frame", False):  # printed on the backdrop
                    p = p @ rz.T
                board_albedo[ob] = tex.albedo(p.astype(np.float64))
        lam = np.empty(n_rays, dtype=np.float32)
        shadow_cand = np.empty(n_rays, dtype=bool)
        _light_terms(d_w, c64, t, normal, light_w.astype(float), cull.basis, cull.window,
                     cull.shadow_map, lam, shadow_cand)
        vis = (lam > 0).astype(np.float32)
        si = np.flatnonzero(shadow_cand)
        if len(si):
            p = centre + t[si, None] * d_w[si]
            vis[si[self._occluded(layer, moving, p + 0.05 * normal[si], light_w)]] = 0.0
        rad = np.empty((n_rays, 3), dtype=np.float32)
        cls = np.empty(n_rays, dtype=np.int8)
        key = np.empty(n_rays, dtype=np.int32)
        _radiance(mat, lam, vis, board_albedo, self._albedo, self._klass,
                  np.float32(self.lighting.ambient), np.float32(self.lighting.key),
                  np.asarray(self.lighting.miss_colour, dtype=np.float32), rad, cls, key)
        return rad, cls, key

    def _occluded(self, layer: _Layer, moving, origin: np.ndarray, light_w) -> np.ndarray:
        """(N,) bool: the segment from each ``origin`` (N, 3) to the light is blocked.

        Origins are already moved 0.05 mm off their surface (float32 at ~1 m).
        """
        import open3d as o3d

        rays = np.empty((len(origin), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = light_w - origin
        occluded = layer.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0,
                                               tfar=1.0).numpy()
        if moving is not None:
            lay, m, pivot = moving
            rays[:, :3] = pivot + _mul3(origin - pivot, m)
            rays[:, 3:] = _mul3(light_w - origin, m)
            occluded |= lay.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0,
                                                  tfar=1.0).numpy()
        self.rays_cast += len(rays)
        return occluded

    def _cast(self, scene, origin: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        import open3d as o3d

        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        out = scene.cast_rays(o3d.core.Tensor(rays))
        self.rays_cast += len(dirs)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_normals")}

    def _shade(self, layer: _Layer, centre, d_w, rz, light_w, moving=None):
        """Radiance (N, 3), class (N,) and a shading key (N,) of world rays ``d_w``.

        The key changes wherever the pixel value may change abruptly (surface,
        shadow, board square); it drives the adaptive anti-aliasing.  ``moving``
        is ``(layer, S, pivot)``: geometry displaced in this view by the rotation
        ``S`` about ``pivot`` (plant sway), hit in its rest frame.
        """

        n_rays = len(d_w)
        # Each candidate: (layer, M) with rays mapped into the layer's frame by row @ M.
        cands = [(layer, None, None), (self._lab, rz.T, None)]
        if moving is not None:
            cands.append((moving[0], moving[1], moving[2]))
        t = np.full(n_rays, np.inf, dtype=np.float32)
        mat = np.full(n_rays, -1, dtype=np.int64)
        normal = np.zeros((n_rays, 3), dtype=np.float32)
        for lay, m, pivot in cands:
            o, d = _into_layer(centre, d_w, m, pivot)
            h = self._cast(lay.scene, o.astype(np.float32), d)
            closer = h["t_hit"] < t
            if not closer.any():
                continue
            t[closer] = h["t_hit"][closer]
            mat[closer] = lay.face_material[h["primitive_ids"][closer].astype(np.int64)]
            n = h["primitive_normals"][closer]
            normal[closer] = n if m is None else _mul3(n, m.T)  # back to the world frame
        hit = np.isfinite(t)
        # Thin leaves are seen from both sides: face the normal towards the camera.
        flip = np.einsum("ij,ij->i", normal, d_w) > 0
        normal[flip] *= -1.0

        idx = np.flatnonzero(hit)
        m_hit = mat[idx]
        albedo = self._albedo[m_hit]
        cls = np.full(n_rays, CLASS_BACKGROUND, dtype=np.int8)
        cls[idx] = self._klass[m_hit]
        key = np.full(n_rays, -8, dtype=np.int32)
        key[idx] = 8 * m_hit.astype(np.int32)
        p = centre + t[idx, None] * d_w[idx]
        for m_tex, tex in self._textured():
            on_board = m_hit == m_tex
            if on_board.any():
                q = p[on_board] @ rz.T if getattr(tex, "lab_frame", False) else p[on_board]
                a = tex.albedo(q.astype(np.float64))
                printed = a >= 0  # a texture may leave parts of its surface unprinted (-1)
                sel = np.flatnonzero(on_board)[printed]
                albedo[sel] = a[printed, None]
                key[idx[sel]] += 4 * (a[printed] < 0.4)
        n_hit = normal[idx]
        to_light = light_w - p
        dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
        lam = np.einsum("ij,ij->i", n_hit, to_light) / np.maximum(dist, 1e-6)
        lit = lam > 0
        vis = np.zeros(len(idx), dtype=np.float32)
        if lit.any():
            occluded = self._occluded(layer, moving, p[lit] + 0.05 * n_hit[lit], light_w)
            vis[lit] = (~occluded).astype(np.float32)
        key[idx] += 2 * (vis > 0)
        light = self.lighting.ambient + self.lighting.key * np.clip(lam, 0.0, None) * vis
        rad = np.empty((n_rays, 3), dtype=np.float32)
        rad[:] = self.lighting.miss_colour
        rad[idx] = albedo * light[:, None]
        return rad, cls, key


def _into_layer(centre, d, m, pivot):
    """Ray origin and directions in a layer's frame (rotation ``m`` about ``pivot``, if any)."""
    if m is None:
        return centre, d
    if pivot is None:
        return centre @ m, _mul3(d, m)
    return pivot + (centre - pivot) @ m, _mul3(d, m)


def _mul3(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``a @ m`` for (N, 3) x (3, 3) float32 (einsum: much faster than matmul for this shape)."""
    return np.einsum("ij,jk->ik", a, m, dtype=np.float32)


# --------------------------------------------------------------------------- fast path kernels
# The fast path (``Renderer.fast``, the default) gives the hits and shading of ``_shade``
# but skips work that cannot change a pixel: the lab backdrop is intersected analytically
# (a convex room seen from inside: the ray leaves through one plane), camera rays enter
# Open3D's turntable scene only inside the view's footprint of its triangles (grown by a
# margin), and shadow rays are cast only where the occluders' triangles cover the texel of
# a shadow map seen from the light.  Serial kernels that release the GIL: the acquisition
# renders its cameras in parallel threads, so each kernel runs on one core.
try:
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba ships with the project's environment
    HAVE_NUMBA = False

if HAVE_NUMBA:
    _jit = njit(cache=True, nogil=True, error_model="numpy")

    @_jit
    def _room_hit(o0, o1, o2, l0, l1, l2, planes, dist, plane_tris, tri, dual):
        """Backdrop hit ``(t, triangle, plane)`` of the lab ray ``o + t l`` (-1: miss).

        The backdrop bounds a convex room around the camera: the ray leaves it
        through the nearest plane it faces (``planes`` (P, 4): unit normal towards
        the room, offset ``n . x + offset = 0``), and hits the backdrop iff that point
        lies in one of the plane's triangles (``plane_tris`` (P, k), -1 padded);
        otherwise it left through an open side and nothing else can be hit.
        ``dist`` (P,): distance of ``o`` from each plane (> 0 in the room).
        """
        # t_k = dist_k / -den_k; compared by cross-multiplication (no division per plane)
        best_num, best_den = 1.0, 0.0
        best_k = -1
        for k in range(planes.shape[0]):
            den = -(planes[k, 0] * l0 + planes[k, 1] * l1 + planes[k, 2] * l2)
            if den > 0.0 and (best_k < 0 or dist[k] * best_den < best_num * den):
                best_num, best_den = dist[k], den
                best_k = k
        if best_k < 0:
            return np.inf, -1, -1
        best = best_num / best_den
        p0, p1, p2 = o0 + best * l0, o1 + best * l1, o2 + best * l2
        # At a seam between two planes the point is on both: a hair's tolerance.
        # Barycentric (u, v) = (dual[j, 0] . q, dual[j, 1] . q), q = p - corner 0.
        for s in range(plane_tris.shape[1]):
            j = plane_tris[best_k, s]
            if j < 0:
                continue
            q0, q1, q2 = p0 - tri[j, 0, 0], p1 - tri[j, 0, 1], p2 - tri[j, 0, 2]
            u = dual[j, 0, 0] * q0 + dual[j, 0, 1] * q1 + dual[j, 0, 2] * q2
            v = dual[j, 1, 0] * q0 + dual[j, 1, 1] * q1 + dual[j, 1, 2] * q2
            if u >= -1e-7 and v >= -1e-7 and u + v <= 1.0 + 1e-7:
                return best, j, best_k
        return np.inf, -1, -1

    @_jit
    def _lambert(centre, t, d0, d1, d2, n0, n1, n2, light, basis, window, shadow_map):
        """Lambert term at ``centre + t d`` with the normal turned towards the camera,
        the turned normal, and whether the shadow ray may be blocked.

        ``shadow_map`` is a pinhole view from the light (``basis`` (3, 3) rows: right,
        down, forward) where every occluder triangle is filled (grown by 2 texels);
        ``window = (x0, y0, scale)`` maps ``(x/z, y/z)`` to its texels.  All points of
        the segment from a surface point to the light fall in one texel, so an empty
        texel proves the shadow ray free.
        """
        if n0 * d0 + n1 * d1 + n2 * d2 > 0:
            n0, n1, n2 = -n0, -n1, -n2
        p0 = np.float32(centre[0] + t * d0)
        p1 = np.float32(centre[1] + t * d1)
        p2 = np.float32(centre[2] + t * d2)
        v0, v1, v2 = light[0] - p0, light[1] - p1, light[2] - p2
        dist = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        lam = (n0 * v0 + n1 * v1 + n2 * v2) / max(dist, 1e-6)
        cand = False
        if lam > 0:
            z = -(basis[2, 0] * v0 + basis[2, 1] * v1 + basis[2, 2] * v2)
            if z > 0.0:  # else behind the light's image plane: no occluder there
                iz = 1.0 / z
                x = -(basis[0, 0] * v0 + basis[0, 1] * v1 + basis[0, 2] * v2) * iz
                y = -(basis[1, 0] * v0 + basis[1, 1] * v1 + basis[1, 2] * v2) * iz
                cx = int(np.floor((x - window[0]) * window[2]))
                cy = int(np.floor((y - window[1]) * window[2]))
                cand = (0 <= cx < shadow_map.shape[1] and 0 <= cy < shadow_map.shape[0]
                        and shadow_map[cy, cx])
        return lam, n0, n1, n2, cand

    @_jit
    def _camera_rays(d_w, centre, rz, planes, plane_tris, tri, dual, tri_attr, t_out, mat_out,
                     n_out):
        """Backdrop hit of each world ray ``(centre, d_w[i])`` (lab frame ``rz``):
        t (inf: miss), material (-1: miss), world normal."""
        o0 = rz[0, 0] * centre[0] + rz[0, 1] * centre[1] + rz[0, 2] * centre[2]
        o1 = rz[1, 0] * centre[0] + rz[1, 1] * centre[1] + rz[1, 2] * centre[2]
        o2 = rz[2, 0] * centre[0] + rz[2, 1] * centre[1] + rz[2, 2] * centre[2]
        dist = planes[:, 0] * o0 + planes[:, 1] * o1 + planes[:, 2] * o2 + planes[:, 3]
        for i in range(d_w.shape[0]):
            d0, d1, d2 = d_w[i, 0], d_w[i, 1], d_w[i, 2]
            t, j, k = _room_hit(o0, o1, o2, rz[0, 0] * d0 + rz[0, 1] * d1 + rz[0, 2] * d2,
                                rz[1, 0] * d0 + rz[1, 1] * d1 + rz[1, 2] * d2,
                                rz[2, 0] * d0 + rz[2, 1] * d1 + rz[2, 2] * d2,
                                planes, dist, plane_tris, tri, dual)
            t_out[i] = t
            mat_out[i] = tri_attr[j] if j >= 0 else -1
            for ax in range(3):  # lab normal back to the world frame: n_w = n_lab @ rz
                n_out[i, ax] = 0.0 if j < 0 else (planes[k, 0] * rz[0, ax] + planes[k, 1]
                                                  * rz[1, ax] + planes[k, 2] * rz[2, ax])

    @_jit
    def _light_terms(d_w, centre, t, normal, light, basis, window, shadow_map, lam_out,
                     shadow_cand):
        """Lambert term of each hit (normal turned towards the camera, in place) and
        whether its shadow ray may be blocked (``_lambert``)."""
        for i in range(d_w.shape[0]):
            lam_out[i] = 0.0
            shadow_cand[i] = False
            if not np.isfinite(t[i]):
                continue
            lam, n0, n1, n2, cand = _lambert(centre, t[i], d_w[i, 0], d_w[i, 1], d_w[i, 2],
                                             normal[i, 0], normal[i, 1], normal[i, 2], light,
                                             basis, window, shadow_map)
            normal[i, 0], normal[i, 1], normal[i, 2] = n0, n1, n2
            lam_out[i] = lam
            shadow_cand[i] = cand

    @_jit
    def _primary(dirs_cam, rot, centre, rz, planes, plane_tris, tri, dual, tri_attr, foot, light,
                 basis, window, shadow_map, albedo, klass, ambient, key_light, miss, rad, fg,
                 key, todo):
        """One band of pixel-centre rays, finished where only the backdrop is involved.

        A pixel outside the turntable scene's footprint whose shadow ray is provably
        free sees the backdrop (or nothing) and is shaded here exactly as in
        ``_radiance``; every other pixel is flagged in ``todo`` for ``_trace``.
        Writes ``rad`` (N, 3), ``fg`` (N,) and ``key`` (N,) of the finished pixels.
        """
        o0 = rz[0, 0] * centre[0] + rz[0, 1] * centre[1] + rz[0, 2] * centre[2]
        o1 = rz[1, 0] * centre[0] + rz[1, 1] * centre[1] + rz[1, 2] * centre[2]
        o2 = rz[2, 0] * centre[0] + rz[2, 1] * centre[1] + rz[2, 2] * centre[2]
        dist = planes[:, 0] * o0 + planes[:, 1] * o1 + planes[:, 2] * o2 + planes[:, 3]
        for i in range(dirs_cam.shape[0]):
            todo[i] = foot[i]
            if foot[i]:
                continue
            c0, c1, c2 = dirs_cam[i, 0], dirs_cam[i, 1], dirs_cam[i, 2]
            d0 = np.float32(c0 * rot[0, 0] + c1 * rot[1, 0] + c2 * rot[2, 0])
            d1 = np.float32(c0 * rot[0, 1] + c1 * rot[1, 1] + c2 * rot[2, 1])
            d2 = np.float32(c0 * rot[0, 2] + c1 * rot[1, 2] + c2 * rot[2, 2])
            t, j, k = _room_hit(o0, o1, o2, rz[0, 0] * d0 + rz[0, 1] * d1 + rz[0, 2] * d2,
                                rz[1, 0] * d0 + rz[1, 1] * d1 + rz[1, 2] * d2,
                                rz[2, 0] * d0 + rz[2, 1] * d1 + rz[2, 2] * d2,
                                planes, dist, plane_tris, tri, dual)
            fg[i] = 0.0
            if j < 0:
                rad[i, 0], rad[i, 1], rad[i, 2] = miss[0], miss[1], miss[2]
                key[i] = -8
                continue
            n0 = planes[k, 0] * rz[0, 0] + planes[k, 1] * rz[1, 0] + planes[k, 2] * rz[2, 0]
            n1 = planes[k, 0] * rz[0, 1] + planes[k, 1] * rz[1, 1] + planes[k, 2] * rz[2, 1]
            n2 = planes[k, 0] * rz[0, 2] + planes[k, 1] * rz[1, 2] + planes[k, 2] * rz[2, 2]
            lam, n0, n1, n2, cand = _lambert(centre, np.float32(t), d0, d1, d2, np.float32(n0),
                                             np.float32(n1), np.float32(n2), light, basis,
                                             window, shadow_map)
            if cand:
                todo[i] = True
                continue
            m = tri_attr[j]
            vis = np.float32(1.0) if lam > 0 else np.float32(0.0)
            lit = np.float32(ambient + key_light * max(np.float32(lam), np.float32(0.0)) * vis)
            rad[i, 0] = albedo[m, 0] * lit
            rad[i, 1] = albedo[m, 1] * lit
            rad[i, 2] = albedo[m, 2] * lit
            key[i] = 8 * m + (2 if vis > 0 else 0)
            fg[i] = np.float32(1.0) if klass[m] == CLASS_PLANT or klass[m] == CLASS_POT \
                else np.float32(0.0)

    @_jit
    def _radiance(mat, lam, vis, board_albedo, albedo, klass, ambient, key_light, miss,
                  rad, cls, key):
        """Radiance (N, 3), class and shading key from material, Lambert term, visibility."""
        for i in range(mat.shape[0]):
            m = mat[i]
            if m < 0:
                rad[i, 0], rad[i, 1], rad[i, 2] = miss[0], miss[1], miss[2]
                cls[i] = 0
                key[i] = -8
                continue
            k = 8 * m
            light = np.float32(ambient + key_light * max(lam[i], np.float32(0.0)) * vis[i])
            if board_albedo[i] >= 0:
                a = board_albedo[i]
                rad[i, 0] = a * light
                rad[i, 1] = a * light
                rad[i, 2] = a * light
                if a < 0.4:
                    k += 4
            else:
                rad[i, 0] = albedo[m, 0] * light
                rad[i, 1] = albedo[m, 1] * light
                rad[i, 2] = albedo[m, 2] * light
            if vis[i] > 0:
                k += 2
            cls[i] = klass[m]
            key[i] = k

    @_jit
    def _edges(key, out):
        """Pixels whose 3 x 3 neighbourhood (clamped at the border) holds two keys."""
        h, w = key.shape
        for r in range(h):
            for c in range(w):
                k = key[r, c]
                e = False
                for rr in range(max(r - 1, 0), min(r + 2, h)):
                    for cc in range(max(c - 1, 0), min(c + 2, w)):
                        if key[rr, cc] != k:
                            e = True
                out[r, c] = e

    @_jit
    def _raster_triangles(tri, margins, out):
        """Set every sample ``(x, y)`` (integer coordinates, ``out[y, x]``) within
        ``margins[i]`` of a triangle ``tri[i]`` (T, 3, 2) (a conservative superset: per
        row, the triangle's x-range over ``y +- margin``, widened by ``margin``)."""
        h, w = out.shape
        for i in range(tri.shape[0]):
            margin = margins[i]
            ys = (tri[i, 0, 1], tri[i, 1, 1], tri[i, 2, 1])
            r0 = max(0, int(np.floor(min(ys) - margin)))
            r1 = min(h - 1, int(np.ceil(max(ys) + margin)))
            for r in range(r0, r1 + 1):
                y0, y1 = r - margin, r + margin
                lo, hi = np.inf, -np.inf
                for e in range(3):
                    xa, ya = tri[i, e, 0], tri[i, e, 1]
                    xb, yb = tri[i, (e + 1) % 3, 0], tri[i, (e + 1) % 3, 1]
                    if y0 <= ya <= y1:
                        lo, hi = min(lo, xa), max(hi, xa)
                    if ya != yb:
                        for yy in (y0, y1):
                            if min(ya, yb) <= yy <= max(ya, yb):
                                x = xa + (yy - ya) * (xb - xa) / (yb - ya)
                                lo, hi = min(lo, x), max(hi, x)
                if lo > hi:
                    continue
                c0 = max(0, int(np.ceil(lo - margin)))
                c1 = min(w - 1, int(np.floor(hi + margin)))
                for c in range(c0, c1 + 1):
                    out[r, c] = 1

    @_jit
    def _unproject_uv(uv, f, fy, cu, cv, d1, d2, iterations, out):
        """Unit camera rays through pixel positions ``uv`` (N, 2) (the fixed-point
        inversion of ``CameraModel.undistort_points``)."""
        for i in range(uv.shape[0]):
            xd = (uv[i, 0] - cu) / f
            yd = (uv[i, 1] - cv) / fy
            x, y = xd, yd
            for _ in range(iterations):
                r2 = x * x + y * y
                s = 1.0 + d1 * r2 + d2 * r2 * r2
                x, y = xd / s, yd / s
            nrm = np.sqrt(x * x + y * y + 1.0)
            out[i, 0] = x / nrm
            out[i, 1] = y / nrm
            out[i, 2] = 1.0 / nrm

    @_jit
    def _tone(rad, inv_gamma, lut, noise, sigma, out):
        """8-bit BGR of linear radiance: gamma, additive noise ``sigma x noise``, rounding.

        ``lut[i] = 255 (i / n) ** inv_gamma`` (n + 1 entries), interpolated linearly
        above ``16 / n`` where its error is below 1e-3 DN (exact ``pow`` below).
        """
        h, w, _ = rad.shape
        has_noise = noise.shape[0] > 0
        n = lut.shape[0] - 1
        for r in range(h):
            for c in range(w):
                for ch in range(3):
                    x = min(max(rad[r, c, ch], np.float32(0.0)), np.float32(1.0))
                    f = x * n
                    if f < 16.0:
                        y = np.float32(255.0) * np.float32(x ** inv_gamma)
                    else:
                        i = min(int(f), n - 1)
                        y = np.float32(lut[i] + (f - i) * (lut[i + 1] - lut[i]))
                    if has_noise:
                        y += sigma * noise[r, c, ch]
                    y = np.rint(y)
                    out[r, c, 2 - ch] = min(max(y, 0.0), 255.0)


def silhouette_mask(vertices: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """(H, W) bool: the pixels whose centre lies in the projection of a mesh (no rendering).

    ``vertices`` (V, 3) mm, turntable frame; ``faces`` (F, 3); ``camera`` a posed
    ``Camera``.  The exact silhouette of a closed mesh seen by that camera, at a
    thousandth of a render's cost: training data for the leaf stages
    (``scripts/train_organ_model.py``); a render's truth mask may differ on pixels the
    surface covers by about half (its anti-aliased coverage decides there).
    """
    w, h = camera.model.width, camera.model.height
    uv = camera.project(np.asarray(vertices, float))
    out = np.zeros((h, w), np.uint8)
    _raster_triangles(np.ascontiguousarray(uv[faces]), np.zeros(len(faces)), out)
    return out.view(bool)

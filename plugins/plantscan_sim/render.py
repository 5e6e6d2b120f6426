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
MAX_CACHED_RAYS = 12_000_000


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
    _layers: dict = field(default_factory=dict, init=False)
    _lab: _Layer | None = field(default=None, init=False)
    _moving: dict = field(default_factory=dict, init=False)
    _cache: dict = field(default_factory=dict, init=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False)
    rays_cast: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self._albedo = np.array([m.albedo for m in self.materials], dtype=np.float32)
        self._klass = np.array([m.klass for m in self.materials], dtype=np.int8)
        for role, mesh in self.world.items():
            self._layers[role] = _Layer(mesh, _raycasting_scene(mesh), mesh.face_attr)
        self._lab = _Layer(self.lab, _raycasting_scene(self.lab), self.lab.face_attr)
        for role, mesh in self.moving.items():
            self._moving[role] = _Layer(mesh, _raycasting_scene(mesh), mesh.face_attr)

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
            dirs = model.unproject(np.stack([uu.ravel(), vv.ravel()], 1)).astype(np.float32)
            bands.append((r0, r1, dirs))
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
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """Render ``role`` seen by ``camera`` (world frame, turntable at ``angle_deg``).

        Adaptive anti-aliasing: one ray through every pixel centre first; every
        pixel whose 3 x 3 neighbourhood is not uniform (another surface, a shadow
        edge or a board square edge) is rendered again with ``ss x ss`` rays and
        box-filtered.  Uniform pixels are exact with one ray.  ``adaptive=False``
        casts ``ss x ss`` rays through every pixel (the plain reference).
        ``sway = (S, pivot)`` displaces the role's moving geometry (the plant) by
        the rotation ``S`` (3, 3) about ``pivot`` (3,) mm, world frame.

        Returns
        -------
        image : (H, W, 3) uint8, BGR
        coverage : (H, W) float32 in [0, 1] or None
            Fraction of each pixel's samples whose first hit is plant or pot.
        """
        from scipy.ndimage import maximum_filter, minimum_filter

        model = camera.model
        w, h = model.width, model.height
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
        radiance = np.empty((h, w, 3), dtype=np.float32)
        fg = np.empty((h, w), dtype=np.float32)
        key = np.empty((h, w), dtype=np.int32)
        if adaptive or ss == 1:
            for r0, r1, dirs_cam in self._centre_bands(model):
                rad, cls, k = self._shade(layer, centre, _mul3(dirs_cam, rot), rz, light_w,
                                          moving)
                radiance[r0:r1] = rad.reshape(r1 - r0, w, 3)
                fg[r0:r1] = ((cls == CLASS_PLANT) | (cls == CLASS_POT)).reshape(r1 - r0, w)
                key[r0:r1] = k.reshape(r1 - r0, w)
        if ss > 1:
            if adaptive:
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
                dirs_cam = model.unproject(uv).astype(np.float32)
                rad, cls, _ = self._shade(layer, centre, _mul3(dirs_cam, rot), rz, light_w,
                                          moving)
                radiance[r, c] = rad.reshape(len(r), n_ss, 3).mean(axis=1)
                fg[r, c] = ((cls == CLASS_PLANT) | (cls == CLASS_POT)).reshape(
                    len(r), n_ss).mean(axis=1)
            self.last_edge_fraction = float(edge.mean())
        img = 255.0 * np.power(np.clip(radiance, 0.0, 1.0), 1.0 / self.lighting.gamma)
        if noise_sigma > 0:
            rng = rng if rng is not None else np.random.default_rng(0)
            img += rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return img[:, :, ::-1].copy(), (fg if want_coverage else None)

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
        import open3d as o3d

        n_rays = len(d_w)
        # Each candidate: (layer, M) with rays mapped into the layer's frame by row @ M.
        cands = [(layer, None, None), (self._lab, rz.T, None)]
        if moving is not None:
            cands.append((moving[0], moving[1], moving[2]))
        t = np.full(n_rays, np.inf, dtype=np.float32)
        mat = np.full(n_rays, -1, dtype=np.int64)
        normal = np.zeros((n_rays, 3), dtype=np.float32)
        for lay, m, pivot in cands:
            if m is None:
                o, d = centre, d_w
            elif pivot is None:
                o, d = centre @ m, _mul3(d_w, m)
            else:
                o, d = pivot + (centre - pivot) @ m, _mul3(d_w, m)
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
        if self.board is not None:
            on_board = m_hit == self.board_material
            if on_board.any():
                a = self.board.albedo(p[on_board].astype(np.float64))
                albedo[on_board] = a[:, None]
                key[idx[on_board]] += 4 * (a < 0.4)
        n_hit = normal[idx]
        to_light = light_w - p
        dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
        lam = np.einsum("ij,ij->i", n_hit, to_light) / np.maximum(dist, 1e-6)
        lit = lam > 0
        vis = np.zeros(len(idx), dtype=np.float32)
        if lit.any():
            origin = p[lit] + 0.05 * n_hit[lit]  # leave the surface (float32 at ~1 m)
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
            vis[lit] = (~occluded).astype(np.float32)
        key[idx] += 2 * (vis > 0)
        light = self.lighting.ambient + self.lighting.key * np.clip(lam, 0.0, None) * vis
        rad = np.empty((n_rays, 3), dtype=np.float32)
        rad[:] = self.lighting.miss_colour
        rad[idx] = albedo * light[:, None]
        return rad, cls, key


def _mul3(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``a @ m`` for (N, 3) x (3, 3) float32 (einsum: much faster than matmul for this shape)."""
    return np.einsum("ij,jk->ik", a, m, dtype=np.float32)

"""Printed patterns on the turntable plate, for calibrating from the plant photos.

A plain plate and a plant with few features leave structure from motion with
nothing to match; a random-dot print on the plate gives every view hundreds of
sharp, unique blobs that turn with the plant (``docs/calibration.md``, "what to
print").  The pattern is a function of the point on the plate, so it is exact at
any resolution and needs no texture image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURES = ("plain", "random-dots", "aruco-dots")

# The marker prints: OpenCV's 4x4 dictionary (6 x 6 cells with the black border), black on
# white.  ``aruco-dots``: one row of markers round the plate's rim and one round the pot
# carrier, numbered from 0 along the rim then the carrier; the ``aruco`` backdrop goes on
# from there (BACKDROP_FIRST_ID).  DICT_4X4_50 is the first 50 of DICT_4X4_250.
MARKER_DICTIONARY = "DICT_4X4_250"
BACKDROP_FIRST_ID = 50
BACKDROP_TEXTURES = ("plain", "aruco")
MARKER_CELLS = 6


def _hash01(i: np.ndarray, j: np.ndarray, seed: int, salt: int) -> np.ndarray:
    """Uniform [0, 1) per integer cell ``(i, j)`` (a 32-bit integer hash, vectorised)."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) \
        ^ ((seed * 83492791 + salt * 2654435761) & 0xFFFFFFFF)
    h &= 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x45D9F3B) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x45D9F3B) & 0xFFFFFFFF
    h ^= h >> 16
    return h.astype(np.float64) / 4294967296.0


@dataclass(frozen=True)
class DotTexture:
    """Random light dots on the top and the rim of a round plate (world frame, mm).

    The top (``z`` within 0.5 mm of ``z_top_mm``) is tiled in ``x, y``; the rim
    in arc length and height.  Each cell of side ``pitch_mm`` holds one dot of
    random radius (0.18-0.38 pitch) at a random place wholly inside the cell, so
    neighbouring dots never merge and no two patches look alike.

    Attributes
    ----------
    radius_mm : float, plate radius
    z_top_mm : float, height of the plate's top face
    pitch_mm : float, cell side
    base, dot : float, albedo of the plate and of the dots (0..1)
    seed : int
    """

    radius_mm: float
    z_top_mm: float = 0.0
    pitch_mm: float = 10.0
    base: float = 0.2
    dot: float = 0.75
    seed: int = 0

    def albedo(self, p_world: np.ndarray) -> np.ndarray:
        """(N,) float32 albedo of plate points ``p_world`` (N, 3) mm, world frame."""
        p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        top = np.abs(p[:, 2] - self.z_top_mm) < 0.5
        a = np.where(top, p[:, 0],
                     self.radius_mm * np.arctan2(p[:, 1], p[:, 0]))
        b = np.where(top, p[:, 1], p[:, 2])
        s = self.pitch_mm
        i, j = np.floor(a / s), np.floor(b / s)
        # The rim's arc length wraps: its last cell may be short, which only clips a dot.
        r = s * (0.18 + 0.2 * _hash01(i, j, self.seed, 1))
        cx = (i * s) + r + (s - 2 * r) * _hash01(i, j, self.seed, 2)
        cy = (j * s) + r + (s - 2 * r) * _hash01(i, j, self.seed, 3)
        on = (a - cx) ** 2 + (b - cy) ** 2 <= r * r
        return np.where(on, self.dot, self.base).astype(np.float32)


@dataclass(frozen=True)
class MarkerBand:
    """A row of ArUco markers printed round a cylinder (world frame, mm), on a white band.

    Marker ``k`` (id ``first_id + k``) is centred at azimuth ``(k + 0.5) 360 / count``
    degrees and at height ``(z_lo + z_hi) / 2``; its image's top row is up (+Z) and its
    columns run with the azimuth, so it reads unmirrored from outside.  The white band
    holds a quiet zone of one marker cell above and below the markers; elsewhere the
    surface is left to ``under`` (the dot print).

    Attributes
    ----------
    radius_mm : float
    z_lo_mm, z_hi_mm : float, the white band's bottom and top
    marker_mm : float, side of a marker (its black border included)
    count : int, markers round the cylinder
    first_id : int
    under : DotTexture, the print outside the band
    """

    radius_mm: float
    z_lo_mm: float
    z_hi_mm: float
    marker_mm: float
    count: int
    first_id: int
    under: DotTexture
    white: float = 0.85
    black: float = 0.04

    def bits(self) -> np.ndarray:
        """(count, 6, 6) bool: True where a marker cell is white."""
        return _marker_bits(self.first_id, self.count)

    def albedo(self, p_world: np.ndarray) -> np.ndarray:
        """(N,) float32 albedo of points ``p_world`` (N, 3) mm, world frame."""
        p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        out = self.under.albedo(p)
        r = np.hypot(p[:, 0], p[:, 1])
        band = (np.abs(r - self.radius_mm) < 0.5) & (p[:, 2] >= self.z_lo_mm) \
            & (p[:, 2] <= self.z_hi_mm)
        if not band.any():
            return out
        q = p[band]
        pitch = 2.0 * np.pi / self.count
        az = np.arctan2(q[:, 1], q[:, 0]) % (2.0 * np.pi)
        k = np.floor(az / pitch).astype(np.int64) % self.count
        s = self.radius_mm * (az - (k + 0.5) * pitch)         # mm along the arc
        zc = 0.5 * (self.z_lo_mm + self.z_hi_mm)
        m = self.marker_mm
        cell = m / MARKER_CELLS
        col = np.floor((s + 0.5 * m) / cell).astype(np.int64)
        row = np.floor((zc + 0.5 * m - q[:, 2]) / cell).astype(np.int64)
        inside = (col >= 0) & (col < MARKER_CELLS) & (row >= 0) & (row < MARKER_CELLS)
        val = np.full(len(q), self.white, np.float32)
        bits = self._bits_cached()
        val[inside] = np.where(bits[k[inside], row[inside], col[inside]], self.white,
                               self.black)
        out[band] = val
        return out

    def _bits_cached(self) -> np.ndarray:
        cached = _BITS.get(self)
        if cached is None:
            cached = _BITS[self] = self.bits()
        return cached


_BITS: dict = {}


def marker_bands(plate_radius_mm: float, plate_bottom_mm: float, carrier_radius_mm: float,
                 carrier_top_mm: float, dots: tuple[DotTexture, DotTexture]
                 ) -> tuple[MarkerBand, MarkerBand]:
    """The ``aruco-dots`` rows: markers of 40 mm round the middle of the plate's rim
    (plate top at z = 0, bottom at ``plate_bottom_mm``) about 17 mm apart, and of 22 mm
    round the pot carrier (z = 0 to ``carrier_top_mm``) about 9 mm apart."""
    rows = []
    first = 0
    for radius, z_lo, z_hi, side, gap, under in (
            (plate_radius_mm, plate_bottom_mm, 0.0, 40.0, 17.0, dots[0]),
            (carrier_radius_mm, 0.0, carrier_top_mm, 22.0, 9.0, dots[1])):
        quiet = side / MARKER_CELLS
        zc = 0.5 * (z_lo + z_hi)
        count = int(2.0 * np.pi * radius // (side + gap))
        rows.append(MarkerBand(radius, zc - 0.5 * side - quiet, zc + 0.5 * side + quiet, side,
                               count, first, under))
        first += count
    return rows[0], rows[1]


def plate_textures(kind: str, plate_radius_mm: float, carrier_radius_mm: float,
                   carrier_top_mm: float, pitch_mm: float, seed: int) -> list:
    """The prints on the plate and on the pot carrier (none for a plain plate).

    The plate's top alone is a plane turning about its own normal, which
    leaves a camera's focal length unobservable (the degenerate case of plane-
    based calibration); the rims and the carrier add surfaces at other depths.
    """
    if kind not in TEXTURES:
        raise ValueError(f"unknown plate texture {kind!r}; valid: {', '.join(TEXTURES)}")
    if kind == "plain":
        return []
    dots = (DotTexture(plate_radius_mm, 0.0, pitch_mm, seed=seed),
            DotTexture(carrier_radius_mm, carrier_top_mm, 0.6 * pitch_mm, seed=seed + 7919))
    if kind == "random-dots":
        return list(dots)
    return list(marker_bands(plate_radius_mm, -60.0, carrier_radius_mm, carrier_top_mm, dots))


def _marker_bits(first_id: int, count: int) -> np.ndarray:
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, MARKER_DICTIONARY))
    return np.stack([d.generateImageMarker(first_id + k, MARKER_CELLS) > 127
                     for k in range(count)])


@dataclass(frozen=True)
class BackdropMarkers:
    """ArUco markers printed on the studio backdrop (lab frame, mm): a grid on the wall
    behind the turntable and one on the floor round it.  They do not turn with the
    plate: seen from two cameras they tie the cameras to each other and cover the whole
    image, which pins the lens distortion where the plant is.

    The arm frame has +X towards the cameras (the lab turned by ``arm_azimuth_deg``);
    the wall is the plane ``x = wall_x_mm``, the floor ``z = floor_z_mm``.  A marker's
    image reads unmirrored from the cameras: on the wall its top row is up, on the floor
    towards the wall.  Outside a marker and its one-cell white margin ``albedo`` is -1
    (the backdrop's own colour).  Markers are numbered from ``first_id``, wall first.
    """

    arm_azimuth_deg: float
    wall_x_mm: float
    floor_z_mm: float
    keep_out_radius_mm: float
    marker_mm: float = 100.0
    pitch_mm: float = 170.0
    first_id: int = BACKDROP_FIRST_ID
    white: float = 0.85
    black: float = 0.04
    lab_frame: bool = True

    def layout(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) marker centres on the wall (y, z) and on the floor (x, y), arm frame."""
        g = self.pitch_mm
        wy, wz = np.meshgrid(np.arange(-6, 7) * g, 60.0 + np.arange(0, 7) * g)
        wall = np.stack([wy.ravel(), wz.ravel()], axis=1)
        fx, fy = np.meshgrid(self.wall_x_mm + 350.0 + np.arange(0, 8) * g, np.arange(-6, 7) * g)
        floor = np.stack([fx.ravel(), fy.ravel()], axis=1)
        clear = np.hypot(floor[:, 0], floor[:, 1]) > self.keep_out_radius_mm + \
            0.75 * self.marker_mm
        return wall, floor[clear]

    def albedo(self, p_lab: np.ndarray) -> np.ndarray:
        """(N,) float32 albedo of backdrop points ``p_lab`` (N, 3), lab frame; -1 off print."""
        p = np.asarray(p_lab, dtype=np.float64).reshape(-1, 3)
        a = np.radians(self.arm_azimuth_deg)
        x = np.cos(a) * p[:, 0] + np.sin(a) * p[:, 1]       # arm frame
        y = -np.sin(a) * p[:, 0] + np.cos(a) * p[:, 1]
        z = p[:, 2]
        out = np.full(len(p), -1.0, np.float32)
        wall, floor = self.layout()
        bits = self._bits()
        m, cell = self.marker_mm, self.marker_mm / MARKER_CELLS
        half = 0.5 * m + cell
        for k0, centres, on, s_coord, t_coord in (
                (0, wall, np.abs(x - self.wall_x_mm) < 0.5, y, -z),
                (len(wall), floor, np.abs(z - self.floor_z_mm) < 0.5, y, x)):
            if not on.any():
                continue
            idx = np.flatnonzero(on)
            s_, t_ = s_coord[idx], t_coord[idx]
            # centres: wall (y, z) -> (s, t) = (y, -z); floor (x, y) -> (y, x)
            cs = centres[:, 0] if k0 == 0 else centres[:, 1]
            ct = -centres[:, 1] if k0 == 0 else centres[:, 0]
            for k in range(len(centres)):
                ds, dt = s_ - cs[k], t_ - ct[k]
                near = (np.abs(ds) < half) & (np.abs(dt) < half)
                if not near.any():
                    continue
                col = np.floor((ds[near] + 0.5 * m) / cell).astype(np.int64)
                row = np.floor((dt[near] + 0.5 * m) / cell).astype(np.int64)
                inside = (col >= 0) & (col < MARKER_CELLS) & (row >= 0) & (row < MARKER_CELLS)
                val = np.full(int(near.sum()), self.white, np.float32)
                val[inside] = np.where(bits[k0 + k, row[inside], col[inside]], self.white,
                                       self.black)
                out[idx[near]] = val
        return out

    def _bits(self) -> np.ndarray:
        cached = _BITS.get(self)
        if cached is None:
            wall, floor = self.layout()
            cached = _BITS[self] = _marker_bits(self.first_id, len(wall) + len(floor))
        return cached

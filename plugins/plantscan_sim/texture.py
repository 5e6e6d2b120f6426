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

TEXTURES = ("plain", "random-dots")


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


def plate_textures(kind: str, plate_radius_mm: float, carrier_radius_mm: float,
                   carrier_top_mm: float, pitch_mm: float, seed: int) -> list[DotTexture]:
    """The prints on the plate and on the pot carrier (none for a plain plate).

    The plate's top alone is a plane turning about its own normal, which
    leaves a camera's focal length unobservable (the degenerate case of plane-
    based calibration); the rims and the carrier add surfaces at other depths.
    """
    if kind not in TEXTURES:
        raise ValueError(f"unknown plate texture {kind!r}; valid: {', '.join(TEXTURES)}")
    if kind == "plain":
        return []
    return [DotTexture(plate_radius_mm, 0.0, pitch_mm, seed=seed),
            DotTexture(carrier_radius_mm, carrier_top_mm, 0.6 * pitch_mm, seed=seed + 7919)]

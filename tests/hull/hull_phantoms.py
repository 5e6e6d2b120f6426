"""Analytic phantoms and cameras for the hull tests: exact masks by ray casting.

Masks are rendered by intersecting every pixel's ray (through the camera
model's own distortion inversion) with convex analytic solids, so the visual
hull's truth is known without running any plantscan code under test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plantscan_core.data import (
    Calibration,
    CameraModel,
    Pose,
    Silhouette,
    Silhouettes,
    ViewRecord,
)


@dataclass
class Sphere:
    centre: tuple[float, float, float]
    radius: float

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = o - np.asarray(self.centre)
        b = np.sum(oc * d, axis=1)
        c = np.sum(oc * oc, axis=1) - self.radius**2
        disc = b * b - c
        return (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p - np.asarray(self.centre), axis=1) <= self.radius


@dataclass
class Box:
    """An oriented box: centre, 3 orthonormal axes (rows) and half extents (mm)."""

    centre: tuple[float, float, float]
    axes: np.ndarray
    half: tuple[float, float, float]

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ax = np.asarray(self.axes, dtype=float)
        oc = (o - np.asarray(self.centre)) @ ax.T
        dd = d @ ax.T
        half = np.asarray(self.half)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - oc) / dd
            t2 = (half - oc) / dd
        tmin = np.nanmax(np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)), axis=1)
        tmax = np.nanmin(np.where(np.isnan(t2), np.inf, np.maximum(t1, t2)), axis=1)
        # A ray parallel to a slab misses unless its origin is inside the slab.
        parallel_out = np.any((dd == 0) & (np.abs(oc) > half), axis=1)
        return (tmax >= np.maximum(tmin, 0)) & ~parallel_out

    def contains(self, p: np.ndarray) -> np.ndarray:
        q = (p - np.asarray(self.centre)) @ np.asarray(self.axes, dtype=float).T
        return np.all(np.abs(q) <= np.asarray(self.half), axis=1)


@dataclass
class Cylinder:
    """Vertical (along +Z) tapered cylinder on the turntable axis."""

    z0: float
    z1: float
    r0: float
    r1: float

    def contains(self, p: np.ndarray) -> np.ndarray:
        t = (p[:, 2] - self.z0) / (self.z1 - self.z0)
        r = self.r0 + t * (self.r1 - self.r0)
        return (t >= 0) & (t <= 1) & (np.hypot(p[:, 0], p[:, 1]) <= r)

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        # Side: x^2 + y^2 = (a + b z)^2 along the ray (a quadratic in t); caps: z = z0, z1.
        b = (self.r1 - self.r0) / (self.z1 - self.z0)
        a = self.r0 - b * self.z0
        ra = a + b * o[:, 2]
        rb = b * d[:, 2]
        qa = d[:, 0] ** 2 + d[:, 1] ** 2 - rb**2
        qb = 2 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] - ra * rb)
        qc = o[:, 0] ** 2 + o[:, 1] ** 2 - ra**2
        disc = qb * qb - 4 * qa * qc
        hit = np.zeros(len(o), dtype=bool)
        ok = (disc >= 0) & (np.abs(qa) > 1e-12)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        for sign in (-1.0, 1.0):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (-qb + sign * sq) / (2 * qa)
            z = o[:, 2] + t * d[:, 2]
            hit |= ok & (t > 0) & (z >= self.z0) & (z <= self.z1) & (ra + rb * t >= 0)
        for zc, rc in ((self.z0, self.r0), (self.z1, self.r1)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (zc - o[:, 2]) / d[:, 2]
            x = o[:, 0] + t * d[:, 0]
            y = o[:, 1] + t * d[:, 1]
            hit |= (t > 0) & (x * x + y * y <= rc * rc)
        return hit


def ring_calibration(f: float = 400.0, size=(320, 240), distance: float = 400.0,
                     elevations=(0.0, 30.0), d1: float = -0.05, d2: float = 0.0):
    """A rig of one camera per elevation, looking at (0, 0, 0) from ``distance`` mm."""
    w, h = size
    model = CameraModel(f=f, cu=(w - 1) / 2 + 3.0, cv=(h - 1) / 2 - 2.0, d1=d1, d2=d2,
                        width=w, height=h)
    poses = {}
    for ti, el in enumerate(elevations):
        e = np.radians(el)
        centre = (distance * np.cos(e), 0.0, distance * np.sin(e))
        poses[("cam0", ti)] = Pose.look_at(centre, (0.0, 0.0, 0.0))
    return Calibration(models={"cam0": model}, poses=poses,
                       tilts_deg={ti: float(el) for ti, el in enumerate(elevations)})


def views(n_angles: int, elevations=(0.0, 30.0)) -> list[ViewRecord]:
    out = []
    for ti, el in enumerate(elevations):
        for a in range(n_angles):
            ang = 360.0 * a / n_angles
            out.append(ViewRecord(index=len(out), role="plant", camera="cam0", tilt_index=ti,
                                  tilt_deg=float(el), angle_index=a, commanded_angle_deg=ang,
                                  measured_angle_deg=None,
                                  file=f"images/plant/cam0_t{ti:02d}_a{a:03d}.png"))
    return out


def render(calibration: Calibration, view_list, solids) -> Silhouettes:
    """Exact silhouettes of the union of ``solids`` (each with ``hit(o, d)``)."""
    items = []
    for v in view_list:
        cam = calibration.camera_for_view(v)
        w, h = cam.model.width, cam.model.height
        uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
        o, d = cam.rays(uv)
        hit = np.zeros(len(uv), dtype=bool)
        for s in solids:
            hit |= s.hit(np.asarray(o), d)
        items.append(Silhouette(v, hit.reshape(h, w)))
    return Silhouettes(items)

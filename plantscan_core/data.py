"""Typed data that crosses stage boundaries.

Units everywhere: millimetres (mm) and degrees (deg) for geometry and angles,
pixels (px) for image coordinates.  The *world frame* is the turntable frame:
origin on the rotation axis at the top of the turntable plate, +Z up along the
axis, right-handed, attached to the plate (so the plant does not move in it).

Image arrays are ``(H, W, 3) uint8`` in OpenCV's BGR order; masks are
``(H, W) bool``; pixel ``(u, v)`` is column ``u``, row ``v`` with the centre of
the top-left pixel at ``(0, 0)``.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from plantscan_core.errors import DataError

ROLES = ("calibration", "background", "plant")


# --------------------------------------------------------------------------- rotations
def rotation_x(deg: float) -> np.ndarray:
    """(3, 3) rotation about +X by ``deg`` degrees (right-handed)."""
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(deg: float) -> np.ndarray:
    """(3, 3) rotation about +Y by ``deg`` degrees (right-handed)."""
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_z(deg: float) -> np.ndarray:
    """(3, 3) rotation about +Z by ``deg`` degrees (right-handed)."""
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_about_axis(direction: Sequence[float], deg: float) -> np.ndarray:
    """(3, 3) rotation by ``deg`` about the unit vector ``direction`` (Rodrigues)."""
    k = np.asarray(direction, dtype=float)
    k = k / np.linalg.norm(k)
    a = math.radians(deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle in degrees of the rotation matrix ``r`` (0..180)."""
    c = (np.trace(r) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


# --------------------------------------------------------------------------- camera model
@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of the seed's camera model: pinhole + two radial terms.

    A point with camera coordinates ``(X, Y, Z)`` (mm, +Z forward, +X right,
    +Y down) has normalised coordinates ``x = X/Z, y = Y/Z``; with
    ``r2 = x*x + y*y`` and ``s = 1 + d1*r2 + d2*r2*r2`` its pixel is
    ``u = f*x*s + cu``, ``v = f*aspect*y*s + cv``.

    Attributes
    ----------
    f : float, px
        Focal length.
    cu, cv : float, px
        Principal point.
    d1, d2 : float
        Radial distortion coefficients (dimensionless, on normalised coords).
    width, height : int, px
        Image size.
    aspect : float
        Pixel aspect ratio fy / fx (1.0 for square pixels, the seed's model;
        real lenses calibrate to within ~1e-3 of it).
    """

    f: float
    cu: float
    cv: float
    d1: float = 0.0
    d2: float = 0.0
    width: int = 0
    height: int = 0
    aspect: float = 1.0

    @property
    def fy(self) -> float:
        """Vertical focal length, px (``f * aspect``)."""
        return self.f * self.aspect

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the matrix
        """(3, 3) float64 pinhole matrix (no distortion)."""
        return np.array([[self.f, 0.0, self.cu], [0.0, self.fy, self.cv], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion vector ``(k1, k2, p1, p2, k3)`` of this model."""
        return np.array([self.d1, self.d2, 0.0, 0.0, 0.0])

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalised undistorted ``(N, 2)`` coords to pixels ``(N, 2)``."""
        xy = np.asarray(xy, dtype=float)
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        s = 1.0 + self.d1 * r2 + self.d2 * r2 * r2
        return xy * s * np.array([self.f, self.fy]) + np.array([self.cu, self.cv])

    def undistort_points(self, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels ``(N, 2)`` to normalised undistorted coords ``(N, 2)``.

        Fixed-point inversion of the radial model; converges to < 1e-9 for the
        distortion of real lenses (|d1 r2| well below 0.5 at the image corners).
        """
        uv = np.asarray(uv, dtype=float)
        xd = (uv - np.array([self.cu, self.cv])) / np.array([self.f, self.fy])
        xy = xd.copy()
        for _ in range(iterations):
            r2 = np.sum(xy * xy, axis=-1, keepdims=True)
            xy = xd / (1.0 + self.d1 * r2 + self.d2 * r2 * r2)
        return xy

    def project_camera_points(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(N, 3)`` mm to pixels ``(N, 2)``; NaN behind the camera."""
        p = np.asarray(points_cam, dtype=float)
        z = p[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where(z > 0, p[..., :2] / z, np.nan)
        return self.distort(xy)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` to unit ray directions ``(N, 3)`` in the camera frame."""
        xy = self.undistort_points(uv)
        rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def scaled(self, factor: float) -> CameraModel:
        """The same lens seen on an image resized by ``factor`` (pixel centres kept)."""
        return CameraModel(
            f=self.f * factor,
            cu=(self.cu + 0.5) * factor - 0.5,
            cv=(self.cv + 0.5) * factor - 0.5,
            d1=self.d1,
            d2=self.d2,
            width=round(self.width * factor),
            height=round(self.height * factor),
            aspect=self.aspect,
        )

    def to_dict(self) -> dict[str, Any]:
        return {k: (float(v) if isinstance(v, float) else int(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraModel:
        keys = ("f", "cu", "cv", "d1", "d2", "width", "height", "aspect")
        return cls(**{k: d[k] for k in keys if k in d})


@dataclass(frozen=True)
class Pose:
    """Rigid transform from the world (turntable) frame to a camera frame.

    ``x_cam = R @ X_world + t``.

    Attributes
    ----------
    R : (3, 3) float64 array, rotation world -> camera
    t : (3,) float64 array, mm
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=float).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float).reshape(3))

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in the world frame, mm."""
        return -self.R.T @ self.t

    def apply(self, points_world: np.ndarray) -> np.ndarray:
        """World points ``(N, 3)`` to camera-frame points ``(N, 3)``."""
        return np.asarray(points_world, dtype=float) @ self.R.T + self.t

    def compose_world(self, m: np.ndarray) -> Pose:
        """Pose of the same camera after the world moved by rotation ``m`` about the origin.

        The returned pose maps ``X`` to ``R @ (m @ X) + t``.
        """
        return Pose(self.R @ m, self.t)

    @classmethod
    def look_at(cls, centre: Sequence[float], target: Sequence[float], up=(0.0, 0.0, 1.0)) -> Pose:
        """Camera at ``centre`` looking at ``target`` with image-up towards ``up``."""
        c = np.asarray(centre, dtype=float)
        z = np.asarray(target, dtype=float) - c
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, dtype=float))
        if np.linalg.norm(x) < 1e-9:
            raise ValueError("look_at: viewing direction is parallel to 'up'")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        r = np.stack([x, y, z])
        return cls(r, -r @ c)

    def to_dict(self) -> dict[str, Any]:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Pose:
        return cls(np.array(d["R"], dtype=float), np.array(d["t"], dtype=float))


@dataclass(frozen=True)
class Camera:
    """A posed camera: intrinsics plus world -> camera pose."""

    model: CameraModel
    pose: Pose

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points ``(N, 3)`` mm -> pixels ``(N, 2)``; NaN for points behind the camera."""
        return self.model.project_camera_points(self.pose.apply(points_world))

    def depth(self, points_world: np.ndarray) -> np.ndarray:
        """(N,) depth along the optical axis, mm."""
        return self.pose.apply(points_world)[..., 2]

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins ``(N, 3)`` and unit directions ``(N, 3)`` in the world frame."""
        d_cam = self.model.unproject(uv)
        d = d_cam @ self.pose.R
        o = np.broadcast_to(self.pose.centre, d.shape)
        return o, d

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model.to_dict(), "pose": self.pose.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        return cls(CameraModel.from_dict(d["model"]), Pose.from_dict(d["pose"]))


# --------------------------------------------------------------------------- scans
@dataclass(frozen=True)
class ViewRecord:
    """One finished image of a scan (one line of ``views.jsonl``).

    Attributes
    ----------
    index : int
        Position in capture order, 0-based.
    role : {"calibration", "background", "plant"}
    camera : str
        Camera name from the recipe.
    tilt_index : int
        Index into the protocol's tilt list.
    tilt_deg : float, deg
        Commanded tilt of the camera arm.
    angle_index : int
        Index of the turntable stop within the revolution.
    commanded_angle_deg : float, deg
        Turntable angle asked for.
    measured_angle_deg : float or None, deg
        Turntable angle read back from the axis (None when it cannot tell).
    file : str
        Image path relative to the scan folder, POSIX separators.
    captured_at : str
        ISO 8601 time stamp.
    """

    index: int
    role: str
    camera: str
    tilt_index: int
    tilt_deg: float
    angle_index: int
    commanded_angle_deg: float
    measured_angle_deg: float | None
    file: str
    captured_at: str = ""

    @property
    def angle_deg(self) -> float:
        """Best known turntable angle: measured when available, else commanded."""
        if self.measured_angle_deg is None:
            return self.commanded_angle_deg
        return self.measured_angle_deg

    @property
    def key(self) -> tuple[str, str, int, int]:
        """(role, camera, tilt_index, angle_index): what identifies a view in a protocol."""
        return (self.role, self.camera, self.tilt_index, self.angle_index)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewRecord:
        return cls(
            index=int(d["index"]),
            role=str(d["role"]),
            camera=str(d["camera"]),
            tilt_index=int(d["tilt_index"]),
            tilt_deg=float(d["tilt_deg"]),
            angle_index=int(d["angle_index"]),
            commanded_angle_deg=float(d["commanded_angle_deg"]),
            measured_angle_deg=(
                None if d.get("measured_angle_deg") is None else float(d["measured_angle_deg"])
            ),
            file=str(d["file"]),
            captured_at=str(d.get("captured_at", "")),
        )


# --------------------------------------------------------------------------- calibration
@dataclass
class TiltAxis:
    """The camera arm's tilt axis, in the world frame at turntable angle 0.

    A camera calibrated at ``reference_tilt_deg`` is moved to tilt ``phi`` by a
    rotation of ``phi - reference_tilt_deg`` about the line through ``origin``
    along ``direction``.
    """

    origin: np.ndarray
    direction: np.ndarray
    reference_tilt_index: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "origin": np.asarray(self.origin, dtype=float).tolist(),
            "direction": np.asarray(self.direction, dtype=float).tolist(),
            "reference_tilt_index": int(self.reference_tilt_index),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TiltAxis:
        return cls(np.array(d["origin"], float), np.array(d["direction"], float),
                   int(d.get("reference_tilt_index", 0)))


TILT_MATCH_DEG = 1e-6
"""Two tilts this close are the same tilt (recipes round stops to 1e-6 deg)."""


@dataclass
class Calibration:
    """Cameras of a turntable rig: the camera of any (camera, tilt, turntable angle).

    Attributes
    ----------
    models : dict camera name -> CameraModel
    poses : dict (camera name, tilt index) -> Pose
        World -> camera at turntable angle 0.
    tilts_deg : dict tilt index -> float, deg
        Commanded tilt of each calibrated tilt index.
    angle_scale : float
        Real turntable angle per commanded degree (gear ratio error), ~1.
    tilt_axis : TiltAxis or None
        When known, cameras at tilts that were never calibrated are available.
    quality : dict
        Free-form quality report of the calibrator (residuals, rejections...).
    view_angles_deg : dict view index -> float, deg
        The true turntable angle of individual views where the calibrator
        measured it (``sfm`` solves every photo's stop; backlash or a missed
        step then no longer blurs the hull).  Views not listed use their
        recorded angle times ``angle_scale``.
    """

    models: dict[str, CameraModel]
    poses: dict[tuple[str, int], Pose]
    tilts_deg: dict[int, float] = field(default_factory=dict)
    angle_scale: float = 1.0
    tilt_axis: TiltAxis | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    view_angles_deg: dict[int, float] = field(default_factory=dict)

    @property
    def camera_names(self) -> list[str]:
        return sorted(self.models)

    def camera_at(self, camera: str, tilt_index: int, angle_deg: float) -> Camera:
        """The posed camera ``camera`` at calibrated tilt ``tilt_index`` and turntable angle.

        Turning the plate by ``+angle_deg`` (counter-clockwise seen from above)
        rotates every world point by ``Rz(angle)`` in the lab, so the camera
        maps ``X`` to ``R @ Rz(angle) @ X + t``.
        """
        try:
            model = self.models[camera]
        except KeyError:
            raise KeyError(
                f"camera {camera!r} is not in the calibration (has {self.camera_names})"
            ) from None
        key = (camera, int(tilt_index))
        if key not in self.poses:
            if self.tilt_axis is not None and tilt_index in self.tilts_deg:
                return self.camera_at_tilt(camera, self.tilts_deg[tilt_index], angle_deg)
            raise KeyError(f"no pose for camera {camera!r} at tilt index {tilt_index}")
        pose = self.poses[key]
        return Camera(model, pose.compose_world(rotation_z(angle_deg * self.angle_scale)))

    def view_angle_deg(self, view: ViewRecord) -> float:
        """Turntable angle of ``view``: the calibration's own estimate for that view when it
        has one (``view_angles_deg``, by view index, already scaled), else the recorded."""
        solved = self.view_angles_deg.get(int(view.index))
        if solved is None:
            return view.angle_deg
        return solved / self.angle_scale

    def camera_for_view(self, view: ViewRecord) -> Camera:
        """The camera that took ``view`` (its measured angle when known).

        A view whose tilt index this calibration knows at another tilt (a
        calibration of another protocol's scan, whose tilt list differs) is
        placed by its tilt in degrees (``camera_at_stop``).
        """
        angle = self.view_angle_deg(view)
        known = self.tilts_deg.get(view.tilt_index)
        if known is not None and abs(known - view.tilt_deg) > TILT_MATCH_DEG:
            return self.camera_at_stop(view.camera, view.tilt_deg, angle)
        if (view.camera, view.tilt_index) not in self.poses and self.tilt_axis is not None:
            return self.camera_at_tilt(view.camera, view.tilt_deg, angle)
        return self.camera_at(view.camera, view.tilt_index, angle)

    def camera_at_stop(self, camera: str, tilt_deg: float, angle_deg: float) -> Camera:
        """The camera at a rig position given in degrees: the calibrated pose of that tilt
        when there is one, else through the tilt-arm axis model (``KeyError`` without)."""
        for ti, t in sorted(self.tilts_deg.items()):
            if abs(t - tilt_deg) <= TILT_MATCH_DEG and (camera, ti) in self.poses:
                return self.camera_at(camera, ti, angle_deg)
        return self.camera_at_tilt(camera, tilt_deg, angle_deg)

    def camera_at_tilt(self, camera: str, tilt_deg: float, angle_deg: float) -> Camera:
        """Camera at any tilt angle, through the tilt-arm axis model."""
        if self.tilt_axis is None:
            raise KeyError("this calibration has no tilt-axis model; only calibrated tilts exist")
        ref = self.tilt_axis.reference_tilt_index
        base = self.poses[(camera, ref)]
        dphi = tilt_deg - self.tilts_deg.get(ref, 0.0)
        q = rotation_about_axis(self.tilt_axis.direction, dphi)
        o = np.asarray(self.tilt_axis.origin, dtype=float)
        # Arm rotation by q about the axis moves the camera: x_cam = R q^T (X - o) + R o + t.
        r = base.R @ q.T
        t = base.R @ (o - q.T @ o) + base.t
        return Camera(self.models[camera], Pose(r, t).compose_world(
            rotation_z(angle_deg * self.angle_scale)))

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "plantscan-calibration/1",
            "units": {"length": "mm", "angle": "deg", "image": "px"},
            "models": {k: v.to_dict() for k, v in sorted(self.models.items())},
            "poses": [
                {"camera": c, "tilt_index": ti, **p.to_dict()}
                for (c, ti), p in sorted(self.poses.items())
            ],
            "tilts_deg": {int(k): float(v) for k, v in sorted(self.tilts_deg.items())},
            "angle_scale": float(self.angle_scale),
            "tilt_axis": None if self.tilt_axis is None else self.tilt_axis.to_dict(),
            "quality": _plain(self.quality),
            **({"view_angles_deg": {int(k): float(v) for k, v in
                                    sorted(self.view_angles_deg.items())}}
               if self.view_angles_deg else {}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        return cls(
            models={k: CameraModel.from_dict(v) for k, v in d["models"].items()},
            poses={(p["camera"], int(p["tilt_index"])): Pose.from_dict(p) for p in d["poses"]},
            tilts_deg={int(k): float(v) for k, v in (d.get("tilts_deg") or {}).items()},
            angle_scale=float(d.get("angle_scale", 1.0)),
            tilt_axis=None if not d.get("tilt_axis") else TiltAxis.from_dict(d["tilt_axis"]),
            quality=d.get("quality") or {},
            view_angles_deg={int(k): float(v)
                             for k, v in (d.get("view_angles_deg") or {}).items()},
        )

    def save(self, path: Path) -> None:
        """Write plain YAML (no OpenCV tags)."""
        import yaml

        from plantscan_core.scanfolder import atomic_write_text

        atomic_write_text(Path(path), yaml.safe_dump(self.to_dict(), sort_keys=False))

    @classmethod
    def load(cls, path: Path) -> Calibration:
        """Read a calibration file, every number checked (``plantscan_core.calibfile``)."""
        from plantscan_core.calibfile import check_calibration_dict
        from plantscan_core.userfiles import load_yaml

        if not Path(path).exists():
            raise DataError(f"{path}: calibration file not found")
        raw = load_yaml(path)
        check_calibration_dict(raw, str(path))
        return cls.from_dict(raw)


def _plain(obj: Any) -> Any:
    """Turn numpy scalars/arrays (and dates: ISO 8601 text) nested in dicts/lists into plain
    Python for YAML/JSON (YAML reads ``sowing_date: 2026-05-01`` as a date)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (datetime.date, datetime.time)):
        return obj.isoformat()
    return obj


plain = _plain


# --------------------------------------------------------------------------- silhouettes
def mask_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """Rows and columns of a 2D mask's bounding box; None when it is empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


class Silhouette:
    """A plant mask of one view, held cropped to the plant's bounding box.

    Attributes
    ----------
    view : ViewRecord
    mask : (H, W) bool array, True = plant (or pot), in the *distorted* image
        as the camera took it.  Built on each access from the crop (a new
        array): read it once per use, or use :attr:`crop`.
    crop : (h, w) bool array
        The mask inside its bounding box ``[u0, u0 + w) x [v0, v0 + h)``
        (``(0, 0)`` for an empty mask); everything outside is background.
    u0, v0 : int, px
        Top-left pixel of the crop.
    shape : (H, W)
        The image's size.

    A plant is 10-20 % of a scan image: 360 masks of 2592x1728 take 1.6 GB as
    full arrays and ~0.2-0.3 GB as crops (issue #10).
    """

    __slots__ = ("view", "crop", "u0", "v0", "shape")

    def __init__(self, view: ViewRecord, mask: np.ndarray):
        m = np.asarray(mask, dtype=bool)
        self.view = view
        self.shape = tuple(int(n) for n in m.shape[:2])
        if m.ndim != 2:
            # Kept as is so consumers can name the bad view (their checks see the shape).
            self.crop, self.u0, self.v0 = m, 0, 0
            return
        box = mask_box(m)
        if box is None:
            self.crop, self.u0, self.v0 = np.zeros((0, 0), bool), 0, 0
            return
        self.v0, self.u0 = int(box[0].start), int(box[1].start)
        self.crop = m[box].copy()

    @property
    def mask(self) -> np.ndarray:
        if self.crop.ndim != 2:
            return self.crop
        out = np.zeros(self.shape, bool)
        h, w = self.crop.shape
        out[self.v0:self.v0 + h, self.u0:self.u0 + w] = self.crop
        return out

    @property
    def area(self) -> int:
        """Plant pixels."""
        return int(np.count_nonzero(self.crop))

    def __repr__(self) -> str:
        return (f"Silhouette(view={self.view.index}, shape={self.shape}, "
                f"crop={self.crop.shape} at ({self.u0}, {self.v0}))")


@dataclass
class Silhouettes:
    """All plant silhouettes of a scan, in view order."""

    items: list[Silhouette]

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self):
        return iter(self.items)

    def __getitem__(self, i: int) -> Silhouette:
        return self.items[i]


# --------------------------------------------------------------------------- volumes and meshes
@dataclass(frozen=True)
class CarvingViews:
    """Where the cameras stood that carved a hull, and how tolerant the carve was.

    What a mesher may know of the views (the cone over the pot's opening that no
    view carves follows from them).

    Attributes
    ----------
    centres_mm : (V, 3) float64 array, mm, turntable frame
        The camera centre of every plant view (the view's turntable angle applied).
    k : int
        A voxel stays in the hull while at most ``k`` views see it outside.
    """

    centres_mm: np.ndarray
    k: int = 0

    @classmethod
    def of(cls, silhouettes: Silhouettes, calibration: Calibration, k: int = 0) -> CarvingViews:
        """The views of ``silhouettes`` placed by ``calibration``."""
        return cls(np.array([calibration.camera_for_view(s.view).pose.centre
                             for s in silhouettes], dtype=float).reshape(-1, 3), int(k))


# Side (voxels) of the blocks of a ``BlockField``: the octree's top cells and the mesher's
# marching-cubes blocks have the same side, so each is one block.
FIELD_BLOCK = 32


class BlockField:
    """A clamped field on a grid, stored block by block: only the blocks the surface may
    cross hold values, every other block is wholly outside (-1) or wholly inside (+1).

    A visual hull is exactly -1 in ~97 % of its voxels; its dense float32 grid is
    3.4 GB at 1024^3, this one a few hundred MB (the mixed blocks near the surface).

    Attributes
    ----------
    shape : (3,) tuple of int
        Voxels of the grid.
    block : int
        Side of a block, voxels; block ``(i, j, k)`` holds voxels
        ``[i * block, (i + 1) * block)`` (and so on along each axis).
    index : (BX, BY, BZ) int32 array
        ``OUTSIDE`` (every voxel -1), ``INSIDE`` (every voxel +1), or the row of
        ``values`` holding the block.
    values : (M, block, block, block) float32 array, voxels
        The mixed blocks; their voxels beyond the grid are -1.
    """

    OUTSIDE = -1
    INSIDE = -2

    def __init__(self, shape: Sequence[int], block: int, index: np.ndarray,
                 values: np.ndarray) -> None:
        self.shape = tuple(int(n) for n in shape)
        self.block = int(block)
        self.index = np.asarray(index, dtype=np.int32)
        self.values = np.asarray(values, dtype=np.float32)
        want = tuple(-(-n // self.block) for n in self.shape)
        if self.index.shape != want or self.values.shape[1:] != (self.block,) * 3:
            raise ValueError(f"BlockField: index {self.index.shape} / values "
                             f"{self.values.shape} do not fit a {self.shape} grid of "
                             f"{self.block}^3 blocks")

    @classmethod
    def from_dense(cls, field: np.ndarray, block: int = FIELD_BLOCK) -> BlockField:
        """The blocks of a dense ``(NX, NY, NZ)`` field (exact: ``dense()`` gives it back)."""
        field = np.asarray(field, dtype=np.float32)
        n = np.array(field.shape)
        nb = -(-n // block)
        index = np.full(tuple(nb), cls.OUTSIDE, dtype=np.int32)
        rows = []
        for b in np.ndindex(*nb):
            sl = tuple(slice(i * block, (i + 1) * block) for i in b)
            part = field[sl]
            if np.all(part == -1.0):
                continue
            if np.all(part == 1.0) and part.shape == (block,) * 3:
                index[b] = cls.INSIDE
                continue
            row = np.full((block,) * 3, -1.0, dtype=np.float32)
            row[tuple(slice(0, s) for s in part.shape)] = part
            index[b] = len(rows)
            rows.append(row)
        values = np.stack(rows) if rows else np.zeros((0,) + (block,) * 3, np.float32)
        return cls(field.shape, block, index, values)

    @property
    def nbytes(self) -> int:
        return int(self.index.nbytes + self.values.nbytes)

    def read(self, lo: Sequence[int], hi: Sequence[int]) -> np.ndarray:
        """The dense box ``[lo, hi)`` of voxel indices (float32), -1 beyond the grid."""
        lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
        out = np.full(tuple(hi - lo), -1.0, dtype=np.float32)
        a = np.maximum(lo, 0)
        b = np.minimum(hi, self.shape)
        if np.any(b <= a):
            return out
        B = self.block
        for bi in np.ndindex(*(tuple((b - 1) // B - a // B + 1))):
            blk = a // B + np.array(bi)
            row = int(self.index[tuple(blk)])
            if row == self.OUTSIDE:
                continue
            g0 = np.maximum(blk * B, a)
            g1 = np.minimum(blk * B + B, b)
            dst = tuple(slice(x - y, z - y) for x, y, z in zip(g0, lo, g1, strict=True))
            if row == self.INSIDE:
                out[dst] = 1.0
            else:
                src = tuple(slice(x - y, z - y) for x, y, z in zip(g0, blk * B, g1, strict=True))
                out[dst] = self.values[row][src]
        return out

    def values_at(self, idx: np.ndarray) -> np.ndarray:
        """(N,) float32 values at voxel indices ``idx`` (N, 3) (within the grid)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, 3)
        B = self.block
        row = self.index[idx[:, 0] // B, idx[:, 1] // B, idx[:, 2] // B]
        out = np.where(row == self.INSIDE, np.float32(1.0), np.float32(-1.0))
        mixed = np.flatnonzero(row >= 0)
        if mixed.size:
            q = idx[mixed] % B
            out[mixed] = self.values[row[mixed], q[:, 0], q[:, 1], q[:, 2]]
        return out

    def materialise(self, blocks: np.ndarray) -> None:
        """Give the implicit blocks ``blocks`` (K, 3) rows of their value (-1 or +1; the
        voxels beyond the grid -1), appended to ``values``."""
        blocks = np.asarray(blocks, dtype=np.int64).reshape(-1, 3)
        rows = self.index[tuple(blocks.T)]
        blocks = blocks[rows < 0]
        if not len(blocks):
            return
        B = self.block
        new = np.full((len(blocks),) + (B,) * 3, -1.0, dtype=np.float32)
        for t, blk in enumerate(blocks):
            if self.index[tuple(blk)] == self.INSIDE:
                room = np.minimum(np.asarray(self.shape) - blk * B, B)
                new[t, :room[0], :room[1], :room[2]] = 1.0
        self.index[tuple(blocks.T)] = np.arange(len(self.values),
                                                len(self.values) + len(blocks), dtype=np.int32)
        self.values = np.concatenate([self.values, new])

    def dense(self) -> np.ndarray:
        """The whole ``(NX, NY, NZ)`` float32 grid (4 bytes a voxel: small grids only)."""
        return self.read((0, 0, 0), self.shape)

    def block_max(self) -> np.ndarray:
        """(BX, BY, BZ) float32: the largest value of each block."""
        out = np.where(self.index == self.INSIDE, np.float32(1.0), np.float32(-1.0))
        rows = self.index >= 0
        if rows.any():
            out[rows] = self.values.reshape(len(self.values), -1).max(axis=1)[self.index[rows]]
        return out


class Volume:
    """A reconstructed occupancy field on a regular grid.

    Attributes
    ----------
    field : (NX, NY, NZ) float32 array
        Continuous inside/outside field: > 0 inside the plant, < 0 outside,
        the surface is the 0 level set (e.g. signed distance in voxels).  For a
        volume made from a ``BlockField`` this is the whole grid, built at each
        access (4 bytes a voxel): code for large grids reads ``blocks``.
    blocks : BlockField or None
        The field block by block, when the volume holds it so (the
        ``octree-hull`` reconstructor does); None for a dense volume.
    origin : (3,) float64 array, mm, turntable frame
        Centre of voxel (0, 0, 0).
    voxel_size : float, mm
    """

    def __init__(self, field: np.ndarray | BlockField, origin: np.ndarray,
                 voxel_size: float) -> None:
        self._field = field
        self.origin = origin
        self.voxel_size = voxel_size

    @property
    def blocks(self) -> BlockField | None:
        return self._field if isinstance(self._field, BlockField) else None

    @property
    def field(self) -> np.ndarray:
        if isinstance(self._field, BlockField):
            return self._field.dense()
        return self._field

    @field.setter
    def field(self, value: np.ndarray | BlockField) -> None:
        self._field = value

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self._field.shape)  # type: ignore[return-value]

    @property
    def occupancy(self) -> np.ndarray:
        """(NX, NY, NZ) bool array, True inside."""
        return self.field > 0

    def voxel_centres(self, idx: np.ndarray) -> np.ndarray:
        """Integer voxel indices ``(N, 3)`` -> centres ``(N, 3)`` mm."""
        return np.asarray(self.origin) + np.asarray(idx, dtype=float) * self.voxel_size

    def save(self, path: Path) -> None:
        """``.npz``: ``field`` (dense), or ``block_index`` / ``block_values`` / ``shape``."""
        b = self.blocks
        if b is None:
            np.savez_compressed(Path(path), field=self._field, origin=np.asarray(self.origin),
                                voxel_size=self.voxel_size)
        else:
            np.savez_compressed(Path(path), block_index=b.index, block_values=b.values,
                                shape=np.asarray(b.shape), origin=np.asarray(self.origin),
                                voxel_size=self.voxel_size)

    @classmethod
    def load(cls, path: Path) -> Volume:
        with np.load(Path(path)) as z:
            if "field" in z.files:
                return cls(z["field"], z["origin"], float(z["voxel_size"]))
            values = z["block_values"]
            blocks = BlockField(tuple(z["shape"]), values.shape[1], z["block_index"], values)
            return cls(blocks, z["origin"], float(z["voxel_size"]))


@dataclass
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64 array, mm, turntable frame
    faces : (F, 3) int64 array, counter-clockwise seen from outside
    rim_vertices : (V, 3) float64 array or None
        The same vertices with the rims of one-voxel-thick parts put where the outside
        field says (``marching-cubes``' ``thin_rims: measure``): the segmenter labels the
        faces on ``vertices``, the measurer measures them on these (docs/reconstruction.md,
        "Thin rims").  None: measure on ``vertices``.
    base_z_mm : float or None
        Height (mm, turntable frame) of the plant's base where the mesher cut the pot
        away: the pot's rim.  The plant's height is measured from it (drooping leaves
        hang below the rim).  None: no pot removed; the height is the vertical extent.
    """

    vertices: np.ndarray
    faces: np.ndarray
    rim_vertices: np.ndarray | None = None
    base_z_mm: float | None = None

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.rim_vertices is not None:
            self.rim_vertices = np.asarray(self.rim_vertices, dtype=np.float64).reshape(-1, 3)
            if self.rim_vertices.shape != self.vertices.shape:
                raise ValueError(f"rim_vertices has {len(self.rim_vertices)} rows for "
                                 f"{len(self.vertices)} vertices")

    def measured(self) -> Mesh:
        """The surface the measurer measures: ``rim_vertices`` when the mesher gave them."""
        return self if self.rim_vertices is None else Mesh(self.rim_vertices, self.faces,
                                                           base_z_mm=self.base_z_mm)

    @property
    def is_empty(self) -> bool:
        return len(self.faces) == 0

    def face_areas(self) -> np.ndarray:
        """(F,) float64 triangle areas, mm²."""
        v = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def area(self) -> float:
        """Total surface area, mm²."""
        return float(self.face_areas().sum())

    def label_centroids(self, face_labels: np.ndarray) -> dict[int, np.ndarray]:
        """Area-weighted centroid ((3,) mm) of the faces of each label >= 0.

        ``face_labels`` : (F,) int array, one label per face (< 0: none).  Where a
        leaf lies, for matching it between scans or with the truth's leaves.
        """
        labels = np.asarray(face_labels).reshape(-1)
        keep = labels >= 0
        if not keep.any():
            return {}
        kept = Mesh(self.vertices, self.faces[keep])  # the labelled faces only (a leaf's
        area = kept.face_areas()  # contact with the stem is a few thousand of 1.7 M faces)
        centre = self.vertices[kept.faces].mean(axis=1)
        ids, index = np.unique(labels[keep], return_inverse=True)
        weight = np.maximum(np.bincount(index, area), 1e-12)
        sums = np.stack([np.bincount(index, area * centre[:, k]) for k in range(3)], axis=1)
        return {int(i): sums[j] / weight[j] for j, i in enumerate(ids)}

    def to_open3d(self):
        import open3d as o3d

        m = o3d.geometry.TriangleMesh()
        m.vertices = o3d.utility.Vector3dVector(self.vertices)
        m.triangles = o3d.utility.Vector3iVector(self.faces.astype(np.int32))
        return m

    @classmethod
    def from_open3d(cls, m) -> Mesh:
        return cls(np.asarray(m.vertices), np.asarray(m.triangles))

    def save(self, path: Path) -> None:
        """Uncompressed ``.npz`` (the run cache): 0.03 s vs 1 s CPU compressed at 1.2 M faces.

        Faces are stored as int32 when they fit (lossless; read back as int64).
        """
        np.savez(Path(path), vertices=self.vertices, faces=_compact_indices(self.faces),
                 **_optional_arrays(self))

    @classmethod
    def load(cls, path: Path) -> Mesh:
        with np.load(Path(path)) as z:
            return _mesh_of(z)


def _optional_arrays(mesh: Mesh) -> dict[str, np.ndarray]:
    """``rim_vertices`` and ``base_z_mm`` for an ``.npz`` (absent when the mesh has none)."""
    out = {} if mesh.rim_vertices is None else {"rim_vertices": mesh.rim_vertices}
    if mesh.base_z_mm is not None:
        out["base_z_mm"] = np.array(float(mesh.base_z_mm))
    return out


def _mesh_of(z) -> Mesh:
    """The mesh of an ``.npz`` written with ``_optional_arrays`` (files before a field: none)."""
    return Mesh(z["vertices"], z["faces"],
                z["rim_vertices"] if "rim_vertices" in z else None,
                float(z["base_z_mm"]) if "base_z_mm" in z else None)


def _compact_indices(faces: np.ndarray) -> np.ndarray:
    """int32 copy of vertex indices when they fit (halves the file), else as given."""
    if faces.size == 0 or int(faces.max()) < 2**31 - 1:
        return faces.astype(np.int32)
    return faces


LABEL_KINDS = ("leaf", "stem", "pot", "debris")  # stored by index in labelled.npz: append only


@dataclass
class LabelledMesh:
    """A mesh with a label per face.

    Attributes
    ----------
    mesh : Mesh
    face_labels : (F,) int32 array
        ``-1`` unassigned; otherwise a key of ``kinds``.
    kinds : dict label -> str
        What each label is: one of ``LABEL_KINDS`` — ``"leaf"``, ``"stem"``, ``"pot"``, or
        ``"debris"`` (surface that is no organ: phantom volume, pot remnants, crumbs; kept
        in the labelled mesh, never counted as leaf).
    evidence : dict label -> dict str -> float
        What the segmenter knows of each label that bears on how far its traits can be
        trusted (e.g. ``phantom_share``, ``fragments``); the measurer turns it into a
        confidence.  Empty when the segmenter says nothing.
    """

    mesh: Mesh
    face_labels: np.ndarray
    kinds: dict[int, str] = field(default_factory=dict)
    evidence: dict[int, dict[str, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.face_labels = np.asarray(self.face_labels, dtype=np.int32).reshape(-1)
        if len(self.face_labels) != len(self.mesh.faces):
            raise ValueError(
                f"face_labels has {len(self.face_labels)} entries for {len(self.mesh.faces)} faces"
            )

    @property
    def leaf_labels(self) -> list[int]:
        return sorted(k for k, v in self.kinds.items() if v == "leaf")

    def submesh(self, label: int) -> Mesh:
        """The faces of one label, with only the vertices they use."""
        faces = self.mesh.faces[self.face_labels == label]
        used, inverse = np.unique(faces, return_inverse=True)
        return Mesh(self.mesh.vertices[used], inverse.reshape(-1, 3))

    def save(self, path: Path) -> None:
        kinds = np.array([[k, LABEL_KINDS.index(v)] for k, v in self.kinds.items()],
                         dtype=np.int64).reshape(-1, 2)
        # Uncompressed, as Mesh.save: the run cache is read back far more often than shipped.
        import json

        evidence = json.dumps({str(k): v for k, v in self.evidence.items()})
        np.savez(Path(path), vertices=self.mesh.vertices, faces=_compact_indices(self.mesh.faces),
                 face_labels=self.face_labels, kinds=kinds, evidence=np.array(evidence),
                 **_optional_arrays(self.mesh))

    @classmethod
    def load(cls, path: Path) -> LabelledMesh:
        with np.load(Path(path)) as z:
            import json

            kinds = {int(k): LABEL_KINDS[int(v)] for k, v in z["kinds"]}
            evidence = ({int(k): v for k, v in json.loads(str(z["evidence"])).items()}
                        if "evidence" in z else {})  # files before the field have none
            return cls(_mesh_of(z), z["face_labels"], kinds, evidence)


# --------------------------------------------------------------------------- traits
@dataclass(frozen=True)
class TraitColumn:
    """One column of the traits tables: what it is, in which unit, how reports show it.

    The leaf columns are ``LeafTraits``'s fields (their metadata, ``LEAF_COLUMNS``),
    the plant ones ``PLANT_TRAITS``.  ``traits.csv``'s header, ``TRAIT_NAMES``,
    the report's columns and the results store's trait dictionary are derived
    from them (docs/formats.md, "The trait table").

    Attributes
    ----------
    name : str
        Column or key, unit in the name (``length_mm``).
    unit : str
        ``mm``, ``mm2``, ``mm3``; ``1`` for a share, score or count; ``""`` for text.
    description : str
        What it is, for a scientist (the store's trait dictionary, MIAPPE).
    trait : str
        Short name of a measured trait (``length``): the ``TRAIT_NAMES`` that are
        evaluated against the truth; ``""`` for quality figures and text.
    label : str
        Title in reports (default: ``trait``, else the name without its unit).
    method : str
        How it is measured (the store's trait dictionary).
    display_unit, display_scale : str, float
        Reports show ``value * display_scale`` in ``display_unit`` (default
        ``unit``; a share 0-1 as %).
    decimals : int
        Decimals in reports (fixed per column, so a column lines up).
    level : {"leaf", "plant"}
    required : bool
        A ``traits.csv`` without the column does not load; an optional one
        missing (tables before it: older runs, the truth) gives its default.
    """

    name: str
    unit: str
    description: str
    trait: str = ""
    label: str = ""
    method: str = ""
    display_unit: str = ""
    display_scale: float = 1.0
    decimals: int = 1
    level: str = "leaf"
    required: bool = False

    @property
    def is_text(self) -> bool:
        return self.unit == ""

    @property
    def title(self) -> str:
        """``length``, ``thick area``, ``total leaf area``: the report's name of it."""
        if self.label or self.trait:
            return self.label or self.trait
        suffix = f"_{self.unit}"
        base = self.name[: -len(suffix)] if self.name.endswith(suffix) else self.name
        return base.replace("_", " ")

    @property
    def header(self) -> str:
        """``length (mm)``, ``area (mm²)``, ``confidence``: a report's column title."""
        unit = self.shown_unit
        return f"{self.title} ({unit})" if unit else self.title

    @property
    def shown_unit(self) -> str:
        """The unit a report writes beside the value (``mm²``; none for a score or count)."""
        unit = self.display_unit or _UNIT_TEXT.get(self.unit, self.unit)
        return "" if unit == "1" else unit


_UNIT_TEXT = {"mm2": "mm²", "mm3": "mm³"}


def _column(unit: str, description: str, *, default: Any = dataclasses.MISSING,
            **info: Any) -> Any:
    """A ``LeafTraits`` field that is a column of ``traits.csv`` (see ``TraitColumn``)."""
    return field(default=default,
                 metadata={"column": {"unit": unit, "description": description, **info}})


# How the flat-leaf traits are measured (docs/leaves.md).
_FLAT = ("flat-leaf measurement of the reconstructed leaf surface (as if dissected onto a "
         "flatbed scanner; docs/leaves.md)")


@dataclass
class LeafTraits:
    """Flat-leaf measurements of one leaf (as if dissected onto a flatbed).

    Every field but ``leaf_id`` is a column of ``traits.csv``, described by its
    metadata (``LEAF_COLUMNS``): a new leaf trait is one field here and the
    measurer's function that fills it.  ``thick_share``, ``confidence``,
    ``confidence_reasons`` and ``quality_flag`` say how far to trust the
    traits (docs/leaves.md, "Trust"); NaN / empty when the measurer does not say.
    """

    leaf_id: int
    length_mm: float = _column("mm", "leaf blade length, base to tip along the midrib",
                               trait="length", method=_FLAT)
    width_mm: float = _column("mm", "largest blade width across the midrib", trait="width",
                              method=_FLAT)
    area_mm2: float = _column("mm2", "one-sided blade area", trait="area", method=_FLAT,
                              decimals=0)
    perimeter_mm: float = _column("mm", "blade outline length", trait="perimeter",
                                  method=_FLAT)
    thick_share: float = _column(
        "1", "share of the leaf's area where the hull is over 3x its median thickness "
        "(phantom volume or a fused organ): a quality figure, not a trait",
        default=math.nan, label="thick area", display_unit="%", display_scale=100.0)
    confidence: float = _column(
        "1", "how far to trust the leaf's measurements (0-1), from the measurer",
        default=math.nan, decimals=2)
    confidence_reasons: str = _column(
        "", "reason codes behind a low confidence, ';'-separated (docs/leaves.md, Trust)",
        default="")
    quality_flag: str = _column("", "ok, or check (confidence under 0.5)", default="")

    def trait(self, name: str) -> float:
        """Value of the trait ``name`` in ``TRAIT_NAMES`` (length, width, area, perimeter)."""
        if name not in _TRAIT_COLUMN:
            raise ValueError(f"unknown trait {name!r}; valid: {', '.join(TRAIT_NAMES)}")
        return float(getattr(self, _TRAIT_COLUMN[name]))


def leaf_columns(leaf_class: type) -> tuple[TraitColumn, ...]:
    """The ``TraitColumn`` of every field of ``leaf_class`` made by ``_column``, in order
    (one without a default is required)."""
    return tuple(TraitColumn(f.name, **f.metadata["column"],
                             required=f.default is dataclasses.MISSING)
                 for f in dataclasses.fields(leaf_class) if "column" in f.metadata)


LEAF_COLUMNS = leaf_columns(LeafTraits)
"""The columns of ``traits.csv`` after ``leaf_id``, in order."""
LEAF_TRAIT_COLUMNS = ("leaf_id",) + tuple(c.name for c in LEAF_COLUMNS)
TRAIT_NAMES = tuple(c.trait for c in LEAF_COLUMNS if c.trait)
_TRAIT_COLUMN = {c.trait: c.name for c in LEAF_COLUMNS if c.trait}


def _plant(name: str, unit: str, description: str, **info: Any) -> TraitColumn:
    return TraitColumn(name, unit, description, level="plant", **info)


PLANT_TRAITS: tuple[TraitColumn, ...] = (
    _plant("height_mm", "mm", "plant height: highest point of the plant above the pot's rim "
           "(the vertical extent when no pot was removed)",
           method="highest point of the plant surface minus the rim of the pot the mesher "
                  "removed, or minus the lowest point"),
    _plant("total_leaf_area_mm2", "mm2", "sum of the one-sided areas of the leaves found",
           method=_FLAT, decimals=0),
    _plant("leaf_count", "1", "number of leaves found", decimals=0),
    _plant("convex_hull_volume_mm3", "mm3", "volume of the convex hull of the plant surface",
           decimals=0),
    _plant("projected_area_mm2", "mm2", "area of the plant seen from above (top view)",
           decimals=0),
    _plant("debris_area_mm2", "mm2", "one-sided area of the surface pieces labelled debris "
           "(neither leaf nor stem)", decimals=0),
    _plant("stem_area_mm2", "mm2", "one-sided area of the surface labelled stem (stems, "
           "petioles, sheaths); a share of the plant's surface above the recipe's "
           "max_stem_share flags the plant (docs/leaves.md, Trust)", decimals=0),
    _plant("low_confidence_leaves", "1", "number of leaves whose quality flag is check",
           decimals=0),
    _plant("quality_flag", "", "ok, check or fail: whether to trust the plant's numbers "
           "(docs/leaves.md, Trust)"),
    _plant("quality_reasons", "", "why the plant is not ok (a list of messages)"),
)
"""The plant-level values a measurer reports (``Traits.plant`` keys, ``plant_traits.json``)."""
PLANT_COLUMN = {c.name: c for c in PLANT_TRAITS}


def leaf_value_text(value: float | str) -> str:
    """How a ``LeafTraits`` column is written in a table: numbers to 4 decimals, text as is."""
    return value if isinstance(value, str) else f"{value:.4f}"


def _leaf_from_row(row: dict[str, str]) -> LeafTraits:
    """A ``LeafTraits`` from a ``traits.csv`` row (an optional column missing: its default)."""
    values: dict[str, Any] = {}
    for c in LEAF_COLUMNS:
        text = row[c.name] if c.required else row.get(c.name)
        if text not in (None, ""):
            values[c.name] = text if c.is_text else float(text)
    return LeafTraits(int(row["leaf_id"]), **values)


@dataclass
class Traits:
    """The traits table of one plant: one row per leaf plus plant-level values.

    ``plant`` keys (when measured): those of ``PLANT_TRAITS`` (``height_mm``,
    ``total_leaf_area_mm2``, ``leaf_count``, ..., ``quality_flag``), and what
    else the measurer says.
    """

    leaves: list[LeafTraits] = field(default_factory=list)
    plant: dict[str, float] = field(default_factory=dict)

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(LEAF_TRAIT_COLUMNS)
        for leaf in self.leaves:
            w.writerow([leaf.leaf_id] + [leaf_value_text(getattr(leaf, c.name))
                                         for c in LEAF_COLUMNS])
        return buf.getvalue()

    def to_dataframe(self, plant_columns: bool = False):
        """The per-leaf table as a pandas ``DataFrame`` (one row per leaf, ``traits.csv``'s
        columns; units in the names: mm, mm2).

        ``plant_columns=True`` adds the plant-level traits as ``plant_*`` columns
        repeated on every row (as ``traits.parquet``), so that many plants'
        frames concatenate into one table; they are always in ``df.attrs["plant"]``.
        """
        import pandas as pd

        columns = {name: [getattr(leaf, name) for leaf in self.leaves]
                   for name in LEAF_TRAIT_COLUMNS}
        df = pd.DataFrame(columns).astype({"leaf_id": "int64"})
        if plant_columns:
            for key, value in sorted(self.plant.items()):
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    df[f"plant_{key}"] = value
        df.attrs["plant"] = dict(self.plant)
        return df

    def save(self, path: Path, plant_path: Path | None = None) -> None:
        from plantscan_core.scanfolder import atomic_write_text

        atomic_write_text(Path(path), self.to_csv())
        if plant_path is not None:
            import json

            atomic_write_text(Path(plant_path), json.dumps(_plain(self.plant), indent=2))

    @classmethod
    def from_csv(cls, text: str, source: str = "traits table") -> Traits:
        """The table of ``traits.csv``'s text; ``DataError`` naming ``source`` and the
        missing columns when a required one is not there."""
        reader = csv.DictReader(io.StringIO(text))
        header = reader.fieldnames or []
        missing = [n for n in ("leaf_id", *(c.name for c in LEAF_COLUMNS if c.required))
                   if n not in header]
        if missing:
            raise DataError(f"{source}: no column {', '.join(missing)} (it has "
                            f"{', '.join(header) or 'no header'}; needed: "
                            f"{', '.join(LEAF_TRAIT_COLUMNS[:5])})")
        return cls([_leaf_from_row(r) for r in reader])

    @classmethod
    def load(cls, path: Path, plant_path: Path | None = None) -> Traits:
        t = cls.from_csv(Path(path).read_text(), str(path))
        if plant_path is not None and Path(plant_path).exists():
            import json

            t.plant = json.loads(Path(plant_path).read_text())
        return t


def mean_relative_error(truth: Iterable[float], measured: Iterable[float]) -> float:
    """The seed's ε = mean(|truth − measurement| / truth).

    Pairs whose truth is not a positive finite number (a closed external mesh has
    perimeter 0) have no relative error and are left out; NaN when none is left.
    """
    t = np.asarray(list(truth), dtype=float)
    m = np.asarray(list(measured), dtype=float)
    defined = np.isfinite(t) & (t > 0)
    if not defined.any():
        return float("nan")
    return float(np.mean(np.abs(t[defined] - m[defined]) / t[defined]))

"""The virtual rig: camera intrinsics and poses on a tilting arm around the turntable.

Lab frame = world (turntable) frame at turntable angle 0.  Every camera sits on
one arm that tilts about a horizontal axis through the aim point
``(0, 0, target_height_mm)``; arm tilt ``phi`` raises each camera's elevation by
``phi``.  A camera at turntable angle ``theta`` maps world points with
``R Rz(theta) X + t`` (the convention of ``plantscan_core.data.Calibration``).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from plantscan_core.data import (
    Calibration,
    Camera,
    CameraModel,
    Pose,
    TiltAxis,
    rotation_about_axis,
    rotation_z,
)
from plantscan_core.stages import StageParams


class SimCameraParams(StageParams):
    """Where a virtual camera sits on the arm and what lens it has."""

    elevation_deg: float = Field(20.0, ge=-80.0, le=89.0,
                                 description="elevation above the aim point at arm tilt 0")
    azimuth_deg: float = Field(0.0, description="azimuth of the camera around the turntable")
    distance_mm: float = Field(1300.0, gt=0.0, description="distance to the aim point")
    hfov_deg: float = Field(38.0, gt=1.0, lt=150.0, description="horizontal field of view")
    d1: float = Field(-0.07, ge=-0.5, le=0.5, description="radial distortion r² term")
    d2: float = Field(0.012, ge=-0.5, le=0.5, description="radial distortion r⁴ term")
    principal_offset: tuple[float, float] = Field(
        (0.004, -0.006), description="principal point offset from the image centre, "
        "as fractions of (width, height)")
    roll_deg: float = Field(0.0, ge=-45.0, le=45.0, description="camera roll about its axis")
    capture_s: float | None = Field(
        None, ge=0.0, le=3600.0, description="timing model only: shutter release to image as a "
        "lab camera would take, in place of the virtual camera's render time, so that "
        "scan --dry-run and the adaptive planner's time budget count a real rig's time")
    download_s: float | None = Field(None, ge=0.0, le=3600.0,
                                     description="timing model only: image to the computer")


def camera_model(p: SimCameraParams, width: int, height: int) -> CameraModel:
    """Intrinsics at ``width x height`` px (focal from the horizontal field of view)."""
    f = 0.5 * width / math.tan(math.radians(p.hfov_deg) / 2.0)
    return CameraModel(f=f, cu=(width - 1) / 2.0 + p.principal_offset[0] * width,
                       cv=(height - 1) / 2.0 + p.principal_offset[1] * height,
                       d1=p.d1, d2=p.d2, width=int(width), height=int(height))


def tilt_axis(target_height_mm: float, arm_azimuth_deg: float) -> TiltAxis:
    """The arm's tilt axis: horizontal, through the aim point, perpendicular to the arm."""
    a = math.radians(arm_azimuth_deg)
    return TiltAxis(np.array([0.0, 0.0, target_height_mm]),
                    np.array([math.sin(a), -math.cos(a), 0.0]), 0)


def base_pose(p: SimCameraParams, target_height_mm: float, arm_azimuth_deg: float) -> Pose:
    """World -> camera at arm tilt 0 and turntable angle 0."""
    e, a = math.radians(p.elevation_deg), math.radians(arm_azimuth_deg + p.azimuth_deg)
    target = np.array([0.0, 0.0, target_height_mm])
    centre = target + p.distance_mm * np.array(
        [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    pose = Pose.look_at(centre, target)
    if p.roll_deg:
        r = rotation_z(p.roll_deg) @ pose.R
        pose = Pose(r, -r @ centre)
    return pose


def tilted_pose(base: Pose, axis: TiltAxis, dphi_deg: float) -> Pose:
    """The pose after the arm turned by ``dphi_deg`` about ``axis`` (as Calibration does)."""
    q = rotation_about_axis(axis.direction, dphi_deg)
    o = np.asarray(axis.origin, dtype=float)
    return Pose(base.R @ q.T, base.R @ (o - q.T @ o) + base.t)


class Rig:
    """Cameras of the virtual rig: models and poses for any (camera, tilt, angle)."""

    def __init__(self, cameras: dict[str, SimCameraParams], image_size: tuple[int, int],
                 tilts_deg: list[float], target_height_mm: float, arm_azimuth_deg: float):
        self.params = cameras
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.tilts_deg = list(tilts_deg)
        self.axis = tilt_axis(target_height_mm, arm_azimuth_deg)
        self.models = {n: camera_model(p, *self.image_size) for n, p in cameras.items()}
        self.base = {n: base_pose(p, target_height_mm, arm_azimuth_deg)
                     for n, p in cameras.items()}

    def pose(self, camera: str, tilt_deg: float) -> Pose:
        """World -> camera at turntable angle 0 and arm tilt ``tilt_deg``."""
        return tilted_pose(self.base[camera], self.axis, tilt_deg)

    def camera(self, camera: str, tilt_deg: float, angle_deg: float) -> Camera:
        return Camera(self.models[camera],
                      self.pose(camera, tilt_deg).compose_world(rotation_z(angle_deg)))

    def calibration(self) -> Calibration:
        """The exact calibration (nominal angles), with the arm's tilt axis."""
        poses = {(n, ti): self.pose(n, t) for n in self.models
                 for ti, t in enumerate(self.tilts_deg)}
        axis = TiltAxis(self.axis.origin, self.axis.direction, 0)
        return Calibration(dict(self.models), poses,
                           {i: float(t) for i, t in enumerate(self.tilts_deg)}, 1.0, axis,
                           {"source": "virtual scanner ground truth"})

"""The turntable rig model: its parameter blocks and the projection of board corners.

Everything here works on detections (pixels of known board corners), never on
files, so real corners from another rig can be calibrated directly.

A board corner ``P`` (mm, board frame) of board ``b`` photographed by camera
``c`` at tilt ``t`` and commanded turntable angle ``theta`` projects as::

    X0    = R_b P + t_b                       board -> turntable frame at angle 0
    X     = Rz(theta * s + e) X0              the plate turned by theta (s: angle scale,
                                              e: error of this turntable stop, optional)
    x_cam = R_ct (X - C_ct)                   world -> camera of (c, t)
    uv    = CameraModel(f, cu, cv, d1, d2, aspect)   pinhole + two radial terms,
                                              fy = f * aspect

Unknowns: per camera ``[f, cu, cv, d1, d2, aspect]`` (aspect held at 1 unless
``fit_aspect``); per (camera, tilt) the rotation
vector of ``R_ct`` and the centre ``C_ct`` (mm); per board the rotation vector of
``R_b`` and ``t_b``; optionally ``s``.  With the rigid-arm model (``ArmModel``)
the poses of the other tilts follow from each camera's pose at the reference
tilt, one tilt axis and one angle error per tilt.  Images alone cannot tell a
rotation of the world about the turntable axis nor a shift along it (the
gauge): they are fixed by holding the reference camera's centre at ``x = 0``
(on the -Y side of the axis) and at ``z = 0`` during the solve; afterwards the
world is shifted along Z so that the lowest board corner is at
``lowest_corner_height_mm``.

``initialise`` gives the first estimate of this model, ``solver`` refines it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from plantscan_core.data import CameraModel, Pose, rotation_z
from plantscan_core.errors import PlantScanError


class CalibrationError(PlantScanError):
    """Calibration impossible or untrustworthy (too few views, diverging solve...)."""


# --------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class Detection:
    """The corners of one board found in one image.

    Attributes
    ----------
    camera : str
    tilt_index : int
    angle_deg : float, deg
        Turntable angle of the image (measured when known, else commanded).
    board : int
        Which board (key of the ``boards`` dict given to the solver).
    corner_ids : (N,) int array
        Row index of each corner in the board's object points.
    uv : (N, 2) float64 array, px
        Detected corner positions (distorted image, pixel centres at integers).
    view_index : int
        Index of the view in the scan (-1 when not from a scan).
    """

    camera: str
    tilt_index: int
    angle_deg: float
    board: int
    corner_ids: np.ndarray
    uv: np.ndarray
    view_index: int = -1


# --------------------------------------------------------------------------- rotations
def rotmats(rv: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(K, 3)`` rad -> rotation matrices ``(K, 3, 3)`` (Rodrigues)."""
    rv = np.asarray(rv, dtype=float).reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=1)
    small = theta < 1e-9
    k = rv / np.where(small, 1.0, theta)[:, None]
    kx = np.zeros((len(rv), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2] = -k[:, 2], k[:, 1]
    kx[:, 1, 0], kx[:, 1, 2] = k[:, 2], -k[:, 0]
    kx[:, 2, 0], kx[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.where(small, theta, np.sin(theta))[:, None, None]
    c = np.where(small, theta**2 / 2.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3)[None] + s * kx + c * (kx @ kx)


def rotvec(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (3,) rotation vector, rad."""
    v, _ = cv2.Rodrigues(np.asarray(r, dtype=float))
    return v.reshape(3)


def mean_rotation(rs: Sequence[np.ndarray]) -> np.ndarray:
    """Chordal mean of rotation matrices (SVD projection of their sum)."""
    u, _, vt = np.linalg.svd(np.sum(rs, axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


# --------------------------------------------------------------------------- projection
# Layout of the parameter vector of one view's cost: intrinsics, camera pose, board pose, scale.
N_INTR, N_POSE = 6, 6
I_INTR, I_CAM, I_BOARD, I_SCALE, I_STOP = 0, 6, 12, 18, 19
N_ALL = 20
VIEW_SIZES = (N_INTR, N_POSE, N_POSE, 1, 1)
INTR_NAMES = ("f", "cu", "cv", "d1", "d2", "aspect")


def project_batch(params: np.ndarray, points: np.ndarray, angle_deg: float) -> np.ndarray:
    """Pixels of board points under ``K`` parameter vectors at once.

    Parameters
    ----------
    params : (K, 20) float64 array
        ``[f, cu, cv, d1, d2, aspect, rc(3), C(3) mm, rb(3), tb(3) mm, s, e deg]`` per row.
    points : (N, 3) float64 array, mm, board frame
    angle_deg : float, deg, commanded turntable angle

    Returns
    -------
    (K, N, 2) float64 array, px
    """
    p = np.atleast_2d(params)
    return project_mats(p[:, :N_INTR], rotmats(p[:, I_CAM:I_CAM + 3]), p[:, I_CAM + 3:I_BOARD],
                        rotmats(p[:, I_BOARD:I_BOARD + 3]), p[:, I_BOARD + 3:I_SCALE],
                        turn_deg(angle_deg, p[:, I_SCALE], p[:, I_STOP]), points)


def turn_deg(angle_deg: float, scale: np.ndarray, stop_deg: np.ndarray) -> np.ndarray:
    """Real turntable angle(s), deg: the commanded ``angle_deg`` times the angle scale
    plus the stop's error, ``(K,)``."""
    return angle_deg * scale + stop_deg


def project_mats(intr: np.ndarray, rc: np.ndarray, centre: np.ndarray, rb: np.ndarray,
                 tb: np.ndarray, turn: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``project_batch`` with the rotations given as matrices.

    Parameters
    ----------
    intr : (K, 6) ``[f, cu, cv, d1, d2, aspect]``
    rc : (K, 3, 3) world -> camera rotations
    centre : (K, 3) camera centres, mm, world frame
    rb : (K, 3, 3), tb : (K, 3) mm, board -> turntable frame at angle 0
    turn : (K,) deg, the real turntable angle (``turn_deg``)
    points : (N, 3) mm, board frame

    Returns
    -------
    (K, N, 2) float64 array, px
    """
    x0 = np.einsum("kij,nj->kni", rb, points) + tb[:, None, :]
    a = np.radians(turn)
    ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
    xw = np.stack([ca * x0[..., 0] - sa * x0[..., 1], sa * x0[..., 0] + ca * x0[..., 1],
                   x0[..., 2]], axis=-1)
    xc = np.einsum("kij,knj->kni", rc, xw - centre[:, None, :])
    xy = xc[..., :2] / xc[..., 2:3]
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    s = 1.0 + intr[:, None, 3:4] * r2 + intr[:, None, 4:5] * r2 * r2
    focal = np.stack([intr[:, 0], intr[:, 0] * intr[:, 5]], axis=-1)[:, None, :]
    return xy * s * focal + intr[:, None, 1:3]


def axis_direction(angles: np.ndarray) -> np.ndarray:
    """Unit vectors ``(K, 3)`` from ``(K, 2)`` [azimuth, elevation] rad (tilt axes are
    near horizontal, far from the poles of this parametrisation)."""
    a = np.atleast_2d(angles)
    ce = np.cos(a[:, 1])
    return np.stack([ce * np.cos(a[:, 0]), ce * np.sin(a[:, 0]), np.sin(a[:, 1])], axis=1)


def arm_pose(ref_pose: np.ndarray, origin: np.ndarray, dir_angles: np.ndarray,
             dphi_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera rotation ``(K, 3, 3)`` and centre ``(K, 3)`` mm of a camera moved
    by ``dphi_deg`` ``(K,)`` about the tilt axis from its reference pose ``(K, 6)``.

    The arm turns by ``q`` about the line through ``origin`` ``(K, 3)``: the
    camera centre goes to ``o + q (C - o)``, its rotation to ``R q^T``.
    """
    q = rotmats(axis_direction(dir_angles) * np.radians(dphi_deg)[:, None])
    rc = rotmats(ref_pose[:, :3]) @ np.transpose(q, (0, 2, 1))
    c = origin + np.einsum("kij,kj->ki", q, ref_pose[:, 3:6] - origin)
    return rc, c


# Layout of the arm cost's parameters: intrinsics, reference pose, axis origin, axis
# direction (azimuth, elevation), tilt error, board pose, scale, stop error.
ARM_SIZES = (N_INTR, N_POSE, 3, 2, 1, N_POSE, 1, 1)
ARM_STARTS = tuple(int(x) for x in np.cumsum((0,) + ARM_SIZES[:-1]))
N_ARM = sum(ARM_SIZES)


def project_arm(params: np.ndarray, points: np.ndarray, angle_deg: float,
                dtilt_deg: float) -> np.ndarray:
    """Pixels ``(K, N, 2)`` of board points seen from a tilt ``dtilt_deg`` away from the
    reference tilt, under ``K`` arm parameter vectors ``(K, 27)`` (``ARM_SIZES``)."""
    p = np.atleast_2d(params)
    o = ARM_STARTS
    rc, c = arm_pose(p[:, o[1]:o[1] + 6], p[:, o[2]:o[2] + 3], p[:, o[3]:o[3] + 2],
                     dtilt_deg + p[:, o[4]])
    return project_mats(p[:, :N_INTR], rc, c, rotmats(p[:, o[5]:o[5] + 3]), p[:, o[5] + 3:o[6]],
                        turn_deg(angle_deg, p[:, o[6]], p[:, o[7]]), points)


@dataclass
class ArmModel:
    """Parameter blocks of the rigid-arm model (``SolveOptions.joint_tilt_axis``)."""

    reference_tilt_index: int
    tilts_deg: dict[int, float]
    origin: np.ndarray                      # (3,) mm, world frame at angle 0
    direction: np.ndarray                   # (2,) azimuth, elevation, rad
    tilt_errors: dict[int, np.ndarray]      # tilt index -> (1,) deg (reference: held at 0)

    def copy(self) -> ArmModel:
        return ArmModel(self.reference_tilt_index, dict(self.tilts_deg), self.origin.copy(),
                        self.direction.copy(), {k: v.copy() for k, v in self.tilt_errors.items()})

    def dtilt(self, tilt_index: int) -> float:
        """Commanded tilt change from the reference tilt, deg."""
        return self.tilts_deg[tilt_index] - self.tilts_deg[self.reference_tilt_index]

    def unit_direction(self) -> np.ndarray:
        return axis_direction(self.direction)[0]


# --------------------------------------------------------------------------- state
@dataclass
class RigState:
    """Parameter blocks of the rig (the arrays Ceres optimises in place)."""

    intrinsics: dict[str, np.ndarray]            # camera -> (5,)
    cam_poses: dict[tuple[str, int], np.ndarray]  # (camera, tilt) -> (6,) [rvec, C]
    board_poses: dict[int, np.ndarray]           # board -> (6,) [rvec, t]
    scale: np.ndarray                            # (1,)
    image_sizes: dict[str, tuple[int, int]]
    stops: dict[tuple[int, float], np.ndarray] = field(default_factory=dict)  # (1,) deg each
    arm: ArmModel | None = None    # set: (camera, tilt) poses follow the rigid-arm model

    def stop(self, d: Detection) -> np.ndarray:
        """Angle-error block of the turntable stop of ``d`` (created at 0 on first use)."""
        return self.stops.setdefault(stop_key(d), np.zeros(1))

    def copy(self) -> RigState:
        return RigState({k: v.copy() for k, v in self.intrinsics.items()},
                        {k: v.copy() for k, v in self.cam_poses.items()},
                        {k: v.copy() for k, v in self.board_poses.items()},
                        self.scale.copy(), dict(self.image_sizes),
                        {k: v.copy() for k, v in self.stops.items()},
                        None if self.arm is None else self.arm.copy())

    def sync_arm(self) -> None:
        """Write the arm model's poses into ``cam_poses`` of the non-reference tilts."""
        arm = self.arm
        if arm is None:
            return
        ref = arm.reference_tilt_index
        for (cam, ti), p in self.cam_poses.items():
            if ti == ref:
                continue
            dphi = np.array([arm.dtilt(ti) + arm.tilt_errors[ti][0]])
            rc, c = arm_pose(self.cam_poses[(cam, ref)][None], arm.origin[None],
                             arm.direction[None], dphi)
            p[:3] = rotvec(rc[0])
            p[3:6] = c[0]

    def params_for(self, d: Detection) -> np.ndarray:
        return np.concatenate([self.intrinsics[d.camera], self.cam_poses[(d.camera, d.tilt_index)],
                               self.board_poses[d.board], self.scale, self.stop(d)])

    def residuals(self, d: Detection, boards: dict[int, np.ndarray]) -> np.ndarray:
        """(N, 2) reprojection residuals of one detection, px."""
        pts = boards[d.board][d.corner_ids]
        return project_batch(self.params_for(d)[None], pts, d.angle_deg)[0] - d.uv

    def model(self, camera: str) -> CameraModel:
        f, cu, cv, d1, d2, aspect = (float(x) for x in self.intrinsics[camera])
        w, h = self.image_sizes[camera]
        return CameraModel(f, cu, cv, d1, d2, int(w), int(h), aspect)

    def pose(self, key: tuple[str, int]) -> Pose:
        p = self.cam_poses[key]
        r = rotmats(p[:3])[0]
        return Pose(r, -r @ p[3:6])

    def apply_gauge(self, yaw_deg: float, dz: float) -> None:
        """Rotate the world by ``yaw_deg`` about Z, then shift it by ``dz`` along Z."""
        q = rotation_z(yaw_deg)
        for p in self.cam_poses.values():
            r = rotmats(p[:3])[0] @ q.T
            p[:3] = rotvec(r)
            p[3:6] = q @ p[3:6] + [0.0, 0.0, dz]
        for p in self.board_poses.values():
            p[:3] = rotvec(q @ rotmats(p[:3])[0])
            p[3:6] = q @ p[3:6] + [0.0, 0.0, dz]
        if self.arm is not None:
            d = q @ self.arm.unit_direction()
            self.arm.direction[:] = [math.atan2(d[1], d[0]), math.asin(np.clip(d[2], -1, 1))]
            self.arm.origin[:] = q @ self.arm.origin + [0.0, 0.0, dz]


def stop_key(d: Detection) -> tuple[int, float]:
    """A turntable stop: every camera at one tilt and one commanded angle shares it."""
    return (d.tilt_index, round(d.angle_deg, 6))


def pose_vec(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``[rotvec, C]`` (6,) of a rotation and a centre."""
    return np.concatenate([rotvec(r), np.asarray(c, dtype=float)])

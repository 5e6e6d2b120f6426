"""Turntable calibration from board detections: initialisation and Ceres refinement.

Everything here works on detections (pixels of known board corners), never on
files, so real corners from another rig can be calibrated directly.

Model
-----
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
``R_b`` and ``t_b``; optionally ``s``.  Images alone cannot tell a rotation of
the world about the turntable axis nor a shift along it (the gauge): they are
fixed by holding the reference camera's centre at ``x = 0`` (on the -Y side of
the axis) and at ``z = 0`` during the solve; afterwards the world is shifted
along Z so that the lowest board corner is at ``lowest_corner_height_mm``.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from plantscan_core.data import Calibration, CameraModel, Pose, TiltAxis, rotation_z
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


@dataclass
class SolveOptions:
    """How the rig is solved.

    Attributes
    ----------
    fix_principal_point : bool
        Hold (cu, cv) at ``principal_points`` (default: image centre).
    principal_points : dict camera -> (cu, cv) px, optional
    fix_distortion : bool
        Hold d1 = d2 = 0 (a rig whose lenses are modelled as distortion-free).
    fit_aspect : bool
        Estimate the pixel aspect ratio (fy = f * aspect) instead of holding it at 1.
    fit_angle_scale : bool
        Estimate the turntable's angle scale (gear ratio error) instead of 1.
    refine : bool
        False returns the seed's initialisation (plane + circle fit) only.
    cauchy_scale_px : float
        Scale of the Cauchy loss of the robust solve.
    outlier_sigma : float
        Corners whose residual exceeds this many sigma (robust) are rejected.
    min_outlier_px : float
        ... unless their residual is below this (px).
    min_views : int
        Fewest detections needed per (camera, tilt).
    lowest_corner_height_mm : float
        World Z of the lowest board corner (fixes the gauge along the axis).
    reference_tilt_index : int or None
        Tilt whose pose anchors the tilt-axis model (default: lowest index).
    max_rms_px, max_rejected_fraction : float
        Above these the calibration is refused (``CalibrationError``).
    max_init_rms_px : float
        An initialisation worse than this means the board spec is wrong: refused at once.
    angle_jitter_deg : float or None
        When set, each turntable stop gets its own angle error (backlash,
        missed steps), estimated with a zero-mean Gaussian prior of this
        standard deviation; None trusts the recorded angles.
    distortion_prior : float or None
        Standard deviation of a zero-mean prior on d1 and d2 (None: no prior).
    prior_noise_px : float
        Corner noise assumed when weighting the priors against the corners.
    cross_validate : bool
        Also solve on even-angle views and report the error on odd ones.
    covariance : bool
        Report parameter 1-sigma from the Ceres covariance.
    max_iterations : int
    joint_tilt_axis : bool
        With two or more tilts, solve the (camera, tilt) poses as one rigid arm:
        each camera's pose at the reference tilt, one tilt axis (origin,
        direction) shared by all cameras and one angle error per tilt index,
        instead of a free pose per (camera, tilt).  A free-pose solve runs
        first; its misfit to the arm model is reported (``quality.tilt_axis``).
    max_arm_rms_ratio : float
        When the arm model's residual RMS of some (camera, tilt) exceeds the free
        poses' by this factor (on the free fit's inliers), the arm is not rigid:
        the free poses are kept and a flag raised.
    """

    fix_principal_point: bool = False
    principal_points: dict[str, tuple[float, float]] = field(default_factory=dict)
    fix_distortion: bool = False
    fit_aspect: bool = False
    fit_angle_scale: bool = False
    refine: bool = True
    cauchy_scale_px: float = 1.0
    outlier_sigma: float = 4.0
    min_outlier_px: float = 0.3
    min_views: int = 3
    lowest_corner_height_mm: float = 0.0
    reference_tilt_index: int | None = None
    max_rms_px: float = 2.0
    max_rejected_fraction: float = 0.05
    max_init_rms_px: float = 50.0
    angle_jitter_deg: float | None = None
    distortion_prior: float | None = 0.3
    prior_noise_px: float = 0.2
    cross_validate: bool = True
    covariance: bool = True
    max_iterations: int = 100
    max_init_views: int = 40
    joint_tilt_axis: bool = True
    max_arm_rms_ratio: float = 1.05


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
                        p[:, I_SCALE], p[:, I_STOP], points, angle_deg)


def project_mats(intr: np.ndarray, rc: np.ndarray, centre: np.ndarray, rb: np.ndarray,
                 tb: np.ndarray, scale: np.ndarray, stop_deg: np.ndarray, points: np.ndarray,
                 angle_deg: float) -> np.ndarray:
    """``project_batch`` with the rotations given as matrices.

    Parameters
    ----------
    intr : (K, 6) ``[f, cu, cv, d1, d2, aspect]``
    rc : (K, 3, 3) world -> camera rotations
    centre : (K, 3) camera centres, mm, world frame
    rb : (K, 3, 3), tb : (K, 3) mm, board -> turntable frame at angle 0
    scale, stop_deg : (K,) angle scale and stop error (deg)
    points : (N, 3) mm, board frame
    angle_deg : float, commanded turntable angle

    Returns
    -------
    (K, N, 2) float64 array, px
    """
    x0 = np.einsum("kij,nj->kni", rb, points) + tb[:, None, :]
    a = np.radians(angle_deg * scale + stop_deg)
    ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
    xw = np.stack([ca * x0[..., 0] - sa * x0[..., 1], sa * x0[..., 0] + ca * x0[..., 1],
                   x0[..., 2]], axis=-1)
    xc = np.einsum("kij,knj->kni", rc, xw - centre[:, None, :])
    xy = xc[..., :2] / xc[..., 2:3]
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    s = 1.0 + intr[:, None, 3:4] * r2 + intr[:, None, 4:5] * r2 * r2
    focal = np.stack([intr[:, 0], intr[:, 0] * intr[:, 5]], axis=-1)[:, None, :]
    return xy * s * focal + intr[:, None, 1:3]


def _fd_jacobian(project, p: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """Pixels ``(N, 2)`` at ``p`` and their Jacobian ``(2N, len(p))`` by forward differences.

    All perturbations go through ``project`` (``(K, len(p)) -> (K, N, 2)``) in one
    call.  Steps are 1e-6 relative (1e-7 for the dimensionless distortion terms):
    the Jacobian is then accurate to ~1e-6 relative, far below corner noise, and
    it only steers the solver (the residuals are exact).  Returns ``(None, ...)``
    when a projection is not finite.
    """
    n = len(p)
    h = 1e-6 * np.maximum(1.0, np.abs(p))
    h[3:5] = 1e-7
    stack = np.repeat(p[None], 1 + n, axis=0)
    stack[1 + np.arange(n), np.arange(n)] += h
    uv = project(stack)
    if not np.all(np.isfinite(uv)):
        return None, np.zeros(0)
    jac = ((uv[1:] - uv[0]).reshape(n, -1) / h[:, None]).T
    return uv[0], jac


def _make_view_cost():
    import pyceres

    class ViewCost(pyceres.CostFunction):
        """All corners of one detection in one cost: 2N residuals, 4 parameter blocks.

        Batching a view amortises the Python call; the Jacobian is a forward
        difference of the vectorised projection (all 20 perturbations in one
        numpy call, ``_fd_jacobian``).
        """

        def __init__(self, points: np.ndarray, uv: np.ndarray, angle_deg: float):
            super().__init__()
            self.points = np.ascontiguousarray(points, dtype=float)
            self.uv = np.ascontiguousarray(uv, dtype=float)
            self.angle_deg = float(angle_deg)
            self.set_num_residuals(2 * len(self.uv))
            self.set_parameter_block_sizes([N_INTR, N_POSE, N_POSE, 1, 1])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            p = np.concatenate([np.asarray(b) for b in parameters])
            if jacobians is None or all(j is None for j in jacobians):
                uv = project_batch(p[None], self.points, self.angle_deg)[0]
                if not np.all(np.isfinite(uv)):
                    return False
                residuals[:] = (uv - self.uv).ravel()
                return True
            uv, jac = _fd_jacobian(lambda x: project_batch(x, self.points, self.angle_deg), p)
            if uv is None:
                return False
            residuals[:] = (uv - self.uv).ravel()
            starts = (I_INTR, I_CAM, I_BOARD, I_SCALE, I_STOP)
            sizes = (N_INTR, N_POSE, N_POSE, 1, 1)
            for j, (s0, n) in enumerate(zip(starts, sizes, strict=True)):
                if jacobians[j] is not None:
                    jacobians[j][:] = jac[:, s0:s0 + n].ravel()
            return True

    return ViewCost


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
                        p[:, o[6]], p[:, o[7]], points, angle_deg)


def _make_arm_cost():
    import pyceres

    class ArmViewCost(pyceres.CostFunction):
        """One view at a non-reference tilt, its camera placed by the arm model."""

        def __init__(self, points: np.ndarray, uv: np.ndarray, angle_deg: float,
                     dtilt_deg: float):
            super().__init__()
            self.points = np.ascontiguousarray(points, dtype=float)
            self.uv = np.ascontiguousarray(uv, dtype=float)
            self.angle_deg = float(angle_deg)
            self.dtilt_deg = float(dtilt_deg)
            self.set_num_residuals(2 * len(self.uv))
            self.set_parameter_block_sizes(list(ARM_SIZES))

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            p = np.concatenate([np.asarray(b) for b in parameters])
            if jacobians is None or all(j is None for j in jacobians):
                uv = project_arm(p[None], self.points, self.angle_deg, self.dtilt_deg)[0]
                if not np.all(np.isfinite(uv)):
                    return False
                residuals[:] = (uv - self.uv).ravel()
                return True
            uv, jac = _fd_jacobian(
                lambda x: project_arm(x, self.points, self.angle_deg, self.dtilt_deg), p)
            if uv is None:
                return False
            residuals[:] = (uv - self.uv).ravel()
            for j, (s0, n) in enumerate(zip(ARM_STARTS, ARM_SIZES, strict=True)):
                if jacobians[j] is not None:
                    jacobians[j][:] = jac[:, s0:s0 + n].ravel()
            return True

    return ArmViewCost


def _make_axis_gauge_cost():
    import pyceres

    class AxisGaugeCost(pyceres.CostFunction):
        """``w * (origin . direction)``: pins the axis origin's free slide along the axis."""

        def __init__(self, weight: float):
            super().__init__()
            self.weight = float(weight)
            self.set_num_residuals(1)
            self.set_parameter_block_sizes([3, 2])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            o, a = np.asarray(parameters[0]), np.asarray(parameters[1])
            d = axis_direction(a)[0]
            residuals[0] = self.weight * float(o @ d)
            if jacobians is not None:
                if jacobians[0] is not None:
                    jacobians[0][:] = self.weight * d
                if jacobians[1] is not None:
                    ce, se = math.cos(a[1]), math.sin(a[1])
                    dd = np.array([[-ce * math.sin(a[0]), -se * math.cos(a[0])],
                                   [ce * math.cos(a[0]), -se * math.sin(a[0])], [0.0, ce]])
                    jacobians[1][:] = self.weight * (o @ dd)
            return True

    return AxisGaugeCost


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


def _pose_vec(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.concatenate([rotvec(r), np.asarray(c, dtype=float)])


# --------------------------------------------------------------------------- initialisation
def label_identical_boards(detections: list[Detection], n_boards: int) -> list[Detection]:
    """Tell apart identical boards standing at different azimuths on the plate.

    A camera sees each board over one arc of turntable angles (while it faces
    the camera); boards back to back give arcs half a turn apart.  The arcs of
    each (camera, tilt) are split at its ``n_boards`` largest gaps (of at least
    one missed stop; another gap of more than three stops means more arcs than
    boards);
    the (camera, tilt) with the most detections defines board 0, 1, ... by its
    arcs, and every other arc takes the board whose arc centre is nearest.
    This assumes all cameras sit within about 90 deg of azimuth of each other
    (one arm), as on a turntable scanner.

    Raises
    ------
    CalibrationError
        A (camera, tilt) whose detections form more arcs than there are boards,
        or two of whose arcs would be the same board.
    """
    if n_boards < 2:
        return list(detections)
    by_ct: dict[tuple[str, int], list[int]] = defaultdict(list)
    for i, d in enumerate(detections):
        by_ct[(d.camera, d.tilt_index)].append(i)
    angles = np.unique(np.round([d.angle_deg % 360.0 for d in detections], 6))
    step = float(np.min(np.diff(angles))) if len(angles) > 1 else 360.0

    def arcs(idx):
        a = np.array([detections[i].angle_deg % 360.0 for i in idx])
        order = np.argsort(a)
        gaps = np.diff(np.concatenate([a[order], [a[order][0] + 360.0]]))
        # Cut at the n largest gaps of at least one missing stop; any other gap of more
        # than three stops means more arcs than boards.
        big = [int(k) for k in np.argsort(-gaps)[:n_boards] if gaps[k] > 1.5 * step]
        rest = np.delete(gaps, big)
        if np.any(rest > 3.0 * step + 1e-6):
            return None
        cuts = np.array(sorted(big), dtype=int)
        if len(cuts) == 0:
            return [list(idx)]
        out = []
        for k, c in enumerate(cuts):  # arc from after cut c to the next cut (circular)
            nxt = cuts[(k + 1) % len(cuts)]
            span = [(c + 1 + j) % len(a) for j in range((nxt - c) % len(a) or len(a))]
            out.append([idx[order[j]] for j in span])
        return out

    def centre(arc):
        a = np.radians([detections[i].angle_deg for i in arc])
        return math.degrees(math.atan2(np.sin(a).sum(), np.cos(a).sum()))

    def dist(x, y):
        return abs((x - y + 180.0) % 360.0 - 180.0)

    ref = max(sorted(by_ct), key=lambda k: len(by_ct[k]))
    def refuse(key, what):
        raise CalibrationError(
            f"camera {key[0]} tilt {key[1]}: the views with a board form {what} of turntable "
            f"angles that cannot be matched to {n_boards} boards (identical chessboards are "
            "told apart by the angles at which each faces the cameras; use ChArUco boards "
            "for other layouts)")

    ref_arcs = arcs(by_ct[ref])
    if ref_arcs is None:
        refuse(ref, f"more than {n_boards} arcs")
    centres = [centre(a) for a in sorted(ref_arcs, key=len, reverse=True)]
    label = {}
    for key, idx in sorted(by_ct.items()):
        ct_arcs = arcs(idx)
        if ct_arcs is None:
            refuse(key, f"more than {n_boards} arcs")
        names = [int(np.argmin([dist(centre(a), c) for c in centres])) for a in ct_arcs]
        if len(set(names)) < len(names):
            refuse(key, f"{len(ct_arcs)} arcs")
        seen = [(round(detections[i].angle_deg, 6), b) for a, b in zip(ct_arcs, names,
                                                                        strict=True) for i in a]
        if len(set(seen)) < len(seen):  # two boards in one image: not separable by angle
            refuse(key, "arcs that overlap (two boards in one image)")
        for a, b in zip(ct_arcs, names, strict=True):
            for i in a:
                label[i] = b
    return [replace(d, board=label[i]) for i, d in enumerate(detections)]


def harmonise_symmetric_order(detections: list[Detection]) -> list[Detection]:
    """Undo 180-degree flips of a symmetric board's corner order along each orbit.

    A chessboard whose inner-corner counts sum to an even number looks the same
    turned by 180 degrees, so a detector may number its corners from either
    end.  Along the orbit of one (camera, tilt, board) consecutive views move
    little, so each view takes the order closer to its predecessor's.
    Only full detections (every corner, ids 0..N-1) are considered.
    """
    groups: dict[tuple, list[int]] = defaultdict(list)
    for i, d in enumerate(detections):
        groups[(d.camera, d.tilt_index, d.board)].append(i)
    out = list(detections)
    for idx in groups.values():
        idx.sort(key=lambda i: out[i].angle_deg)
        prev = None
        for i in idx:
            d = out[i]
            if prev is not None and len(d.uv) == len(prev.uv):
                same = np.mean(np.linalg.norm(d.uv - prev.uv, axis=1))
                flip = np.mean(np.linalg.norm(d.uv[::-1] - prev.uv, axis=1))
                if flip < same:
                    out[i] = replace(d, uv=d.uv[::-1].copy())
            prev = out[i]
    return out


def _init_intrinsics(cam: str, dets: list[Detection], boards: dict[int, np.ndarray],
                     size: tuple[int, int], opt: SolveOptions) -> np.ndarray:
    """Mono calibration of one camera (OpenCV ``calibrateCamera``) on a subset of views."""
    usable = [d for d in dets if len(d.uv) >= 6]
    if len(usable) > opt.max_init_views:
        pick = np.linspace(0, len(usable) - 1, opt.max_init_views).round().astype(int)
        usable = [usable[i] for i in sorted(set(pick))]
    obj = [boards[d.board][d.corner_ids].astype(np.float32) for d in usable]
    img = [d.uv.reshape(-1, 1, 2).astype(np.float32) for d in usable]
    k = cv2.initCameraMatrix2D(obj, img, size)
    f0 = float(np.sqrt(k[0, 0] * k[1, 1]))
    cu, cv_ = opt.principal_points.get(cam, ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0))
    k = np.array([[f0, 0, cu], [0, f0, cv_], [0, 0, 1.0]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3)
    if opt.fix_principal_point:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if opt.fix_distortion:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    _, k, dist, _, _ = cv2.calibrateCamera(obj, img, size, k, np.zeros(5), flags=flags)
    return np.array([(k[0, 0] + k[1, 1]) / 2, k[0, 2], k[1, 2], dist.ravel()[0],
                     dist.ravel()[1], 1.0], dtype=float)


def _board_to_camera(d: Detection, intr: np.ndarray, boards: dict[int, np.ndarray]):
    """(R, t) board -> camera of one detection (PnP with the camera's intrinsics)."""
    k = np.array([[intr[0], 0, intr[1]], [0, intr[0] * intr[5], intr[2]], [0, 0, 1.0]])
    dist = np.array([intr[3], intr[4], 0.0, 0.0, 0.0])
    obj = boards[d.board][d.corner_ids].astype(np.float64)
    ok, rv, tv = cv2.solvePnP(obj, d.uv.astype(np.float64), k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rv, tv = cv2.solvePnP(obj, d.uv.astype(np.float64), k, dist)
    ok, rv, tv = cv2.solvePnP(obj, d.uv.astype(np.float64), k, dist, rv, tv, True,
                              cv2.SOLVEPNP_ITERATIVE)
    return cv2.Rodrigues(rv)[0], tv.reshape(3)


def fit_plane_circle_axis(orbits: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """Turntable axis in a camera frame from the orbits of board corners (the seed's method).

    Parameters
    ----------
    orbits : list of (angles (M,) deg, points (M, 3) mm camera frame)
        Positions of one board corner photographed at several turntable angles.

    Returns
    -------
    direction : (3,) unit vector, camera frame, oriented so that increasing
        turntable angle is a right-handed rotation about it
    point : (3,) mm, camera frame, a point on the axis

    Notes
    -----
    All orbits lie in parallel planes: one SVD of the orbit-centred points
    gives the common normal.  Each orbit's centre comes from Coope's linear
    least-squares circle fit in its plane; the axis passes through the centres.
    """
    centred = np.concatenate([p - p.mean(axis=0) for _, p in orbits])
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    n = vt[2]
    e1, e2 = vt[0], vt[1]
    centres, turn = [], 0.0
    for ang, p in orbits:
        m = p.mean(axis=0)
        x, y = (p - m) @ e1, (p - m) @ e2
        a = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
        sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
        c = m + sol[0] * e1 + sol[1] * e2
        centres.append(c)
        order = np.argsort(ang)
        q = p[order] - c
        turn += float(np.sum(np.cross(q[:-1], q[1:]) @ n * np.sign(np.diff(ang[order]))))
    if turn < 0:
        n = -n
    return n, np.mean(centres, axis=0)


def initialise(detections: list[Detection], boards: dict[int, np.ndarray],
               image_sizes: dict[str, tuple[int, int]], opt: SolveOptions) -> RigState:
    """The seed's initialisation: mono calibration, plane + circle axis fit, board transfer.

    1. ``calibrateCamera`` per camera gives intrinsics; PnP gives every view's
       board -> camera transform.
    2. The (camera, tilt) with the most detections fixes the world: the
       turntable axis from the plane + circle fit of its corner orbits, the
       board poses at angle 0 from its views.
    3. Every other (camera, tilt) gets its pose from views of a board whose
       turntable-frame pose is already known (the "stereo" transfer between
       tilts and cameras); new boards seen there become known in turn.
    """
    by_cam: dict[str, list[Detection]] = defaultdict(list)
    by_ct: dict[tuple[str, int], list[Detection]] = defaultdict(list)
    for d in detections:
        by_cam[d.camera].append(d)
        by_ct[(d.camera, d.tilt_index)].append(d)
    intr = {c: _init_intrinsics(c, ds, boards, image_sizes[c], opt) for c, ds in by_cam.items()}
    b2c = {id(d): _board_to_camera(d, intr[d.camera], boards) for d in detections}

    def n_angles(key):
        return len({round(d.angle_deg, 6) for d in by_ct[key]})

    ref = max(sorted(by_ct), key=lambda k: (n_angles(k), len(by_ct[k])))
    if n_angles(ref) < 3:
        raise CalibrationError(
            "no (camera, tilt) saw a board at 3 or more turntable angles; the turntable axis "
            f"cannot be found (best: camera {ref[0]} tilt {ref[1]} with {n_angles(ref)} angles)")
    orbits = []
    for b in sorted({d.board for d in by_ct[ref]}):
        ds = [d for d in by_ct[ref] if d.board == b]
        for cid in range(len(boards[b])):
            ang, pts = [], []
            for d in ds:
                hit = np.nonzero(d.corner_ids == cid)[0]
                if len(hit):
                    r, t = b2c[id(d)]
                    ang.append(d.angle_deg)
                    pts.append(r @ boards[b][cid] + t)
            if len(ang) >= 3 and np.ptp(ang) > 0:
                orbits.append((np.array(ang), np.array(pts)))
    axis, point = fit_plane_circle_axis(orbits)
    # World frame of the reference: Z = axis, X = any perpendicular, origin on the axis.
    ez = axis
    seed = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = seed - ez * (seed @ ez)
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    r_ref = np.stack([ex, ey, ez], axis=1)   # columns: world axes in camera coordinates
    poses: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {ref: (r_ref, point)}

    board_world: dict[int, list[tuple[np.ndarray, np.ndarray]]] = defaultdict(list)

    def add_board_estimates(key):
        rc, tc = poses[key]
        for d in by_ct[key]:
            r, t = b2c[id(d)]
            rz = rotation_z(-d.angle_deg)
            # board -> world at angle theta, then undo the plate's rotation
            board_world[d.board].append((rz @ rc.T @ r, rz @ rc.T @ (t - tc)))

    add_board_estimates(ref)
    pending = [k for k in sorted(by_ct) if k != ref]
    while pending:
        known = {b: (mean_rotation([r for r, _ in v]), np.mean([t for _, t in v], axis=0))
                 for b, v in board_world.items()}
        progress = False
        for key in list(pending):
            ests = []
            for d in by_ct[key]:
                if d.board in known:
                    rb, tb = known[d.board]
                    r, t = b2c[id(d)]
                    rz = rotation_z(d.angle_deg)
                    # camera <- board = (camera <- world) (world <- board at theta)
                    rw = r @ (rz @ rb).T
                    ests.append((rw, t - rw @ (rz @ tb)))
            if ests:
                poses[key] = (mean_rotation([r for r, _ in ests]),
                              np.mean([t for _, t in ests], axis=0))
                add_board_estimates(key)
                pending.remove(key)
                progress = True
        if not progress:
            raise CalibrationError(
                "these (camera, tilt) share no board with the others, so they cannot be placed "
                f"in one frame: {', '.join(f'{c} tilt {t}' for c, t in pending)}")
    known = {b: (mean_rotation([r for r, _ in v]), np.mean([t for _, t in v], axis=0))
             for b, v in board_world.items()}
    state = RigState(
        intrinsics=intr,
        cam_poses={k: _pose_vec(r, -r.T @ t) for k, (r, t) in poses.items()},
        board_poses={b: _pose_vec(r, t) for b, (r, t) in known.items()},
        scale=np.array([1.0]),
        image_sizes=dict(image_sizes),
    )
    _normalise_gauge(state, reference_key(state))
    return state


def reference_key(state: RigState) -> tuple[str, int]:
    """The (camera, tilt) that anchors the gauge: first camera, lowest tilt index."""
    return min(state.cam_poses)


def gauge_key(state: RigState) -> tuple[str, int]:
    """The pose block held by the gauge (with an arm model: one at the arm's reference tilt)."""
    if state.arm is None:
        return reference_key(state)
    return min(k for k in state.cam_poses if k[1] == state.arm.reference_tilt_index)


def attach_arm(state: RigState, axis: TiltAxis, tilts_deg: dict[int, float]) -> None:
    """Switch ``state`` to the rigid-arm model, starting from a fitted ``axis``."""
    d = np.asarray(axis.direction, dtype=float) / np.linalg.norm(axis.direction)
    o = np.asarray(axis.origin, dtype=float)
    tilts = sorted({t for _, t in state.cam_poses})
    state.arm = ArmModel(axis.reference_tilt_index, {t: float(tilts_deg[t]) for t in tilts},
                         o - d * (o @ d),
                         np.array([math.atan2(d[1], d[0]), math.asin(np.clip(d[2], -1, 1))]),
                         {t: np.zeros(1) for t in tilts})
    state.sync_arm()


def _normalise_gauge(state: RigState, ref: tuple[str, int]) -> None:
    """Turn the world so the reference camera centre is on -Y and at Z = 0."""
    c = state.cam_poses[ref][3:6]
    yaw = -90.0 - math.degrees(math.atan2(c[1], c[0]))
    state.apply_gauge(yaw, 0.0)
    state.apply_gauge(0.0, -float(state.cam_poses[ref][5]))


# --------------------------------------------------------------------------- refinement
@dataclass
class SolveReport:
    """What one Ceres solve did."""

    termination: str
    iterations: int
    seconds: float
    initial_cost: float
    final_cost: float
    usable: bool


def _build_problem(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
                   masks: dict[int, np.ndarray], opt: SolveOptions, robust: bool):
    import pyceres

    view_cost = _make_view_cost()
    arm = state.arm
    arm_cost = _make_arm_cost() if arm is not None else None
    problem = pyceres.Problem()
    loss = pyceres.CauchyLoss(opt.cauchy_scale_px) if robust else pyceres.TrivialLoss()
    n_res = 0
    for i, d in enumerate(detections):
        keep = masks[i]
        if keep.sum() < 4:
            continue
        pts = boards[d.board][d.corner_ids[keep]]
        if arm is not None and d.tilt_index != arm.reference_tilt_index:
            # The camera of this tilt is its reference-tilt pose moved about the arm's axis.
            cost = arm_cost(pts, d.uv[keep], d.angle_deg, arm.dtilt(d.tilt_index))
            blocks = [state.intrinsics[d.camera],
                      state.cam_poses[(d.camera, arm.reference_tilt_index)], arm.origin,
                      arm.direction, arm.tilt_errors[d.tilt_index], state.board_poses[d.board],
                      state.scale, state.stop(d)]
        else:
            cost = view_cost(pts, d.uv[keep], d.angle_deg)
            blocks = [state.intrinsics[d.camera], state.cam_poses[(d.camera, d.tilt_index)],
                      state.board_poses[d.board], state.scale, state.stop(d)]
        problem.add_residual_block(cost, loss, blocks)
        n_res += 2 * int(keep.sum())
    if arm is not None:
        # Sliding the axis origin along the axis changes nothing: pin it nearest the world
        # origin (weight: 1 mm of slide weighs like one corner's noise).
        problem.add_residual_block(_make_axis_gauge_cost()(1.0), None,
                                   [arm.origin, arm.direction])
    fixed = fixed_intrinsics(opt)
    for arr in state.intrinsics.values():
        if len(fixed) == N_INTR:
            problem.set_parameter_block_constant(arr)
        elif fixed:
            problem.set_manifold(arr, pyceres.SubsetManifold(N_INTR, fixed))
        if not opt.fix_distortion and opt.distortion_prior is not None:
            # A board near the image centre leaves d2 (and d1) almost unobserved; a weak
            # zero-mean prior keeps them at lens-like values without biasing covered data.
            problem.add_residual_block(
                _make_prior_cost(N_INTR, [3, 4])(opt.prior_noise_px / opt.distortion_prior),
                None, [arr])
    # Gauge: the reference camera centre stays at x = 0 and z = 0 (see module docstring).
    problem.set_manifold(state.cam_poses[gauge_key(state)], pyceres.SubsetManifold(6, [3, 5]))
    if not opt.fit_angle_scale:
        problem.set_parameter_block_constant(state.scale)
    stops = {stop_key(d) for i, d in enumerate(detections) if masks[i].sum() >= 4}
    for key in stops:
        block = state.stops[key]
        if opt.angle_jitter_deg is None:
            problem.set_parameter_block_constant(block)
        else:
            # Gaussian prior: a stop's error is ~N(0, angle_jitter_deg), in units of the
            # corner noise so that it weighs like that many pixels of evidence.
            weight = opt.prior_noise_px / opt.angle_jitter_deg
            problem.add_residual_block(_make_prior_cost()(weight), None, [block])
    return problem, n_res


def fixed_intrinsics(opt: SolveOptions) -> list[int]:
    """Indices of ``[f, cu, cv, d1, d2, aspect]`` held constant under ``opt``."""
    return (([1, 2] if opt.fix_principal_point else []) + ([3, 4] if opt.fix_distortion else [])
            + ([] if opt.fit_aspect else [5]))


def _make_prior_cost(size: int = 1, which: Sequence[int] = (0,)):
    import pyceres

    which = list(which)

    class PriorCost(pyceres.CostFunction):
        """residual = weight * x[which] (zero-mean Gaussian prior on some entries)."""

        def __init__(self, weight: float):
            super().__init__()
            self.weight = float(weight)
            self.set_num_residuals(len(which))
            self.set_parameter_block_sizes([size])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            x = np.asarray(parameters[0])
            residuals[:] = self.weight * x[which]
            if jacobians is not None and jacobians[0] is not None:
                jac = np.zeros((len(which), size))
                jac[np.arange(len(which)), which] = self.weight
                jacobians[0][:] = jac.ravel()
            return True

    return PriorCost


def _solve(problem, opt: SolveOptions) -> SolveReport:
    import pyceres

    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR
    options.max_num_iterations = opt.max_iterations
    options.function_tolerance = 1e-12
    options.parameter_tolerance = 1e-12
    options.gradient_tolerance = 1e-14
    options.num_threads = 1
    options.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(options, problem, summary)
    return SolveReport(str(summary.termination_type).split(".")[-1],
                       int(summary.num_successful_steps + summary.num_unsuccessful_steps),
                       time.perf_counter() - t0, float(summary.initial_cost),
                       float(summary.final_cost), bool(summary.IsSolutionUsable()))


def inlier_masks(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
                 opt: SolveOptions, masks: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``masks`` minus the corners beyond ``outlier_sigma`` robust sigma (per camera)."""
    norms = {i: np.linalg.norm(state.residuals(d, boards), axis=1)
             for i, d in enumerate(detections)}
    # Noise differs between cameras (sensor, focus, a detector that rounds): one sigma
    # per camera.  The median of a 2-D Gaussian residual norm is 1.1774 sigma (Rayleigh).
    sigma = {}
    for cam in state.intrinsics:
        kept = np.concatenate([norms[i][masks[i]] for i in norms
                               if detections[i].camera == cam] or [np.zeros(1)])
        sigma[cam] = max(float(np.median(kept)) / 1.1774, 1e-6)
    # A corner within min_outlier_px is never an outlier: rendered or very sharp corners
    # have tiny noise but non-Gaussian tails, and a few tenths of a pixel is detector-level.
    return {i: masks[i] & (norms[i] <= max(opt.outlier_sigma * sigma[detections[i].camera],
                                           opt.min_outlier_px)) for i in norms}


def refine(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
           opt: SolveOptions, masks: dict[int, np.ndarray] | None = None,
           reject: bool = True) -> tuple[dict[int, np.ndarray], list[SolveReport], Any]:
    """Robust (Cauchy) solve, reject outliers at ``outlier_sigma``, then plain solves.

    ``state`` is updated in place; ``reject=False`` stops after the robust solve.
    Returns the kept-corner masks per detection, the solve reports and the final
    Ceres problem (for the covariance).
    """
    masks = {i: np.ones(len(d.uv), bool) for i, d in enumerate(detections)} if masks is None \
        else masks
    reports = []
    problem, _ = _build_problem(state, detections, boards, masks, opt, robust=True)
    reports.append(_solve(problem, opt))
    state.sync_arm()
    for _ in range(3 if reject else 0):
        new = inlier_masks(state, detections, boards, opt, masks)
        changed = any(np.any(new[i] != masks[i]) for i in masks)
        masks = new
        problem, _ = _build_problem(state, detections, boards, masks, opt, robust=False)
        reports.append(_solve(problem, opt))
        state.sync_arm()
        if not changed:
            break
    return masks, reports, problem


# --------------------------------------------------------------------------- tilt axis
def fit_tilt_axis(poses: dict[tuple[str, int], Pose], tilts_deg: dict[int, float],
                  reference_tilt_index: int) -> tuple[TiltAxis, dict[str, float]] | None:
    """Tilt-arm axis (world frame at turntable angle 0) from poses at several tilts.

    Moving the arm by ``dphi`` about the axis (``q`` = rotation by ``dphi``
    about ``direction`` through ``origin``) turns a camera pose ``(R, t)`` into
    ``(R q^T, R (o - q^T o) + t)``.  The direction is the least-squares fit of
    the rotation vectors of ``q_i = R_i^T R_ref`` against the commanded
    ``dphi_i``; the origin the least-squares solution of
    ``R_ref^T (t_i - t_ref) = (I - q_i^T) o`` (its component along the axis,
    which is arbitrary, is the one nearest the world origin).

    Returns None when no camera has two tilts.  The second value reports how
    well the axis reproduces the calibrated poses (mm, deg).
    """
    pairs = []
    for (cam, ti), pose in poses.items():
        ref = poses.get((cam, reference_tilt_index))
        if ti == reference_tilt_index or ref is None or ti not in tilts_deg:
            continue
        dphi = tilts_deg[ti] - tilts_deg[reference_tilt_index]
        if abs(dphi) < 1e-6:
            continue
        pairs.append((ref, pose, math.radians(dphi)))
    if not pairs:
        return None
    num = sum(rotvec(p.R.T @ r.R) * d for r, p, d in pairs)
    direction = num / np.linalg.norm(num)
    a_rows, b_rows = [], []
    for r, p, d in pairs:
        q = rotmats(direction * d)[0]
        a_rows.append(np.eye(3) - q.T)
        b_rows.append(r.R.T @ (p.t - r.t))
    origin, *_ = np.linalg.lstsq(np.concatenate(a_rows), np.concatenate(b_rows), rcond=None)
    axis = TiltAxis(origin, direction, reference_tilt_index)
    # How well the one-axis model reproduces each calibrated pose.
    cal = Calibration({}, dict(poses), dict(tilts_deg), 1.0, axis)
    worst_c, worst_r, angle_err = 0.0, 0.0, 0.0
    for r, p, d in pairs:
        q = rotmats(direction * d)[0]
        rr = r.R @ q.T
        tt = r.R @ (origin - q.T @ origin) + r.t
        worst_c = max(worst_c, float(np.linalg.norm(-rr.T @ tt - p.centre)))
        worst_r = max(worst_r, math.degrees(np.linalg.norm(rotvec(rr.T @ p.R))))
        angle_err = max(angle_err, abs(np.linalg.norm(rotvec(p.R.T @ r.R)) - abs(d)))
    del cal
    return axis, {"max_centre_misfit_mm": worst_c, "max_rotation_misfit_deg": worst_r,
                  "max_tilt_angle_misfit_deg": math.degrees(angle_err)}


# --------------------------------------------------------------------------- reports
def residual_stats(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
                   masks: dict[int, np.ndarray] | None = None) -> dict[str, Any]:
    """RMS / max / mean residual (px) overall, per camera, per (camera, tilt), per view."""
    per_cam: dict[str, list[np.ndarray]] = defaultdict(list)
    per_ct: dict[str, list[np.ndarray]] = defaultdict(list)
    views, alln = [], []
    for i, d in enumerate(detections):
        n = np.linalg.norm(state.residuals(d, boards), axis=1)
        if masks is not None:
            n = n[masks[i]]
        if not len(n):
            continue
        alln.append(n)
        per_cam[d.camera].append(n)
        per_ct[f"{d.camera}/t{d.tilt_index}"].append(n)
        views.append({"camera": d.camera, "tilt_index": d.tilt_index,
                      "angle_deg": round(d.angle_deg, 6), "board": d.board,
                      "view_index": d.view_index, "corners": len(n),
                      "rms_px": _rms(n), "max_px": float(n.max())})

    def summ(groups):
        return {k: {"rms_px": _rms(np.concatenate(v)), "max_px": float(np.concatenate(v).max()),
                    "mean_px": float(np.concatenate(v).mean()), "views": len(v)}
                for k, v in sorted(groups.items())}

    a = np.concatenate(alln)
    return {"rms_px": _rms(a), "mean_px": float(a.mean()), "max_px": float(a.max()),
            "corners": int(len(a)), "per_camera": summ(per_cam), "per_camera_tilt": summ(per_ct),
            "per_view": views}


def _rms(n: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(n) ** 2)))


def _arm_pose_covariance(state: RigState, cam: str, tilt: int, ambient) -> np.ndarray:
    """(6, 6) covariance of ``[rotvec, C]`` of an arm-model pose, propagated (first order)
    from its reference pose, the axis and its tilt error."""
    arm = state.arm
    bs = [state.cam_poses[(cam, arm.reference_tilt_index)], arm.origin, arm.direction,
          arm.tilt_errors[tilt]]
    x0 = np.concatenate(bs)

    def pose_of(x):
        rc, c = arm_pose(x[None, :6], x[None, 6:9], x[None, 9:11],
                         np.array([arm.dtilt(tilt) + x[11]]))
        return np.concatenate([rotvec(rc[0]), c[0]])

    jac = np.zeros((6, len(x0)))
    for k in range(len(x0)):
        h = 1e-6 * max(1.0, abs(x0[k]))
        e = np.zeros_like(x0)
        e[k] = h
        jac[:, k] = (pose_of(x0 + e) - pose_of(x0 - e)) / (2 * h)
    return jac @ ambient(bs) @ jac.T


def _covariance(problem, state: RigState, n_res: int, final_cost: float,
                opt: SolveOptions) -> dict[str, Any]:
    """Parameter 1-sigma from the Jacobian Ceres evaluates at the solution.

    ``cov = sigma^2 (J^T J)^-1`` in each block's tangent space, with ``sigma^2``
    the residual variance.  The columns are scaled to unit norm before the
    inversion (pixels per radian and per pixel of focal length differ by 1e6,
    which Ceres' own ``Covariance`` reports as rank deficiency).
    """
    import pyceres

    arm = state.arm
    blocks = (list(state.intrinsics.values()) + list(state.cam_poses.values())
              + list(state.board_poses.values()) + [state.scale]
              + [state.stops[k] for k in sorted(state.stops)])
    if arm is not None:
        blocks += [arm.origin, arm.direction] + [arm.tilt_errors[t]
                                                 for t in sorted(arm.tilt_errors)]
    blocks = [b for b in blocks if problem.has_parameter_block(b)]
    eopt = pyceres.EvaluateOptions()
    eopt.set_parameter_blocks(blocks)
    eopt.apply_loss_function = False
    crs = problem.evaluate_jacobian(eopt)
    rows, cols, vals = (np.asarray(x) for x in (crs.rows, crs.cols, crs.values))
    jac = np.zeros((crs.num_rows, crs.num_cols))
    jac[np.repeat(np.arange(crs.num_rows), np.diff(rows)), cols] = vals
    sizes = [0 if problem.is_parameter_block_constant(b) else
             problem.parameter_block_tangent_size(b) for b in blocks]
    if sum(sizes) != jac.shape[1]:
        sizes = [problem.parameter_block_tangent_size(b) for b in blocks]
    norms = np.linalg.norm(jac, axis=0)
    live = norms > 0
    js = jac[:, live] / norms[live]
    sigma2 = 2.0 * final_cost / max(n_res - int(live.sum()), 1)
    u, sv, vt = np.linalg.svd(js, full_matrices=False)
    if sv[-1] < 1e-10 * sv[0]:
        return {"error": f"Jacobian rank-deficient (condition {sv[0] / sv[-1]:.3g})"}
    inv = (vt.T / sv**2) @ vt
    cov = np.zeros((jac.shape[1], jac.shape[1]))
    idx = np.nonzero(live)[0]
    cov[np.ix_(idx, idx)] = inv / np.outer(norms[live], norms[live]) * sigma2
    offs = np.concatenate([[0], np.cumsum(sizes)])

    def block(b):
        i = next(k for k, x in enumerate(blocks) if x is b)
        return cov[offs[i]:offs[i + 1], offs[i]:offs[i + 1]]

    gauge = state.cam_poses[gauge_key(state)]

    def ambient(bs):
        """Covariance of the ambient entries of blocks ``bs`` (held entries: 0)."""
        idx_cov, idx_amb, n = [], [], 0
        for b in bs:
            i = next(k for k, x in enumerate(blocks) if x is b)
            free = [0, 1, 2, 4] if b is gauge else list(range(offs[i + 1] - offs[i]))
            idx_cov += list(range(offs[i], offs[i + 1]))
            idx_amb += [n + k for k in free]
            n += len(b)
        out_ = np.zeros((n, n))
        out_[np.ix_(idx_amb, idx_amb)] = cov[np.ix_(idx_cov, idx_cov)]
        return out_

    out: dict[str, Any] = {"residual_sigma_px": math.sqrt(sigma2), "models": {}, "poses": {}}
    fixed = fixed_intrinsics(opt)
    free = [k for k in range(N_INTR) if k not in fixed]
    names = INTR_NAMES
    for cam, arr in state.intrinsics.items():
        c = block(arr)
        if c.shape[0] == len(free):
            out["models"][cam] = {names[k]: float(np.sqrt(max(c[i, i], 0)))
                                  for i, k in enumerate(free)}
    for (cam, ti), arr in state.cam_poses.items():
        if not problem.has_parameter_block(arr):  # an arm-model pose: propagate
            c = _arm_pose_covariance(state, cam, ti, ambient)
        else:
            c = block(arr)
        if c.shape[0] == 6:
            centre = float(np.sqrt(max(np.trace(c[3:, 3:]), 0)))
        else:  # the gauge-anchored reference camera: only C_y free
            centre = float(np.sqrt(max(c[3, 3], 0)))
        out["poses"][f"{cam}/t{ti}"] = {
            "centre_mm": centre,
            "rotation_deg": math.degrees(math.sqrt(max(np.trace(c[:3, :3]), 0))),
        }
    if opt.fit_angle_scale:
        out["angle_scale"] = float(np.sqrt(max(block(state.scale)[0, 0], 0)))
    return out


# --------------------------------------------------------------------------- entry point
def calibrate_turntable(detections: list[Detection], boards: dict[int, np.ndarray],
                        image_sizes: dict[str, tuple[int, int]], tilts_deg: dict[int, float],
                        options: SolveOptions | None = None,
                        symmetric_boards: bool = False) -> Calibration:
    """Calibrate a turntable rig from board detections.

    Parameters
    ----------
    detections : list of Detection
    boards : dict board -> (N, 3) float64 array, mm, board frame
        Object points of each board's corners (``corner_ids`` index rows).
    image_sizes : dict camera -> (width, height) px
    tilts_deg : dict tilt index -> commanded tilt, deg
    options : SolveOptions
    symmetric_boards : bool
        True when a board looks the same turned by 180 degrees (corner order
        then harmonised along each orbit).

    Returns
    -------
    Calibration
        Models, poses per (camera, tilt), the tilt axis (when two or more
        tilts), the angle scale and the quality report.

    Raises
    ------
    CalibrationError
        Too few detections for a (camera, tilt), disconnected views, a solve
        that did not converge, residual RMS or rejections above the limits.
    """
    opt = options or SolveOptions()
    if not detections:
        raise CalibrationError("no board detections to calibrate from")
    if symmetric_boards:
        detections = harmonise_symmetric_order(detections)
    counts: dict[tuple[str, int], int] = defaultdict(int)
    for d in detections:
        counts[(d.camera, d.tilt_index)] += 1
    few = {k: n for k, n in counts.items() if n < opt.min_views}
    if few:
        listing = ", ".join(f"camera {c} tilt {t}: {n}" for (c, t), n in sorted(few.items()))
        raise CalibrationError(f"too few board detections (need at least {opt.min_views} per "
                               f"camera and tilt): {listing}")
    t0 = time.perf_counter()
    coverage = {}
    for cam, (w, h) in image_sizes.items():
        uv = np.concatenate([d.uv for d in detections if d.camera == cam] or [np.zeros((0, 2))])
        half_diag = math.hypot(w / 2.0, h / 2.0)
        r = np.linalg.norm(uv - [(w - 1) / 2.0, (h - 1) / 2.0], axis=1) if len(uv) else [0.0]
        coverage[cam] = float(np.max(r) / half_diag)
    state = initialise(detections, boards, image_sizes, opt)
    init_stats = residual_stats(state, detections, boards)
    if not np.isfinite(init_stats["rms_px"]) or init_stats["rms_px"] > opt.max_init_rms_px:
        # Far beyond any lens model: the object points do not describe the detected board.
        raise CalibrationError(
            f"the initial calibration leaves {init_stats['rms_px']:.3g} px RMS (limit "
            f"max_init_rms_px {opt.max_init_rms_px}); the board spec (cols, rows, square size) "
            "does not match the detections")
    quality: dict[str, Any] = {
        "method": "plane+circle initialisation" + (" + pyceres refinement" if opt.refine else ""),
        "initialisation": {"rms_px": init_stats["rms_px"], "max_px": init_stats["max_px"]},
        "detections": len(detections),
        "radial_coverage": coverage,
        "flags": [f"camera {c}: board corners reach only {100 * v:.0f} % of the half-diagonal; "
                  "lens distortion beyond is extrapolated" for c, v in coverage.items()
                  if v < 0.6],
    }
    masks = None
    tilt_indices = {t for _, t in state.cam_poses}
    ref_tilt = opt.reference_tilt_index if opt.reference_tilt_index is not None \
        else min(tilt_indices)
    if opt.refine:
        arm_mode = opt.joint_tilt_axis and len(tilt_indices) >= 2
        # With the arm model to follow, the free poses need only the robust solve (a start
        # and the model check); outliers are rejected in the final model.
        masks, reports, problem = refine(state, detections, boards, opt, reject=not arm_mode)
        if arm_mode:
            # Free poses first: their misfit to one rigid arm checks the model, then the arm
            # model is solved jointly (far fewer pose parameters, every tilt informs all).
            free = {k: state.pose(k) for k in state.cam_poses}
            fitted = fit_tilt_axis(free, tilts_deg, ref_tilt)
            missing = sorted({c for c, _ in free} - {c for c, t in free if t == ref_tilt})
            if fitted is None or missing:
                quality["flags"].append(
                    "joint tilt-axis model not used: cameras without the reference tilt "
                    f"{ref_tilt}: {', '.join(missing) or 'all'}")
            else:
                axis, quality["tilt_axis"] = fitted
                quality["tilt_axis"]["model_check"] = (
                    "free (camera, tilt) poses vs the best one-axis arm through them")
                free_state, free_masks = state.copy(), masks
                attach_arm(state, axis, tilts_deg)
                masks, more, problem = refine(state, detections, boards, opt, masks)
                reports += more
                # A rigid arm costs almost nothing in residual when true (fewer parameters,
                # same fit); a clearly worse fit of some (camera, tilt) means the arm is not
                # one rigid rotation.  Compared on the inliers of the free fit, per pose.
                inl = inlier_masks(free_state, detections, boards, opt, free_masks)
                per_free = residual_stats(free_state, detections, boards, inl)["per_camera_tilt"]
                per_arm = residual_stats(state, detections, boards, inl)["per_camera_tilt"]
                ratio = {k: per_arm[k]["rms_px"] / max(v["rms_px"], 1e-12)
                         for k, v in per_free.items()}
                worst = max(ratio, key=ratio.get)
                quality["tilt_axis"].update({
                    "rms_free_poses_px": {k: v["rms_px"] for k, v in per_free.items()},
                    "rms_arm_model_px": {k: v["rms_px"] for k, v in per_arm.items()},
                    "worst_rms_ratio": ratio[worst]})
                if ratio[worst] > opt.max_arm_rms_ratio:
                    quality["flags"].append(
                        f"the tilting arm is not one rigid rotation: with the joint tilt-axis "
                        f"model {worst} leaves {per_arm[worst]['rms_px']:.3g} px RMS against "
                        f"{per_free[worst]['rms_px']:.3g} px with free poses (free poses kept; "
                        "cameras at uncalibrated tilts are approximate)")
                    state = free_state
                    masks, more, problem = refine(state, detections, boards, opt, free_masks)
                    reports += more
        final = reports[-1]
        quality["solver"] = {"solves": [r.__dict__ for r in reports]}
        if not final.usable or final.termination not in ("CONVERGENCE", "NO_CONVERGENCE"):
            raise CalibrationError(
                f"the calibration solve failed ({final.termination}); initial RMS "
                f"{init_stats['rms_px']:.3g} px — check the board spec and the turntable angles")
        if final.termination == "NO_CONVERGENCE":
            quality["flags"].append(f"solver stopped after {opt.max_iterations} iterations")
        total = sum(len(m) for m in masks.values())
        rejected = [(i, np.nonzero(~m)[0]) for i, m in masks.items() if (~m).any()]
        n_rej = sum(len(r) for _, r in rejected)
        quality["rejected_corners"] = n_rej
        quality["rejected_fraction"] = n_rej / total
        quality["rejected"] = [
            {"camera": detections[i].camera, "tilt_index": detections[i].tilt_index,
             "angle_deg": detections[i].angle_deg, "board": detections[i].board,
             "view_index": detections[i].view_index,
             "corner": int(detections[i].corner_ids[j]),
             "residual_px": float(np.linalg.norm(state.residuals(detections[i], boards)[j]))}
            for i, js in rejected for j in js][:2000]
        n_res = 2 * (total - n_rej)
        if opt.covariance:
            try:
                quality["sigma"] = _covariance(problem, state, n_res, final.final_cost, opt)
            except Exception as exc:  # noqa: BLE001 - a report item, never fatal
                quality["sigma"] = {"error": str(exc)}
        if opt.cross_validate:
            quality["cross_validation"] = _cross_validate(state, detections, boards, masks, opt)
    stats = residual_stats(state, detections, boards, masks)
    quality.update({k: stats[k] for k in ("rms_px", "mean_px", "max_px", "corners",
                                          "per_camera", "per_camera_tilt", "per_view")})
    n_poses = len(state.cam_poses) if state.arm is None else sum(
        1 for _, t in state.cam_poses if t == state.arm.reference_tilt_index)
    n_params = (N_INTR - len(fixed_intrinsics(opt))) * len(state.intrinsics) + 6 * (
        n_poses + len(state.board_poses)) + (0 if state.arm is None else 3 + len(tilt_indices))
    quality["corner_noise_px"] = stats["rms_px"] * math.sqrt(
        2 * stats["corners"] / max(2 * stats["corners"] - n_params, 1) / 2.0)
    # Gauge along the axis: the lowest board corner at the requested height.
    zmin = min(float(np.min((rotmats(p[:3])[0] @ boards[b].T)[2] + p[5]))
               for b, p in state.board_poses.items())
    state.apply_gauge(0.0, opt.lowest_corner_height_mm - zmin)
    models = {c: state.model(c) for c in state.intrinsics}
    poses = {k: state.pose(k) for k in state.cam_poses}
    if opt.angle_jitter_deg is not None and state.stops:
        errs = sorted(((float(v[0]), k) for k, v in state.stops.items()), key=lambda x: -abs(x[0]))
        quality["stop_angle_error_deg"] = {
            "rms": float(np.sqrt(np.mean([e * e for e, _ in errs]))),
            "max": abs(errs[0][0]),
            "largest": [{"tilt_index": k[0], "angle_deg": k[1], "error_deg": e}
                        for e, k in errs[:10]]}
    quality["boards"] = {str(b): {"R": rotmats(p[:3])[0].tolist(), "t": p[3:].tolist()}
                         for b, p in state.board_poses.items()}
    tilt_axis = None
    if state.arm is not None:
        arm = state.arm
        tilt_axis = TiltAxis(arm.origin.copy(), arm.unit_direction(), arm.reference_tilt_index)
        quality["tilt_axis"]["joint"] = True
        quality["tilt_axis"]["tilt_error_deg"] = {int(t): float(v[0])
                                                  for t, v in sorted(arm.tilt_errors.items())}
    elif len(tilt_indices) >= 2:
        fitted = fit_tilt_axis(poses, tilts_deg, ref_tilt)
        if fitted is not None:
            tilt_axis, info = fitted
            quality["tilt_axis"] = {**quality.get("tilt_axis", {}), **info, "joint": False}
    quality["seconds"] = time.perf_counter() - t0
    if opt.refine:
        if stats["rms_px"] > opt.max_rms_px:
            raise CalibrationError(
                f"calibration residual RMS {stats['rms_px']:.3g} px exceeds max_rms_px "
                f"{opt.max_rms_px} (worst: {_worst(stats)}); check the board spec")
        if quality["rejected_fraction"] > opt.max_rejected_fraction:
            raise CalibrationError(
                f"{quality['rejected_corners']} corners ({100 * quality['rejected_fraction']:.1f}"
                f" %) rejected as outliers, above max_rejected_fraction "
                f"{opt.max_rejected_fraction}; worst view: {_worst(stats)}")
    return Calibration(models, poses, {int(k): float(v) for k, v in tilts_deg.items()
                                       if any(t == k for _, t in poses)},
                       float(state.scale[0]), tilt_axis, quality)


def _worst(stats: dict[str, Any]) -> str:
    v = max(stats["per_view"], key=lambda x: x["rms_px"])
    return (f"camera {v['camera']} tilt {v['tilt_index']} angle {v['angle_deg']:g} board "
            f"{v['board']} view {v['view_index']}: {v['rms_px']:.3g} px RMS")


def _cross_validate(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
                    masks: dict[int, np.ndarray], opt: SolveOptions) -> dict[str, Any]:
    """Solve on even turntable stops, report the reprojection error on the odd ones."""
    angles = sorted({round(d.angle_deg, 6) for d in detections})
    rank = {a: i for i, a in enumerate(angles)}
    even = [i for i, d in enumerate(detections) if rank[round(d.angle_deg, 6)] % 2 == 0]
    odd = [i for i, d in enumerate(detections) if rank[round(d.angle_deg, 6)] % 2 == 1]
    train = [detections[i] for i in even]
    if not odd or len({(d.camera, d.tilt_index) for d in train}) < len(state.cam_poses):
        return {"skipped": "too few views to split by odd/even angle"}
    sub = state.copy()
    for i in odd:  # held-out stops keep no angle error fitted on themselves
        sub.stop(detections[i])[:] = 0.0
    problem, _ = _build_problem(sub, train, boards, {j: masks[i] for j, i in enumerate(even)},
                                replace(opt, cross_validate=False), robust=False)
    _solve(problem, opt)
    sub.sync_arm()
    held = np.concatenate([np.linalg.norm(sub.residuals(detections[i], boards), axis=1)[masks[i]]
                           for i in odd])
    fit = np.concatenate([np.linalg.norm(sub.residuals(detections[i], boards), axis=1)[masks[i]]
                          for i in even])
    return {"train": "even angle stops", "rms_train_px": _rms(fit), "rms_heldout_px": _rms(held),
            "difference_px": _rms(held) - _rms(fit)}

"""Turntable-constrained bundle adjustment of feature tracks.

The model is the chessboard calibrator's (``plantscan_calib.model``) with the
board corners replaced by free 3D points: a point ``X`` (turntable frame at
angle 0) seen from camera ``c`` at tilt ``t`` and turntable stop ``k`` projects
as ``CameraModel(R_ct (Rz(theta_k * s + e_k) X - C_ct))``; a point fixed in the
lab (a backdrop marker) is seen at angle 0 in every photo.  Unknowns: per camera
``[f, cu, cv, d1, d2]`` (the aspect held), per (camera, tilt) ``R_ct, C_ct``, per
stop the angle error ``e_k`` (a zero-mean Gaussian prior of ``angle_sigma_deg``:
the commanded angles, with the turntable's backlash as their uncertainty),
optionally the angle scale ``s``, and every point.  There are no per-photo poses:
72 photos of two cameras have 12 pose unknowns, not 432.  Optional Gaussian
priors: the principal point about the image centre, approximate (camera, tilt)
poses.

Gauge: the reference camera's centre is held; with the stop priors this fixes
the world's turn about the axis, its height and its scale, which are set
afterwards (``scale``).

Solvers (``BundleOptions.solver``):

* ``lm`` (default): Levenberg-Marquardt compiled with numba, the points
  eliminated (Schur complement: the reduced camera system is dense and small),
  analytic Jacobians (``_project_jac``, tested against central differences of
  ``_project``), Cauchy loss by iteratively reweighted least squares.
* ``ceres``: pyceres, one residual block per track with central-difference
  Jacobians; ~100x slower, kept as the plain reference the compiled solve is
  tested against (tests/sfm/test_sfm_solver.py).  It has no lab-fixed points.

``adjust`` runs a robust solve, drops observations beyond
max(``outlier_px``, 4 robust sigma) and solves again; ``parameter_sigma`` gives
every parameter's 1-sigma from the reduced normal equations.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from plantscan_calib.model import project_mats, rotmats, rotvec, turn_deg

from plantscan_core.data import CameraModel, Pose, rotation_z
from plantscan_sfm.features import OBSERVATION_KINDS, SfmView, Tracks
from plantscan_sfm.initialise import GroupPose

try:
    import numba

    _jit = numba.njit(cache=True, nogil=True, fastmath=False)
except ImportError:  # pragma: no cover - numba is a dependency
    def _jit(f):
        return f


@_jit
def _project(intr, pose, stop_deg, scale, x, theta_deg, out):
    """Pixel of point ``x`` (3,) under ``intr`` (6,), ``pose`` [rotvec, C] (6,), into out."""
    a = math.radians(theta_deg * scale + stop_deg)
    ca, sa = math.cos(a), math.sin(a)
    xw0 = ca * x[0] - sa * x[1] - pose[3]
    xw1 = sa * x[0] + ca * x[1] - pose[4]
    xw2 = x[2] - pose[5]
    r0, r1, r2 = pose[0], pose[1], pose[2]
    th = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if th < 1e-12:
        c0 = xw0 + (r1 * xw2 - r2 * xw1)
        c1 = xw1 + (r2 * xw0 - r0 * xw2)
        c2 = xw2 + (r0 * xw1 - r1 * xw0)
    else:
        k0, k1, k2 = r0 / th, r1 / th, r2 / th
        ct, st = math.cos(th), math.sin(th)
        kd = k0 * xw0 + k1 * xw1 + k2 * xw2
        c0 = xw0 * ct + (k1 * xw2 - k2 * xw1) * st + k0 * kd * (1.0 - ct)
        c1 = xw1 * ct + (k2 * xw0 - k0 * xw2) * st + k1 * kd * (1.0 - ct)
        c2 = xw2 * ct + (k0 * xw1 - k1 * xw0) * st + k2 * kd * (1.0 - ct)
    if c2 <= 1e-9:
        return False
    px, py = c0 / c2, c1 / c2
    r2_ = px * px + py * py
    s = 1.0 + intr[3] * r2_ + intr[4] * r2_ * r2_
    out[0] = intr[0] * px * s + intr[1]
    out[1] = intr[0] * intr[5] * py * s + intr[2]
    return True


@_jit
def _observe_track(p, offsets, thetas, uv, res, jac, want):
    """Residuals (2L,) and Jacobian (2L, len(p)) of one track's ``L`` observations.

    ``p`` holds every parameter block of the track back to back; ``offsets`` (L, 5)
    gives, per observation, where its [intrinsics, pose, stop, scale, point]
    blocks start in ``p``.
    """
    q = p.copy()
    hi = np.empty(2)
    lo = np.empty(2)
    out = np.empty(2)
    sizes = (6, 6, 1, 1, 3)
    for o in range(offsets.shape[0]):
        oi, op, os_, oc, ox = offsets[o, 0], offsets[o, 1], offsets[o, 2], offsets[o, 3], \
            offsets[o, 4]
        if not _project(p[oi:oi + 6], p[op:op + 6], p[os_], p[oc], p[ox:ox + 3], thetas[o],
                        out):
            return False
        res[2 * o] = out[0] - uv[o, 0]
        res[2 * o + 1] = out[1] - uv[o, 1]
        if not want:
            continue
        for b in range(5):
            start = offsets[o, b]
            for k in range(sizes[b]):
                c = start + k
                h = 1e-6 * max(1.0, abs(p[c]))
                if b == 0 and (k == 3 or k == 4):
                    h = 1e-7
                q[c] = p[c] + h
                ok1 = _project(q[oi:oi + 6], q[op:op + 6], q[os_], q[oc], q[ox:ox + 3],
                               thetas[o], hi)
                q[c] = p[c] - h
                ok2 = _project(q[oi:oi + 6], q[op:op + 6], q[os_], q[oc], q[ox:ox + 3],
                               thetas[o], lo)
                q[c] = p[c]
                if not (ok1 and ok2):
                    return False
                jac[2 * o, c] = (hi[0] - lo[0]) / (2.0 * h)
                jac[2 * o + 1, c] = (hi[1] - lo[1]) / (2.0 * h)
    return True


def _make_track_cost():
    import pyceres

    class TrackCost(pyceres.CostFunction):
        """All observations of one point: blocks [point 3, then each distinct camera
        intrinsics 6, pose 6, stop 1 and the angle scale 1 it is seen with]."""

        def __init__(self, uv: np.ndarray, thetas: np.ndarray, offsets: np.ndarray,
                     sizes: list[int], inv_noise: np.ndarray):
            super().__init__()
            self.w = np.repeat(np.asarray(inv_noise, dtype=float), 2)
            self.unit = bool(np.all(self.w == 1.0))
            self.uv = np.ascontiguousarray(uv, dtype=float)
            self.thetas = np.ascontiguousarray(thetas, dtype=float)
            self.offsets = np.ascontiguousarray(offsets, dtype=np.int64)
            self.sizes = sizes
            self.starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
            self.n = int(self.starts[-1])
            self.set_num_residuals(2 * len(self.uv))
            self.set_parameter_block_sizes(list(sizes))

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            p = np.concatenate(parameters)
            if jacobians is None:
                ok = _observe_track(p, self.offsets, self.thetas, self.uv, residuals,
                                    _DUMMY2, False)
                if ok and not self.unit:
                    residuals[:] = residuals * self.w
                return ok
            jac = np.zeros((len(residuals), self.n))
            if not _observe_track(p, self.offsets, self.thetas, self.uv, residuals, jac, True):
                return False
            if not self.unit:
                residuals[:] = residuals * self.w
                jac *= self.w[:, None]
            st = self.starts
            for j, jb in enumerate(jacobians):
                if jb is not None:
                    jb[:] = jac[:, st[j]:st[j + 1]].ravel()
            return True

    return TrackCost


_DUMMY2 = np.zeros((1, 1))


def _make_prior_cost(size: int):
    import pyceres

    class PriorCost(pyceres.CostFunction):
        """``weight * (x - mean)`` (a Gaussian prior on a whole block)."""

        def __init__(self, mean: np.ndarray, weight: np.ndarray):
            super().__init__()
            self.mean = np.asarray(mean, dtype=float).reshape(size)
            self.weight = np.broadcast_to(np.asarray(weight, dtype=float), (size,)).copy()
            self.set_num_residuals(size)
            self.set_parameter_block_sizes([size])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            x = np.asarray(parameters[0])
            residuals[:] = self.weight * (x - self.mean)
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = np.diag(self.weight).ravel()
            return True

    return PriorCost


def _make_pose_prior_cost():
    import pyceres

    class PosePriorCost(pyceres.CostFunction):
        """Prior on a (camera, tilt) pose: centre within ``sigma_mm``, rotation ``sigma_deg``."""

        def __init__(self, r: np.ndarray, c: np.ndarray, sigma_mm: float, sigma_deg: float):
            super().__init__()
            self.r = np.asarray(r, dtype=float)
            self.c = np.asarray(c, dtype=float)
            self.wc = 1.0 / sigma_mm
            self.wr = 1.0 / math.radians(sigma_deg)
            self.set_num_residuals(6)
            self.set_parameter_block_sizes([6])

        def _res(self, p: np.ndarray) -> np.ndarray:
            dr = rotvec(rotmats(p[:3])[0] @ self.r.T)
            return np.concatenate([self.wr * dr, self.wc * (p[3:6] - self.c)])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            p = np.array(parameters[0], dtype=float)
            r0 = self._res(p)
            residuals[:] = r0
            if jacobians is not None and jacobians[0] is not None:
                jac = np.zeros((6, 6))
                for k in range(6):
                    q = p.copy()
                    q[k] += 1e-7
                    jac[:, k] = (self._res(q) - r0) / 1e-7
                jacobians[0][:] = jac.ravel()
            return True

    return PosePriorCost


@dataclass
class BoardView:
    """One photo of a calibration board by one camera: its corners are known points up
    to the board's rigid pose, which is free (``pose``: [rotvec, t], board frame mm to
    camera frame).  They tie the camera's intrinsics -- the principal point above all,
    which a turntable orbit leaves loose -- and nothing else: the board's pose is its
    own, so neither its units nor where it stood matter.

    Attributes
    ----------
    points : (N, 3) float64 array, mm, board frame
    uv : (N, 2) float64 array, px (detected corners)
    pose : (6,) float64 array
    noise : float
        The corners' noise relative to a refined dot's (the residual's weight is 1 / noise).
    view_index : int
        The photo's index in the scan.
    tilt_deg : float
        How far the board is turned from facing the camera, deg.
    angle_deg, group : float, (camera, tilt) or None
        The photo's turntable angle and (camera, tilt): with ``TurntableState.board_rig``
        the board stood on the turntable, and its corners go through the rig's own pose.
    """

    points: np.ndarray
    uv: np.ndarray
    pose: np.ndarray
    noise: float = 1.0
    view_index: int = -1
    tilt_deg: float = float("nan")
    angle_deg: float | None = None
    group: tuple[str, int] | None = None

    def copy(self) -> BoardView:
        return BoardView(self.points, self.uv, self.pose.copy(), self.noise, self.view_index,
                         self.tilt_deg, self.angle_deg, self.group)


def project_board(intr: np.ndarray, pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of board ``points`` (N, 3) under ``intr`` (6,) and the board's
    ``pose`` [rotvec, t] (6,): the camera model of ``_project``."""
    return _pixels(intr, points @ rotmats(pose[:3])[0].T + pose[3:6])


def project_board_rig(intr: np.ndarray, pose: np.ndarray, rig: np.ndarray, angle_deg: float,
                      points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of board ``points`` (N, 3, mm) on the turntable: ``rig`` (7,)
    [rotvec, t, log scale] places the board in the turntable frame at angle 0 (state
    units), the turntable turns it by ``angle_deg``, the (camera, tilt) ``pose``
    [rotvec, C] and ``intr`` see it."""
    x = math.exp(rig[6]) * (points @ rotmats(rig[:3])[0].T) + rig[3:6]
    xw = x @ rotation_z(angle_deg).T
    return _pixels(intr, (xw - pose[3:6]) @ rotmats(pose[:3])[0].T)


def _pixels(intr: np.ndarray, x: np.ndarray) -> np.ndarray:
    px, py = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
    r2 = px * px + py * py
    s = 1.0 + intr[3] * r2 + intr[4] * r2 * r2
    return np.stack([intr[0] * px * s + intr[1], intr[0] * intr[5] * py * s + intr[2]], 1)


@dataclass
class TurntableState:
    """Parameter blocks of the turntable model (arrays Ceres optimises in place)."""

    intrinsics: dict[str, np.ndarray]                 # camera -> (6,)
    poses: dict[tuple[str, int], np.ndarray]          # (camera, tilt) -> (6,) [rotvec, C]
    stops: dict[tuple[int, float], np.ndarray]        # (tilt, commanded angle) -> (1,) deg
    scale: np.ndarray                                 # (1,) turntable angle scale
    points: np.ndarray                                # (n_tracks, 3)
    image_sizes: dict[str, tuple[int, int]]
    reference: tuple[str, int] = ("", 0)
    pose_priors: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict)
    boards: dict[str, BoardView] = field(default_factory=dict)
    board_rig: np.ndarray | None = None     # (7,) the board on the turntable, when tied

    def model(self, camera: str) -> CameraModel:
        f, cu, cv, d1, d2, aspect = (float(x) for x in self.intrinsics[camera])
        w, h = self.image_sizes[camera]
        return CameraModel(f, cu, cv, d1, d2, int(w), int(h), aspect)

    def group_pose(self, g: tuple[str, int]) -> GroupPose:
        p = self.poses[g]
        return GroupPose(rotmats(p[:3])[0], p[3:6].copy())

    def pose(self, g: tuple[str, int]) -> Pose:
        gp = self.group_pose(g)
        return Pose(gp.R, -gp.R @ gp.C)

    def view_angles(self, views: list[SfmView]) -> np.ndarray:
        """Solved turntable angle of each photo, deg."""
        return np.array([v.view.angle_deg * float(self.scale[0])
                         + float(self.stops[stop_key(v)][0]) for v in views])

    def copy(self) -> TurntableState:
        return TurntableState({k: v.copy() for k, v in self.intrinsics.items()},
                              {k: v.copy() for k, v in self.poses.items()},
                              {k: v.copy() for k, v in self.stops.items()},
                              self.scale.copy(), self.points.copy(), dict(self.image_sizes),
                              self.reference, dict(self.pose_priors),
                              {c: b.copy() for c, b in self.boards.items()},
                              None if self.board_rig is None else self.board_rig.copy())


def stop_key(v: SfmView) -> tuple[int, float]:
    """A turntable stop: every camera at one tilt and one commanded angle shares it."""
    return (v.view.tilt_index, round(v.view.angle_deg, 6))


def new_state(views: list[SfmView], models: dict[str, CameraModel],
              poses: dict[tuple[str, int], GroupPose], points: np.ndarray,
              reference: tuple[str, int]) -> TurntableState:
    return TurntableState(
        intrinsics={c: np.array([m.f, m.cu, m.cv, m.d1, m.d2, m.aspect], float)
                    for c, m in models.items()},
        poses={g: np.concatenate([rotvec(p.R), p.C]) for g, p in poses.items()},
        stops={stop_key(v): np.zeros(1) for v in views},
        scale=np.array([1.0]),
        points=np.array(points, dtype=float),
        image_sizes={c: (m.width, m.height) for c, m in models.items()},
        reference=reference)


def residuals(state: TurntableState, views: list[SfmView], tracks: Tracks) -> np.ndarray:
    """(M, 2) reprojection residuals of every observation, px (NaN behind a camera)."""
    out = np.full((len(tracks.view), 2), np.nan)
    group = 2 * tracks.view.astype(np.int64) + tracks.lab_of()   # (photo, lab-fixed)
    order = np.argsort(group, kind="stable")
    firsts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
    for ks in np.split(order, firsts[1:]):
        i, fixed = divmod(int(group[ks[0]]), 2)
        v = views[i]
        p = state.poses[v.group]
        # a lab-fixed point is seen at turntable angle 0 in every photo
        theta, stop = (0.0, np.zeros(1)) if fixed else (v.view.angle_deg,
                                                        state.stops[stop_key(v)])
        uv = project_mats(state.intrinsics[v.view.camera][None], rotmats(p[:3]), p[None, 3:6],
                          np.eye(3)[None], np.zeros((1, 3)),
                          turn_deg(theta, state.scale, stop),
                          state.points[tracks.track[ks]])[0]
        # project_mats has no cheirality test: points behind the camera are invalid.
        rz = np.radians(theta * state.scale[0] + stop[0])
        c, s = math.cos(rz), math.sin(rz)
        x = state.points[tracks.track[ks]]
        xw = np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], 1)
        depth = (xw - p[3:6]) @ rotmats(p[:3])[0][2]
        uv[depth <= 0] = np.nan
        out[ks] = uv - tracks.uv[ks]
    return out


@dataclass
class BundleOptions:
    """How the turntable bundle adjustment runs.

    Attributes
    ----------
    angle_sigma_deg : float or None
        Standard deviation of a stop's angle error (None: the angles are exact).
    fit_angle_scale : bool
    fix_principal_point, fix_distortion : bool
    cauchy_scale_px : float
        Scale of the Cauchy loss (in units of each observation's noise: px for a dot).
    outlier_px : float
        Observations beyond max(this, 4 robust sigma) are dropped after the robust solve.
        Both are tight because wrong matches of a repeated print pull a shallow view's
        focal length: on the virtual paper-72 dicot, started at the truth (principal point
        the truth's), 1.0 and 1.5 px left cam0 (8 deg of elevation) at f -3.6 % with 187
        kept observations > 2 px from the truth; 0.5 and 1.0 px: f -0.7 %.
    prior_noise_px : float
        Keypoint noise assumed when weighing the priors against the observations.
    pose_prior_mm, pose_prior_deg : float
        Standard deviation of the (camera, tilt) pose priors, when any.
    fixed_focal : list of camera names whose focal length is held (given by the lab).
    principal_point_sigma_px : float or None
        A Gaussian prior holding the free principal point near the image centre (its
        standard deviation; None: no prior).  One orbit leaves the principal point and
        the camera's pitch nearly interchangeable (a rotation about the camera's centre
        moves the image almost as a shift does); the prior keeps that valley bounded.
    max_iterations : int
    threads : int
    solver : str
        ``lm`` (the compiled Schur-complement Levenberg-Marquardt) or ``ceres`` (pyceres,
        one Python cost per track: the plain reference, ~100x slower).
    """

    angle_sigma_deg: float | None = 0.5
    fit_angle_scale: bool = False
    fix_principal_point: bool = False
    fix_distortion: bool = False
    cauchy_scale_px: float = 0.5
    outlier_px: float = 1.0
    prior_noise_px: float = 0.1
    principal_point_sigma_px: float | None = None
    pose_prior_mm: float = 10.0
    pose_prior_deg: float = 5.0
    max_iterations: int = 50
    threads: int = 2
    solver: str = "lm"
    fixed_focal: list[str] = field(default_factory=list)


@dataclass
class BundleReport:
    solves: list[dict[str, Any]]
    observations: int
    rejected: int
    seconds: float


@dataclass
class _BlockLayout:
    """The parameter blocks of one track's cost, each once, and where each starts."""

    blocks: list[np.ndarray]
    sizes: list[int]
    where: dict

    def slot(self, key, arr: np.ndarray) -> int:
        if key not in self.where:
            self.where[key] = sum(self.sizes)
            self.blocks.append(arr)
            self.sizes.append(len(arr))
        return self.where[key]


def _build(state: TurntableState, views: list[SfmView], tracks: Tracks, keep: np.ndarray,
           opt: BundleOptions, robust: bool):
    import pyceres

    track_cost = _make_track_cost()
    problem = pyceres.Problem()
    loss = pyceres.CauchyLoss(opt.cauchy_scale_px) if robust else None
    # Ceres keeps pointers: each point block is a row view of state.points, moved in place.
    point_blocks = {}
    inv_noise = 1.0 / tracks.noise_of()
    idx = np.flatnonzero(keep)
    bounds = np.flatnonzero(np.diff(tracks.track[idx])) + 1
    for obs in np.split(idx, bounds):
        if len(obs) < 2:
            continue
        t = int(tracks.track[obs[0]])
        point_blocks[t] = state.points[t]
        layout = _BlockLayout([point_blocks[t]], [3], {})
        offsets = np.zeros((len(obs), 5), np.int64)
        thetas = np.empty(len(obs))
        for o, k in enumerate(obs):
            v = views[int(tracks.view[k])]
            sk = stop_key(v)
            offsets[o] = (layout.slot(("i", v.view.camera), state.intrinsics[v.view.camera]),
                          layout.slot(("p", v.group), state.poses[v.group]),
                          layout.slot(("s", sk), state.stops[sk]),
                          layout.slot(("c",), state.scale), 0)
            thetas[o] = v.view.angle_deg
        problem.add_residual_block(track_cost(tracks.uv[obs], thetas, offsets, layout.sizes,
                                              inv_noise[obs]), loss, layout.blocks)
    fixed = ([1, 2] if opt.fix_principal_point else []) + \
        ([3, 4] if opt.fix_distortion else []) + [5]
    centre_prior = _make_prior_cost(6)
    for cam, arr in state.intrinsics.items():
        if problem.has_parameter_block(arr):
            held = sorted(set(fixed) | ({0} if cam in opt.fixed_focal else set()))
            problem.set_manifold(arr, pyceres.SubsetManifold(6, held))
            if opt.principal_point_sigma_px and not opt.fix_principal_point:
                w, h = state.image_sizes[cam]
                mean = np.array([0.0, (w - 1) / 2, (h - 1) / 2, 0.0, 0.0, 0.0])
                wt = opt.prior_noise_px / opt.principal_point_sigma_px
                problem.add_residual_block(
                    centre_prior(mean, np.array([0.0, wt, wt, 0.0, 0.0, 0.0])), None, [arr])
    ref = state.poses[state.reference]
    problem.set_manifold(ref, pyceres.SubsetManifold(6, [3, 4, 5]))
    if not opt.fit_angle_scale:
        problem.set_parameter_block_constant(state.scale)
    prior = _make_prior_cost(1)
    for arr in state.stops.values():
        if not problem.has_parameter_block(arr):
            continue
        if opt.angle_sigma_deg is None:
            problem.set_parameter_block_constant(arr)
        else:
            problem.add_residual_block(
                prior(np.zeros(1), opt.prior_noise_px / opt.angle_sigma_deg), None, [arr])
    pose_prior = _make_pose_prior_cost()
    for g, (r, c) in state.pose_priors.items():
        if g in state.poses and problem.has_parameter_block(state.poses[g]) \
                and g != state.reference:
            problem.add_residual_block(
                pose_prior(r, c, opt.pose_prior_mm / opt.prior_noise_px,
                           opt.pose_prior_deg / opt.prior_noise_px), None, [state.poses[g]])
    return problem, point_blocks


def _solve(problem, opt: BundleOptions) -> dict[str, Any]:
    import pyceres

    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR
    options.max_num_iterations = opt.max_iterations
    options.function_tolerance = 1e-10
    options.parameter_tolerance = 1e-10
    options.num_threads = opt.threads
    options.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(options, problem, summary)
    return {"termination": str(summary.termination_type).split(".")[-1],
            "iterations": int(summary.num_successful_steps + summary.num_unsuccessful_steps),
            "seconds": time.perf_counter() - t0, "initial_cost": float(summary.initial_cost),
            "final_cost": float(summary.final_cost), "usable": bool(summary.IsSolutionUsable())}


def adjust(state: TurntableState, views: list[SfmView], tracks: Tracks, opt: BundleOptions,
           keep: np.ndarray | None = None, rounds: int = 2) -> tuple[np.ndarray, BundleReport]:
    """Robust solve, drop outliers, plain solve (``rounds`` times); ``state`` in place.

    Returns the kept observations (M,) bool and the report.
    """
    t0 = time.perf_counter()
    if opt.solver == "ceres" and tracks.lab_of().any():
        raise ValueError("the Ceres reference solve has no lab-fixed points; use solver 'lm'")
    keep = np.isfinite(state.points[tracks.track, 0]) if keep is None else keep.copy()
    # A point behind a camera has no projection: Ceres would refuse the whole problem.
    keep &= np.isfinite(residuals(state, views, tracks)).all(axis=1)
    solves = []
    robust = True
    for _ in range(rounds + 1):
        if opt.solver == "ceres":
            problem, blocks = _build(state, views, tracks, keep, opt, robust)
            solves.append(_solve(problem, opt))
            del blocks  # views into state.points: Ceres moved the points in place
        else:
            solves.append(solve_lm(state, views, tracks, keep, opt, robust))
        # residuals in units of each observation's own noise (markers are noisier)
        r = np.linalg.norm(residuals(state, views, tracks), axis=1) / tracks.noise_of()
        ok = np.isfinite(r)
        sigma = float(np.median(r[keep & ok])) / 1.1774 if (keep & ok).any() else 1.0
        new = keep & ok & (r <= max(opt.outlier_px, 4.0 * sigma))
        # a track needs two observations
        counts = np.bincount(tracks.track[new], minlength=tracks.n_tracks)
        new &= counts[tracks.track] >= 2
        changed = not np.array_equal(new, keep)
        keep = new
        if not robust and not changed:
            break
        robust = False
    return keep, BundleReport(solves, int(keep.sum()), int((~keep).sum()),
                              time.perf_counter() - t0)



INTRINSIC_NAMES = ("f", "cu", "cv", "d1", "d2")


def parameter_sigma(state: TurntableState, views: list[SfmView], tracks: Tracks,
                    keep: np.ndarray, opt: BundleOptions) -> dict[str, Any]:
    """1-sigma of the rig's parameters at the solution, from the Jacobian.

    The reduced camera system of the solve (every point eliminated: the Schur
    complement of the normal equations), priors included and undamped, is inverted
    with its columns scaled to unit norm; the residual variance (in units of each
    observation's noise) scales the result.  Parameters held by the options or the
    gauge get no sigma.  Centres are in the state's units.

    Returns ``models`` (camera -> sigma of f, cu, cv, d1, d2), ``poses``
    (group -> ``rotation_deg``, ``centre_units``), ``stop_angle_deg``,
    ``residual_sigma_px`` and the ``covariance`` with its ``index`` (block -> row).
    """
    lay = layout_of(state, views, tracks, opt)
    keep = keep.copy()
    counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
    keep &= (counts[tracks.track] >= 2) & np.isfinite(state.points[tracks.track, 0])
    prob = _Problem(lay, tracks.track, np.searchsorted(tracks.track,
                                                       np.arange(tracks.n_tracks + 1)),
                    tracks.uv, 1.0 / tracks.noise_of(), keep, None,
                    _prior_terms(state, lay, opt))
    cam, points = pack(state, lay), np.nan_to_num(state.points)
    lin = _linearised(prob, cam, points)
    s_mat = _system(prob, lin, cam, 0.0)[0]
    live = np.flatnonzero(lay.free & (np.diag(s_mat) > 0))
    sub = s_mat[np.ix_(live, live)]
    d = np.sqrt(np.diag(sub))
    u, sv, vt = np.linalg.svd(sub / np.outer(d, d))
    out: dict[str, Any] = {}
    if sv[-1] < 1e-12 * sv[0]:
        out["warning"] = f"information rank-deficient (condition {sv[0] / sv[-1]:.3g})"
    cov_live = (vt.T / np.maximum(sv, 1e-12 * sv[0])) @ u.T / np.outer(d, d)
    n_res = 2 * int(keep.sum())
    n_points = int(np.sum(np.bincount(tracks.track[keep], minlength=tracks.n_tracks) >= 2))
    sigma2 = float(np.sum(lin.res[keep] ** 2)) / max(n_res - len(live) - 3 * n_points, 1)
    cov = np.zeros((lay.size, lay.size))
    cov[np.ix_(live, live)] = cov_live * sigma2
    var = np.diag(cov)
    out.update({"residual_sigma_px": math.sqrt(sigma2), "models": {}, "poses": {}})
    for c in state.intrinsics:
        i = lay.index[("i", c)]
        out["models"][c] = {nm: float(math.sqrt(max(var[i + k], 0.0)))
                            for k, nm in enumerate(INTRINSIC_NAMES) if lay.free[i + k]}
    for g in state.poses:
        i = lay.index[("p", g)]
        out["poses"][g] = {
            "rotation_deg": math.degrees(math.sqrt(max(var[i:i + 3].sum(), 0.0))),
            "centre_units": math.sqrt(max(var[i + 3:i + 6].sum(), 0.0))}
    angles = [math.sqrt(max(var[lay.index[("s", k)]], 0.0)) for k in state.stops
              if lay.free[lay.index[("s", k)]]]
    if angles:
        out["stop_angle_deg"] = {"median": float(np.median(angles)), "max": float(max(angles))}
    out["covariance"], out["index"] = cov, lay.index
    return out


# --------------------------------------------------------------------------- LM solver
# Levenberg-Marquardt with the points eliminated (Schur complement), compiled: the
# Ceres problem above calls one Python cost per track per evaluation, which spent
# ~1 s per iteration on 30k observations (benchmarks/sfm.py); here one compiled
# pass linearises every observation and builds the reduced camera system.  The Ceres
# solve stays as the plain reference it is tested against (tests/sfm).

N_LOCAL = 14  # camera parameters one observation touches: intrinsics 6, pose 6, stop, scale


@dataclass
class Layout:
    """Where each parameter block sits in the camera vector, and each observation's."""

    index: dict                # block key -> first entry in the camera vector
    size: int
    obs_blocks: np.ndarray     # (M, 4) int64: intrinsics, pose, stop, scale entries
    theta: np.ndarray          # (M,) commanded angle, deg
    free: np.ndarray           # (size,) bool


def layout_of(state: TurntableState, views: list[SfmView], tracks: Tracks,
              opt: BundleOptions) -> Layout:
    cams, groups, stops = sorted(state.intrinsics), sorted(state.poses), sorted(state.stops)
    index: dict = {}
    n = 0
    boards = [c for c in sorted(state.boards) if c in state.intrinsics
              and not _on_rig(state, state.boards[c])]
    rig = [(("B",), 7)] if any(_on_rig(state, b) for b in state.boards.values()) else []
    for key, size in ([(("i", c), 6) for c in cams] + [(("p", g), 6) for g in groups]
                      + [(("s", k), 1) for k in stops] + [(("c",), 1), (("lab",), 1)]
                      + [(("b", c), 6) for c in boards] + rig):
        index[key] = n
        n += size
    # photos of cameras this state does not hold (an orbit solved alone) are never seen
    per_view = np.array([[index.get(("i", v.view.camera), -1), index.get(("p", v.group), -1),
                          index.get(("s", stop_key(v)), -1), index[("c",)]] for v in views],
                        np.int64)
    free = np.ones(n, bool)
    for c in cams:
        i = index[("i", c)]
        free[i + 5] = False
        if opt.fix_principal_point:
            free[i + 1:i + 3] = False
        if opt.fix_distortion:
            free[i + 3:i + 5] = False
        if c in opt.fixed_focal:
            free[i] = False
    ref = index[("p", state.reference)]
    free[ref + 3:ref + 6] = False
    if not opt.fit_angle_scale:
        free[index[("c",)]] = False
    if opt.angle_sigma_deg is None:
        for k in stops:
            free[index[("s", k)]] = False
    free[index[("lab",)]] = False
    theta = np.array([v.view.angle_deg for v in views])[tracks.view]
    blocks = per_view[tracks.view]
    # a lab-fixed point: angle 0 and no stop error (the held zero entry "lab")
    lab = tracks.lab_of()
    theta[lab] = 0.0
    blocks[lab, 2] = index[("lab",)]
    return Layout(index, n, blocks, theta, free)


def _on_rig(state: TurntableState, board: BoardView) -> bool:
    """The board photo goes through the rig's pose (the board tied to the turntable)."""
    return state.board_rig is not None and board.angle_deg is not None \
        and board.group in state.poses


def _block(state: TurntableState, key: tuple) -> np.ndarray:
    kind = key[0]
    if kind == "B":
        return state.board_rig
    return (state.intrinsics[key[1]] if kind == "i" else state.poses[key[1]] if kind == "p"
            else state.stops[key[1]] if kind == "s" else state.boards[key[1]].pose
            if kind == "b" else state.scale)


def pack(state: TurntableState, lay: Layout) -> np.ndarray:
    cam = np.zeros(lay.size)
    for key, i in lay.index.items():
        if key[0] == "lab":
            continue
        arr = _block(state, key)
        cam[i:i + len(arr)] = arr
    return cam


def unpack(cam: np.ndarray, state: TurntableState, lay: Layout) -> None:
    for key, i in lay.index.items():
        if key[0] == "lab":
            continue
        arr = _block(state, key)
        arr[:] = cam[i:i + len(arr)]


@_jit
def _project_obs(cam, blocks, x, theta, out):
    i, p, s, c = blocks[0], blocks[1], blocks[2], blocks[3]
    return _project(cam[i:i + 6], cam[p:p + 6], cam[s], cam[c], x, theta, out)


@_jit
def _residuals_lm(cam, points, obs_blocks, track, theta, uv, inv_noise, keep, res):
    """Weighted residuals (M, 2) of the kept observations; False if one is behind."""
    out = np.empty(2)
    for o in range(len(track)):
        if not keep[o]:
            res[o, 0] = 0.0
            res[o, 1] = 0.0
            continue
        if not _project_obs(cam, obs_blocks[o], points[track[o]], theta[o], out):
            return False
        res[o, 0] = (out[0] - uv[o, 0]) * inv_noise[o]
        res[o, 1] = (out[1] - uv[o, 1]) * inv_noise[o]
    return True


def _rotation_and_jacobian(rv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R = exp([rv]x) and the left Jacobian of SO(3) at ``rv`` (d(R x)/d rv = -[R x]x J)."""
    th = float(np.linalg.norm(rv))
    k = np.array([[0.0, -rv[2], rv[1]], [rv[2], 0.0, -rv[0]], [-rv[1], rv[0], 0.0]])
    kk = k @ k
    if th < 1e-8:
        return np.eye(3) + k + 0.5 * kk, np.eye(3) + 0.5 * k + kk / 6.0
    s1, c1 = math.sin(th), math.cos(th)
    return (np.eye(3) + (s1 / th) * k + ((1.0 - c1) / th ** 2) * kk,
            np.eye(3) + ((1.0 - c1) / th ** 2) * k + ((th - s1) / th ** 3) * kk)


@_jit
def _project_jac(intr, pose, rot, jl, stop_deg, scale, x, theta_deg, uv, jc, jp):
    """Pixel ``uv`` (2,) of point ``x`` and its analytic Jacobians: ``jc`` (2, 14) wrt
    [f, cu, cv, d1, d2, aspect, rotvec 3, C 3, stop, scale] and ``jp`` (2, 3) wrt ``x``;
    ``rot``, ``jl``: the pose's rotation and its left Jacobian (``_rotation_and_jacobian``).
    The same model as ``_project`` (its closed form is the reference in the tests)."""
    deg = math.pi / 180.0
    a = (theta_deg * scale + stop_deg) * deg
    ca, sa = math.cos(a), math.sin(a)
    x0, x1, x2 = x[0], x[1], x[2]
    w0, w1, w2 = ca * x0 - sa * x1 - pose[3], sa * x0 + ca * x1 - pose[4], x2 - pose[5]
    da0, da1 = -sa * x0 - ca * x1, ca * x0 - sa * x1          # d (Rz(a) x) / d a
    c0 = rot[0, 0] * w0 + rot[0, 1] * w1 + rot[0, 2] * w2
    c1 = rot[1, 0] * w0 + rot[1, 1] * w1 + rot[1, 2] * w2
    c2 = rot[2, 0] * w0 + rot[2, 1] * w1 + rot[2, 2] * w2
    if c2 <= 1e-9:
        return False
    iz = 1.0 / c2
    px, py = c0 * iz, c1 * iz
    r2 = px * px + py * py
    f, asp, d1, d2 = intr[0], intr[5], intr[3], intr[4]
    dist = 1.0 + d1 * r2 + d2 * r2 * r2
    uv[0] = f * px * dist + intr[1]
    uv[1] = f * asp * py * dist + intr[2]
    dd = d1 + 2.0 * d2 * r2
    a00 = f * (dist + 2.0 * px * px * dd)
    a01 = f * 2.0 * px * py * dd
    a10 = f * asp * 2.0 * px * py * dd
    a11 = f * asp * (dist + 2.0 * py * py * dd)
    # d uv / d c (2, 3)
    e00, e01, e02 = a00 * iz, a01 * iz, -(a00 * px + a01 * py) * iz
    e10, e11, e12 = a10 * iz, a11 * iz, -(a10 * px + a11 * py) * iz
    jc[0, 0], jc[1, 0] = px * dist, asp * py * dist
    jc[0, 1], jc[1, 1] = 1.0, 0.0
    jc[0, 2], jc[1, 2] = 0.0, 1.0
    jc[0, 3], jc[1, 3] = f * px * r2, f * asp * py * r2
    jc[0, 4], jc[1, 4] = f * px * r2 * r2, f * asp * py * r2 * r2
    jc[0, 5], jc[1, 5] = 0.0, f * py * dist
    # d c / d rotvec = -[c]x J_l  ->  row k of -[c]x: (0, c2, -c1), (-c2, 0, c0), (c1, -c0, 0)
    for j in range(3):
        g0 = c2 * jl[1, j] - c1 * jl[2, j]
        g1 = -c2 * jl[0, j] + c0 * jl[2, j]
        g2 = c1 * jl[0, j] - c0 * jl[1, j]
        jc[0, 6 + j] = e00 * g0 + e01 * g1 + e02 * g2
        jc[1, 6 + j] = e10 * g0 + e11 * g1 + e12 * g2
        # d c / d C = -R ; d c / d x = R Rz(a)
        jc[0, 9 + j] = -(e00 * rot[0, j] + e01 * rot[1, j] + e02 * rot[2, j])
        jc[1, 9 + j] = -(e10 * rot[0, j] + e11 * rot[1, j] + e12 * rot[2, j])
    q0 = rot[0, 0] * da0 + rot[0, 1] * da1
    q1 = rot[1, 0] * da0 + rot[1, 1] * da1
    q2 = rot[2, 0] * da0 + rot[2, 1] * da1
    g0 = (e00 * q0 + e01 * q1 + e02 * q2) * deg
    g1 = (e10 * q0 + e11 * q1 + e12 * q2) * deg
    jc[0, 12], jc[1, 12] = g0, g1
    jc[0, 13], jc[1, 13] = g0 * theta_deg, g1 * theta_deg
    for j in range(3):
        # column j of R Rz(a): Rz(a) column j is (ca, sa, 0), (-sa, ca, 0), (0, 0, 1)
        if j == 0:
            m0, m1, m2 = ca, sa, 0.0
        elif j == 1:
            m0, m1, m2 = -sa, ca, 0.0
        else:
            m0, m1, m2 = 0.0, 0.0, 1.0
        k0 = rot[0, 0] * m0 + rot[0, 1] * m1 + rot[0, 2] * m2
        k1 = rot[1, 0] * m0 + rot[1, 1] * m1 + rot[1, 2] * m2
        k2 = rot[2, 0] * m0 + rot[2, 1] * m1 + rot[2, 2] * m2
        jp[0, j] = e00 * k0 + e01 * k1 + e02 * k2
        jp[1, j] = e10 * k0 + e11 * k1 + e12 * k2
    return True


@_jit
def _linearise(cam, rots, jls, points, obs_blocks, track, theta, uv, inv_noise, keep, res,
               jc, jp):
    """Weighted residuals (M, 2) and Jacobians wrt the observation's 14 camera entries
    (M, 2, 14) and its point (M, 2, 3), analytic (``_project_jac``); ``rots``, ``jls``
    (n_cam, 3, 3): rotation and left Jacobian of the pose whose block starts there."""
    out = np.empty(2)
    j1 = np.empty((2, N_LOCAL))
    j2 = np.empty((2, 3))
    for o in range(len(track)):
        if not keep[o]:
            continue
        i, p, s, c = obs_blocks[o, 0], obs_blocks[o, 1], obs_blocks[o, 2], obs_blocks[o, 3]
        if not _project_jac(cam[i:i + 6], cam[p:p + 6], rots[p], jls[p], cam[s], cam[c],
                            points[track[o]], theta[o], out, j1, j2):
            return False
        w = inv_noise[o]
        res[o, 0] = (out[0] - uv[o, 0]) * w
        res[o, 1] = (out[1] - uv[o, 1]) * w
        for r in range(2):
            for k in range(N_LOCAL):
                jc[o, r, k] = j1[r, k] * w
            for k in range(3):
                jp[o, r, k] = j2[r, k] * w
    return True


@_jit
def _local_entries(b, out):
    for k in range(N_LOCAL):
        out[k] = b[0] + k if k < 6 else b[1] + k - 6 if k < 12 else b[2] if k == 12 else b[3]


@_jit
def _reduced_system(n_cam, track_start, obs_blocks, keep, robust_w, res, jc, jp, lam,
                    s_mat, b_vec, u_diag, v_inv, g_p):
    """The reduced camera system ``S dc = -b`` with every point eliminated.

    ``robust_w`` (M,) are the IRLS weights of the robust loss; ``lam`` damps the
    points' 3 x 3 blocks (LM).  Fills ``s_mat`` (n_cam, n_cam), ``b_vec``, the camera
    block's diagonal ``u_diag`` (for its damping), the damped inverse point blocks
    ``v_inv`` (T, 3, 3) and the point gradients ``g_p``; a track with fewer than two
    kept observations is left out (its ``v_inv`` is zero).
    """
    ent = np.empty(N_LOCAL, np.int64)
    pos = -np.ones(n_cam, np.int64)
    loc = np.empty(n_cam, np.int64)
    # one triangle of each observation's and each track's symmetric products, in whatever
    # order its global entries come (an observation's 14 entries are distinct), mirrored
    # once at the end: half the multiply-adds of the full square
    half = np.zeros((n_cam, n_cam))
    for t in range(len(track_start) - 1):
        a0, a1 = track_start[t], track_start[t + 1]
        v = np.zeros((3, 3))
        g = np.zeros(3)
        n_loc = 0
        n_kept = 0
        for o in range(a0, a1):
            n_kept += keep[o]
        v_inv[t] = 0.0
        g_p[t] = 0.0
        if n_kept < 2:
            continue
        for o in range(a0, a1):
            if not keep[o]:
                continue
            _local_entries(obs_blocks[o], ent)
            for k in range(N_LOCAL):
                if pos[ent[k]] < 0:
                    pos[ent[k]] = n_loc
                    loc[n_loc] = ent[k]
                    n_loc += 1
        wmat = np.zeros((n_loc, 3))
        for o in range(a0, a1):
            if not keep[o]:
                continue
            rw = robust_w[o]
            _local_entries(obs_blocks[o], ent)
            for r in range(2):
                for i in range(3):
                    g[i] += rw * jp[o, r, i] * res[o, r]
                    for j in range(3):
                        v[i, j] += rw * jp[o, r, i] * jp[o, r, j]
            for k in range(N_LOCAL):
                gk = ent[k]
                c0, c1 = rw * jc[o, 0, k], rw * jc[o, 1, k]
                b_vec[gk] += c0 * res[o, 0] + c1 * res[o, 1]
                u_diag[gk] += c0 * jc[o, 0, k] + c1 * jc[o, 1, k]
                for m in range(k, N_LOCAL):
                    half[gk, ent[m]] += c0 * jc[o, 0, m] + c1 * jc[o, 1, m]
                pk = pos[gk]
                for i in range(3):
                    wmat[pk, i] += c0 * jp[o, 0, i] + c1 * jp[o, 1, i]
        for i in range(3):
            v[i, i] += lam * v[i, i] + 1e-12
        vi = np.linalg.inv(v)
        v_inv[t] = vi
        g_p[t] = g
        wv = wmat @ vi
        for a in range(n_loc):
            ga = loc[a]
            for i in range(3):
                b_vec[ga] -= wv[a, i] * g[i]
            for c in range(a, n_loc):
                half[ga, loc[c]] -= wv[a, 0] * wmat[c, 0] + wv[a, 1] * wmat[c, 1] \
                    + wv[a, 2] * wmat[c, 2]
        for a in range(n_loc):
            pos[loc[a]] = -1
    for a in range(n_cam):
        s_mat[a, a] += half[a, a]
        for c in range(a + 1, n_cam):
            s_mat[a, c] += half[a, c] + half[c, a]
            s_mat[c, a] += half[a, c] + half[c, a]


@_jit
def _point_steps(n_cam, track_start, obs_blocks, keep, robust_w, jc, jp, v_inv, g_p, dc,
                 dx):
    """Point steps ``dx`` (T, 3) = -V^-1 (g_p + W' dc) for camera step ``dc``."""
    ent = np.empty(N_LOCAL, np.int64)
    for t in range(len(track_start) - 1):
        wdc = np.zeros(3)
        dx[t] = 0.0
        if v_inv[t, 0, 0] == 0.0 and v_inv[t, 1, 1] == 0.0:
            continue
        for o in range(track_start[t], track_start[t + 1]):
            if not keep[o]:
                continue
            rw = robust_w[o]
            _local_entries(obs_blocks[o], ent)
            for r in range(2):
                jd = 0.0
                for k in range(N_LOCAL):
                    jd += jc[o, r, k] * dc[ent[k]]
                for i in range(3):
                    wdc[i] += rw * jp[o, r, i] * jd
        rhs = g_p[t] + wdc
        for i in range(3):
            dx[t, i] = -(v_inv[t, i, 0] * rhs[0] + v_inv[t, i, 1] * rhs[1]
                         + v_inv[t, i, 2] * rhs[2])


@dataclass
class _Problem:
    """One LM solve's fixed inputs (the observations) and its layout."""

    lay: Layout
    track: np.ndarray
    track_start: np.ndarray
    uv: np.ndarray
    inv_noise: np.ndarray
    keep: np.ndarray
    robust_scale: float | None
    priors: list            # (entries (k,), residual function of cam -> (r,)) pairs


def _prior_terms(state: TurntableState, lay: Layout, opt: BundleOptions) -> list:
    """Gaussian priors on camera entries as (entries, residual function) pairs, each
    weighted as the solve weighs a keypoint of ``prior_noise_px``."""
    terms = []
    if opt.angle_sigma_deg is not None:
        w = opt.prior_noise_px / opt.angle_sigma_deg
        for k in state.stops:
            i = lay.index[("s", k)]
            terms.append((np.array([i]), lambda c, i=i, w=w: w * c[i:i + 1]))
    if opt.principal_point_sigma_px and not opt.fix_principal_point:
        w = opt.prior_noise_px / opt.principal_point_sigma_px
        for cam, (wd, ht) in state.image_sizes.items():
            if ("i", cam) not in lay.index:
                continue
            i = lay.index[("i", cam)] + 1
            mean = np.array([(wd - 1) / 2, (ht - 1) / 2])
            terms.append((np.array([i, i + 1]),
                          lambda c, i=i, m=mean, w=w: w * (c[i:i + 2] - m)))
    for g, (r0, c0) in state.pose_priors.items():
        if g == state.reference or ("p", g) not in lay.index:
            continue
        i = lay.index[("p", g)]
        wr = opt.prior_noise_px / math.radians(opt.pose_prior_deg)
        wc = opt.prior_noise_px / opt.pose_prior_mm

        def pose_res(c, i=i, r0=r0, c0=c0, wr=wr, wc=wc):
            dr = rotvec(rotmats(c[i:i + 3])[0] @ np.asarray(r0).T)
            return np.concatenate([wr * dr, wc * (c[i + 3:i + 6] - np.asarray(c0))])

        terms.append((np.arange(i, i + 6), pose_res))
    for cam, board in state.boards.items():
        if ("i", cam) not in lay.index:
            continue
        if _on_rig(state, board) and ("B",) in lay.index:
            i, p, j = lay.index[("i", cam)], lay.index[("p", board.group)], lay.index[("B",)]

            def rig_res(c, i=i, p=p, j=j, b=board):
                return ((project_board_rig(c[i:i + 6], c[p:p + 6], c[j:j + 7], b.angle_deg,
                                           b.points) - b.uv) / b.noise).ravel()

            terms.append((np.r_[np.arange(i, i + 6), np.arange(p, p + 6),
                                np.arange(j, j + 7)], rig_res))
            continue
        if ("b", cam) not in lay.index:
            continue
        i, j = lay.index[("i", cam)], lay.index[("b", cam)]

        def board_res(c, i=i, j=j, b=board):
            return ((project_board(c[i:i + 6], c[j:j + 6], b.points) - b.uv) / b.noise).ravel()

        terms.append((np.r_[np.arange(i, i + 6), np.arange(j, j + 6)], board_res))
    return terms


def _cost(prob: _Problem, cam: np.ndarray, points: np.ndarray) -> tuple[float, np.ndarray]:
    """Robust cost and the residuals (M, 2); inf when a point falls behind a camera."""
    res = np.zeros((len(prob.track), 2))
    if not _residuals_lm(cam, points, prob.lay.obs_blocks, prob.track, prob.lay.theta, prob.uv,
                         prob.inv_noise, prob.keep, res):
        return math.inf, res
    sq = res[:, 0] ** 2 + res[:, 1] ** 2
    if prob.robust_scale:
        b2 = prob.robust_scale ** 2
        cost = float(np.sum(b2 * np.log1p(sq / b2)))
    else:
        cost = float(np.sum(sq))
    for _, fn in prob.priors:
        r = fn(cam)
        cost += float(r @ r)
    return cost, res


@dataclass
class _Linear:
    """The problem linearised at one point: weighted residuals, Jacobians, IRLS weights."""

    res: np.ndarray
    jc: np.ndarray
    jp: np.ndarray
    robust_w: np.ndarray


def _linearised(prob: _Problem, cam: np.ndarray, points: np.ndarray) -> _Linear:
    m = len(prob.track)
    res = np.zeros((m, 2))
    jc = np.zeros((m, 2, N_LOCAL))
    jp = np.zeros((m, 2, 3))
    rots = np.zeros((prob.lay.size, 3, 3))
    jls = np.zeros((prob.lay.size, 3, 3))
    for key, i in prob.lay.index.items():
        if key[0] == "p":
            rots[i], jls[i] = _rotation_and_jacobian(cam[i:i + 3])
    if not _linearise(cam, rots, jls, points, prob.lay.obs_blocks, prob.track,
                      prob.lay.theta, prob.uv, prob.inv_noise, prob.keep, res, jc, jp):
        raise FloatingPointError("a point fell behind a camera")
    sq = res[:, 0] ** 2 + res[:, 1] ** 2
    robust_w = 1.0 / (1.0 + sq / prob.robust_scale ** 2) if prob.robust_scale else \
        np.ones(m)
    return _Linear(res, jc, jp, robust_w)


def _system(prob: _Problem, lin: _Linear, cam: np.ndarray, lam: float):
    """The reduced camera system at damping ``lam`` (points eliminated), priors added:
    ``s_mat``, ``b_vec``, the camera diagonal ``u_diag``, and ``v_inv, g_p`` for the
    point step."""
    n = prob.lay.size
    n_t = len(prob.track_start) - 1
    s_mat, b_vec, u_diag = np.zeros((n, n)), np.zeros(n), np.zeros(n)
    v_inv, g_p = np.zeros((n_t, 3, 3)), np.zeros((n_t, 3))
    _reduced_system(n, prob.track_start, prob.lay.obs_blocks, prob.keep, lin.robust_w,
                    lin.res, lin.jc, lin.jp, lam, s_mat, b_vec, u_diag, v_inv, g_p)
    for entries, fn in prob.priors:
        r0 = fn(cam)
        jac = np.zeros((len(r0), len(entries)))
        for k, e in enumerate(entries):
            q = cam.copy()
            q[e] += 1e-7
            jac[:, k] = (fn(q) - r0) / 1e-7
        s_mat[np.ix_(entries, entries)] += jac.T @ jac
        u_diag[entries] += np.sum(jac ** 2, axis=0)
        b_vec[entries] += jac.T @ r0
    return s_mat, b_vec, u_diag, v_inv, g_p


def _free_solve(s_mat: np.ndarray, b_vec: np.ndarray, free: np.ndarray) -> np.ndarray:
    dc = np.zeros(len(b_vec))
    f = np.flatnonzero(free)
    sub = s_mat[np.ix_(f, f)]
    d = np.sqrt(np.maximum(np.diag(sub), 1e-300))
    dc[f] = -np.linalg.lstsq(sub / np.outer(d, d), b_vec[f] / d, rcond=1e-14)[0] / d
    return dc


def solve_lm(state: TurntableState, views: list[SfmView], tracks: Tracks, keep: np.ndarray,
             opt: BundleOptions, robust: bool) -> dict[str, Any]:
    """Levenberg-Marquardt on the turntable model, ``state`` moved in place."""
    t0 = time.perf_counter()
    lay = layout_of(state, views, tracks, opt)
    keep = keep.copy()
    counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
    keep &= counts[tracks.track] >= 2
    prob = _Problem(lay, tracks.track, np.searchsorted(tracks.track,
                                                       np.arange(tracks.n_tracks + 1)),
                    tracks.uv, 1.0 / tracks.noise_of(), keep,
                    opt.cauchy_scale_px if robust else None, _prior_terms(state, lay, opt))
    cam, points = pack(state, lay), state.points.copy()
    points[~np.isfinite(points)] = 0.0
    cost, _ = _cost(prob, cam, points)
    initial, lam, it, termination = cost, 1e-3, 0, "NO_CONVERGENCE"
    while it < opt.max_iterations:
        lin = _linearised(prob, cam, points)
        while True:
            it += 1
            s_mat, b_vec, u_diag, v_inv, g_p = _system(prob, lin, cam, lam)
            dc = _free_solve(s_mat + np.diag(lam * np.maximum(u_diag, 1e-12)), b_vec,
                             lay.free)
            dx = np.zeros((len(prob.track_start) - 1, 3))
            _point_steps(lay.size, prob.track_start, lay.obs_blocks, keep, lin.robust_w,
                         lin.jc, lin.jp, v_inv, g_p, dc, dx)
            new_cost, _ = _cost(prob, cam + dc, points + dx)
            if new_cost < cost or lam > 1e10 or it >= opt.max_iterations:
                break
            lam *= 4.0
        if not new_cost < cost:
            termination = "CONVERGENCE" if lam > 1e10 else termination
            break
        decrease = (cost - new_cost) / max(cost, 1e-300)
        cam, points, cost = cam + dc, points + dx, new_cost
        lam = max(lam / 3.0, 1e-9)
        if decrease < 1e-10:
            termination = "CONVERGENCE"
            break
    unpack(cam, state, lay)
    finite = np.isfinite(state.points[:, 0])
    state.points[finite] = points[finite]
    return {"termination": termination, "iterations": it,
            "seconds": time.perf_counter() - t0, "initial_cost": initial,
            "final_cost": cost, "usable": bool(np.isfinite(cost))}


# --------------------------------------------------------------- per-track consistency
def _point_fit(prob: _Problem, cam: np.ndarray, points: np.ndarray
               ) -> tuple[_Linear, np.ndarray, np.ndarray]:
    """The problem linearised at ``points``, each track's normal matrix (T, 3, 3) and its
    inverse (zero where a track has fewer than two kept observations)."""
    lin = _linearised(prob, cam, points)
    k = np.flatnonzero(prob.keep)
    n_t = len(prob.track_start) - 1
    normal = np.zeros((n_t, 3, 3))
    np.add.at(normal, prob.track[k], np.einsum("mri,mrj->mij", lin.jp[k], lin.jp[k]))
    counts = np.bincount(prob.track[k], minlength=n_t)
    ok = (counts >= 2) & (np.abs(np.linalg.det(normal)) > 1e-300)
    inv = np.zeros_like(normal)
    inv[ok] = np.linalg.inv(normal[ok])
    return lin, normal, inv


def refine_points(state: TurntableState, views: list[SfmView], tracks: Tracks,
                  keep: np.ndarray, opt: BundleOptions, iterations: int = 4) -> None:
    """Every kept track's point moved to its least-squares position under the held
    cameras (Gauss-Newton, a few steps), in place."""
    lay = layout_of(state, views, tracks, opt)
    prob = _Problem(lay, tracks.track, np.searchsorted(tracks.track,
                                                       np.arange(tracks.n_tracks + 1)),
                    tracks.uv, 1.0 / tracks.noise_of(), keep, None, [])
    cam = pack(state, lay)
    points = np.nan_to_num(state.points)
    k = np.flatnonzero(keep)
    for _ in range(iterations):
        lin, _, inv = _point_fit(prob, cam, points)
        grad = np.zeros((len(points), 3))
        np.add.at(grad, tracks.track[k], np.einsum("mri,mr->mi", lin.jp[k], lin.res[k]))
        step = -np.einsum("tij,tj->ti", inv, grad)
        trial = points + step
        if not np.isfinite(_cost(prob, cam, trial)[0]):
            break
        points = trial
    live = np.isfinite(state.points[:, 0])
    state.points[live] = points[live]


def deleted_residuals(state: TurntableState, views: list[SfmView], tracks: Tracks,
                      keep: np.ndarray, opt: BundleOptions) -> tuple[np.ndarray, np.ndarray]:
    """Each kept observation's residual against its track's point triangulated from the
    track's *other* observations (the leave-one-out residual, to first order), squared
    and in units of the observation's noise, and its degrees of freedom (1 or 2).

    The track's point is refitted without the observation: for the least-squares point
    with Jacobian ``J`` and hat matrix ``H = J (J'J)^-1 J'``, the observation's deleted
    residual is ``(I - H_ii)^-1 r_i`` with covariance ``sigma^2 (I - H_ii)^-1``, so
    ``r_i' (I - H_ii)^+ r_i / sigma^2`` is chi-square with as many degrees of freedom as
    ``I - H_ii`` has rank.  A wrong match that the joint fit half absorbs (a short track,
    the point pulled towards it) stands out here; the cameras' own leverage (thousands
    of observations each) is neglected.  ``state.points`` must be the least-squares
    points (``refine_points`` or a solve).  Not kept: NaN, 0.
    """
    lay = layout_of(state, views, tracks, opt)
    keep = keep & np.isfinite(state.points[tracks.track, 0])
    counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
    keep &= counts[tracks.track] >= 2
    prob = _Problem(lay, tracks.track, np.searchsorted(tracks.track,
                                                       np.arange(tracks.n_tracks + 1)),
                    tracks.uv, 1.0 / tracks.noise_of(), keep, None, [])
    lin, _, inv = _point_fit(prob, pack(state, lay), np.nan_to_num(state.points))
    k = np.flatnonzero(keep)
    jp = lin.jp[k]
    hat = np.einsum("mri,mij,msj->mrs", jp, inv[tracks.track[k]], jp)
    w, vec = np.linalg.eigh(np.eye(2)[None] - hat)
    good = w > 1e-6      # a direction the point alone fits exactly carries no test
    proj = np.einsum("mrs,mr->ms", vec, lin.res[k])
    q = np.sum(np.where(good, proj ** 2 / np.where(good, w, 1.0), 0.0), axis=1)
    stat = np.full(len(tracks.view), np.nan)
    dof = np.zeros(len(tracks.view), np.int64)
    stat[k], dof[k] = q, good.sum(axis=1)
    return stat, dof


def reject_inconsistent(state: TurntableState, views: list[SfmView], tracks: Tracks,
                        keep: np.ndarray, opt: BundleOptions, k_sigma: float = 3.0,
                        passes: int = 4, min_sigma: float = 0.02
                        ) -> tuple[np.ndarray, dict[str, Any]]:
    """Drop, track by track, the observation whose deleted residual
    (``deleted_residuals``) is beyond ``k_sigma`` of its camera's robust residual scale,
    the worst of a track first, until every track is consistent; the cameras held.

    A wrong match of a repeated print (one dot taken for its neighbour) in a track of
    a few photos shifts the fitted point and spreads its error over the good
    observations, which the plain residual bound then misses.  The scale ``sigma`` is
    per camera (the low camera's keypoints are noisier): from the median of the
    two-degree-of-freedom statistics (a chi-square of 2 has median 2 ln 2).  The bound
    is the tail of a ``k_sigma`` Rayleigh (exp(-k^2 / 2): 1.1 % of good observations at
    3) at each statistic's own degrees of freedom.  A track left with one observation
    goes.  ``sigma`` is at least ``min_sigma`` (noise units: px for a dot), so that exact
    pixels do not turn rounding into outliers.  Returns the kept observations and counts.
    """
    from scipy.stats import chi2

    keep = keep.copy()
    tail = math.exp(-k_sigma ** 2 / 2.0)
    bound = {1: float(chi2.isf(tail, 1)), 2: float(chi2.isf(tail, 2))}
    cams = np.array([v.view.camera for v in views])[tracks.view]
    start = int(keep.sum())
    info: dict[str, Any] = {"k_sigma": k_sigma, "passes": 0, "sigma": {}}
    for _ in range(passes):
        refine_points(state, views, tracks, keep, opt)
        stat, dof = deleted_residuals(state, views, tracks, keep, opt)
        ratio = np.zeros(len(stat))
        for c in np.unique(cams):
            two = (cams == c) & (dof == 2) & np.isfinite(stat)
            if two.sum() < 10:
                continue
            s2 = max(float(np.median(stat[two])) / (2.0 * math.log(2.0)), min_sigma ** 2)
            info["sigma"][str(c)] = math.sqrt(s2)
            sel = (cams == c) & (dof > 0) & np.isfinite(stat)
            ratio[sel] = stat[sel] / s2 / np.where(dof[sel] == 2, bound[2], bound[1])
        bad = ratio > 1.0
        if not bad.any():
            break
        # the worst of each track only: one wrong match inflates its track-mates' too
        order = np.lexsort((-ratio, tracks.track))
        first = np.r_[True, np.diff(tracks.track[order]) != 0]
        worst = np.zeros(len(stat), bool)
        worst[order[first]] = True
        keep &= ~(bad & worst)
        counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
        keep &= counts[tracks.track] >= 2
        info["passes"] += 1
    info["rejected_observations"] = start - int(keep.sum())
    return keep, info


# The noise unit of the weighed solve: the default Cauchy scale (0.5) and outlier bound
# (1.0) are then 2 and 4 of each kind's own sigma, and the priors are weighed against
# observations of this many px.
NOISE_UNIT_PX = 0.25
# A (camera, kind) class with fewer kept observations takes its kind's scale over all
# cameras (a median of fewer is itself noisy).
MIN_CLASS_OBSERVATIONS = 30


def noise_by_kind(state: TurntableState, views: list[SfmView], tracks: Tracks,
                  keep: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
    """Each observation's noise from the residuals of its class (camera x kind).

    A raw SIFT keypoint, one moved to a printed dot's centroid and a marker's corner are
    not equally good (virtual paper-72 dicot against the truth: 0.17, 0.025 and
    0.12-0.22 px robust sigma), and weighed alike the many raw keypoints of a camera
    seeing the plate at a grazing angle pull the rig.  The robust sigma of every
    (camera, kind) class's kept residuals at the current solution, in units of
    ``NOISE_UNIT_PX``, becomes its observations' noise.

    Returns
    -------
    noise : (M,) float64 array, in units of NOISE_UNIT_PX
    report : dict, ``"camera/kind"`` -> {observations, sigma_px}
    """
    err = np.linalg.norm(residuals(state, views, tracks), axis=1)
    ok = keep & np.isfinite(err)
    kind = tracks.kind_of()
    camera = np.array([views[i].view.camera for i in tracks.view])
    noise = np.ones(len(err))
    report: dict[str, Any] = {}
    for k, name in enumerate(OBSERVATION_KINDS):
        of_kind = kind == k
        if not (of_kind & ok).any():
            continue
        kind_sigma = float(np.median(err[of_kind & ok])) / 1.1774
        for c in sorted(set(camera[of_kind])):
            cls = of_kind & (camera == c)
            n = int((cls & ok).sum())
            sigma = float(np.median(err[cls & ok])) / 1.1774 if n >= MIN_CLASS_OBSERVATIONS \
                else kind_sigma
            noise[cls] = max(sigma, 1e-3) / NOISE_UNIT_PX
            report[f"{c}/{name}"] = {"observations": n, "sigma_px": sigma}
    return noise, report



# The stop-angle search (``search_stop_angles``): how far and how finely, and what fits.
ANGLE_SEARCH_DEG = 3.0
ANGLE_SEARCH_STEP_DEG = 0.05
ANGLE_SEARCH_INLIER_PX = 2.0


@_jit
def _turn_counts(intr, pose, scale, theta_deg, stop_deg, points, uv, inlier_px):
    """For each stop angle of ``stop_deg`` (K,): the smooth count of ``search_stop_angles``
    (each observation 1 - (e / inlier_px)^2 where positive) of the points (N, 3) seen at
    pixels ``uv`` (N, 2) in one photo, the points held; a point behind the camera counts
    0.  Smooth (1 at 0 px, 0 from the bound on) because the peak of a plain count is a
    plateau a few steps wide."""
    out = np.zeros(len(stop_deg))
    px = np.empty(2)
    for j in range(len(stop_deg)):
        acc = 0.0
        for n in range(len(points)):
            if not _project(intr, pose, stop_deg[j], scale, points[n], theta_deg, px):
                continue
            e2 = ((px[0] - uv[n, 0]) ** 2 + (px[1] - uv[n, 1]) ** 2) / (inlier_px * inlier_px)
            if e2 < 1.0:
                acc += 1.0 - e2
        out[j] = acc
    return out


def search_stop_angles(state: TurntableState, views: list[SfmView], tracks: Tracks,
                       min_gain: float = 1.5) -> dict[str, float]:
    """Stops whose recorded angle is wrong, found by search; ``state.stops`` in place.

    The first solve holds the recorded angles (a far start), so a stop the turntable
    missed by 1 deg has every observation tens of px off and loses them all to the
    outlier bound; the later solves, which free the angles, never see it again (on the
    virtual paper-72 dicot with 20 % of the stops 1 deg off: 48k of 56k observations
    kept, 4.3 px of volume reprojection).  Each stop is turned by -3..3 deg in steps of
    0.05 deg with the points held, and the turn with the most observations within 2 px
    (each counted by 1 - (e / 2 px)^2) is taken when it has ``min_gain`` times the count
    of the recorded angle; the solves refine it.

    Returns ``"tilt/angle"`` -> the turn applied, deg, for the stops moved.
    """
    offsets = np.arange(-ANGLE_SEARCH_DEG, ANGLE_SEARCH_DEG + ANGLE_SEARCH_STEP_DEG / 2,
                        ANGLE_SEARCH_STEP_DEG)
    k = len(offsets)
    zero = int(np.argmin(np.abs(offsets)))
    finite = np.isfinite(state.points[tracks.track, 0]) & ~tracks.lab_of()
    counts: dict[tuple[int, float], np.ndarray] = defaultdict(lambda: np.zeros(k))
    order = np.argsort(tracks.view, kind="stable")
    starts = np.searchsorted(tracks.view[order], np.arange(len(views) + 1))
    for i, v in enumerate(views):
        ks = order[starts[i]:starts[i + 1]]
        ks = ks[finite[ks]]
        if not len(ks):
            continue
        key = stop_key(v)
        counts[key] += _turn_counts(state.intrinsics[v.view.camera], state.poses[v.group],
                                    float(state.scale[0]), v.view.angle_deg,
                                    float(state.stops[key][0]) + offsets,
                                    state.points[tracks.track[ks]], tracks.uv[ks],
                                    ANGLE_SEARCH_INLIER_PX)
    moved = {}
    for key, c in counts.items():
        best = int(np.argmax(c))
        if best != zero and c[best] >= min_gain * max(c[zero], 1.0):
            state.stops[key][0] += offsets[best]
            moved[f"{key[0]}/{key[1]:g}"] = float(offsets[best])
    return moved

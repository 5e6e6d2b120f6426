"""Turntable-constrained bundle adjustment of feature tracks (pyceres).

The model is the chessboard calibrator's (``plantscan_calib.model``) with the
board corners replaced by free 3D points: a point ``X`` (turntable frame at
angle 0) seen from camera ``c`` at tilt ``t`` and turntable stop ``k`` projects
as ``CameraModel(R_ct (Rz(theta_k * s + e_k) X - C_ct))``.  Unknowns: per camera
``[f, cu, cv, d1, d2]``, per (camera, tilt) ``R_ct, C_ct``, per stop the angle
error ``e_k`` (a zero-mean Gaussian prior of ``angle_sigma_deg``: the commanded
angles, with the turntable's backlash as their uncertainty), optionally the
angle scale ``s``, and every point.  There are no per-photo poses: 72 photos of
two cameras have 12 pose unknowns, not 432.

Gauge: the reference camera's centre is held at ``(0, -D, 0)``; this fixes
the world's turn about the axis, its height and its scale, which are set
afterwards (``scale``).

One Ceres residual block per track (a Python cost per observation spent most
of the solve in the Python call); its projections and Jacobian (central
differences of the closed-form projection, in one compiled call) are computed
by ``_observe_track``, whose plain reference is
``plantscan_calib.model.project_mats``.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from plantscan_calib.model import project_mats, rotmats, rotvec, turn_deg

from plantscan_core.data import CameraModel, Pose
from plantscan_sfm.features import SfmView, Tracks
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
                     sizes: list[int]):
            super().__init__()
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
                return _observe_track(p, self.offsets, self.thetas, self.uv, residuals,
                                      _DUMMY2, False)
            jac = np.zeros((len(residuals), self.n))
            if not _observe_track(p, self.offsets, self.thetas, self.uv, residuals, jac, True):
                return False
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


def _make_surface_cost(kind: str):
    import pyceres

    class SurfaceCost(pyceres.CostFunction):
        """A printed point lies on the plate: ``w (z - h)`` (its top, a plane normal to the
        axis) or ``w (sqrt(x^2 + y^2) - rho)`` (its rim, a cylinder about the axis)."""

        def __init__(self, weight: float):
            super().__init__()
            self.w = float(weight)
            self.set_num_residuals(1)
            self.set_parameter_block_sizes([3, 1])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            x, h = parameters[0], parameters[1]
            if kind == "plane":
                residuals[0] = self.w * (x[2] - h[0])
                d = (0.0, 0.0, self.w)
            else:
                r = math.hypot(x[0], x[1])
                if r < 1e-9:
                    return False
                residuals[0] = self.w * (r - h[0])
                d = (self.w * x[0] / r, self.w * x[1] / r, 0.0)
            if jacobians is not None:
                if jacobians[0] is not None:
                    jacobians[0][:] = d
                if jacobians[1] is not None:
                    jacobians[1][0] = -self.w
            return True

    return SurfaceCost


@dataclass
class PlateSurfaces:
    """Tracks printed on the plate's top (a plane normal to the axis) and its rim (a
    cylinder about it), with the plane's height and the rim's radius as unknowns.

    ``weight``: residual per unit of distance off the surface (px per model unit).
    """

    top_tracks: np.ndarray
    rim_tracks: np.ndarray
    height: np.ndarray     # (1,) model units
    radius: np.ndarray     # (1,) model units
    weight: float


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
    plate: PlateSurfaces | None = None

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
                              self.reference, dict(self.pose_priors), self.plate)


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
    by_view = defaultdict(list)
    for k, i in enumerate(tracks.view):
        by_view[int(i)].append(k)
    for i, ks in by_view.items():
        v = views[i]
        ks = np.array(ks)
        p = state.poses[v.group]
        uv = project_mats(state.intrinsics[v.view.camera][None], rotmats(p[:3]), p[None, 3:6],
                          np.eye(3)[None], np.zeros((1, 3)),
                          turn_deg(v.view.angle_deg, state.scale, state.stops[stop_key(v)]),
                          state.points[tracks.track[ks]])[0]
        # project_mats has no cheirality test: points behind the camera are invalid.
        rz = np.radians(v.view.angle_deg * state.scale[0] + state.stops[stop_key(v)][0])
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
    outlier_px : float
        Observations beyond max(this, 4 robust sigma) are dropped after the robust solve.
    prior_noise_px : float
        Keypoint noise assumed when weighing the priors against the observations.
    pose_prior_mm, pose_prior_deg : float
        Standard deviation of the (camera, tilt) pose priors, when any.
    fixed_focal : list of camera names whose focal length is held (given by the lab).
    max_iterations : int
    threads : int
    """

    angle_sigma_deg: float | None = 0.5
    fit_angle_scale: bool = False
    fix_principal_point: bool = False
    fix_distortion: bool = False
    cauchy_scale_px: float = 1.0
    outlier_px: float = 1.5
    prior_noise_px: float = 0.5
    pose_prior_mm: float = 10.0
    pose_prior_deg: float = 5.0
    max_iterations: int = 50
    threads: int = 2
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
        problem.add_residual_block(track_cost(tracks.uv[obs], thetas, offsets, layout.sizes),
                                   loss, layout.blocks)
    fixed = ([1, 2] if opt.fix_principal_point else []) + \
        ([3, 4] if opt.fix_distortion else []) + [5]
    for cam, arr in state.intrinsics.items():
        if problem.has_parameter_block(arr):
            held = sorted(set(fixed) | ({0} if cam in opt.fixed_focal else set()))
            problem.set_manifold(arr, pyceres.SubsetManifold(6, held))
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
    if state.plate is not None:
        pl = state.plate
        for kind, ids, arr in (("plane", pl.top_tracks, pl.height),
                               ("cylinder", pl.rim_tracks, pl.radius)):
            cost = _make_surface_cost(kind)
            for t in ids:
                if int(t) in point_blocks:
                    problem.add_residual_block(cost(pl.weight), None,
                                               [point_blocks[int(t)], arr])
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
    keep = np.isfinite(state.points[tracks.track, 0]) if keep is None else keep.copy()
    # A point behind a camera has no projection: Ceres would refuse the whole problem.
    keep &= np.isfinite(residuals(state, views, tracks)).all(axis=1)
    solves = []
    robust = True
    for _ in range(rounds + 1):
        problem, blocks = _build(state, views, tracks, keep, opt, robust)
        solves.append(_solve(problem, opt))
        del blocks  # views into state.points: Ceres moved the points in place
        r = np.linalg.norm(residuals(state, views, tracks), axis=1)
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


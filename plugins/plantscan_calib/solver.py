"""Turntable calibration from board detections: the Ceres refinement and its quality.

The rig model (parameter blocks, projection) is in ``model``, its first estimate
in ``initialise``.  Here: the options of the solve (``SolveOptions``, the base of
the turntable calibrator's parameters), one finite-difference cost for a view's
corners under either pose model, the robust solve with outlier rejection, the
free-poses versus rigid-arm choice, the covariance, and ``CalibrationQuality``:
everything a user needs to judge the calibration, saved with it.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import cache
from typing import Any

import numpy as np
from pydantic import Field

from plantscan_calib.initialise import (
    attach_arm,
    fit_tilt_axis,
    gauge_key,
    harmonise_symmetric_order,
    initialise,
    label_identical_boards,
)
from plantscan_calib.model import (
    ARM_SIZES,
    INTR_NAMES,
    N_INTR,
    VIEW_SIZES,
    CalibrationError,
    Detection,
    RigState,
    arm_pose,
    axis_direction,
    project_arm,
    project_batch,
    rotmats,
    rotvec,
    stop_key,
)
from plantscan_core.data import Calibration, TiltAxis
from plantscan_core.stages import StageParams, StageWarning

__all__ = ["CalibrationError", "CalibrationQuality", "Detection", "SolveOptions",
           "TurntableSolution", "calibrate_turntable", "label_identical_boards",
           "solve_turntable"]

# Rejected corners listed by name in the quality report, worst first: a list a person can
# read in the YAML (``rejected_corners`` counts them all).
MAX_LISTED_REJECTED = 2000
# A camera whose board corners reach less of the image's half-diagonal than this has its
# lens distortion beyond them extrapolated: flagged.
MIN_RADIAL_COVERAGE = 0.6


# --------------------------------------------------------------------------- options
class SolveOptions(StageParams):
    """How the rig is solved: the solver's parameters (``calibrate.params`` of ``turntable``).

    The turntable calibrator's ``Params`` extends this model, so each option has one
    default, here, and is set flat in a recipe (``calibrate.params.outlier_sigma``).
    """

    fix_principal_point: bool = Field(
        False, description="hold (cu, cv) at principal_points (default: the image centre)")
    principal_points: dict[str, tuple[float, float]] = Field(
        default_factory=dict, description="camera -> (cu, cv) px held by fix_principal_point")
    fix_distortion: bool = Field(
        False, description="hold d1 = d2 = 0 (lenses modelled as distortion-free)")
    fit_aspect: bool = Field(False, description="estimate the pixel aspect ratio "
                             "(fy = f * aspect); off: square pixels, as the seed")
    fit_angle_scale: bool = Field(
        False, description="estimate the turntable's angle scale (gear ratio error)")
    refine: bool = Field(
        True, description="false: the seed's initialisation (plane + circle fit) only")
    cauchy_scale_px: float = Field(1.0, gt=0, description="Cauchy loss scale of the robust "
                                   "solve, px")
    outlier_sigma: float = Field(4.0, gt=1, description="corners beyond this many robust "
                                 "sigma (per camera) are rejected")
    min_outlier_px: float = Field(0.3, ge=0, description="a corner closer than this is "
                                  "never rejected as an outlier")
    min_views: int = Field(3, ge=1, description="fewest board detections per camera and tilt")
    lowest_corner_height_mm: float = Field(
        0.0, description="world Z of the lowest board corner (fixes the frame along the axis)")
    reference_tilt_index: int | None = Field(
        None, description="tilt whose pose anchors the tilt-axis model (default: the lowest)")
    max_rms_px: float = Field(2.0, gt=0, description="a larger residual RMS is refused")
    max_rejected_fraction: float = Field(0.05, ge=0, le=1, description="a larger share of "
                                         "rejected corners is refused")
    max_init_rms_px: float = Field(50.0, gt=0, description="an initialisation worse than "
                                   "this means the board spec is wrong: refused at once")
    angle_jitter_deg: float | None = Field(
        None, gt=0, description="each turntable stop gets its own angle error with a "
        "zero-mean Gaussian prior of this sigma (backlash, missed steps); null trusts the "
        "recorded angles")
    distortion_prior: float | None = Field(
        0.3, gt=0, description="sigma of a zero-mean prior on d1 and d2 (null: none)")
    prior_noise_px: float = Field(0.2, gt=0, description="corner noise assumed when weighing "
                                  "the priors against the corners, px")
    cross_validate: bool = Field(
        True, description="also solve on even-angle views, report the error on odd ones")
    covariance: bool = Field(True, description="report parameter 1-sigma (Jacobian at the "
                             "solution)")
    max_iterations: int = Field(100, ge=1)
    max_init_views: int = Field(40, ge=3, description="views per camera of the initial mono "
                                "calibration")
    joint_tilt_axis: bool = Field(True, description="solve the (camera, tilt) poses as one "
                                  "rigid tilting arm (one axis, one angle error per tilt)")
    max_arm_rms_ratio: float = Field(
        1.05, ge=1, description="the arm model is dropped (free poses kept, flagged) when it "
        "leaves some (camera, tilt) this much more residual RMS than free poses")


def fixed_intrinsics(opt: SolveOptions) -> list[int]:
    """Indices of ``[f, cu, cv, d1, d2, aspect]`` held constant under ``opt``."""
    return (([1, 2] if opt.fix_principal_point else []) + ([3, 4] if opt.fix_distortion else [])
            + ([] if opt.fit_aspect else [5]))


# --------------------------------------------------------------------------- costs
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


@cache
def _projection_cost():
    import pyceres

    class ProjectionCost(pyceres.CostFunction):
        """All corners of one detection in one cost: 2N residuals, one parameter block
        per entry of ``sizes`` (the layout of ``project``'s parameter rows).

        ``project`` maps ``(K, sum(sizes))`` parameter rows to ``(K, N, 2)`` pixels:
        batching a view amortises the Python call, and the Jacobian is a forward
        difference of the vectorised projection (all perturbations in one numpy
        call, ``_fd_jacobian``).  A view seen from a free pose projects with
        ``project_batch``, one moved by the arm model with ``project_arm``.
        """

        def __init__(self, project: Callable[[np.ndarray], np.ndarray], uv: np.ndarray,
                     sizes: Sequence[int]):
            super().__init__()
            self.project = project
            self.uv = np.ascontiguousarray(uv, dtype=float)
            self.sizes = tuple(int(n) for n in sizes)
            self.starts = tuple(int(x) for x in np.cumsum((0,) + self.sizes[:-1]))
            self.set_num_residuals(2 * len(self.uv))
            self.set_parameter_block_sizes(list(self.sizes))

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            p = np.concatenate([np.asarray(b) for b in parameters])
            if jacobians is None or all(j is None for j in jacobians):
                uv = self.project(p[None])[0]
                if not np.all(np.isfinite(uv)):
                    return False
                residuals[:] = (uv - self.uv).ravel()
                return True
            uv, jac = _fd_jacobian(self.project, p)
            if uv is None:
                return False
            residuals[:] = (uv - self.uv).ravel()
            for j, (s0, n) in enumerate(zip(self.starts, self.sizes, strict=True)):
                if jacobians[j] is not None:
                    jacobians[j][:] = jac[:, s0:s0 + n].ravel()
            return True

    return ProjectionCost


def _view_cost(points: np.ndarray, uv: np.ndarray, angle_deg: float):
    """The cost of a view from a free (camera, tilt) pose (blocks ``VIEW_SIZES``)."""
    pts, angle = np.ascontiguousarray(points, dtype=float), float(angle_deg)
    return _projection_cost()(lambda x: project_batch(x, pts, angle), uv, VIEW_SIZES)


def _arm_cost(points: np.ndarray, uv: np.ndarray, angle_deg: float, dtilt_deg: float):
    """The cost of a view at a non-reference tilt, its camera placed by the arm model
    (blocks ``ARM_SIZES``)."""
    pts, angle, dtilt = np.ascontiguousarray(points, dtype=float), float(angle_deg), float(
        dtilt_deg)
    return _projection_cost()(lambda x: project_arm(x, pts, angle, dtilt), uv, ARM_SIZES)


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

    arm = state.arm
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
            cost = _arm_cost(pts, d.uv[keep], d.angle_deg, arm.dtilt(d.tilt_index))
            blocks = [state.intrinsics[d.camera],
                      state.cam_poses[(d.camera, arm.reference_tilt_index)], arm.origin,
                      arm.direction, arm.tilt_errors[d.tilt_index], state.board_poses[d.board],
                      state.scale, state.stop(d)]
        else:
            cost = _view_cost(pts, d.uv[keep], d.angle_deg)
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
    the residual variance (``_tangent_covariance``); per camera the 1-sigma of its
    free intrinsics, per (camera, tilt) of its centre (mm) and rotation (deg).
    """
    arm = state.arm
    blocks = (list(state.intrinsics.values()) + list(state.cam_poses.values())
              + list(state.board_poses.values()) + [state.scale]
              + [state.stops[k] for k in sorted(state.stops)])
    if arm is not None:
        blocks += [arm.origin, arm.direction] + [arm.tilt_errors[t]
                                                 for t in sorted(arm.tilt_errors)]
    blocks = [b for b in blocks if problem.has_parameter_block(b)]
    solved = _tangent_covariance(problem, blocks, n_res, final_cost)
    if isinstance(solved, str):
        return {"error": solved}
    cov, offs, sigma2 = solved

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
    for cam, arr in state.intrinsics.items():
        c = block(arr)
        if c.shape[0] == len(free):
            out["models"][cam] = {INTR_NAMES[k]: float(np.sqrt(max(c[i, i], 0)))
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


def _tangent_covariance(problem, blocks: list[np.ndarray], n_res: int,
                        final_cost: float) -> tuple[np.ndarray, np.ndarray, float] | str:
    """Covariance of ``blocks`` in their tangent spaces, the blocks' offsets in it and the
    residual variance; or why it cannot be had (a rank-deficient Jacobian).

    The columns are scaled to unit norm before the inversion (pixels per radian and
    per pixel of focal length differ by 1e6, which Ceres' own ``Covariance`` reports
    as rank deficiency).
    """
    import pyceres

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
        return f"Jacobian rank-deficient (condition {sv[0] / sv[-1]:.3g})"
    inv = (vt.T / sv**2) @ vt
    cov = np.zeros((jac.shape[1], jac.shape[1]))
    idx = np.nonzero(live)[0]
    cov[np.ix_(idx, idx)] = inv / np.outer(norms[live], norms[live]) * sigma2
    return cov, np.concatenate([[0], np.cumsum(sizes)]), sigma2

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
                                opt.model_copy(update={"cross_validate": False}), robust=False)
    _solve(problem, opt)
    sub.sync_arm()
    held = np.concatenate([np.linalg.norm(sub.residuals(detections[i], boards), axis=1)[masks[i]]
                           for i in odd])
    fit = np.concatenate([np.linalg.norm(sub.residuals(detections[i], boards), axis=1)[masks[i]]
                          for i in even])
    return {"train": "even angle stops", "rms_train_px": _rms(fit), "rms_heldout_px": _rms(held),
            "difference_px": _rms(held) - _rms(fit)}


# --------------------------------------------------------------------------- quality
@dataclass
class CalibrationQuality:
    """How far to trust a calibration: what the solve measured, saved with it.

    ``to_dict`` is the calibration's ``quality`` mapping (``calibration.yaml``,
    the HTML report; docs/calibration.md describes every entry).  Pixels are px of
    the full-size calibration images.

    Attributes
    ----------
    method : str
    detections : int
        Board detections (views x boards) used.
    initialisation : dict
        ``rms_px``, ``max_px`` of the seed's initialisation.
    radial_coverage : dict camera -> float
        How far out the board corners reach, as a share of the image's half-diagonal.
    flags : list of StageWarning
        What a user should know (coded; the YAML holds their messages).
    rms_px, mean_px, max_px : float
        Residuals of the kept corners.
    corners : int
    per_camera, per_camera_tilt : dict
        ``rms_px``, ``max_px``, ``mean_px``, ``views`` per camera, per ``camera/tN``.
    per_view : list of dict
    corner_noise_px : float
        The corners' noise, corrected for the parameters fitted.
    boards : dict
        Each board's pose at turntable angle 0 (``R``, ``t`` mm).
    seconds : float
    solver : dict or None
        ``solves``: every Ceres solve (termination, iterations, costs).
    rejected_corners, rejected_fraction : int, float or None
    rejected : list of dict or None
        The rejected corners, worst first (at most ``MAX_LISTED_REJECTED``).
    sigma : dict or None
        Parameter 1-sigma (``_covariance``), or ``error``.
    cross_validation : dict or None
        Training (even stops) and held-out (odd stops) RMS, px.
    tilt_axis : dict or None
        The tilt-arm check and fit: misfits, free against arm-model RMS, tilt errors.
    stop_angle_error_deg : dict or None
        With ``angle_jitter_deg``: RMS, max and the largest errors of the stops.
    """

    method: str
    detections: int
    initialisation: dict[str, float]
    radial_coverage: dict[str, float]
    flags: list[StageWarning] = field(default_factory=list)
    rms_px: float = math.nan
    mean_px: float = math.nan
    max_px: float = math.nan
    corners: int = 0
    per_camera: dict[str, Any] = field(default_factory=dict)
    per_camera_tilt: dict[str, Any] = field(default_factory=dict)
    per_view: list[dict[str, Any]] = field(default_factory=list)
    corner_noise_px: float = math.nan
    boards: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    solver: dict[str, Any] | None = None
    rejected_corners: int | None = None
    rejected_fraction: float | None = None
    rejected: list[dict[str, Any]] | None = None
    sigma: dict[str, Any] | None = None
    cross_validation: dict[str, Any] | None = None
    tilt_axis: dict[str, Any] | None = None
    stop_angle_error_deg: dict[str, Any] | None = None

    def flag(self, code: str, message: str) -> None:
        self.flags.append(StageWarning(code, message))

    def set_residuals(self, stats: dict[str, Any]) -> None:
        """The residual figures of ``residual_stats`` of the kept corners."""
        for name in ("rms_px", "mean_px", "max_px", "corners", "per_camera", "per_camera_tilt",
                     "per_view"):
            setattr(self, name, stats[name])

    def to_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if v is not None}
        out["flags"] = [w.message for w in self.flags]
        return out


# --------------------------------------------------------------------------- entry point
@dataclass
class TurntableSolution:
    """A calibration and its typed quality (``calibration.quality`` is ``quality.to_dict()``)."""

    calibration: Calibration
    quality: CalibrationQuality


def calibrate_turntable(detections: list[Detection], boards: dict[int, np.ndarray],
                        image_sizes: dict[str, tuple[int, int]], tilts_deg: dict[int, float],
                        options: SolveOptions | None = None,
                        symmetric_boards: bool = False) -> Calibration:
    """Calibrate a turntable rig from board detections (``solve_turntable``'s calibration)."""
    return solve_turntable(detections, boards, image_sizes, tilts_deg, options,
                           symmetric_boards).calibration


def solve_turntable(detections: list[Detection], boards: dict[int, np.ndarray],
                    image_sizes: dict[str, tuple[int, int]], tilts_deg: dict[int, float],
                    options: SolveOptions | None = None,
                    symmetric_boards: bool = False) -> TurntableSolution:
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
    TurntableSolution
        The calibration (models, poses per (camera, tilt), the tilt axis when two
        or more tilts, the angle scale) and its ``CalibrationQuality``.

    Raises
    ------
    CalibrationError
        Too few detections for a (camera, tilt), disconnected views, a solve
        that did not converge, residual RMS or rejections above the limits.
    """
    opt = options or SolveOptions()
    detections = _checked_detections(detections, opt, symmetric_boards)
    t0 = time.perf_counter()
    state = initialise(detections, boards, image_sizes, opt)
    quality = _initial_quality(state, detections, boards, image_sizes, opt)
    tilt_indices = {t for _, t in state.cam_poses}
    ref_tilt = opt.reference_tilt_index if opt.reference_tilt_index is not None \
        else min(tilt_indices)
    masks = None
    if opt.refine:
        state, masks = _refined(state, detections, boards, tilts_deg, ref_tilt, opt, quality)
    stats = residual_stats(state, detections, boards, masks)
    quality.set_residuals(stats)
    quality.corner_noise_px = _corner_noise(stats, state, opt)
    # Gauge along the axis: the lowest board corner at the requested height.
    zmin = min(float(np.min((rotmats(p[:3])[0] @ boards[b].T)[2] + p[5]))
               for b, p in state.board_poses.items())
    state.apply_gauge(0.0, opt.lowest_corner_height_mm - zmin)
    models = {c: state.model(c) for c in state.intrinsics}
    poses = {k: state.pose(k) for k in state.cam_poses}
    if opt.angle_jitter_deg is not None and state.stops:
        quality.stop_angle_error_deg = _stop_errors(state)
    quality.boards = {str(b): {"R": rotmats(p[:3])[0].tolist(), "t": p[3:].tolist()}
                      for b, p in state.board_poses.items()}
    tilt_axis = _final_tilt_axis(state, poses, tilts_deg, ref_tilt, quality)
    quality.seconds = time.perf_counter() - t0
    if opt.refine:
        _check_limits(stats, quality, opt)
    calibration = Calibration(models, poses, {int(k): float(v) for k, v in tilts_deg.items()
                                              if any(t == k for _, t in poses)},
                              float(state.scale[0]), tilt_axis, quality.to_dict())
    return TurntableSolution(calibration, quality)


def _checked_detections(detections: list[Detection], opt: SolveOptions,
                        symmetric_boards: bool) -> list[Detection]:
    """The detections (symmetric boards' corner order harmonised); ``CalibrationError``
    without any, or with fewer than ``min_views`` for some (camera, tilt)."""
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
    return detections


def radial_coverage(detections: list[Detection],
                    image_sizes: dict[str, tuple[int, int]]) -> dict[str, float]:
    """Per camera, how far out its board corners reach: share of the half-diagonal."""
    coverage = {}
    for cam, (w, h) in image_sizes.items():
        uv = np.concatenate([d.uv for d in detections if d.camera == cam] or [np.zeros((0, 2))])
        half_diag = math.hypot(w / 2.0, h / 2.0)
        r = np.linalg.norm(uv - [(w - 1) / 2.0, (h - 1) / 2.0], axis=1) if len(uv) else [0.0]
        coverage[cam] = float(np.max(r) / half_diag)
    return coverage


def _initial_quality(state: RigState, detections: list[Detection],
                     boards: dict[int, np.ndarray], image_sizes: dict[str, tuple[int, int]],
                     opt: SolveOptions) -> CalibrationQuality:
    """The quality record of the initialisation; ``CalibrationError`` when it is far beyond
    any lens model (the board spec does not match the detections)."""
    init_stats = residual_stats(state, detections, boards)
    if not np.isfinite(init_stats["rms_px"]) or init_stats["rms_px"] > opt.max_init_rms_px:
        raise CalibrationError(
            f"the initial calibration leaves {init_stats['rms_px']:.3g} px RMS (limit "
            f"max_init_rms_px {opt.max_init_rms_px}); the board spec (cols, rows, square size) "
            "does not match the detections")
    coverage = radial_coverage(detections, image_sizes)
    quality = CalibrationQuality(
        method="plane+circle initialisation" + (" + pyceres refinement" if opt.refine else ""),
        detections=len(detections),
        initialisation={"rms_px": init_stats["rms_px"], "max_px": init_stats["max_px"]},
        radial_coverage=coverage)
    for c, v in coverage.items():
        if v < MIN_RADIAL_COVERAGE:
            quality.flag("low-coverage", f"camera {c}: board corners reach only {100 * v:.0f} % "
                         "of the half-diagonal; lens distortion beyond is extrapolated")
    return quality


def _refined(state: RigState, detections: list[Detection], boards: dict[int, np.ndarray],
             tilts_deg: dict[int, float], ref_tilt: int, opt: SolveOptions,
             quality: CalibrationQuality) -> tuple[RigState, dict[int, np.ndarray]]:
    """The refined rig and its kept corners: free poses, then the rigid arm when it fits;
    the solves, rejections, covariance and cross-validation into ``quality``."""
    arm_mode = opt.joint_tilt_axis and len({t for _, t in state.cam_poses}) >= 2
    # With the arm model to follow, the free poses need only the robust solve (a start
    # and the model check); outliers are rejected in the final model.
    masks, reports, problem = refine(state, detections, boards, opt, reject=not arm_mode)
    chosen = _arm_or_free(state, masks, detections, boards, (tilts_deg, ref_tilt), opt,
                          quality) if arm_mode else None
    if chosen is not None:
        state, masks, more, problem = chosen
        reports += more
    final = reports[-1]
    quality.solver = {"solves": [r.__dict__ for r in reports]}
    if not final.usable or final.termination not in ("CONVERGENCE", "NO_CONVERGENCE"):
        raise CalibrationError(
            f"the calibration solve failed ({final.termination}); initial RMS "
            f"{quality.initialisation['rms_px']:.3g} px — check the board spec and the "
            "turntable angles")
    if final.termination == "NO_CONVERGENCE":
        quality.flag("no-convergence", f"solver stopped after {opt.max_iterations} iterations")
    n_res = 2 * (sum(len(m) for m in masks.values()) - _record_rejections(
        quality, state, detections, boards, masks))
    if opt.covariance:
        try:
            quality.sigma = _covariance(problem, state, n_res, final.final_cost, opt)
        except Exception as exc:  # noqa: BLE001 - a report item, never fatal
            quality.sigma = {"error": str(exc)}
    if opt.cross_validate:
        quality.cross_validation = _cross_validate(state, detections, boards, masks, opt)
    return state, masks


def _arm_or_free(state: RigState, masks: dict[int, np.ndarray], detections: list[Detection],
                 boards: dict[int, np.ndarray], tilts: tuple[dict[int, float], int],
                 opt: SolveOptions, quality: CalibrationQuality):
    """From the free poses' robust solve: the rigid-arm model when it fits the (camera,
    tilt) poses as well, else the free poses (flagged).  Returns the state, the kept
    corners, the solves and the last problem; None (flagged) when some camera lacks the
    reference tilt (the free poses' robust solve stands)."""
    tilts_deg, ref_tilt = tilts
    # Free poses first: their misfit to one rigid arm checks the model, then the arm
    # model is solved jointly (far fewer pose parameters, every tilt informs all).
    free = {k: state.pose(k) for k in state.cam_poses}
    fitted = fit_tilt_axis(free, tilts_deg, ref_tilt)
    missing = sorted({c for c, _ in free} - {c for c, t in free if t == ref_tilt})
    if fitted is None or missing:
        quality.flag("no-joint-tilt-axis", "joint tilt-axis model not used: cameras without "
                     f"the reference tilt {ref_tilt}: {', '.join(missing) or 'all'}")
        return None
    axis, quality.tilt_axis = fitted
    quality.tilt_axis["model_check"] = (
        "free (camera, tilt) poses vs the best one-axis arm through them")
    free_state, free_masks = state.copy(), masks
    attach_arm(state, axis, tilts_deg)
    masks, reports, problem = refine(state, detections, boards, opt, masks)
    # A rigid arm costs almost nothing in residual when true (fewer parameters, same
    # fit); a clearly worse fit of some (camera, tilt) means the arm is not one rigid
    # rotation.  Compared on the inliers of the free fit, per pose.
    inl = inlier_masks(free_state, detections, boards, opt, free_masks)
    per_free = residual_stats(free_state, detections, boards, inl)["per_camera_tilt"]
    per_arm = residual_stats(state, detections, boards, inl)["per_camera_tilt"]
    ratio = {k: per_arm[k]["rms_px"] / max(v["rms_px"], 1e-12) for k, v in per_free.items()}
    worst = max(ratio, key=ratio.get)
    quality.tilt_axis.update({
        "rms_free_poses_px": {k: v["rms_px"] for k, v in per_free.items()},
        "rms_arm_model_px": {k: v["rms_px"] for k, v in per_arm.items()},
        "worst_rms_ratio": ratio[worst]})
    if ratio[worst] > opt.max_arm_rms_ratio:
        quality.flag(
            "arm-not-rigid", f"the tilting arm is not one rigid rotation: with the joint "
            f"tilt-axis model {worst} leaves {per_arm[worst]['rms_px']:.3g} px RMS against "
            f"{per_free[worst]['rms_px']:.3g} px with free poses (free poses kept; cameras at "
            "uncalibrated tilts are approximate)")
        state = free_state
        masks, more, problem = refine(state, detections, boards, opt, free_masks)
        reports += more
    return state, masks, reports, problem


def _record_rejections(quality: CalibrationQuality, state: RigState,
                       detections: list[Detection], boards: dict[int, np.ndarray],
                       masks: dict[int, np.ndarray]) -> int:
    """The rejected corners into ``quality`` (count, share, the worst by name); returns
    their number."""
    total = sum(len(m) for m in masks.values())
    rejected = [(i, np.nonzero(~m)[0]) for i, m in masks.items() if (~m).any()]
    n_rej = sum(len(r) for _, r in rejected)
    quality.rejected_corners = n_rej
    quality.rejected_fraction = n_rej / total
    listed = []
    for i, js in rejected:
        d = detections[i]
        res = np.linalg.norm(state.residuals(d, boards), axis=1)
        listed += [{"camera": d.camera, "tilt_index": d.tilt_index, "angle_deg": d.angle_deg,
                    "board": d.board, "view_index": d.view_index,
                    "corner": int(d.corner_ids[j]), "residual_px": float(res[j])} for j in js]
    listed.sort(key=lambda r: -r["residual_px"])
    quality.rejected = listed[:MAX_LISTED_REJECTED]
    return n_rej


def _corner_noise(stats: dict[str, Any], state: RigState, opt: SolveOptions) -> float:
    """The corners' noise (px): the residual RMS corrected for the parameters fitted."""
    tilt_indices = {t for _, t in state.cam_poses}
    n_poses = len(state.cam_poses) if state.arm is None else sum(
        1 for _, t in state.cam_poses if t == state.arm.reference_tilt_index)
    n_params = (N_INTR - len(fixed_intrinsics(opt))) * len(state.intrinsics) + 6 * (
        n_poses + len(state.board_poses)) + (0 if state.arm is None else 3 + len(tilt_indices))
    return stats["rms_px"] * math.sqrt(
        2 * stats["corners"] / max(2 * stats["corners"] - n_params, 1) / 2.0)


def _stop_errors(state: RigState) -> dict[str, Any]:
    """RMS, max and the ten largest fitted turntable-stop angle errors, deg."""
    errs = sorted(((float(v[0]), k) for k, v in state.stops.items()), key=lambda x: -abs(x[0]))
    return {"rms": float(np.sqrt(np.mean([e * e for e, _ in errs]))), "max": abs(errs[0][0]),
            "largest": [{"tilt_index": k[0], "angle_deg": k[1], "error_deg": e}
                        for e, k in errs[:10]]}


def _final_tilt_axis(state: RigState, poses: dict, tilts_deg: dict[int, float],
                     ref_tilt: int, quality: CalibrationQuality) -> TiltAxis | None:
    """The tilt axis: the arm model's, or one fitted to the free poses of two or more
    tilts (its misfit into ``quality.tilt_axis``); None with one tilt."""
    if state.arm is not None:
        arm = state.arm
        quality.tilt_axis["joint"] = True
        quality.tilt_axis["tilt_error_deg"] = {int(t): float(v[0])
                                               for t, v in sorted(arm.tilt_errors.items())}
        return TiltAxis(arm.origin.copy(), arm.unit_direction(), arm.reference_tilt_index)
    if len({t for _, t in state.cam_poses}) < 2:
        return None
    fitted = fit_tilt_axis(poses, tilts_deg, ref_tilt)
    if fitted is None:
        return None
    tilt_axis, info = fitted
    quality.tilt_axis = {**(quality.tilt_axis or {}), **info, "joint": False}
    return tilt_axis


def _check_limits(stats: dict[str, Any], quality: CalibrationQuality, opt: SolveOptions) -> None:
    """``CalibrationError`` when the residual RMS or the rejected share is above its limit."""
    if stats["rms_px"] > opt.max_rms_px:
        raise CalibrationError(
            f"calibration residual RMS {stats['rms_px']:.3g} px exceeds max_rms_px "
            f"{opt.max_rms_px} (worst: {_worst(stats)}); check the board spec")
    if quality.rejected_fraction > opt.max_rejected_fraction:
        raise CalibrationError(
            f"{quality.rejected_corners} corners ({100 * quality.rejected_fraction:.1f}"
            f" %) rejected as outliers, above max_rejected_fraction "
            f"{opt.max_rejected_fraction}; worst view: {_worst(stats)}")

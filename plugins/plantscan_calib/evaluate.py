"""Compare an estimated calibration with the virtual scanner's exact one.

Images cannot tell a rotation of the world about the turntable axis, nor a
shift along it (the gauge, see ``solver``).  Before comparing, the estimate is
moved by the one rotation about Z and shift along Z that best superimpose its
camera centres on the true ones; both numbers are reported.  Everything else
(intrinsics, poses relative to the axis, the axis itself) is compared as is.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from plantscan_core.data import Calibration, Camera, Pose, rotation_angle_deg, rotation_z


def gauge_alignment(est: Calibration, truth: Calibration) -> tuple[float, float]:
    """(yaw deg, dz mm) moving ``est``'s world onto ``truth``'s (least squares on centres)."""
    keys = sorted(set(est.poses) & set(truth.poses))
    if not keys:
        raise ValueError("the calibrations share no (camera, tilt) pose")
    ce = np.array([est.poses[k].centre for k in keys])
    ct = np.array([truth.poses[k].centre for k in keys])
    dz = float(np.mean(ct[:, 2] - ce[:, 2]))
    cross = np.sum(ce[:, 0] * ct[:, 1] - ce[:, 1] * ct[:, 0])
    dot = np.sum(ce[:, 0] * ct[:, 0] + ce[:, 1] * ct[:, 1])
    return math.degrees(math.atan2(cross, dot)), dz


def _moved(pose: Pose, yaw_deg: float, dz: float) -> Pose:
    """The same camera expressed in the world rotated by ``yaw`` about Z and shifted by dz."""
    q = rotation_z(yaw_deg)
    r = pose.R @ q.T
    c = q @ pose.centre + np.array([0.0, 0.0, dz])
    return Pose(r, -r @ c)


def aligned(est: Calibration, truth: Calibration) -> tuple[Calibration, float, float]:
    """``est`` with its gauge moved onto ``truth``'s, plus (yaw deg, dz mm)."""
    yaw, dz = gauge_alignment(est, truth)
    poses = {k: _moved(p, yaw, dz) for k, p in est.poses.items()}
    axis = None
    if est.tilt_axis is not None:
        from plantscan_core.data import TiltAxis

        q = rotation_z(yaw)
        axis = TiltAxis(q @ est.tilt_axis.origin + [0.0, 0.0, dz], q @ est.tilt_axis.direction,
                        est.tilt_axis.reference_tilt_index)
    return (Calibration(est.models, poses, est.tilts_deg, est.angle_scale, axis, est.quality),
            yaw, dz)


def compare_calibrations(est: Calibration, truth: Calibration, volume_points: np.ndarray,
                         angles_deg=tuple(range(0, 360, 30))) -> dict[str, Any]:
    """Errors of ``est`` against ``truth``.

    Parameters
    ----------
    volume_points : (N, 3) float64 array, mm, world frame
        Points spread through the plant volume; their projections by the
        true and estimated cameras at ``angles_deg`` give
        ``volume_reprojection_px_rms``.

    Returns
    -------
    dict with ``camera_centre_error_mm.{mean,max}``,
    ``rotation_error_deg.{mean,max}``, ``volume_reprojection_px_rms``,
    ``volume_reprojection_px_max``, ``intrinsics`` (per camera abs errors),
    ``axis_direction_error_deg`` (turntable axis seen from each camera),
    ``angle_scale_error``, ``gauge`` and, when ``truth`` has tilts ``est`` did
    not calibrate, ``uncalibrated_tilts`` (same errors through the tilt axis).
    """
    est_a, yaw, dz = aligned(est, truth)
    keys = sorted(set(est_a.poses) & set(truth.poses))
    centre = [float(np.linalg.norm(est_a.poses[k].centre - truth.poses[k].centre)) for k in keys]
    rot = [rotation_angle_deg(est_a.poses[k].R.T @ truth.poses[k].R) for k in keys]
    axis_err = []
    for k in keys:
        a_e, a_t = est.poses[k].R[:, 2], truth.poses[k].R[:, 2]
        axis_err.append(math.degrees(math.acos(float(np.clip(a_e @ a_t, -1, 1)))))
    out: dict[str, Any] = {
        "camera_centre_error_mm": {"mean": float(np.mean(centre)), "max": float(np.max(centre))},
        "rotation_error_deg": {"mean": float(np.mean(rot)), "max": float(np.max(rot))},
        "axis_direction_error_deg": {"mean": float(np.mean(axis_err)),
                                     "max": float(np.max(axis_err))},
        "angle_scale_error": float(est.angle_scale - truth.angle_scale),
        "gauge": {"yaw_deg": yaw, "dz_mm": dz},
        "poses_compared": len(keys),
        "per_pose": {f"{c}/t{t}": {"centre_error_mm": ce, "rotation_error_deg": re}
                     for (c, t), ce, re in zip(keys, centre, rot, strict=True)},
    }
    intr = {}
    for cam in sorted(set(est.models) & set(truth.models)):
        me, mt = est.models[cam], truth.models[cam]
        intr[cam] = {k: abs(getattr(me, k) - getattr(mt, k)) for k in ("f", "cu", "cv", "d1",
                                                                       "d2")}
    out["intrinsics"] = intr
    reproj = _volume_reprojection(
        [(lambda a, k=k: est_a.camera_at(k[0], k[1], a),
          lambda a, k=k: truth.camera_at(k[0], k[1], a)) for k in keys],
        volume_points, angles_deg)
    out["volume_reprojection_px_rms"], out["volume_reprojection_px_max"] = reproj
    extra = sorted(k for k in truth.poses if k not in est.poses)
    if extra and est_a.tilt_axis is not None:
        pairs, ce, re = [], [], []
        for cam, ti in extra:
            if cam not in est.models or ti not in truth.tilts_deg:
                continue
            tilt = truth.tilts_deg[ti]
            cam_e = est_a.camera_at_tilt(cam, tilt, 0.0)
            ce.append(float(np.linalg.norm(cam_e.pose.centre - truth.poses[(cam, ti)].centre)))
            re.append(rotation_angle_deg(cam_e.pose.R.T @ truth.poses[(cam, ti)].R))
            pairs.append((lambda a, c=cam, t=tilt: est_a.camera_at_tilt(c, t, a),
                          lambda a, k=(cam, ti): truth.camera_at(k[0], k[1], a)))
        if pairs:
            rms, mx = _volume_reprojection(pairs, volume_points, angles_deg)
            out["uncalibrated_tilts"] = {
                "tilts": sorted({truth.tilts_deg[t] for _, t in extra}),
                "camera_centre_error_mm": {"mean": float(np.mean(ce)), "max": float(np.max(ce))},
                "rotation_error_deg": {"mean": float(np.mean(re)), "max": float(np.max(re))},
                "volume_reprojection_px_rms": rms, "volume_reprojection_px_max": mx}
    return out


def _volume_reprojection(pairs, points: np.ndarray, angles_deg) -> tuple[float, float]:
    diffs = []
    for est_at, truth_at in pairs:
        for a in angles_deg:
            ct: Camera = truth_at(a)
            ce: Camera = est_at(a)
            ut, ue = ct.project(points), ce.project(points)
            m = ct.model
            inside = (np.isfinite(ut).all(axis=1) & np.isfinite(ue).all(axis=1)
                      & (ut[:, 0] >= 0) & (ut[:, 0] < m.width) & (ut[:, 1] >= 0)
                      & (ut[:, 1] < m.height))
            diffs.append(np.linalg.norm(ue[inside] - ut[inside], axis=1))
    d = np.concatenate(diffs) if diffs else np.array([np.nan])
    if not len(d):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(d**2))), float(np.max(d))


def plant_volume_points(truth_dir: Path, n: int = 800, seed: int = 1) -> np.ndarray:
    """Points spread through the plant's volume: the true plant's bounding cylinder, if known."""
    from plantscan_calib.synthetic import volume_points

    path = Path(truth_dir) / "plant.npz"
    if path.exists():
        with np.load(path) as z:
            v = np.asarray(z["vertices"], dtype=float)
        r = float(np.max(np.linalg.norm(v[:, :2], axis=1)))
        return volume_points(r, (float(v[:, 2].min()), float(v[:, 2].max())), n, seed)
    return volume_points(n=n, seed=seed)


def evaluate_run(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    """The ``calibration`` section of ``plantscan evaluate`` (None without both files)."""
    est_path, truth_path = Path(run_dir) / "calibration.yaml", Path(truth_dir) / "calibration.yaml"
    if not est_path.exists() or not truth_path.exists():
        return None
    est, truth = Calibration.load(est_path), Calibration.load(truth_path)
    res = compare_calibrations(est, truth, plant_volume_points(truth_dir))
    q = est.quality or {}
    for k in ("rms_px", "max_px", "rejected_corners", "corner_noise_px"):
        if k in q:
            res[f"calibrator_{k}"] = q[k]
    return {"calibration": res}

"""The first estimate of the rig model: the seed's initialisation, and the tilt axis.

Mono calibration per camera (OpenCV), the turntable axis from the plane + circle
fit of the board corners' orbits, board poses transferred between cameras and
tilts; identical boards told apart; the tilt-arm axis fitted to poses at several
tilts.  ``solver`` refines the result.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from plantscan_calib.model import (
    ArmModel,
    CalibrationError,
    Detection,
    RigState,
    mean_rotation,
    pose_vec,
    rotmats,
    rotvec,
)
from plantscan_core.data import Calibration, Pose, TiltAxis, rotation_z
from plantscan_core.parallel import opencv_threads

if TYPE_CHECKING:
    from plantscan_calib.solver import SolveOptions


# --------------------------------------------------------------------------- boards
def _angle_arcs(detections: list[Detection], idx: list[int], n_boards: int,
                step: float) -> list[list[int]] | None:
    """The detections ``idx`` (one camera and tilt) split into arcs of turntable angles at
    the ``n_boards`` largest gaps of at least one missing stop (``step`` deg); None when
    another gap of more than three stops means more arcs than boards."""
    a = np.array([detections[i].angle_deg % 360.0 for i in idx])
    order = np.argsort(a)
    gaps = np.diff(np.concatenate([a[order], [a[order][0] + 360.0]]))
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


def _arc_centre(detections: list[Detection], arc: list[int]) -> float:
    """Circular mean of the turntable angles of the detections ``arc``, deg."""
    a = np.radians([detections[i].angle_deg for i in arc])
    return math.degrees(math.atan2(np.sin(a).sum(), np.cos(a).sum()))


def _angle_distance(x: float, y: float) -> float:
    """|x - y| on the circle, deg."""
    return abs((x - y + 180.0) % 360.0 - 180.0)


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
        return _angle_arcs(detections, idx, n_boards, step)

    def refuse(key, what):
        raise CalibrationError(
            f"camera {key[0]} tilt {key[1]}: the views with a board form {what} of turntable "
            f"angles that cannot be matched to {n_boards} boards (identical chessboards are "
            "told apart by the angles at which each faces the cameras; use ChArUco boards "
            "for other layouts)")

    ref = max(sorted(by_ct), key=lambda k: len(by_ct[k]))
    ref_arcs = arcs(by_ct[ref])
    if ref_arcs is None:
        refuse(ref, f"more than {n_boards} arcs")
    centres = [_arc_centre(detections, a) for a in sorted(ref_arcs, key=len, reverse=True)]
    label = {}
    for key, idx in sorted(by_ct.items()):
        ct_arcs = arcs(idx)
        if ct_arcs is None:
            refuse(key, f"more than {n_boards} arcs")
        names = [int(np.argmin([_angle_distance(_arc_centre(detections, a), c)
                                for c in centres])) for a in ct_arcs]
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


# --------------------------------------------------------------------------- initialisation
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
    # OpenCV on one thread: calibrateCamera sums its normal equations in parallel, and the
    # order of the sums changed the calibration from run to run (1e-9 relative in f,
    # measured on the demo scan); one thread makes it reproducible.
    with opencv_threads(1):
        intr = {c: _init_intrinsics(c, ds, boards, image_sizes[c], opt)
                for c, ds in by_cam.items()}
        b2c = {id(d): _board_to_camera(d, intr[d.camera], boards) for d in detections}
    ref, r_ref, point = _reference_frame(by_ct, b2c, boards)
    poses, board_world = _place_views(by_ct, b2c, ref, (r_ref, point))
    known = {b: (mean_rotation([r for r, _ in v]), np.mean([t for _, t in v], axis=0))
             for b, v in board_world.items()}
    state = RigState(
        intrinsics=intr,
        cam_poses={k: pose_vec(r, -r.T @ t) for k, (r, t) in poses.items()},
        board_poses={b: pose_vec(r, t) for b, (r, t) in known.items()},
        scale=np.array([1.0]),
        image_sizes=dict(image_sizes),
    )
    _normalise_gauge(state, reference_key(state))
    return state


def _reference_frame(by_ct: dict[tuple[str, int], list[Detection]], b2c: dict,
                     boards: dict[int, np.ndarray]) -> tuple[tuple[str, int], np.ndarray,
                                                             np.ndarray]:
    """The (camera, tilt) that saw a board at the most turntable angles, and the world
    frame in its camera: rotation (columns: world axes; Z the turntable axis) and a
    point of the axis (mm), from the plane + circle fit of its corners' orbits."""
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
    return ref, np.stack([ex, ey, ez], axis=1), point


def _place_views(by_ct: dict[tuple[str, int], list[Detection]], b2c: dict,
                 ref: tuple[str, int], ref_pose: tuple[np.ndarray, np.ndarray]):
    """Every (camera, tilt)'s (R, t) camera <- world, from boards whose pose at angle 0 is
    known (the reference's first, then each newly placed one's), and every board's
    estimates of its pose at angle 0.  ``CalibrationError`` naming the (camera, tilt)
    that share no board with the others."""
    poses: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {ref: ref_pose}
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
    return poses, board_world

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

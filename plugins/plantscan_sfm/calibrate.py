"""Structure from motion with the turntable's constraints: photos in, ``Calibration`` out.

1. SIFT features and verified matches between turntable neighbours (``features``).
2. Focal length, axis and one pose per (camera, tilt) from two-view geometry
   (``initialise``), or from approximate poses given with the scan.
3. Triangulation, then the turntable bundle adjustment (``bundle``): one axis,
   the commanded angles as priors, one pose per (camera, tilt), intrinsics per
   camera with radial distortion.
4. Metric scale and height from the plate (``scale``), world frame as the
   chessboard calibrator's: axis = +Z, origin on the axis at the plate's top.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections import Counter, defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from plantscan_calib.initialise import fit_tilt_axis
from plantscan_calib.model import rotmats, rotvec

from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord, rotation_z
from plantscan_sfm import bundle, features, initialise
from plantscan_sfm.features import SfmError, SfmView, Tracks
from plantscan_sfm.initialise import GroupPose
from plantscan_sfm.scale import metric_frame

ADVICE_TEXTURE = ("print a random-dot pattern and lay it on the turntable plate (docs/"
                  "calibration.md, 'calibrating from the plant photos'), or calibrate with a "
                  "board (calibrate.plugin: turntable)")


@dataclass
class SfmSettings:
    """Everything the ``sfm`` calibrator's recipe parameters set (see ``plugin.Params``)."""

    role: str = "plant"
    max_features: int = 8192
    max_image_size: int = 3200
    first_octave: int | None = None
    orbit_neighbours: int = 3
    cross_window_deg: float | None = None
    exhaustive_below: int = 16
    ransac_px: float = 2.0
    scale: str = "plate"
    plate_diameter_mm: float | None = None
    camera_distance_mm: float | None = None
    plate_top_mm: float = 0.0
    angle_sigma_deg: float | None = 0.5
    fit_angle_scale: bool = False
    fix_principal_point: bool = True
    fix_distortion: bool = False
    min_tracks: int = 200
    min_view_observations: int = 15
    max_rms_px: float = 1.5
    threads: int = 2
    max_observations: int = 200_000
    focal_px: dict[str, float] | None = None
    principal_point_px: dict[str, tuple[float, float]] | None = None
    fit_focal: bool = False
    principal_point_prior: float | None = 0.015
    markers: str | None = "DICT_4X4_250"
    marker_mm: float | None = None
    refine_dots: bool = True
    reject_sigma: float | None = None
    weigh_by_kind: bool | None = None
    board: dict[str, Any] | None = None
    board_role: str = "calibration"
    board_noise: float = 1.0
    board_corners: dict[str, list[tuple]] | None = None
    board_on_turntable: bool = False
    prior_poses: dict[tuple[str, int], Pose] | None = None
    prior_focal: dict[str, float] | None = None
    workspace: Path | None = None
    timings: dict[str, float] = field(default_factory=dict)


def _image_sizes(scan, views: list[ViewRecord]) -> dict[str, tuple[int, int]]:
    from PIL import Image

    sizes: dict[str, tuple[int, int]] = {}
    first: dict[str, ViewRecord] = {}
    for v in views:
        with Image.open(scan.path_of(v)) as im:
            size = im.size
        if v.camera in sizes and sizes[v.camera] != size:
            raise SfmError(f"camera {v.camera}: photos of different sizes: {first[v.camera].file} "
                           f"is {sizes[v.camera][0]}x{sizes[v.camera][1]}, {v.file} is "
                           f"{size[0]}x{size[1]}")
        sizes.setdefault(v.camera, size)
        first.setdefault(v.camera, v)
    return sizes


def calibrate_scan(scan, settings: SfmSettings) -> Calibration:
    """Calibrate the rig of ``scan`` from the photos of ``settings.role``."""
    views = scan.views_by_role(settings.role)
    if len(views) < 3:
        raise SfmError(f"{scan.root}: {len(views)} '{settings.role}' photos; structure from "
                       "motion needs at least 3 per camera and tilt")
    per_group = Counter((v.camera, v.tilt_index) for v in views)
    few = {g: n for g, n in per_group.items() if n < 3}
    if few:
        raise SfmError(f"{scan.root}: too few photos for " + ", ".join(
            f"camera {c} tilt {t} ({n})" for (c, t), n in sorted(few.items())) +
            "; structure from motion needs at least 3 per camera and tilt")
    sizes = _image_sizes(scan, views)
    if settings.board is not None and settings.board_corners is None:
        settings.board_corners = detect_board_views(scan, settings)
    if settings.workspace is not None:
        settings.workspace.mkdir(parents=True, exist_ok=True)
        return _calibrate(scan, views, sizes, settings, settings.workspace)
    with tempfile.TemporaryDirectory(prefix="plantscan-sfm-") as tmp:
        return _calibrate(scan, views, sizes, settings, Path(tmp))


def detect_board_views(scan, settings: SfmSettings
                       ) -> dict[str, list[tuple[int, np.ndarray, np.ndarray]]]:
    """The board's corners in the photos of ``settings.board_role``, per camera: (view
    index, board points (N, 3) mm, corners (N, 2) px, turntable angle deg, (camera,
    tilt)) of every photo where it is found
    (the chessboard calibrator's detector; ``settings.board`` its ``BoardSpec`` fields).
    A camera with no photo of the board is a named error."""
    from plantscan_calib.detect import BoardSpec
    from plantscan_calib.plugin import detect_views

    spec = BoardSpec(**settings.board)
    views = scan.views_by_role(settings.board_role)
    dets, _, _ = detect_views(scan, views, spec, workers=settings.threads)
    obj = spec.object_points()
    out: dict[str, list] = defaultdict(list)
    for d in dets:
        out[d.camera].append((int(d.view_index), obj[d.corner_ids], np.asarray(d.uv, float),
                              float(d.angle_deg), (d.camera, int(d.tilt_index))))
    cams = sorted({v.camera for v in scan.views_by_role(settings.role)})
    missing = [c for c in cams if not out.get(c)]
    if missing:
        raise SfmError(
            f"{scan.root}: no '{settings.board_role}' photo shows the board "
            f"({spec.cols}x{spec.rows} inner corners) for camera(s) {', '.join(missing)} "
            f"({len(views)} such photos); photograph the board once per camera, turned 30-60 "
            "deg from facing it (docs/sfm.md, 'one board photo per camera')")
    return dict(out)


def match_scan(scan, views: list[ViewRecord], settings: SfmSettings, work: Path
               ) -> tuple[list[SfmView], Path, Tracks]:
    """Steps 1 of the module doc: features, pairs, verified matches, tracks."""
    t = settings.timings
    t0 = time.perf_counter()
    sviews = features.workspace_views(scan, views, work)
    sizes = _image_sizes(scan, views)
    octave = settings.first_octave
    if octave is None:  # small photos: upsample once so that printed dots of a few px count
        octave = -1 if max(w * h for w, h in sizes.values()) < 800_000 else 0
    db = features.extract_features(work, sviews, settings.max_features,
                                   settings.max_image_size, settings.threads, octave)
    t["features_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cross = settings.cross_window_deg if settings.cross_window_deg is not None \
        else features.default_cross_window(sviews)
    pairs = features.plan_pairs(sviews, settings.orbit_neighbours, cross,
                                settings.exhaustive_below)
    features.match_pairs(db, work, sviews, pairs, settings.threads, settings.ransac_px)
    t["matching_s"] = time.perf_counter() - t0
    tracks = features.read_tracks(db, sviews)
    tracks.stats["pairs_matched"] = len(pairs)
    if settings.refine_dots or settings.markers:
        t0 = time.perf_counter()
        tracks = refine_and_mark(scan, sviews, tracks, settings)
        t["dots_and_markers_s"] = time.perf_counter() - t0
    return sviews, db, tracks


def refine_and_mark(scan, views: list[SfmView], tracks: Tracks, settings: SfmSettings
                    ) -> Tracks:
    """Keypoints moved to their dots' centroids, and the printed markers' corners added
    as tracks of their own (``plantscan_sfm.markers``)."""
    from plantscan_sfm import markers

    uv = tracks.uv.copy()
    on_dot = np.zeros(len(uv), bool)
    grays = []
    by_view = np.argsort(tracks.view, kind="stable")
    starts = np.searchsorted(tracks.view[by_view], np.arange(len(views) + 1))
    for i, v in enumerate(views):
        gray = markers.read_gray(scan.path_of(v.view))
        if settings.refine_dots:
            obs = by_view[starts[i]:starts[i + 1]]
            labels, centres = markers.dot_centroids(gray)
            uv[obs], on_dot[obs] = markers.snap_to_dots(uv[obs], labels, centres)
        if settings.markers:
            grays.append(gray)
    out = Tracks(tracks.view, tracks.track, uv, dict(tracks.stats), tracks.noise,
                 tracks.marker, dot=on_dot)
    out.stats["keypoints_on_dots"] = int(on_dot.sum())
    if settings.markers:
        corners = markers.detect_markers(grays, settings.markers)
        turning, lab = markers.split_static(corners, views)
        mt = turning.tracks()
        out = Tracks.concat([out, mt, lab])
        out.stats.update({"marker_detections": int(len(corners.view) // 4),
                          "marker_corner_tracks": mt.n_tracks,
                          "lab_marker_corner_tracks": lab.n_tracks,
                          "markers_per_photo": float(len(corners.view) / 4 / len(views))})
    return out


def _calibrate(scan, views: list[ViewRecord], sizes: dict[str, tuple[int, int]],
               settings: SfmSettings, work: Path) -> Calibration:
    t_all = time.perf_counter()
    sviews, _, tracks = match_scan(scan, views, settings, work)
    _check_texture(tracks, sviews, settings, scan.root)
    return solve_tracks(sviews, tracks, sizes, settings, t_all)


def _check_texture(tracks: Tracks, views: list[SfmView], settings: SfmSettings,
                   root: Path) -> None:
    """The named failure of a textureless scene: too few features or tracks."""
    kp = tracks.stats.get("keypoints_per_photo", 0.0)
    if tracks.n_tracks < settings.min_tracks:
        raise SfmError(
            f"{root}: too few features to calibrate from: {tracks.n_tracks} feature tracks over "
            f"{len(views)} photos ({kp:.0f} keypoints per photo, "
            f"{tracks.stats.get('verified_pairs', 0)} of {tracks.stats.get('pairs_matched', 0)} "
            f"photo pairs matched; need calibrate.params.min_tracks = {settings.min_tracks}). "
            f"The scene is too plain: {ADVICE_TEXTURE}")


def solve_tracks(views: list[SfmView], tracks: Tracks, sizes: dict[str, tuple[int, int]],
                 settings: SfmSettings, t_start: float | None = None) -> Calibration:
    """Steps 2-4 of the module doc, from tracks."""
    t = settings.timings
    t_start = time.perf_counter() if t_start is None else t_start
    t0 = time.perf_counter()
    tracks = _cap_observations(tracks, settings.max_observations)
    commanded = np.array([v.view.angle_deg for v in views])
    state, init_info, tracks = _initial_state(views, tracks, sizes, settings, commanded)
    t["initialisation_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    held_focal = sorted(settings.focal_px or {}) if not settings.fit_focal else []
    width = max(w for w, _ in sizes.values())
    state.boards = board_views(state, settings.board_corners or {}, settings.board_noise)
    # a board photo of every camera fixes its principal point: freed, unless the lab gave it
    fix_pp = settings.fix_principal_point and not (
        state.boards and set(state.boards) >= set(state.intrinsics)
        and not settings.principal_point_px)
    opt = bundle.BundleOptions(angle_sigma_deg=settings.angle_sigma_deg, fixed_focal=held_focal,
                               fit_angle_scale=settings.fit_angle_scale,
                               fix_principal_point=fix_pp,
                               fix_distortion=settings.fix_distortion, threads=settings.threads,
                               principal_point_sigma_px=settings.principal_point_prior * width
                               if settings.principal_point_prior else None)
    # First with the principal point, distortion and angles held (a far start), then all.
    first = bundle.BundleOptions(**{**opt.__dict__, "fix_distortion": True,
                                    "fix_principal_point": True, "angle_sigma_deg": None,
                                    "outlier_px": 4.0})
    # The starts are independent and the compiled solver releases the GIL: ``threads`` at a
    # time.  (Ranking them by a cheaper pass was measured and not kept: docs/sfm.md,
    # session 15.)

    def solve_from(f_start: dict[str, float]) -> tuple:
        cand = state.copy()
        for cam, f in f_start.items():
            cand.intrinsics[cam][0] = f
        _retriangulate(cand, views, tracks)
        keep, rep1 = bundle.adjust(cand, views, tracks, first, rounds=1)
        searched = bundle.search_stop_angles(cand, views, tracks) \
            if settings.angle_sigma_deg is not None else {}
        keep = _clean_tracks(cand, views, tracks, keep, CLEAN_PX)
        if settings.board_on_turntable and cand.boards:
            cand.board_rig = board_rig_start(cand)
        keep, rep2 = bundle.adjust(cand, views, tracks, opt, keep=keep, rounds=2)
        return truncated_cost(cand, views, tracks), cand, keep, rep1, rep2, searched

    starts = focal_starts(state, held_focal)
    with ThreadPoolExecutor(max(settings.threads, 1)) as pool:
        runs = list(pool.map(solve_from, starts))
    tried = [{"f_start_px": {c: float(f) for c, f in f_start.items()},
              "f_px": {c: float(v[0]) for c, v in run[1].intrinsics.items()},
              "truncated_cost": run[0]} for f_start, run in zip(starts, runs, strict=True)]
    best = min(runs, key=lambda run: run[0])   # the first of equal costs
    _, state, keep, rep1, rep2, searched = best
    rep2.solves = rep1.solves + rep2.solves
    noise_info = None
    # weighed when the principal point is known (given, or fixed by a board photo of every
    # camera); held at the image centre the rig is biased, and weighing measured worse
    weigh = settings.weigh_by_kind if settings.weigh_by_kind is not None else (
        settings.principal_point_px is not None or (
            bool(state.boards) and set(state.boards) >= set(state.intrinsics)))
    if weigh:
        tracks, noise_info = _weigh_by_kind(state, views, tracks, keep)
        opt = replace(opt, prior_noise_px=bundle.NOISE_UNIT_PX)
        keep, rep3 = bundle.adjust(state, views, tracks, opt, keep=keep, rounds=2)
        rep2.solves += rep3.solves
        # again at the weighed solution: the first estimate still holds the rig's own error
        # of the alike-weighed fit (a 0.03 px dot kind measured 0.07 px there)
        tracks, noise_info = _weigh_by_kind(state, views, tracks, keep)
        keep, rep3 = bundle.adjust(state, views, tracks, opt, keep=keep, rounds=1)
        rep2.solves += rep3.solves
    reject_info = None
    if settings.reject_sigma:
        # wrong matches the joint fit half absorbs: each track's observations against the
        # point the others give, then the rig solved again without those beyond the bound
        keep, reject_info = bundle.reject_inconsistent(state, views, tracks, keep, opt,
                                                       settings.reject_sigma)
        keep, rep3 = bundle.adjust(state, views, tracks, opt, keep=keep, rounds=1)
        rep2.solves += rep3.solves
    t["bundle_s"] = time.perf_counter() - t0
    res = bundle.residuals(state, views, tracks)
    err = np.linalg.norm(res, axis=1)
    quality = _quality(state, views, tracks, keep, err, settings)
    quality["initialisation"] = init_info
    quality["stops_found_off_deg"] = searched
    quality["solver"] = {"solves": rep2.solves, "focal_starts": tried}
    if reject_info is not None:
        quality["inconsistent_observations"] = reject_info
    if noise_info is not None:
        quality["noise_by_kind"] = noise_info
    if state.boards:
        quality["board_views"] = _board_report(state)
    final = rep2.solves[-1]
    if not final["usable"]:
        raise SfmError(f"the turntable bundle adjustment failed ({final['termination']})")
    t0 = time.perf_counter()
    sigma = bundle.parameter_sigma(state, views, tracks, keep, opt)
    t["sigma_s"] = time.perf_counter() - t0
    _check_focal(state, sigma, init_info, settings)
    # Metric scale and height.
    counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
    solid = counts >= 3
    ref_c = state.poses[state.reference][3:6]
    s, z0, sinfo = metric_frame(state.points[solid], float(np.hypot(ref_c[0], ref_c[1])),
                                settings.scale, settings.plate_diameter_mm,
                                settings.camera_distance_mm,
                                marker_edges=marker_edges(state, tracks, solid),
                                marker_mm=settings.marker_mm)
    quality["scale"] = sinfo
    if state.board_rig is not None:  # the board's squares against the plate: one scale
        quality["board_views"]["scale_vs_plate"] = float(s * math.exp(state.board_rig[6]))
    quality["sigma"] = _sigma_report(sigma, s)
    for p in state.poses.values():
        p[3:6] = s * p[3:6] + np.array([0.0, 0.0, settings.plate_top_mm - s * z0])
    state.points[:] = s * state.points + np.array([0.0, 0.0, settings.plate_top_mm - s * z0])
    if quality["rms_px"] > settings.max_rms_px:
        raise SfmError(f"the turntable model leaves {quality['rms_px']:.3g} px RMS (limit "
                       f"max_rms_px {settings.max_rms_px}); the photos do not fit one rigid "
                       "scene turning about one axis (a plant that moved, wrong angles?)")
    models = {c: state.model(c) for c in state.intrinsics}
    poses = {g: state.pose(g) for g in state.poses}
    tilts = {v.view.tilt_index: v.view.tilt_deg for v in views}
    tilt_axis = None
    if len({g[1] for g in poses}) >= 2:
        fitted = fit_tilt_axis(poses, tilts, min(g[1] for g in poses))
        if fitted is not None:
            tilt_axis, quality["tilt_axis"] = fitted
    angles = state.view_angles(views)
    view_angles = {int(v.view.index): float(a) for v, a in zip(views, angles, strict=True)}
    if settings.prior_poses:
        quality["prior_poses_moved"] = _prior_moves(settings.prior_poses, poses)
    t["total_s"] = time.perf_counter() - t_start
    quality["seconds"] = dict(t)
    quality["method"] = "sfm: pycolmap SIFT + turntable-constrained bundle adjustment (pyceres)"
    return Calibration(models, poses, {k: float(v) for k, v in tilts.items()},
                       float(state.scale[0]), tilt_axis, quality, view_angles)


def board_views(state: bundle.TurntableState,
                candidates: dict[str, list[tuple[int, np.ndarray, np.ndarray]]],
                noise: float = 1.0) -> dict[str, bundle.BoardView]:
    """One board photo per camera for the bundle (``bundle.BoardView``), its pose from
    the corners under the initial intrinsics (OpenCV's PnP).

    Of a camera's photos (``candidates``: view index, board points (N, 3) mm, corners
    (N, 2) px) the one whose board is turned farthest from facing the camera (up to
    ``BOARD_MAX_TILT_DEG``) among those with at least 80 % of the most corners found: a
    board square-on to the camera moves in the image as the principal point does (a
    plane parallel to the image shifts, whatever its depth), an oblique one does not.
    """
    import cv2

    out = {}
    for cam, cands in candidates.items():
        if cam not in state.intrinsics or not cands:
            continue
        f, cu, cv_, _, _, asp = state.intrinsics[cam]
        k_mat = np.array([[f, 0.0, cu], [0.0, f * asp, cv_], [0.0, 0.0, 1.0]])
        most = max(len(c[2]) for c in cands)
        best = None
        for view_index, pts, uv, *where in cands:
            if len(uv) < 0.8 * most or len(uv) < 6:
                continue
            ok, rv, tv = cv2.solvePnP(pts.astype(np.float64), uv.astype(np.float64), k_mat,
                                      None, flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                continue
            normal = cv2.Rodrigues(rv)[0][:, 2]
            centre = cv2.Rodrigues(rv)[0] @ pts.mean(axis=0) + tv.ravel()
            tilt = math.degrees(math.acos(min(1.0, abs(float(normal @ centre))
                                              / float(np.linalg.norm(centre)))))
            if tilt > BOARD_MAX_TILT_DEG:
                continue
            if best is None or tilt > best[0]:
                best = (tilt, view_index, pts, uv, np.r_[rv.ravel(), tv.ravel()], where)
        if best is not None:
            angle, group = best[5] if best[5] else (None, None)
            out[cam] = bundle.BoardView(np.asarray(best[2], float), np.asarray(best[3], float),
                                        best[4].astype(float), noise, int(best[1]), best[0],
                                        angle, None if group is None else tuple(group))
    return out


# A board turned beyond this from facing the camera: corners foreshortened and blurred.
BOARD_MAX_TILT_DEG = 65.0


def board_rig_start(state: bundle.TurntableState) -> np.ndarray | None:
    """The board on the turntable (``TurntableState.board_rig``: [rotvec, t, log scale],
    board mm to the turntable frame at angle 0, state units) from each camera's own
    board pose and the solved camera poses: the scale that makes the cameras agree on
    where the board's origin is.  None with fewer than two such photos."""
    ends = []
    for b in state.boards.values():
        if b.angle_deg is None or b.group not in state.poses:
            continue
        cam = state.group_pose(b.group)
        back = rotation_z(-b.angle_deg) @ cam.R.T
        ends.append((back @ b.pose[3:6], rotation_z(-b.angle_deg) @ cam.C,
                     back @ rotmats(b.pose[:3])[0]))
    if len(ends) < 2:
        return None
    a = np.array([e[0] for e in ends])
    c = np.array([e[1] for e in ends])
    da, dc = a - a.mean(axis=0), c - c.mean(axis=0)
    k = -float(np.sum(da * dc)) / max(float(np.sum(da * da)), 1e-300)
    if not k > 0:
        return None
    origin = (k * a + c).mean(axis=0)
    return np.r_[rotvec(ends[0][2]), origin, math.log(k)]


def _weigh_by_kind(state: bundle.TurntableState, views: list[SfmView], tracks: Tracks,
                   keep: np.ndarray) -> tuple[Tracks, dict[str, Any]]:
    """``tracks`` with each observation's noise from its (camera, kind) class, and every
    board photo's corners weighed by their own residual (``bundle.noise_by_kind``)."""
    noise, info = bundle.noise_by_kind(state, views, tracks, keep)
    for cam, b in state.boards.items():
        sigma = float(np.sqrt(np.mean(np.sum(_board_residuals(state, cam, b) ** 2, axis=1))
                              / 2.0))
        b.noise = max(sigma, 1e-3) / bundle.NOISE_UNIT_PX
        info[f"{cam}/board"] = {"observations": len(b.uv), "sigma_px": sigma}
    return replace(tracks, noise=noise), info


def _board_residuals(state: bundle.TurntableState, cam: str, b: bundle.BoardView
                     ) -> np.ndarray:
    if bundle._on_rig(state, b):
        return bundle.project_board_rig(state.intrinsics[cam], state.poses[b.group],
                                        state.board_rig, b.angle_deg, b.points) - b.uv
    return bundle.project_board(state.intrinsics[cam], b.pose, b.points) - b.uv


def _board_report(state: bundle.TurntableState) -> dict[str, Any]:
    out = {}
    for cam, b in state.boards.items():
        r = _board_residuals(state, cam, b)
        out[cam] = {"view_index": b.view_index, "corners": len(b.uv),
                    "rms_px": float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))),
                    "board_tilt_deg": b.tilt_deg, "on_turntable": bundle._on_rig(state, b)}
    return out


def marker_edges(state: bundle.TurntableState, tracks: Tracks, solid: np.ndarray
                 ) -> np.ndarray:
    """Lengths (state units) of the printed markers' vertical edges (corners 0-3, 1-2)
    whose both ends are well triangulated: a marker's side, whatever the surface's
    curvature round the axis."""
    if tracks.marker is None:
        return np.zeros(0)
    key_of = np.full(tracks.n_tracks, -1, np.int64)
    m = tracks.marker >= 0
    key_of[tracks.track[m]] = tracks.marker[m]
    ok = solid & (key_of >= 0) & np.isfinite(state.points[:, 0])
    where = {int(k): int(t) for t, k in enumerate(key_of) if ok[t]}
    out = []
    for k, t in where.items():
        marker, corner = divmod(k, 4)
        if corner in (0, 1):
            other = where.get(marker * 4 + (3 if corner == 0 else 2))
            if other is not None:
                out.append(float(np.linalg.norm(state.points[t] - state.points[other])))
    return np.array(out)


def _check_focal(state: bundle.TurntableState, sigma: dict, init_info: dict,
                 settings: SfmSettings) -> None:
    """A focal length the photos leave loose is a named error, never a calibration."""
    for cam, sd in sigma["models"].items():
        f = float(state.intrinsics[cam][0])
        if "f" in sd and sd["f"] > FOCAL_MAX_SIGMA * f:
            starts = {k: v for k, v in init_info.items() if k.startswith(f"pose_{cam}/")}
            raise SfmError(
                f"camera {cam}: the photos do not fix the focal length (f = {f:.0f} px "
                f"+- {sd['f']:.0f} px, 1 sigma{'; orbit starts: ' + str(starts) if starts else ''}"
                f"); give the lens's focal length (calibrate.params.focal_px.{cam}: focal "
                "length / pixel pitch), print the marker rows (docs/sfm.md, 'what to print') "
                "so that the cameras share points, or print texture at other depths")


# After the first solve (principal point, distortion and angles held) an observation
# this far (in its own noise units: px for a dot) from its retriangulated point is a
# wrong match; at the truth, 10 % of cam0's keypoints on the virtual paper-72 print are
# 16-80 px off (one dot of the print matched for another), its good ones within 1 px.
CLEAN_PX = 2.0


# The joint solve's 1-sigma of a focal length above 2 %: undetermined.  A determined
# virtual paper-72 orbit pair gives 0.1-0.3 %; a shallow one several tens of %.
FOCAL_MAX_SIGMA = 0.05


def _sigma_report(sigma: dict, mm_per_unit: float) -> dict[str, Any]:
    """The 1-sigma of ``bundle.parameter_sigma`` for the quality report, centres in mm."""
    out: dict[str, Any] = {"residual_sigma_px": sigma["residual_sigma_px"],
                           "models": sigma["models"], "poses": {}}
    for (cam, tilt), sd in sigma["poses"].items():
        out["poses"][f"{cam}/t{tilt}"] = {"rotation_deg": sd["rotation_deg"],
                                          "centre_mm": sd["centre_units"] * mm_per_unit}
    if "stop_angle_deg" in sigma:
        out["stop_angle_deg"] = sigma["stop_angle_deg"]
    if "warning" in sigma:
        out["warning"] = sigma["warning"]
    return out


def _cap_observations(tracks: Tracks, cap: int) -> Tracks:
    """At most about ``cap`` observations: every marker corner, and whole feature tracks
    drawn in a seeded random order (``CAP_SEED``) until the cap is reached.

    Drawing tracks at random keeps the scene's surfaces in their proportions.  Keeping
    the longest tracks first (as before) kept only the plate's top once the cap bound:
    its tracks are the longest (both cameras, every stop), and on exact correspondences
    of the virtual paper-72 rig (276k observations, cap 200k) every rim point went, the
    plate's radius came from the top's edge and the centres 15-17 mm off (0.05 mm
    uncapped)."""
    if len(tracks.view) <= cap:
        return tracks
    marker = np.zeros(tracks.n_tracks, bool)
    marker[tracks.track[tracks.marker_of() >= 0]] = True
    length = np.bincount(tracks.track, minlength=tracks.n_tracks)
    order = np.random.default_rng(CAP_SEED).permutation(np.flatnonzero(~marker))
    room = cap - int(length[marker].sum())
    chosen = marker.copy()
    chosen[order[np.cumsum(length[order]) <= room]] = True
    out = tracks.subset(chosen[tracks.track])
    out.stats["observations_capped_from"] = int(len(tracks.view))
    return out


CAP_SEED = 0  # one scan, one subset of tracks: the same calibration on every run


def _initial_state(views: list[SfmView], tracks: Tracks, sizes: dict[str, tuple[int, int]],
                   settings: SfmSettings, commanded: np.ndarray):
    info: dict[str, Any] = {}
    groups = sorted({v.group for v in views})
    if settings.prior_poses:
        missing = [g for g in groups if g not in settings.prior_poses]
        if missing:
            raise SfmError("the approximate poses given with the scan lack " + ", ".join(
                f"camera {c} tilt {t}" for c, t in missing))
        focal = settings.prior_focal or {}
        models = {c: CameraModel(focal[c], *principal_point(settings, c, (w, h)), 0, 0, w, h)
                  for c, (w, h) in sizes.items() if c in focal}
        for c, size in sizes.items():
            if c not in models:
                motions = [m for g, ms in initialise.orbit_pairs(views, tracks).items()
                           if g[0] == c for m in ms]
                f, finfo = initialise.focal_from_turns(motions, size)
                models[c] = CameraModel(f, *principal_point(settings, c, size), 0, 0, *size)
                info[f"focal_{c}"] = finfo
        poses = {g: GroupPose(settings.prior_poses[g].R, settings.prior_poses[g].centre)
                 for g in groups}
        info["source"] = "approximate poses given with the scan"
    else:
        motions = initialise.orbit_pairs(views, tracks)
        shared = initialise.groups_sharing_tracks(tracks, views)
        own, focal = {}, defaultdict(list)
        for g in groups:
            if not motions.get(g):
                raise SfmError(f"camera {g[0]} tilt {g[1]}: no two photos a few turntable stops "
                               f"apart share enough features. {ADVICE_TEXTURE}")
        # each orbit alone, ``threads`` at a time (OpenCV and the compiled solver release
        # the GIL; OpenCV's RANSAC seeds itself per call)
        with ThreadPoolExecutor(max(settings.threads, 1)) as pool:
            orbits = list(pool.map(lambda g: _orbit_start(
                views, tracks, motions[g], g, sizes[g[0]], settings, g in shared), groups))
        for g, (f, own[g], info[f"pose_{g[0]}/t{g[1]}"]) in zip(groups, orbits, strict=True):
            focal[g[0]].append(f)
        models = {c: CameraModel(float(np.median(focal[c])), *principal_point(settings, c, (w, h)),
                                 0, 0, w, h) for c, (w, h) in sizes.items()}
        poses, info["link"], merged = initialise.link_groups(
            tracks, views, models, own, commanded,
            settings.plate_diameter_mm if settings.scale == "plate" else None)
        if merged:
            tracks = merge_tracks(tracks, np.concatenate(list(merged.values())))
            info["link"]["tracks_merged"] = int(sum(len(m) for m in merged.values()))
        info["source"] = "two-view geometry of turntable neighbours"
    ref = max(groups, key=lambda g: int(np.sum([views[i].group == g for i in tracks.view])))
    poses = _normalise(poses, ref)
    pts, spread = initialise.triangulate(tracks, views, models, poses, commanded)
    pts[~(spread > 1.0)] = np.nan
    state = bundle.new_state(views, models, poses, pts, ref)
    if settings.prior_poses:
        state.pose_priors = {g: (p.R, p.C) for g, p in _normalise(
            {g: GroupPose(settings.prior_poses[g].R, settings.prior_poses[g].centre)
             for g in groups}, ref, keep_scale=True).items()}
    info["reference"] = f"{ref[0]}/t{ref[1]}"
    return state, info, tracks


def principal_point(settings: SfmSettings, camera: str, size: tuple[int, int]
                    ) -> tuple[float, float]:
    """(cu, cv) of ``camera``, px: ``settings.principal_point_px`` when given, else the
    image centre."""
    given = (settings.principal_point_px or {}).get(camera)
    if given is not None:
        return float(given[0]), float(given[1])
    return (size[0] - 1) / 2, (size[1] - 1) / 2


def merge_tracks(tracks: Tracks, pairs: np.ndarray) -> Tracks:
    """Tracks with each pair ``(a, b)`` of track ids (``pairs`` (K, 2)) made one."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = tracks.n_tracks
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(g, directed=False)
    _, t = np.unique(label[tracks.track], return_inverse=True)
    return tracks.reordered(np.arange(len(tracks.view)), t)


def _orbit_start(views: list[SfmView], tracks: Tracks, motions, group: tuple[str, int],
                 size: tuple[int, int], settings: SfmSettings, shared: bool = False
                 ) -> tuple[float, GroupPose, dict[str, Any]]:
    """Focal length and pose of one (camera, tilt) from its own orbit, multi-start.

    Two-view geometry fixes the axis for a given focal length but not the focal
    length itself when most features lie on the plate (a plane turning about its
    normal: the degenerate case of plane-based calibration).  So a short bundle
    adjustment of this orbit alone (the angles held, no distortion) starts from
    each of several focal lengths, and the lowest cost wins.  When rival focal lengths
    fit about equally well the photos of this orbit do not decide: an error unless
    ``shared`` (the orbit shares tracks with another camera or tilt, whose joint solve
    may fix it; its sigma is checked afterwards).

    Nor does it fix the axis's tilt towards the camera well when most points lie on the
    plate: on the virtual 640 x 427 printed plate the median axis of the essential
    matrices came out 33-43 deg off the true one; from there the short adjustment of
    one orbit stopped 25 deg off (8.6x the cost of the right minimum) and the full one
    at a rig turned 179 deg (0.76 px RMS against 0.27): in two runs of three as
    COLMAP's RANSAC inliers varied, and with its seed fixed at 0.  So the best
    focal length's start is also tried with the axis tipped towards and away from the
    camera by ``ORBIT_TILTS_DEG``, and again the lowest cost wins: the result is chosen
    by cost among fixed starts, not by the luck of the first one.
    """
    w, h = size
    in_group = np.array([views[i].group == group for i in tracks.view])
    sub = _cap_observations(tracks.subset(in_group), 4000)
    given = (settings.focal_px or {}).get(group[0])
    if given is not None:
        starts = [float(given)]
    else:
        f_turns, _ = initialise.focal_from_turns(motions, size)
        starts = sorted({f_turns, *(k * max(w, h) for k in (0.7, 1.0, 1.4, 2.0, 2.8))})
    opt = bundle.BundleOptions(angle_sigma_deg=None, fix_principal_point=True,
                               fix_distortion=True, max_iterations=15, outlier_px=8.0,
                               threads=settings.threads,
                               fixed_focal=[group[0]] if given is not None and not
                               settings.fit_focal else [])
    tried: list[dict[str, Any]] = []
    best = None
    commanded = np.array([v.view.angle_deg for v in views])

    two_view: dict[float, GroupPose | None] = {}   # the tipped starts reuse their f's

    def attempt(f0: float, tip_deg: float) -> None:
        nonlocal best
        if f0 not in two_view:
            try:
                two_view[f0] = initialise.group_pose(motions, f0, size)[0]
            except SfmError:
                two_view[f0] = None
        pose = two_view[f0]
        if pose is None:
            return
        if tip_deg:  # the axis tipped about the world x axis (across the line of sight)
            pose = GroupPose(pose.R @ rotation_x(tip_deg).T, pose.C)
        model = CameraModel(f0, *principal_point(settings, group[0], size), 0, 0, w, h)
        pts, spread = initialise.triangulate(sub, views, {group[0]: model}, {group: pose},
                                             commanded)
        pts[~(spread > 1.0)] = np.nan
        st = bundle.new_state([views[i] for i in range(len(views))], {group[0]: model},
                              {group: pose}, pts, group)
        seen = np.isfinite(bundle.residuals(st, views, sub)).all(axis=1)
        if seen.sum() < 0.5 * len(seen):  # most points behind the camera: a hopeless start
            return
        keep, rep = bundle.adjust(st, views, sub, opt, rounds=0)
        if not rep.solves[-1]["usable"] or not keep.any():
            return
        cost = rep.solves[-1]["final_cost"] / max(int(keep.sum()), 1)
        tried.append({"f_start_px": f0, "tip_deg": tip_deg,
                      "f_px": float(st.intrinsics[group[0]][0]), "cost_per_obs": cost})
        if best is None or cost < best[0]:
            best = (cost, float(st.intrinsics[group[0]][0]), st.group_pose(group), f0)

    for f0 in starts:
        attempt(f0, 0.0)
    if best is not None:
        for tip in ORBIT_TILTS_DEG:
            attempt(best[3], tip)
    if best is None:
        raise SfmError(f"camera {group[0]} tilt {group[1]}: no start gives a usable orbit")
    # A start that ends at a clearly different focal length for about the same cost means
    # these photos do not fix the focal length (a shallow scene: focal length and distance
    # trade off); a calibration from them would look fine and be wrong.
    rivals = [t for t in tried if abs(t["f_px"] / best[1] - 1.0) > FOCAL_RIVAL_GAP
              and t["cost_per_obs"] < (1.0 + FOCAL_RIVAL_COST) * best[0]]
    if rivals and not shared:
        raise SfmError(
            f"camera {group[0]} tilt {group[1]}: the photos do not fix the focal length "
            f"(f = {best[1]:.0f} px and f = {rivals[0]['f_px']:.0f} px fit them equally "
            f"well: {best[0]:.3g} and {rivals[0]['cost_per_obs']:.3g} per observation); give "
            f"the lens's focal length (calibrate.params.focal_px.{group[0]}: focal length / "
            "pixel pitch) or print texture at other depths (the plate's rim, the pot carrier)")
    return best[1], best[2], {"starts": tried, "f_px": best[1],
                              "rival_focal_px": [t["f_px"] for t in rivals]}


def rotation_x(deg: float) -> np.ndarray:
    """Rotation by ``deg`` about the x axis (3, 3)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# Two focal lengths more than 5 % apart whose orbit costs differ by less than 10 %: the
# photos do not decide between them (the virtual 640 x 427 orbits: 1.4 and 2.8 image
# widths within 2 % of each other's cost; a determined orbit separates them by > 3x).
FOCAL_RIVAL_GAP = 0.05
FOCAL_RIVAL_COST = 0.10
# Tips of the axis tried beside two-view geometry's (see _orbit_start): its error reached
# 43 deg on the virtual 640 x 427 printed plate; from that start, tips of 40 and 60 deg
# (3 and 17 deg off) converged to the right minimum, 0 and 20 deg (43 and 23 off) did not.
ORBIT_TILTS_DEG = (-60.0, -40.0, -20.0, 20.0, 40.0, 60.0)


def _normalise(poses: dict[tuple[str, int], GroupPose], ref: tuple[str, int],
               keep_scale: bool = False) -> dict[tuple[str, int], GroupPose]:
    """Turn the world about the axis so the reference camera is on -Y at height 0 and,
    unless ``keep_scale``, at ``NOMINAL_DISTANCE`` from the axis (the bundle's gauge)."""
    c = poses[ref].C
    yaw = -90.0 - math.degrees(math.atan2(c[1], c[0]))
    rz = rotation_z(yaw)
    s = 1.0 if keep_scale else initialise.NOMINAL_DISTANCE / max(float(np.hypot(c[0], c[1])),
                                                                1e-9)
    dz = 0.0 if keep_scale else -s * c[2]
    return {g: GroupPose(p.R @ rz.T, s * (rz @ p.C) + np.array([0.0, 0.0, dz]))
            for g, p in poses.items()}


def focal_starts(state: bundle.TurntableState, held: list[str]) -> list[dict[str, float]]:
    """Focal lengths (px per camera) to start the joint solve from: each camera's own
    orbit's, then every camera at one camera's, for each camera (starts within
    ``SAME_START`` of an earlier one dropped; ``held`` cameras keep theirs).

    Each orbit fixes its focal length poorly (a plate seen at 8 deg of elevation, a far
    camera), and from one wrong start the joint solve stays in a wrong minimum: on the
    virtual paper-72 dicot (dev seed 0) the orbits gave 1796 and 2090 px (truth 1882),
    the joint solve ended with cam0 4.2 % off and 54 mm from its place; started with
    both at 1796 px or both at 2090 px it found both within 0.2 % and 0.9 mm."""
    own = {c: float(v[0]) for c, v in state.intrinsics.items() if c not in held}
    starts = [own]
    for f in own.values():
        cand = dict.fromkeys(own, f)
        if all(any(abs(cand[c] / s[c] - 1.0) > SAME_START for c in own) for s in starts):
            starts.append(cand)
    return starts


# Two starts whose focal lengths all agree to 1 % are one start.
SAME_START = 0.01
# Residuals beyond this (in each observation's noise units: px for a dot) count as this
# much in the cost that chooses between starts: a wrong match costs the same wherever it is.
TRUNCATE_AT = 1.0


def truncated_cost(state: bundle.TurntableState, views: list[SfmView], tracks: Tracks
                   ) -> float:
    """Sum over every observation of min(residual / noise, ``TRUNCATE_AT``)**2: the cost
    two solves of the same observations are compared by, whatever each kept."""
    e = np.linalg.norm(bundle.residuals(state, views, tracks), axis=1) / tracks.noise_of()
    return float(np.sum(np.minimum(np.nan_to_num(e, nan=TRUNCATE_AT), TRUNCATE_AT) ** 2))


def _retriangulate(state: bundle.TurntableState, views: list[SfmView], tracks: Tracks
                   ) -> None:
    """The points again from the state's cameras (at the recorded angles)."""
    models = {c: state.model(c) for c in state.intrinsics}
    poses = {g: state.group_pose(g) for g in state.poses}
    pts, spread = initialise.triangulate(tracks, views, models, poses, state.view_angles(views))
    pts[~(spread > 1.0)] = np.nan
    state.points[:] = pts


def _clean_tracks(state: bundle.TurntableState, views: list[SfmView], tracks: Tracks,
                  keep: np.ndarray, max_px: float, passes: int = 2) -> np.ndarray:
    """Points again from the refined cameras and the kept observations, then every
    observation within ``max_px`` of its point kept (one dropped earlier comes back
    when it fits), twice.  A wrong match joins two dots of a repeated print into one
    track; its minority observations fall out here.  Returns the kept observations."""
    models = {c: state.model(c) for c in state.intrinsics}
    poses = {g: state.group_pose(g) for g in state.poses}
    angles = state.view_angles(views)
    for _ in range(passes):
        pts, spread = initialise.triangulate(tracks, views, models, poses, angles, obs=keep)
        pts[~(spread > 1.0)] = np.nan
        state.points[:] = pts
        err = np.linalg.norm(bundle.residuals(state, views, tracks), axis=1) \
            / tracks.noise_of()
        keep = np.isfinite(err) & (err <= max_px)
        counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
        keep &= counts[tracks.track] >= 2
    return keep


def _quality(state: bundle.TurntableState, views: list[SfmView], tracks: Tracks,
             keep: np.ndarray, err: np.ndarray, settings: SfmSettings) -> dict[str, Any]:
    e = err[keep]
    per_cam: dict[str, list[float]] = defaultdict(list)
    per_view = np.zeros(len(views), int)
    for k in np.flatnonzero(keep):
        per_cam[views[tracks.view[k]].view.camera].append(err[k])
        per_view[tracks.view[k]] += 1
    lengths = np.bincount(tracks.track[keep])
    lengths = lengths[lengths > 0]
    weak = [int(views[i].view.index) for i in np.flatnonzero(
        per_view < settings.min_view_observations)]
    flags = []
    if weak:
        flags.append(f"{len(weak)} photos hold fewer than {settings.min_view_observations} "
                     f"inlier features (view indices {weak[:10]}); their turntable angles stay "
                     "at the commanded values")
    angles = state.view_angles(views)
    commanded = np.array([v.view.angle_deg for v in views])
    moved = angles - commanded
    return {
        "rms_px": float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan"),
        "mean_px": float(np.mean(e)) if len(e) else float("nan"),
        "per_camera": {c: {"rms_px": float(np.sqrt(np.mean(np.square(v)))),
                           "observations": len(v)} for c, v in sorted(per_cam.items())},
        "observations": int(keep.sum()), "rejected_observations": int((~keep).sum()),
        "tracks": int(len(lengths)),
        "track_length": {"mean": float(lengths.mean()) if len(lengths) else 0.0,
                         "median": float(np.median(lengths)) if len(lengths) else 0.0,
                         "max": int(lengths.max()) if len(lengths) else 0},
        "views": len(views),
        "registered_views": int(np.sum(per_view >= settings.min_view_observations)),
        "observations_per_view": {"min": int(per_view.min()), "median": float(
            np.median(per_view))},
        "stop_angle_change_deg": {"rms": float(np.sqrt(np.mean(moved ** 2))),
                                  "max": float(np.max(np.abs(moved)))},
        "features": dict(tracks.stats),
        "flags": flags,
    }


def _prior_moves(prior: dict[tuple[str, int], Pose], poses: dict[tuple[str, int], Pose]
                 ) -> dict[str, dict[str, float]]:
    """How far the solve moved each approximate pose (centre mm, rotation deg)."""
    out = {}
    for g, p in poses.items():
        if g in prior:
            q = prior[g]
            out[f"{g[0]}/t{g[1]}"] = {
                "centre_mm": float(np.linalg.norm(p.centre - q.centre)),
                "rotation_deg": math.degrees(float(np.linalg.norm(rotvec(p.R @ q.R.T))))}
    return out


__all__ = ["SfmError", "SfmSettings", "calibrate_scan", "solve_tracks", "match_scan",
           "rotmats"]

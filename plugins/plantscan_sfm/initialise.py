"""Turntable initialisation from two-view geometry: focal length, axis and camera poses.

Between two photos of one camera at turntable angles ``a_i`` and ``a_j`` the
scene turned by ``d = a_j - a_i`` about the axis, so the camera moved by

    x_j = Q x_i + t,   Q = R Rz(d) R^T,   t = (I - Q) o

where ``R`` is the camera's world -> camera rotation and ``o`` the world origin
(a point of the axis) in camera coordinates.  The essential matrix of the pair
gives ``Q`` and the direction of ``t``.  Hence, per (camera, tilt):

* the focal length is the one whose essential matrices turn by the commanded
  angles (a wrong focal length shrinks or stretches every rotation);
* the axis in camera coordinates, ``R e_z``, is the mean rotation axis of the
  ``Q``; the direction from the camera to the axis, ``R e_y``, follows from ``t``;
* the camera sits at ``C = (0, -D, 0)`` for an arbitrary distance ``D`` (scale
  and height come later, from the plate).

Cameras and tilts initialised this way each have their own yaw, height and
scale about the common axis; points seen from two of them fix those three
numbers (a similarity turning only about the axis), in a tree grown from the
(camera, tilt) with the most observations.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np

from plantscan_core.data import CameraModel, rotation_z
from plantscan_sfm.features import SfmError, SfmView, Tracks

NOMINAL_DISTANCE = 1000.0  # arbitrary units until the metric scale is known
# Linking by shape is accepted only when it is clear: an azimuth correlation peak this many
# standard deviations above the rest and this many point pairs within tolerance after the
# fit (on the virtual paper-72 plate, cameras at 8 and 48 deg of elevation see the rim and
# the top: 135 of 4032 points within 1 mm of the other's even with the exact cameras, and
# the peak lands 129 deg off; a wrong link must be an error, never a calibration).
MIN_AZIMUTH_CONTRAST = 8.0
MIN_SHAPE_PAIRS = 200
# Two groups sharing the corners of two markers or more are linked on those alone; four
# (one marker) suffice to check a link made otherwise.  A link after which the markers'
# corners lie more than this share of the plate's radius apart is contradicted (the
# virtual grass scan's wrong link: cam0 240 mm and 450 mm off on a 200 mm radius; a
# right link leaves the initial triangulation's error, a few mm).
MIN_MARKER_LINK_POINTS = 8
MIN_MARKER_CHECK_POINTS = 4
MARKER_CONTRADICTION = 0.1


@dataclass
class GroupPose:
    """World -> camera rotation ``R`` (3, 3) and centre ``C`` (3,) of one (camera, tilt)."""

    R: np.ndarray
    C: np.ndarray


def pair_correspondences(tracks: Tracks, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(K, 2)`` in photos ``a`` and ``b`` of the tracks seen in both."""
    ia = np.flatnonzero(tracks.view == a)
    ib = np.flatnonzero(tracks.view == b)
    common, ka, kb = np.intersect1d(tracks.track[ia], tracks.track[ib], return_indices=True)
    return tracks.uv[ia[ka]], tracks.uv[ib[kb]]


def _relative_pose(pa: np.ndarray, pb: np.ndarray, f: float, centre: tuple[float, float],
                   threshold_px: float):
    """(Q, t unit, inliers) of photo b from photo a under focal ``f`` (no distortion)."""
    k = np.array([[f, 0.0, centre[0]], [0.0, f, centre[1]], [0.0, 0.0, 1.0]])
    e, mask = cv2.findEssentialMat(pa, pb, k, cv2.RANSAC, 0.999, threshold_px)
    if e is None or e.shape != (3, 3):
        return None
    n, r, t, mask2 = cv2.recoverPose(e, pa, pb, k, mask=mask)
    if n < 8:
        return None
    return r, t.reshape(3), int(n)


def _rotvec(r: np.ndarray) -> np.ndarray:
    v, _ = cv2.Rodrigues(np.asarray(r, dtype=float))
    return v.reshape(3)


@dataclass
class PairMotion:
    a: int
    b: int
    delta_deg: float      # commanded turn from a to b
    pa: np.ndarray
    pb: np.ndarray


def orbit_pairs(views: list[SfmView], tracks: Tracks, max_stops: int = 2,
                min_points: int = 30) -> dict[tuple[str, int], list[PairMotion]]:
    """Pairs of photos of each (camera, tilt) one or two stops apart, with their matches."""
    groups: dict[tuple[str, int], list[int]] = defaultdict(list)
    for i, v in enumerate(views):
        groups[v.group].append(i)
    out: dict[tuple[str, int], list[PairMotion]] = {}
    for g, idx in groups.items():
        idx = sorted(idx, key=lambda i: views[i].view.angle_deg)
        m = len(idx)
        motions = []
        for k in range(m):
            for s in range(1, max_stops + 1):
                if m < 3 or (s >= m):
                    continue
                a, b = idx[k], idx[(k + s) % m]
                d = (views[b].view.angle_deg - views[a].view.angle_deg + 180.0) % 360.0 - 180.0
                if abs(d) < 1.0 or abs(d) > 60.0:
                    continue
                pa, pb = pair_correspondences(tracks, a, b)
                if len(pa) >= min_points:
                    motions.append(PairMotion(a, b, d, pa, pb))
        out[g] = motions
    return out


def groups_sharing_tracks(tracks: Tracks, views: list[SfmView], min_tracks: int = 8
                          ) -> set[tuple[str, int]]:
    """The (camera, tilt) groups sharing at least ``min_tracks`` tracks with another."""
    gid = {g: k for k, g in enumerate(sorted({v.group for v in views}))}
    obs_g = np.array([gid[views[i].group] for i in tracks.view], np.int64)
    n_g = len(gid)
    seen = np.zeros((tracks.n_tracks, n_g), bool)
    seen[tracks.track, obs_g] = True
    multi = seen[seen.sum(axis=1) >= 2]
    counts = multi.sum(axis=0)
    return {g for g, k in gid.items() if counts[k] >= min_tracks}


def focal_from_turns(motions: list[PairMotion], size: tuple[int, int],
                     threshold_px: float = 1.5) -> tuple[float, dict]:
    """Focal length (px) whose essential matrices turn by the commanded angles.

    A log-spaced search from 0.3 to 5 image widths, refined twice around the
    best; the figure of merit is the median over pairs of the relative error
    of the recovered turn ``|angle(Q)| / |d| - 1``.
    """
    if not motions:
        raise SfmError("no two photos of a camera a few turntable stops apart share enough "
                       "matched features to start from")
    w, h = size
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    use = sorted(motions, key=lambda m: -len(m.pa))[:12]

    def misfit(f: float) -> float:
        errs = []
        for m in use:
            rel = _relative_pose(m.pa, m.pb, f, centre, threshold_px)
            if rel is None:
                errs.append(1.0)
                continue
            ang = math.degrees(np.linalg.norm(_rotvec(rel[0])))
            errs.append(abs(ang / abs(m.delta_deg) - 1.0))
        return float(np.median(errs))

    lo, hi, n = math.log(0.3 * max(w, h)), math.log(5.0 * max(w, h)), 24
    best = None
    for _ in range(3):
        grid = np.exp(np.linspace(lo, hi, n))
        scores = [misfit(f) for f in grid]
        k = int(np.argmin(scores))
        best = (float(grid[k]), float(scores[k]))
        step = (hi - lo) / (n - 1)
        lo, hi, n = math.log(best[0]) - 1.5 * step, math.log(best[0]) + 1.5 * step, 9
    return best[0], {"turn_misfit": best[1], "pairs": len(use)}


def group_pose(motions: list[PairMotion], f: float, size: tuple[int, int],
               threshold_px: float = 1.5) -> tuple[GroupPose, dict]:
    """Pose of one (camera, tilt) about the axis from its orbit pairs (see module doc)."""
    w, h = size
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    axes, towards, turns = [], [], []
    for m in motions:
        rel = _relative_pose(m.pa, m.pb, f, centre, threshold_px)
        if rel is None:
            continue
        q, t, _ = rel
        rv = _rotvec(q)
        ang = np.linalg.norm(rv)
        if ang < 1e-6:
            continue
        a = rv / math.radians(m.delta_deg)   # rotation by +d about a
        a /= np.linalg.norm(a)
        # (I - Q) o = t restricted to the plane normal to a: o up to scale, with sign.
        p = np.eye(3) - np.outer(a, a)
        o, *_ = np.linalg.lstsq((np.eye(3) - q) @ p, t, rcond=None)
        o = p @ o
        if np.linalg.norm(o) < 1e-9:
            continue
        axes.append(a)
        towards.append(o / np.linalg.norm(o))
        turns.append(math.degrees(ang) / abs(m.delta_deg))
    if len(axes) < 2:
        raise SfmError("too few photo pairs of one camera give a usable relative pose "
                       f"({len(axes)}); the photos share too few features")
    ez = np.median(np.array(axes), axis=0)
    ez /= np.linalg.norm(ez)
    ey = np.median(np.array(towards), axis=0)
    ey -= ez * (ey @ ez)
    ey /= np.linalg.norm(ey)
    ex = np.cross(ey, ez)
    r = np.stack([ex, ey, ez], axis=1)
    spread = float(np.degrees(np.median(np.arccos(np.clip(np.array(axes) @ ez, -1, 1)))))
    return GroupPose(r, np.array([0.0, -NOMINAL_DISTANCE, 0.0])), {
        "pairs": len(axes), "axis_spread_deg": spread, "turn_ratio": float(np.median(turns))}


def triangulate(tracks: Tracks, views: list[SfmView], models: dict[str, CameraModel],
                poses: dict[tuple[str, int], GroupPose], angles_deg: np.ndarray,
                obs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mid-point triangulation of every track (world frame at turntable angle 0).

    ``angles_deg`` (n_views,) is the turntable angle of each photo (a lab-fixed
    point, ``tracks.lab``, is seen at angle 0 in all); ``obs`` (M,) bool the
    observations to use (default: those of posed groups).

    Returns points ``(n_tracks, 3)`` and the largest angle between two of a
    track's rays ``(n_tracks,)``, deg (NaN where fewer than two rays).
    """
    n = tracks.n_tracks
    v = tracks.view
    posed = np.array([views[i].group in poses for i in range(len(views))])
    use = posed[v] if obs is None else (obs & posed[v])
    centres = np.zeros((len(v), 3))
    dirs = np.zeros((len(v), 3))
    lab = tracks.lab_of()
    for i, sv in enumerate(views):
        if not posed[i]:
            continue
        pose = poses[sv.group]
        for fixed in (False, True):
            sel = np.flatnonzero((v == i) & use & (lab == fixed))
            if not len(sel):
                continue
            # a lab-fixed point is where it is at turntable angle 0 in every photo
            rz = rotation_z(0.0 if fixed else -angles_deg[i])
            rays = models[sv.view.camera].unproject(tracks.uv[sel])
            dirs[sel] = rays @ (rz @ pose.R.T).T
            centres[sel] = rz @ pose.C
    a = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    proj[~use] = 0.0
    np.add.at(a, tracks.track, proj)
    np.add.at(b, tracks.track, np.einsum("kij,kj->ki", proj, centres))
    counts = np.bincount(tracks.track[use], minlength=n)
    ok = counts >= 2
    a[~ok] = np.eye(3)
    det = np.linalg.det(a)
    ok &= np.abs(det) > 1e-12
    a[~ok] = np.eye(3)
    pts = np.linalg.solve(a, b[:, :, None])[:, :, 0]
    pts[~ok] = np.nan
    # Widest ray pair of each track: compare each ray with the track's mean direction.
    mean_dir = np.zeros((n, 3))
    np.add.at(mean_dir, tracks.track[use], dirs[use])
    norm = np.linalg.norm(mean_dir, axis=1, keepdims=True)
    mean_dir = mean_dir / np.where(norm > 0, norm, 1.0)
    cosang = np.clip(np.einsum("ki,ki->k", dirs, mean_dir[tracks.track]), -1, 1)
    spread = np.zeros(n)
    np.maximum.at(spread, tracks.track[use], np.degrees(np.arccos(cosang[use])))
    spread[~ok] = np.nan
    return pts, 2.0 * spread


def link_groups(tracks: Tracks, views: list[SfmView], models: dict[str, CameraModel],
                poses: dict[tuple[str, int], GroupPose], angles_deg: np.ndarray,
                plate_diameter_mm: float | None = None,
                ) -> tuple[dict[tuple[str, int], GroupPose], dict, dict]:
    """Bring every (camera, tilt) into the frame of the one with the most observations.

    Each group's own triangulation and the reference's share points; the
    similarity ``X_ref = s Rz(phi) X + dz e_z`` (the two frames share the axis)
    is fitted on them robustly.  Groups whose photos share no tracks with the
    others (views too different for SIFT, as 8 and 48 degrees of elevation on a
    printed plate) are linked by the shape of their point clouds, made metric
    by the plate (``_register_by_shape``).  Groups linked to no posed group
    raise SfmError.

    Returns the poses, a report, and per group linked by shape the pairs of
    tracks ``(K, 2)`` (its, the other's) found to be the same points.
    """
    group_of_view = [v.group for v in views]
    gid = {g: k for k, g in enumerate(sorted(set(group_of_view)))}
    obs_gid = np.array([gid[group_of_view[i]] for i in tracks.view], dtype=np.int64)
    counts = {g: int(np.sum(obs_gid == k)) for g, k in gid.items()}
    ref = max(sorted(poses), key=lambda g: counts.get(g, 0))
    own = {}
    for g in poses:
        sel = obs_gid == gid[g]
        pts, spread = triangulate(tracks, views, models, {g: poses[g]}, angles_deg, sel)
        own[g] = np.where((spread > 2.0)[:, None], pts, np.nan)
    placed = {ref: poses[ref]}
    links = {}
    is_marker = np.zeros(tracks.n_tracks, bool)
    is_marker[tracks.track[tracks.marker_of() >= 0]] = True
    pending = [g for g in poses if g != ref]
    while pending:
        # Marker ids name the same corner in every camera without matching, so a pair of
        # groups sharing enough of them is linked on them alone, before any pair linked by
        # matched features only (a repeated print matched across cameras can agree on a
        # wrong link: the virtual grass scan's 301 shared tracks did).
        best = None
        for g in pending:
            for h in placed:
                both = np.isfinite(own[g][:, 0]) & np.isfinite(own[h][:, 0])
                n_marker = int(np.sum(both & is_marker))
                rank = (n_marker >= MIN_MARKER_LINK_POINTS, int(both.sum()))
                if both.sum() >= 8 and (best is None or rank > best[3]):
                    best = (g, h, int(both.sum()), rank)
        if best is None and plate_diameter_mm is not None:
            found = _register_by_shape(pending, placed, own, plate_diameter_mm)
            if found is not None:
                g, h, n_common, (s, phi, dz, inl), pairs = found
                _check_markers(g, h, own, is_marker, (s, phi, dz), "3D shape")
                _place(g, h, s, phi, dz, n_common, inl, poses, placed, links, "3D shape",
                       pairs)
                pending.remove(g)
                continue
        if best is None:
            raise SfmError(
                "these cameras/tilts share too few triangulated points with the others to be "
                f"placed in one frame: {', '.join(f'{c} tilt {t}' for c, t in pending)}. "
                "Their photos share no features with the other cameras' (SIFT does not match "
                "a print seen from elevations 40 degrees apart); add a tilt or camera between "
                "them, print texture that both see at a similar angle (the rim and pot "
                "carrier), or calibrate with a board (calibrate.plugin: turntable)")
        g, h, n_common, (by_markers, _) = best
        both = np.isfinite(own[g][:, 0]) & np.isfinite(own[h][:, 0])
        how = "marker ids" if by_markers else "shared tracks"
        fit_on = both & is_marker if by_markers else both
        s, phi, dz, inl = _axial_similarity(own[g][fit_on], own[h][fit_on])
        _check_markers(g, h, own, is_marker, (s, phi, dz), how)
        _place(g, h, s, phi, dz, int(fit_on.sum()), inl, poses, placed, links, how)
        # shared features the link puts apart join different points (of a repeated print)
        ids = np.flatnonzero(both & ~is_marker)
        links[g][3]["features_apart"] = int(np.sum(
            _link_residuals(own[g][ids], own[h][ids], (s, phi, dz))
            > MARKER_CONTRADICTION * _radius(own[h][fit_on])))
        pending.remove(g)
    info = {"reference": f"{ref[0]}/t{ref[1]}",
            "links": {f"{g[0]}/t{g[1]}": v[3] for g, v in links.items()}}
    merged = {g: v[4] for g, v in links.items() if v[4] is not None}
    return placed, info, merged


def _link_residuals(x: np.ndarray, y: np.ndarray, link: tuple[float, float, float]
                    ) -> np.ndarray:
    """Distances (K,) between ``y`` and ``x`` moved by the link ``(s, phi deg, dz)``."""
    s, phi, dz = link
    moved = s * x @ rotation_z(phi).T + np.array([0.0, 0.0, dz])
    return np.linalg.norm(moved - y, axis=1)


def _radius(points: np.ndarray) -> float:
    """Median distance of ``points`` (K, 3) from the axis."""
    return float(np.median(np.hypot(points[:, 0], points[:, 1])))


def _check_markers(g, h, own, is_marker: np.ndarray, link: tuple[float, float, float],
                   how: str) -> None:
    """A link that the markers g and h both see do not follow is a named error.

    ``MARKER_CONTRADICTION``: the marker corners' median distance after the link, as a
    share of their median distance from the axis (the plate's radius, whatever the
    frame's units)."""
    both = np.isfinite(own[g][:, 0]) & np.isfinite(own[h][:, 0]) & is_marker
    if both.sum() < MIN_MARKER_CHECK_POINTS:
        return
    y = own[h][both]
    radius = _radius(y)
    off = float(np.median(_link_residuals(own[g][both], y, link)))
    if off > MARKER_CONTRADICTION * radius:
        raise SfmError(
            f"the link of {g[0]} tilt {g[1]} to {h[0]} tilt {h[1]} by {how} is contradicted "
            f"by the {int(both.sum())} marker corners both see: after it they lie "
            f"{off / radius:.0%} of the plate's radius apart (limit "
            f"{MARKER_CONTRADICTION:.0%}). The photos' matched features join different "
            "points of a repeated print, or two printed markers share an id; print the "
            "marker rows with distinct ids (docs/sfm.md, 'what to print')")


def _place(g, h, s, phi, dz, n_common, inl, poses, placed, links, how, pairs=None) -> None:
    """Put group ``g`` in the reference frame through ``h`` (``X_h = s Rz(phi) X_g + dz``)."""
    # own[h] is in h's initial frame; bring the result through h's own link.
    sh, phih, dzh = links.get(h, (1.0, 0.0, 0.0))[:3]
    s_tot, phi_tot, dz_tot = sh * s, phih + phi, sh * dz + dzh
    rz = rotation_z(phi_tot)
    p = poses[g]
    placed[g] = GroupPose(p.R @ rz.T, s_tot * (rz @ p.C) + np.array([0.0, 0.0, dz_tot]))
    links[g] = (s_tot, phi_tot, dz_tot, {"linked_to": f"{h[0]}/t{h[1]}", "by": how,
                                         "common_points": n_common, "inliers": inl}, pairs)


def _metric(points: np.ndarray, plate_diameter_mm: float) -> tuple[float, float]:
    """(mm per unit, plate-top height) of one group's own points, from the plate."""
    from plantscan_sfm.scale import metric_frame

    s, z0, _ = metric_frame(points, 1.0, "plate", plate_diameter_mm, None)
    return s, z0


def _register_by_shape(pending, placed, own, plate_diameter_mm: float,
                       tol_mm: float = 1.5):
    """Link a group that shares no tracks: its points and a placed group's, both made
    metric by the plate, differ only by a turn about the axis; the turn with the most
    points within ``tol_mm`` of each other wins, then a least-squares fit on them.

    Returns ``(g, h, n_pairs, (s, phi, dz, inliers), pairs)`` (``pairs``: (K, 2)
    track ids of g and h found to be one point, for merging tracks), or None.
    """
    from scipy.spatial import cKDTree

    best = None
    for g in pending:
        xg = own[g][np.isfinite(own[g][:, 0])]
        ig = np.flatnonzero(np.isfinite(own[g][:, 0]))
        if len(xg) < 50:
            continue
        try:
            sg, zg = _metric(xg, plate_diameter_mm)
        except SfmError:
            continue
        for h in placed:
            xh = own[h][np.isfinite(own[h][:, 0])]
            ih = np.flatnonzero(np.isfinite(own[h][:, 0]))
            if len(xh) < 50:
                continue
            try:
                sh, zh = _metric(xh, plate_diameter_mm)
            except SfmError:
                continue
            mg = sg * xg - np.array([0.0, 0.0, sg * zg])
            mh = sh * xh - np.array([0.0, 0.0, sh * zh])
            tree = cKDTree(mh)
            phi, contrast = azimuth_offset(mg, mh, 0.25 * plate_diameter_mm)
            if contrast < MIN_AZIMUTH_CONTRAST:
                continue
            s, dz = 1.0, 0.0
            # Pairs at the found turn, then the similarity (metric frames), tightening.
            for tol in (4 * tol_mm, 2 * tol_mm, tol_mm, tol_mm):
                moved = s * mg @ rotation_z(phi).T + np.array([0.0, 0.0, dz])
                d, j = tree.query(moved, distance_upper_bound=tol)
                ok = np.isfinite(d)
                if ok.sum() < 8:
                    break
                s, phi, dz, inl = _axial_similarity(mg[ok], mh[j[ok]])
            if ok.sum() < MIN_SHAPE_PAIRS:
                continue
            # mutual nearest neighbours only, for merging tracks
            back = cKDTree(s * mg @ rotation_z(phi).T + np.array([0.0, 0.0, dz]))
            _, jb = back.query(mh[j[ok]])
            mutual = np.flatnonzero(ok)[jb == np.flatnonzero(ok)]
            s_units = s * sg / sh
            dz_units = (dz - s * sg * zg + sh * zh) / sh
            pairs = np.stack([ig[mutual], ih[j[mutual]]], axis=1)
            cand = (g, h, int(len(mutual)), (s_units, phi, dz_units, inl), pairs)
            if best is None or cand[2] > best[2]:
                best = cand
    return best


def azimuth_offset(x: np.ndarray, y: np.ndarray, min_radius: float,
                   bin_deg: float = 0.05, smooth_bins: float = 2.0) -> tuple[float, float]:
    """Turn (deg) about the axis that best lays the points ``x`` (K, 3) onto ``y`` (L, 3),
    and the peak's contrast (its height above the rest, in standard deviations).

    The azimuth of a point does not change with the scale or the height of its
    frame, so the turn is the peak of the circular cross-correlation of the two
    clouds' azimuth densities (points beyond ``min_radius``, whose azimuth is
    precise), smoothed over ``smooth_bins`` bins.
    """
    n = int(round(360.0 / bin_deg))

    def density(p):
        r = np.hypot(p[:, 0], p[:, 1])
        a = np.degrees(np.arctan2(p[r > min_radius, 1], p[r > min_radius, 0])) % 360.0
        h = np.bincount((a / bin_deg).astype(int) % n, minlength=n).astype(float)
        k = np.fft.rfftfreq(n)
        return np.fft.rfft(h) * np.exp(-2.0 * (np.pi * k * smooth_bins) ** 2)

    corr = np.fft.irfft(density(y) * np.conj(density(x)), n)
    k = int(np.argmax(corr))
    # Peak height over the correlation's spread elsewhere: how sure the turn is.
    away = np.abs(((np.arange(n) - k + n // 2) % n) - n // 2) > int(3.0 / bin_deg)
    contrast = float((corr[k] - np.median(corr[away])) / (np.std(corr[away]) + 1e-12))
    return float(k * bin_deg), contrast


def _axial_similarity(x: np.ndarray, y: np.ndarray, iterations: int = 5
                      ) -> tuple[float, float, float, int]:
    """``y ~ s Rz(phi) x + dz e_z`` (x, y: (K, 3)); returns s, phi (deg), dz, inliers.

    The horizontal part is one complex ratio (least squares), refitted on the
    points within 3 robust sigma of the fit.
    """
    zx = x[:, 0] + 1j * x[:, 1]
    zy = y[:, 0] + 1j * y[:, 1]
    keep = np.ones(len(x), bool)
    s, phi, dz = 1.0, 0.0, 0.0
    for _ in range(iterations):
        w = np.sum(np.conj(zx[keep]) * zy[keep]) / np.sum(np.abs(zx[keep]) ** 2)
        s, phi = float(abs(w)), float(np.degrees(np.angle(w)))
        dz = float(np.median(y[keep, 2] - s * x[keep, 2]))
        pred = np.stack([(w * zx).real, (w * zx).imag, s * x[:, 2] + dz], axis=1)
        r = np.linalg.norm(pred - y, axis=1)
        sigma = 1.4826 * np.median(r[keep]) + 1e-12
        new = r < 3.0 * sigma
        if new.sum() < 4 or np.array_equal(new, keep):
            break
        keep = new
    return s, phi, dz, int(keep.sum())

"""Printed ArUco markers and dots: identified points and sub-pixel dot centres.

SIFT matches a printed dot pattern between neighbouring turntable stops of one
camera, but not between cameras far apart in elevation (8 and 48 degrees on the
virtual paper-72 rig see the print at 4x different foreshortening).  A row of
ArUco markers round the plate's rim and the pot carrier fixes that: each
marker's id names its four corners in every photo of every camera, so the
corners are tracks shared by all cameras, found without matching.  Markers of a
known side also give the metric scale (``scale: markers``).

A SIFT keypoint sits on a dot's difference-of-Gaussians extremum, which the
dot's shading and its neighbours pull by a few tenths of a pixel; the dot's own
intensity-weighted centroid is steadier (median 0.06 px against the analytic
dot centres of the virtual print, 0.15 px at the 90th percentile, seen from
48 degrees).  ``dot_centroids`` finds the bright blobs of a photo and
``snap_to_dots`` moves each keypoint that lies on one to its centroid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from plantscan_sfm.features import SfmError, SfmView, Tracks

DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_5X5_100",
                "DICT_5X5_250", "DICT_6X6_250")
# Corner noise of a detected marker relative to a refined dot's: sub-pixel corners of
# the virtual print are within 0.31 px (median) of the truth, dots within 0.06-0.09 px.
MARKER_NOISE = 4.0
# Photos are upsampled this much before detection: markers 20-30 px high at 48 degrees
# of foreshortening are found twice as often (virtual paper-72 print, 1296 x 864).
DETECTION_UPSAMPLE = 2


@dataclass
class MarkerCorners:
    """Marker corners found in the photos: observation ``k`` is corner ``corner[k]``
    (0..3: the marker image's top-left, top-right, bottom-right, bottom-left) of marker
    ``marker_id[k]`` in photo ``view[k]`` at pixel ``uv[k]``."""

    view: np.ndarray
    marker_id: np.ndarray
    corner: np.ndarray
    uv: np.ndarray

    def tracks(self) -> Tracks:
        """One track per (marker, corner) seen in at least two photos."""
        key = self.marker_id.astype(np.int64) * 4 + self.corner
        counts = dict(zip(*np.unique(key, return_counts=True), strict=True))
        keep = np.array([counts[k] >= 2 for k in key], bool)
        _, track = np.unique(key[keep], return_inverse=True)
        order = np.argsort(track, kind="stable")
        return Tracks(self.view[keep][order], track[order], self.uv[keep][order], {},
                      np.full(len(order), MARKER_NOISE), key[keep][order])


    def subset(self, keep: np.ndarray) -> MarkerCorners:
        return MarkerCorners(self.view[keep], self.marker_id[keep], self.corner[keep],
                             self.uv[keep])


# A marker whose corners stay within this of their median between the photos of one camera
# and tilt is fixed in the lab (printed on the backdrop), not on the turning plate (the
# plate's markers move by tens of pixels between turntable stops).
STATIC_PX = 1.0
# ... in at least this share of the photos that see it.  The plant and its shadow turn
# across the backdrop: on the virtual paper-72 dicot 11 of the 12 backdrop markers both
# cameras see were partly hidden in a few photos, their refined corners 1-12 px off there,
# and an all-photos rule called them turning (360 px from the truth as turning points).
STATIC_SHARE = 0.5


def split_static(corners: MarkerCorners, views: list[SfmView]) -> tuple[MarkerCorners, Tracks]:
    """Markers on the turning plate, and lab tracks of the markers fixed in the lab.

    In each camera and tilt that sees a marker in three photos or more, a photo is
    *still* when all four corners lie within ``STATIC_PX`` of their median over those
    photos.  A marker is fixed when it is still in at least ``STATIC_SHARE`` of the
    photos (and three) of every such camera and tilt.  A fixed corner gives one
    observation per camera and tilt (the median over its still photos: every photo sees
    it from the same place; the others, partly hidden, are dropped) and a track when two
    cameras or tilts see it.  Markers no camera and tilt sees three times stay turning.
    """
    if not len(corners.view):
        return corners, Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    group = np.array([hash(views[i].group) for i in corners.view], np.int64)
    _, gid = np.unique(group, return_inverse=True)
    moving_ids, fixed_ids = set(), set()
    med: dict = {}
    for m, g in sorted(set(zip(corners.marker_id.tolist(), gid.tolist()))):
        sel = np.flatnonzero((corners.marker_id == m) & (gid == g))
        photos = np.unique(corners.view[sel])
        if len(photos) < 3:
            continue
        # (photos, 4 corners, 2): a marker is detected once per photo (detect_markers)
        uv = np.full((len(photos), 4, 2), np.nan)
        uv[np.searchsorted(photos, corners.view[sel]), corners.corner[sel]] = corners.uv[sel]
        centre = np.median(uv, axis=0)
        still = np.all(np.linalg.norm(uv - centre, axis=2) <= STATIC_PX, axis=1)
        if still.sum() < max(3, STATIC_SHARE * len(photos)):
            moving_ids.add(m)
            continue
        fixed_ids.add(m)
        for c in range(4):
            med[(m, g, c)] = (np.median(uv[still, c], axis=0), int(photos[still][0]))
    fixed_ids -= moving_ids
    fixed = np.isin(corners.marker_id, list(fixed_ids))
    rows = [(m * 4 + c, view, uv) for (m, g, c), (uv, view) in med.items() if m in fixed_ids]
    keys = np.array([r[0] for r in rows], np.int64)
    counts = dict(zip(*np.unique(keys, return_counts=True), strict=True)) if rows else {}
    rows = [r for r in rows if counts[r[0]] >= 2]
    if not rows:
        lab = Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    else:
        keys = np.array([r[0] for r in rows], np.int64)
        _, track = np.unique(keys, return_inverse=True)
        order = np.argsort(track, kind="stable")
        lab = Tracks(np.array([r[1] for r in rows], np.int64)[order], track[order],
                     np.array([r[2] for r in rows])[order], {},
                     np.full(len(rows), MARKER_NOISE), keys[order], np.ones(len(rows), bool))
    return corners.subset(~fixed), lab


def _detector(dictionary: str):
    if dictionary not in DICTIONARIES:
        raise ValueError(f"unknown marker dictionary {dictionary!r}; valid: "
                         f"{', '.join(DICTIONARIES)}")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 4
    params.cornerRefinementMinAccuracy = 0.01
    params.cornerRefinementMaxIterations = 50
    return cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)


def detect_markers(gray_images, dictionary: str = "DICT_4X4_50") -> MarkerCorners:
    """ArUco marker corners in each of ``gray_images`` (an iterable of (H, W) uint8).

    A marker id seen twice in one photo is ambiguous there and dropped from it.
    """
    det = _detector(dictionary)
    up = DETECTION_UPSAMPLE
    views, ids, corners, uvs = [], [], [], []
    for i, gray in enumerate(gray_images):
        big = cv2.resize(gray, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
        found, found_ids, _ = det.detectMarkers(big)
        if found_ids is None:
            continue
        found_ids = found_ids.ravel()
        uniq, counts = np.unique(found_ids, return_counts=True)
        once = set(uniq[counts == 1].tolist())
        for c, m in zip(found, found_ids, strict=True):
            if int(m) not in once:
                continue
            views += [i] * 4
            ids += [int(m)] * 4
            corners += [0, 1, 2, 3]
            # pixel centres: (x + 0.5) * up - 0.5 in the upsampled photo
            uvs.append((c.reshape(4, 2).astype(np.float64) + 0.5) / up - 0.5)
    if not views:
        return MarkerCorners(np.zeros(0, np.int64), np.zeros(0, np.int64),
                             np.zeros(0, np.int64), np.zeros((0, 2)))
    return MarkerCorners(np.array(views, np.int64), np.array(ids, np.int64),
                         np.array(corners, np.int64), np.concatenate(uvs))


def dot_centroids(gray: np.ndarray, contrast: float = 8.0, min_area: int = 3,
                  max_area: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Bright blobs of a photo: (H, W) int32 labels (0: none) and (L + 1, 2) centroids, px.

    A blob is a connected set of pixels at least ``contrast`` grey levels above a
    6-pixel Gaussian blur of the photo, of ``min_area``-``max_area`` pixels and not
    touching the photo's border; its centre is the centroid of its pixels weighted by
    that excess.  Labels of rejected blobs are 0.
    """
    g = gray.astype(np.float32)
    excess = g - cv2.GaussianBlur(g, (0, 0), 6.0)
    mask = (excess > contrast).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    yy, xx = np.nonzero(mask)
    lab = labels[yy, xx]
    w = excess[yy, xx].astype(np.float64)
    sw = np.maximum(np.bincount(lab, weights=w, minlength=n), 1e-9)
    cx = np.bincount(lab, weights=w * xx, minlength=n) / sw
    cy = np.bincount(lab, weights=w * yy, minlength=n) / sw
    area = stats[:, cv2.CC_STAT_AREA]
    x0, y0 = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    x1 = x0 + stats[:, cv2.CC_STAT_WIDTH]
    y1 = y0 + stats[:, cv2.CC_STAT_HEIGHT]
    good = (area >= min_area) & (area <= max_area) & (x0 > 0) & (y0 > 0) \
        & (x1 < g.shape[1]) & (y1 < g.shape[0])
    good[0] = False
    remap = np.where(good, np.arange(n), 0).astype(np.int32)
    return remap[labels], np.stack([cx, cy], axis=1)


def snap_to_dots(uv: np.ndarray, labels: np.ndarray, centres: np.ndarray,
                 max_shift_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``uv`` (K, 2) moved to the centroid of the blob they lie on.

    Returns the positions (K, 2) and which were moved (K,) bool; a keypoint more
    than ``max_shift_px`` from its blob's centroid (a corner of a large blob, not a
    dot) stays where it is.
    """
    h, w = labels.shape
    ij = np.rint(uv).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    lab = np.zeros(len(uv), np.int64)
    lab[inside] = labels[ij[inside, 1], ij[inside, 0]]
    moved = lab > 0
    new = uv.copy()
    new[moved] = centres[lab[moved]]
    far = np.linalg.norm(new - uv, axis=1) > max_shift_px
    new[far] = uv[far]
    return new, moved & ~far


def read_gray(path) -> np.ndarray:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise SfmError(f"{path}: cannot read the photo")
    return gray


__all__ = ["MarkerCorners", "detect_markers", "dot_centroids", "snap_to_dots", "SfmView"]

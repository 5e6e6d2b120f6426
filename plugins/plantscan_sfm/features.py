"""SIFT features, turntable-aware image pairs, verified matches and tracks (pycolmap).

The scan's photos are linked (not copied) into a COLMAP workspace with one
folder per camera, so that COLMAP's ``PER_FOLDER`` mode gives one COLMAP camera
per scanner camera: every tilt and turntable stop of a camera shares its
intrinsics, as in the turntable model.  Features and matches live in COLMAP's
own database, which COLMAP's unconstrained mapper (``baseline``) reads too.

Which pairs are matched follows from the turntable: the photos of one camera
and tilt are a closed orbit, so each is matched with its neighbours a few stops
away on either side (the loop closes by itself, the angles being circular),
and with the photos of the other cameras and tilts taken at nearly the same
turntable angle.  For a handful of photos every pair is matched.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plantscan_core.data import ViewRecord
from plantscan_core.errors import PlantScanError

RANSAC_SEED = 0  # geometric verification's random seed (match_pairs): one run, one result


class SfmError(PlantScanError):
    """Structure from motion could not calibrate the rig; the message says what to change."""


@dataclass(frozen=True)
class SfmView:
    """One photo used for structure from motion.

    Attributes
    ----------
    view : ViewRecord
    name : str
        Its image name in the COLMAP workspace (``<camera>/<file name>``).
    """

    view: ViewRecord
    name: str

    @property
    def group(self) -> tuple[str, int]:
        """(camera, tilt index): the photos sharing one camera pose in the turntable model."""
        return (self.view.camera, self.view.tilt_index)


# What an observation is (``Tracks.kind_of``): a SIFT keypoint as found, one moved to a
# printed dot's centroid, a turning marker's corner, a lab-fixed marker's corner.
OBSERVATION_KINDS = ("keypoint", "dot", "marker", "lab marker")


@dataclass
class Tracks:
    """Feature tracks: each a 3D point seen in several photos.

    Attributes
    ----------
    view : (M,) int64 array
        Index of the photo of each observation (into the list of ``SfmView``).
    track : (M,) int64 array
        Track of each observation, 0..n_tracks-1; observations sorted by track.
    uv : (M, 2) float64 array, px
        Keypoint position (plantscan's convention: the top-left pixel's centre at 0, 0).
    noise : (M,) float64 array or None
        Each observation's noise relative to a refined dot's (1): the bundle weighs its
        residual by 1 / noise (None: all 1).
    marker : (M,) int64 array or None
        ``marker_id * 4 + corner`` of an observation of a printed marker's corner, -1
        for a feature (None: no markers).
    lab : (M,) bool array or None
        The observation is of a point fixed in the lab (a marker on the backdrop), not
        of one turning with the plate (None: none is).
    dot : (M,) bool array or None
        The keypoint was moved to a printed dot's centroid (None: none was).
    """

    view: np.ndarray
    track: np.ndarray
    uv: np.ndarray
    stats: dict = field(default_factory=dict)
    noise: np.ndarray | None = None
    marker: np.ndarray | None = None
    lab: np.ndarray | None = None
    dot: np.ndarray | None = None

    def lab_of(self) -> np.ndarray:
        """(M,) bool: observations of lab-fixed points."""
        return np.zeros(len(self.view), bool) if self.lab is None else self.lab

    def dot_of(self) -> np.ndarray:
        """(M,) bool: keypoints moved to a printed dot's centroid."""
        return np.zeros(len(self.view), bool) if self.dot is None else self.dot

    def kind_of(self) -> np.ndarray:
        """(M,) int: what each observation is, an index into ``OBSERVATION_KINDS``."""
        kind = np.where(self.dot_of(), 1, 0)
        kind[self.marker_of() >= 0] = 2
        kind[self.lab_of()] = 3
        return kind

    def marker_of(self) -> np.ndarray:
        """(M,) marker corner of every observation, -1 for features."""
        return np.full(len(self.view), -1, np.int64) if self.marker is None else self.marker

    def reordered(self, keep: np.ndarray, track: np.ndarray) -> Tracks:
        """Observations ``keep`` (indices or bool) with new track ids ``track``, sorted."""
        order = np.argsort(track, kind="stable")
        def pick(a):
            return None if a is None else a[keep][order]
        return Tracks(self.view[keep][order], np.asarray(track)[order], self.uv[keep][order],
                      dict(self.stats), pick(self.noise), pick(self.marker), pick(self.lab),
                      pick(self.dot))

    def noise_of(self) -> np.ndarray:
        """(M,) relative noise of every observation."""
        return np.ones(len(self.view)) if self.noise is None else self.noise

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    def subset(self, keep_obs: np.ndarray) -> Tracks:
        """The observations ``keep_obs`` (bool (M,)), tracks renumbered, singletons dropped."""
        keep = np.flatnonzero(keep_obs) if np.asarray(keep_obs).dtype == bool \
            else np.asarray(keep_obs)
        t = self.track[keep]
        counts = np.bincount(t, minlength=self.n_tracks)
        keep = keep[counts[t] >= 2]
        _, t = np.unique(self.track[keep], return_inverse=True)
        return self.reordered(keep, t)

    @staticmethod
    def concat(parts: list[Tracks]) -> Tracks:
        """The tracks of ``parts`` side by side (track ids renumbered, stats of the first)."""
        parts = [p for p in parts if len(p.view)]
        if not parts:
            return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
        offsets = np.cumsum([0] + [p.n_tracks for p in parts[:-1]])
        noise = marker = lab = dot = None
        if any(p.dot is not None for p in parts):
            dot = np.concatenate([p.dot_of() for p in parts])
        if any(p.noise is not None for p in parts):
            noise = np.concatenate([p.noise_of() for p in parts])
        if any(p.marker is not None for p in parts):
            marker = np.concatenate([p.marker_of() for p in parts])
        if any(p.lab is not None for p in parts):
            lab = np.concatenate([p.lab_of() for p in parts])
        return Tracks(np.concatenate([p.view for p in parts]),
                      np.concatenate([p.track + o for p, o in zip(parts, offsets, strict=True)]),
                      np.concatenate([p.uv for p in parts]), dict(parts[0].stats), noise,
                      marker, lab, dot)


def workspace_views(scan, views: list[ViewRecord], work_dir: Path) -> list[SfmView]:
    """Link the photos into ``work_dir/images/<camera>/`` and name them for COLMAP."""
    out = []
    for v in views:
        src = scan.path_of(v)
        name = f"{v.camera}/{src.name}"
        dst = work_dir / "images" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if dst.is_symlink() or dst.exists():
            dst.unlink()
        os.symlink(src, dst)
        out.append(SfmView(v, name))
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise SfmError(f"two photos of one camera share a file name ({dup[0]}); the COLMAP "
                       "workspace needs one name per photo")
    return out


def extract_features(work_dir: Path, views: list[SfmView], max_features: int,
                     max_image_size: int, threads: int, first_octave: int = 0) -> Path:
    """SIFT on every photo (CPU) into ``work_dir/database.db``; returns its path."""
    import pycolmap

    db = work_dir / "database.db"
    if db.exists():
        db.unlink()
    opt = pycolmap.FeatureExtractionOptions()
    opt.num_threads = threads
    opt.max_image_size = max_image_size
    opt.sift.max_num_features = max_features
    opt.sift.first_octave = first_octave
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "RADIAL"
    pycolmap.extract_features(db, work_dir / "images", image_names=[v.name for v in views],
                              camera_mode=pycolmap.CameraMode.PER_FOLDER, reader_options=reader,
                              extraction_options=opt, device=pycolmap.Device.cpu)
    return db


def _circular_gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def plan_pairs(views: list[SfmView], orbit_neighbours: int, cross_window_deg: float,
               exhaustive_below: int) -> list[tuple[int, int]]:
    """Photo pairs to match (indices into ``views``), each once.

    Photos of one (camera, tilt) are paired with the ``orbit_neighbours``
    nearest turntable stops on each side; photos of different (camera, tilt)
    whose angles differ by at most ``cross_window_deg``; every pair when there
    are fewer than ``exhaustive_below`` photos.
    """
    n = len(views)
    if n < exhaustive_below:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    groups: dict[tuple[str, int], list[int]] = defaultdict(list)
    for i, v in enumerate(views):
        groups[v.group].append(i)
    pairs = set()
    for idx in groups.values():
        idx = sorted(idx, key=lambda i: views[i].view.angle_deg % 360.0)
        m = len(idx)
        for k in range(m):
            for s in range(1, min(orbit_neighbours, m // 2) + 1):
                a, b = idx[k], idx[(k + s) % m]
                if a != b:
                    pairs.add((min(a, b), max(a, b)))
    keys = sorted(groups)
    for gi, ga in enumerate(keys):
        for gb in keys[gi + 1:]:
            for a in groups[ga]:
                for b in groups[gb]:
                    if _circular_gap(views[a].view.angle_deg,
                                     views[b].view.angle_deg) <= cross_window_deg + 1e-6:
                        pairs.add((min(a, b), max(a, b)))
    return sorted(pairs)


def match_pairs(db: Path, work_dir: Path, views: list[SfmView], pairs: list[tuple[int, int]],
                threads: int, max_error_px: float) -> None:
    """SIFT matching and geometric verification (F/E/H RANSAC) of ``pairs``, into ``db``."""
    import pycolmap

    pair_file = work_dir / "pairs.txt"
    pair_file.write_text("".join(f"{views[a].name} {views[b].name}\n" for a, b in pairs))
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = threads
    popt = pycolmap.ImportedPairingOptions()
    popt.match_list_path = str(pair_file)
    vopt = pycolmap.TwoViewGeometryOptions()
    vopt.ransac.max_error = max_error_px
    # COLMAP's RANSAC seeds itself from std::random_device unless given a seed (-1): the
    # same photos gave other inlier sets from run to run (and, through them, another
    # calibration). One fixed seed: every pair's verification is the same on every run and
    # with any number of threads.
    vopt.ransac.random_seed = RANSAC_SEED
    # Features of the lab (backdrop, stand) do not turn with the plate: a match that
    # stays put between two photos of one camera is not a point of the turntable scene.
    vopt.filter_stationary_matches = True
    pycolmap.match_image_pairs(db, matching_options=mopt, pairing_options=popt,
                               verification_options=vopt, device=pycolmap.Device.cpu)


def read_tracks(db: Path, views: list[SfmView]) -> Tracks:
    """Tracks from the verified matches in ``db``: connected keypoints, one per photo.

    A connected set of keypoints holding two keypoints of one photo is a chain
    of wrong matches: it is dropped whole.
    """
    import pycolmap
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    t0 = time.perf_counter()
    database = pycolmap.Database.open(db)
    try:
        by_name = {im.name: im.image_id for im in database.read_all_images()}
        missing = [v.name for v in views if v.name not in by_name]
        if missing:
            raise SfmError(f"COLMAP read no features from {missing[0]} "
                           f"({len(missing)} photos): unreadable image?")
        id_to_view = {by_name[v.name]: i for i, v in enumerate(views)}
        kps = [np.asarray(database.read_keypoints(by_name[v.name]))[:, :2].astype(np.float64)
               for v in views]
        pair_ids, geoms = database.read_two_view_geometries()
    finally:
        database.close()
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
    rows, cols = [], []
    n_pairs_verified = 0
    for pid, g in zip(pair_ids, geoms, strict=True):
        m = np.asarray(g.inlier_matches)
        if len(m) == 0:
            continue
        id1, id2 = pycolmap.pair_id_to_image_pair(pid)
        if id1 not in id_to_view or id2 not in id_to_view:
            continue
        n_pairs_verified += 1
        rows.append(offsets[id_to_view[id1]] + m[:, 0].astype(np.int64))
        cols.append(offsets[id_to_view[id2]] + m[:, 1].astype(np.int64))
    stats = {"keypoints_per_photo": float(np.mean([len(k) for k in kps])) if kps else 0.0,
             "verified_pairs": n_pairs_verified}
    n_nodes = int(offsets[-1])
    if not rows:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), stats)
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n_nodes, n_nodes))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    node = np.flatnonzero(size[label] >= 2)
    view_of = np.searchsorted(offsets, node, side="right") - 1
    lab = label[node]
    # A track with two keypoints of one photo is dropped whole.
    key = lab.astype(np.int64) * (len(views) + 1) + view_of
    uniq, counts = np.unique(key, return_counts=True)
    bad_tracks = np.unique(uniq[counts > 1] // (len(views) + 1))
    ok = ~np.isin(lab, bad_tracks)
    node, view_of, lab = node[ok], view_of[ok], lab[ok]
    _, track = np.unique(lab, return_inverse=True)
    order = np.argsort(track, kind="stable")
    # COLMAP puts the top-left pixel's centre at (0.5, 0.5); plantscan at (0, 0).
    uv = np.concatenate(kps)[node[order]] - 0.5
    stats.update({"tracks": int(track.max()) + 1 if len(track) else 0,
                  "conflicting_tracks_dropped": int(len(bad_tracks)),
                  "seconds": time.perf_counter() - t0})
    return Tracks(view_of[order].astype(np.int64), track[order].astype(np.int64), uv, stats)


def angle_step_deg(views: list[SfmView]) -> float:
    """Smallest turntable step between photos of one (camera, tilt), deg."""
    groups: dict[tuple[str, int], list[float]] = defaultdict(list)
    for v in views:
        groups[v.group].append(v.view.angle_deg % 360.0)
    steps = []
    for a in groups.values():
        a = np.sort(np.unique(np.round(a, 6)))
        if len(a) > 1:
            steps.append(float(np.min(np.diff(np.concatenate([a, [a[0] + 360.0]])))))
    return min(steps) if steps else 360.0


def default_cross_window(views: list[SfmView]) -> float:
    """Half a turntable step more than one step: the stops next to the same angle."""
    return 1.5 * angle_step_deg(views)

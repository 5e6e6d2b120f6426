"""A learned judge of the stem: which parts of what the rules call stem are blades.

The rules of ``curvature-regions`` call a region stem when its normals turn all round
its long axis (a tube).  A grass blade 3-6 mm wide is a slab about as thick as it is wide
in a 512³ hull, so the tube test takes narrow blades for stem, whole (grass validation
seeds 1000-1004: 14 of 23 missed blades, session 13), and with them the bases of blades
that run along the culms.  With ``judge_stem_parts`` on, the stem is cut into **parts**:
its faces off the straight culms (RANSAC axes, as ``base_reach_mm`` finds them; all stem
faces above the ground band when none is found), in connected pieces of at least
``MIN_PART_UNITS2`` (one side, mesh units squared).  Each part gets the piece features of
``plantscan_leaves.pieces`` (scale-free; the part as if it were a piece, beside the
leaves) and its distance from the culms, and gradient-boosted trees (LightGBM, trained on
the virtual scanner's truth by ``scripts/train_stem_part_model.py``) say whether it is a
blade.  A blade part becomes a numbered leaf piece; the piece judge that runs next
(``judge_pieces``) keeps it as a leaf, joins it to the blade it continues, or calls it
debris, as it does with the rules' own pieces.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from plantscan_leaves import geometry as geo
from plantscan_leaves import pieces as pc

MODEL_FILE = "stem_part_model.json.gz"
MIN_PART_UNITS2 = 30.0  # one side: a smaller part is a crumb (the smallest blades are ~100)
BLADE_PROBABILITY = 0.5  # a part the trees give at least this is a blade
FEATURE_NAMES = (*pc.FEATURE_NAMES,
                 "culm_distance_units",  # median distance from the nearest culm axis, u
                 "culm_distance_share",  # that over the plant's height
                 "found_culms")  # how many straight culms the stem holds
CLASS_NAMES = ("stem", "blade")


@dataclass
class StemParts:
    """The parts of one plant's stem: ``part`` (F,) part of each face (-1: none, the
    culms and crumbs), ``m`` parts, ``features`` (m, len(FEATURE_NAMES))."""

    part: np.ndarray
    m: int
    features: np.ndarray


def stem_parts(s: pc.PieceSurface, labels: np.ndarray, n: int, ground_z: float) -> StemParts:
    """The stem parts of ``labels`` (F,) (0 stem, 1..n leaves, larger: debris) and their
    features (module docstring)."""
    from plantscan_leaves import segment as sg

    stem = labels == sg.STEM_LABEL
    u = s.unit
    nf = len(labels)
    none = StemParts(np.full(nf, -1, np.int64), 0, np.zeros((0, len(FEATURE_NAMES)),
                                                            np.float32))
    if not stem.any():
        return none
    axes = sg._stem_culms(stem, s.centroids, s.normals)
    dist = sg._axis_distance(s.centroids, axes)
    off = (dist > np.median([a[4] for a in axes]) + sg.CULM_MARGIN_MM if axes
           else np.ones(nf, bool))
    comp = geo.components(nf, s.pairs, stem & off & (s.centroids[:, 2] > ground_z))
    on = comp >= 0
    if not on.any():
        return none
    area = np.bincount(comp[on], s.areas[on]) / 2.0
    keep = area >= MIN_PART_UNITS2 * u * u
    new = np.full(len(area), -1, np.int64)
    new[keep] = np.arange(int(keep.sum()))
    part = np.where(on, new[np.maximum(comp, 0)], -1)
    m = int(keep.sum())
    if not m:
        return none
    # the parts as pieces n+1..n+m beside the leaves (debris, if any, stays stem here)
    ext = np.where(labels > n, sg.STEM_LABEL, labels).astype(np.int64)
    ext[part >= 0] = n + 1 + part[part >= 0]
    feats = pc.piece_features(s, ext, n + m).features[n:]
    z = s.vertices[:, 2]
    height = max(float(np.ptp(z)), 1e-12)
    finite = np.where(np.isfinite(dist), dist, np.nan)
    med = np.array([np.nanmedian(finite[part == k]) if np.isfinite(finite[part == k]).any()
                    else np.nan for k in range(m)])
    extra = np.stack([med / u, med / height, np.full(m, float(len(axes)))], axis=1)
    return StemParts(part, m, np.hstack([feats, extra]).astype(np.float32))


StemPartModel = pc.BinaryModel  # probabilities(parts): (m,) that each part is a blade


def save_model(booster, config: dict, path: Path) -> None:
    """One gzip'd JSON file, as the piece judge's (``pieces.save_model``)."""
    pc.save_model(booster, config, path, FEATURE_NAMES, CLASS_NAMES)


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> StemPartModel:
    """The stem-part model at ``path``: None, the shipped one (``MODEL_FILE``); a file name
    without a folder, another shipped in ``plantscan_leaves/models``; else a file path."""
    booster, body = pc.read_model(path, MODEL_FILE, FEATURE_NAMES, "stem-part model",
                                  "plantscan_leaves.stem_parts",
                                  "scripts/train_stem_part_model.py")
    return StemPartModel(booster, body["config"], body["config_sha256"])


def blades_from_stem(labels: np.ndarray, n: int, parts: StemParts, prob: np.ndarray
                     ) -> tuple[np.ndarray, int, int]:
    """``labels`` with every part judged a blade (``prob`` >= ``BLADE_PROBABILITY``) a new
    leaf n+1, n+2, ...; returns the labels, the new number of leaves and how many parts
    became leaves.  Labels above n (debris) move up by as many."""
    blade = np.flatnonzero(prob >= BLADE_PROBABILITY)
    if not len(blade):
        return labels, n, 0
    out = labels.copy()
    out[labels > n] += len(blade)
    for k, b in enumerate(blade, start=1):
        out[parts.part == b] = n + k
    return out, n + len(blade), len(blade)

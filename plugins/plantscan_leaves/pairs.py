"""A learned judge of touching leaves: are two leaves that share a border one leaf?

The piece judge (``plantscan_leaves.pieces``) calls each numbered leaf on its own: a
leaf, a fragment to join to its partner, or debris.  When a crease cuts a leaf into two
large halves, each half looks like a whole leaf and is kept as one (dicot validation
seeds 1000-1009, session 23: 6 leaves split in two, every one of them into pieces of
which the judge called both a leaf, the smaller at a leaf probability of 0.5-1.0).
Whether two pieces are one leaf is a question about the *pair*: how long their shared
border is against their size, whether the surface runs on smoothly across it, whether
their union is still a flat slab, whether one continues the other along its long axis.

With ``judge_pairs`` on, every pair of leaves that share border edges after the piece
judge gets the features ``FEATURE_NAMES`` (scale-free like the pieces': lengths in
mesh units ``u`` or relative to the pieces, areas relative to the plant's largest
leaf), and gradient-boosted trees (LightGBM, trained on the virtual scanner's truth by
``scripts/train_pair_model.py``) give the probability that both are one truth leaf.
Pairs at ``MERGE_PROBABILITY`` or more are merged, most likely first (union-find: a
leaf merged with two neighbours makes one leaf of the three).  A merged leaf's evidence
says so (``fragments``, ``weakest_merge``: the trust stage's ``rejoined``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from plantscan_leaves import geometry as geo
from plantscan_leaves import pieces as pc

MODEL_FILE = "pair_model.json.gz"
MERGE_PROBABILITY = 0.5  # a pair the trees give at least this is one leaf
FEATURE_NAMES = (
    "small_area_share",  # the smaller leaf's area over the plant's largest leaf's
    "large_area_share",  # the larger's
    "area_ratio",  # smaller over larger
    "log_small_area_units2",  # log of the smaller's area in mesh units squared
    "shared_per_size",  # shared border edges x u / sqrt(smaller's area)
    "shared_share_small",  # shared border edges over the smaller's border edges
    "shared_share_large",  # over the larger's
    "small_stem_share",  # share of the smaller's border edges on the stem
    "large_stem_share",  # the larger's
    "plane_agreement",  # |cos| between the two mean planes' normals
    "border_smoothness",  # mean cos between the normals of the faces across the border
    "border_curvature_units",  # mean curvature x u of the faces on the shared border
    "axis_agreement",  # |cos| between the two long axes
    "offset_along_axis",  # centroid offset along the larger's long axis over its length
    "offset_across_axis",  # across it, over its length
    "small_elongation",  # sqrt(1st / 2nd eigenvalue) of the smaller
    "large_elongation",  # of the larger
    "union_elongation",  # of the union
    "small_flatness",  # sqrt(3rd / 2nd eigenvalue) of the smaller
    "large_flatness",  # of the larger
    "union_flatness",  # of the union: two leaves at an angle are no slab
    "union_normal_spread",  # 2nd / 1st eigenvalue of the union's normal tensor
    "height_gap_share",  # |mean height difference| over the plant's height
)


@dataclass
class Pairs:
    """The touching leaf pairs of one plant: ``pairs`` (k, 2) labels (smaller, larger by
    area), ``features`` (k, len(FEATURE_NAMES))."""

    pairs: np.ndarray
    features: np.ndarray


def _spread(s0, s1, s2):
    """Covariance from moments (any leading shape)."""
    w = np.maximum(s0, 1e-30)[..., None, None]
    mean = s1 / w[..., 0]
    return s2 / w - mean[..., :, None] * mean[..., None, :], mean


def pair_features(s: pc.PieceSurface, labels: np.ndarray, n: int) -> Pairs:
    """The leaf pairs of ``labels`` (F,) (0 stem, 1..n leaves, larger: debris) that share
    border edges, and their features (module docstring)."""
    k = len(FEATURE_NAMES)
    lab = np.where(labels > n, 0, labels).astype(np.int64)  # debris borders count as stem
    a, b = s.pairs[:, 0], s.pairs[:, 1]
    la, lb = lab[a], lab[b]
    both = (la != lb) & (la > 0) & (lb > 0)
    if not both.any():
        return Pairs(np.zeros((0, 2), np.int64), np.zeros((0, k), np.float32))
    m = n + 1
    u = s.unit
    on = lab > 0  # the leaves' faces (the stem's moments are not used)
    w = s.areas[on]
    c0, c1, c2 = geo.label_moments(lab[on], m, w, s.centroids[on])
    n0, _, n2 = geo.label_moments(lab[on], m, w, s.normals[on])
    area = c0 / 2.0  # one side
    largest = max(float(area[1:].max()), 1e-30)
    # borders per label
    cross = la != lb
    src = np.r_[la[cross], lb[cross]]
    dst = np.r_[lb[cross], la[cross]]
    border = np.bincount(src, minlength=m).astype(float)
    to_stem = np.bincount(src[dst == 0], minlength=m).astype(float)
    # shared edges per pair (smaller label first in the key), with smoothness and curvature
    lo, hi = np.minimum(la[both], lb[both]), np.maximum(la[both], lb[both])
    key = lo * m + hi
    keys, inv, shared = np.unique(key, return_inverse=True, return_counts=True)
    cos = np.einsum("ij,ij->i", s.normals[a[both]], s.normals[b[both]])
    smooth = np.bincount(inv, cos) / shared
    curv = np.bincount(inv, 0.5 * (s.curvature[a[both]] + s.curvature[b[both]]) * u) / shared
    p, q = keys // m, keys % m
    small = np.where(area[p] <= area[q], p, q)
    large = np.where(area[p] <= area[q], q, p)

    cov, mean = _spread(c0, c1, c2)
    ev, vec = np.linalg.eigh(cov)  # ascending
    ev = np.maximum(ev, 0.0)
    axis = vec[:, :, 2]
    length = 4.0 * np.sqrt(ev[:, 2])
    ntens = n2 / np.maximum(n0, 1e-30)[:, None, None]
    nev, nvec = np.linalg.eigh(ntens)
    plane = nvec[:, :, 2]
    ucov, _ = _spread(c0[small] + c0[large], c1[small] + c1[large], c2[small] + c2[large])
    uev = np.maximum(np.linalg.eigvalsh(ucov), 0.0)
    unt = (n2[small] + n2[large]) / np.maximum(n0[small] + n0[large], 1e-30)[:, None, None]
    unev = np.linalg.eigvalsh(unt)
    z = s.vertices[:, 2]
    height = max(float(np.ptp(z)), 1e-12)
    d = mean[small] - mean[large]
    along = np.einsum("ij,ij->i", d, axis[large])
    across = np.linalg.norm(d - along[:, None] * axis[large], axis=1)
    safe_len = np.maximum(length[large], 1e-30)

    def elong(e):
        return np.sqrt(e[:, 2] / np.maximum(e[:, 1], 1e-30))

    def flat(e):
        return np.sqrt(e[:, 0] / np.maximum(e[:, 1], 1e-30))

    feats = np.stack([
        area[small] / largest,
        area[large] / largest,
        area[small] / np.maximum(area[large], 1e-30),
        np.log(np.maximum(area[small], 1e-30) / (u * u)),
        shared * u / np.sqrt(np.maximum(area[small], 1e-30)),
        shared / np.maximum(border[small], 1.0),
        shared / np.maximum(border[large], 1.0),
        to_stem[small] / np.maximum(border[small], 1.0),
        to_stem[large] / np.maximum(border[large], 1.0),
        np.abs(np.einsum("ij,ij->i", plane[small], plane[large])),
        smooth,
        curv,
        np.abs(np.einsum("ij,ij->i", axis[small], axis[large])),
        np.abs(along) / safe_len,
        across / safe_len,
        elong(ev[small]),
        elong(ev[large]),
        elong(uev),
        flat(ev[small]),
        flat(ev[large]),
        flat(uev),
        unev[:, 1] / np.maximum(unev[:, 2], 1e-30),
        np.abs(mean[small, 2] - mean[large, 2]) / height,
    ], axis=1)
    return Pairs(np.stack([small, large], 1).astype(np.int64), feats.astype(np.float32))


def merge_pairs(labels: np.ndarray, n: int, pairs: Pairs, prob: np.ndarray,
                threshold: float = MERGE_PROBABILITY, parent: np.ndarray | None = None
                ) -> tuple[np.ndarray, int, dict[int, tuple[int, float]], np.ndarray]:
    """Labels with the pairs at ``threshold`` or more merged, most likely first.

    Returns the new labels (0 stem, 1..n' leaves numbered in the order of their lowest old
    label, n' + 1 debris when there was debris), n', {new leaf: (old leaves merged into
    it, weakest merge probability)} and the new label of every old one (n + 2,).
    ``parent`` (n + 1,): the leaf each old leaf was cut from by an earlier tentative split
    (None: each its own); leaves of one parent merged count as one, and their merge is
    not a join (the weakest probability is that of merges across parents, 1 when none).
    """
    parent = np.arange(n + 1) if parent is None else np.asarray(parent)
    root = np.arange(n + 1)

    def find(i: int) -> int:
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    weakest: dict[int, float] = {}
    for j in np.argsort(-prob, kind="stable"):
        if prob[j] < threshold:
            break
        a, b = int(pairs.pairs[j, 0]), int(pairs.pairs[j, 1])
        ra, rb = find(a), find(b)
        if ra != rb:
            lo, hi = min(ra, rb), max(ra, rb)
            root[hi] = lo
            join = float(prob[j]) if parent[a] != parent[b] else 1.0
            weakest[lo] = min(weakest.get(lo, 1.0), weakest.pop(hi, 1.0), join)
    group = np.array([find(i) for i in range(n + 1)])
    firsts = np.unique(group[1:])
    new_of_group = {int(g): i + 1 for i, g in enumerate(firsts)}
    new = np.zeros(n + 2, np.int64)
    new[1:n + 1] = [new_of_group[int(g)] for g in group[1:]]
    n_new = len(firsts)
    new[n + 1] = n_new + 1  # debris keeps its place after the leaves
    lab = np.where(labels > n, n + 1, labels).astype(np.int64)
    counts = np.bincount(group[1:], minlength=n + 1)
    merged = {new_of_group[int(g)]: (len(set(parent[1:][group[1:] == g].tolist())),
                                     weakest.get(int(g), 1.0))
              for g in firsts if counts[g] > 1}
    return new[lab], n_new, merged, new


PairModel = pc.BinaryModel  # probabilities(pairs): (k,) that each pair is one leaf


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> PairModel:
    """The pair model at ``path`` (as ``pieces.load_model``: None the shipped one,
    ``MODEL_FILE``; a bare name another shipped file; else a path)."""
    booster, body = pc.read_model(path, MODEL_FILE, FEATURE_NAMES, "pair model",
                                  "plantscan_leaves.pairs", "scripts/train_pair_model.py")
    return PairModel(booster, body["config"], body["config_sha256"])

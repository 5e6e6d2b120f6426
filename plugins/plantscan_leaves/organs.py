"""Organs learned from the virtual scanner: a per-sample classifier and leaf instances.

The surface is cut into samples (``plantscan_leaves.features``); gradient-boosted trees
(LightGBM), trained on exactly labelled visual hulls of virtual plants
(``scripts/train_organ_model.py``), give every sample the probability of being

* ``STEM`` (stem, petiole, culm, sheath),
* ``LEAF`` (the inside of a leaf blade),
* ``EDGE`` (a leaf blade within two samples of another organ: where a leaf meets
  the stem or touches another leaf),
* ``DEBRIS`` (remnants of the pot cut),

and of lying on *phantom volume* (more than ``PHANTOM_UNITS`` mesh units from the true
surface: hull the views could not carve).  Leaf instances are then grown over the
sample graph: the connected cores of ``LEAF`` samples are the seeds; they grow, ring
by ring, into the ``LEAF`` and ``EDGE`` samples around them; what no seed reaches is
a leaf of its own when it is big enough, else joins the leaf it touches most, else
is debris.  Every size is in mesh units (``u``, about a voxel), so the labels do not
depend on the plant's unit or scale.
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from pydantic import Field

from plantscan_core.data import LabelledMesh, Mesh
from plantscan_core.stages import StageParams, StageReport
from plantscan_leaves import geometry as geo
from plantscan_leaves.features import FEATURE_NAMES, SurfaceSamples, surface_samples

STEM, LEAF, EDGE, DEBRIS = 0, 1, 2, 3
CLASS_NAMES = ("stem", "leaf", "edge", "debris")
PHANTOM_UNITS = 4.0  # hull farther than this (mesh units) from the true surface: phantom volume
MODEL_FILES = {"organ": "organ_model.txt.gz", "phantom": "phantom_model.txt.gz",
               "merge": "merge_model.txt.gz"}


@dataclass
class OrganModel:
    """The shipped boosters: organ classes (4), phantom volume and fragment merges (binary)."""

    organ: object
    phantom: object
    merge: object

    def predict(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S, 4) class probabilities and (S,) phantom probability of each sample."""
        x = np.asarray(features, dtype=np.float32)
        return (np.asarray(self.organ.predict(x, num_threads=2)).reshape(len(x), -1),
                np.asarray(self.phantom.predict(x, num_threads=2)).reshape(-1))

    def merge_probability(self, pair_features: np.ndarray) -> np.ndarray:
        """(n,) probability that each candidate pair of fragments is one leaf."""
        return np.asarray(self.merge.predict(pair_features, num_threads=1)).reshape(-1)


def _booster(text: str):
    import lightgbm as lgb

    return lgb.Booster(model_str=text)


@lru_cache(maxsize=4)
def model_root(folder: str | None = None):
    """The folder holding the organ model's files (``MODEL_FILES``): None, the one shipped
    in ``plantscan_leaves/models``."""
    return resources.files("plantscan_leaves") / "models" if folder is None else Path(folder)


def load_model(folder: str | None = None) -> OrganModel:
    """The organ model in ``folder`` (the three files of ``MODEL_FILES``, as
    ``scripts/train_organ_model.py --out`` writes them); None: the one shipped in
    ``plantscan_leaves/models``.  Loaded once per process and folder."""
    from plantscan_core.errors import DataError

    root = model_root(folder)
    boosters = {}
    for key, name in MODEL_FILES.items():
        path = root / name
        try:
            boosters[key] = _booster(gzip.decompress(path.read_bytes()).decode())
        except (OSError, FileNotFoundError) as exc:
            raise DataError(f"{path}: organ model missing ({exc}); "
                            "scripts/train_organ_model.py writes it") from exc
    names = tuple(boosters["organ"].feature_name())
    if names != tuple(FEATURE_NAMES):
        raise DataError(f"{root / MODEL_FILES['organ']}: trained on other features than "
                        "plantscan_leaves.features computes; retrain it "
                        "(scripts/train_organ_model.py)")
    return OrganModel(boosters["organ"], boosters["phantom"], boosters["merge"])


def grow(labels: np.ndarray, pairs: np.ndarray, open_: np.ndarray) -> np.ndarray:
    """Spread labels (>= 0) into the ``open_`` nodes labelled -1, ring by ring; a node reached
    by several labels in one ring takes the largest (the result does not depend on order)."""
    labels = labels.copy()
    a, b = pairs[:, 0], pairs[:, 1]
    keep = open_[a] | open_[b]
    a, b = a[keep], b[keep]
    while True:
        la, lb = labels[a], labels[b]
        to_a = (la < 0) & (lb >= 0) & open_[a]
        to_b = (lb < 0) & (la >= 0) & open_[b]
        if not (to_a.any() or to_b.any()):
            return labels
        np.maximum.at(labels, a[to_a], lb[to_a])
        np.maximum.at(labels, b[to_b], la[to_b])


def _renumber(labels: np.ndarray) -> np.ndarray:
    """Labels >= 0 renumbered 0..n-1 in order of first appearance of their value; others kept."""
    out = labels.copy()
    ok = labels >= 0
    if ok.any():
        _, inv = np.unique(labels[ok], return_inverse=True)
        out[ok] = inv
    return out


def _touch_counts(pairs: np.ndarray, src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """For every (group of ``src`` >= 0, label of ``dst`` >= 0) pair of neighbouring samples:
    the unique (src, dst) pairs and how many sample pairs join them."""
    a, b = pairs[:, 0], pairs[:, 1]
    s = np.r_[src[a], src[b]]
    d = np.r_[dst[b], dst[a]]
    ok = (s >= 0) & (d >= 0)
    if not ok.any():
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    m = int(d[ok].max()) + 1
    key, cnt = np.unique(s[ok] * m + d[ok], return_counts=True)
    return np.stack([key // m, key % m], axis=1), cnt


def _best_neighbour(pairs: np.ndarray, group: np.ndarray, target: np.ndarray,
                    n_groups: int) -> np.ndarray:
    """(n_groups,) the ``target`` label each group shares most sample pairs with (-1: none)."""
    out = np.full(n_groups, -1, np.int64)
    links, cnt = _touch_counts(pairs, group, target)
    if len(links):
        order = np.lexsort((-cnt, links[:, 0]))
        first = order[np.r_[True, links[order][1:, 0] != links[order][:-1, 0]]]
        out[links[first, 0]] = links[first, 1]
    return out


CREASE = 0.12  # concave curvature x smoothing scale beyond which a sample cuts a core (the rules'
#                0.08 /mm at 1.5 mm smoothing): a crease between organs, never across a blade
GAP_UNITS = 6.0  # a piece of its own (a tip the hull broke off) may join a leaf this close, u


@dataclass
class InstanceParams:
    """Sizes of the instance step in mesh units (``u``) squared, one side of a leaf."""

    min_core_units2: float = 30.0
    min_leaf_units2: float = 150.0


@dataclass
class Fragments:
    """Pieces of leaf surface to be merged into leaves, and what joins them.

    ``of_sample`` (S,) fragment of each sample (-1: not a leaf piece); ``moments``
    (G, 16) summed sample moments; ``prob`` (G, 4) area-weighted mean class
    probabilities; ``log_thick`` (G,) area-weighted mean log thickness (mm);
    ``stem_border`` (G,) sample pairs with stem samples; ``links``: dict
    (f, g) f < g -> [border pairs, sum of P(edge) + P(stem) on both sides,
    min concave curvature, gap mm].
    """

    of_sample: np.ndarray
    moments: np.ndarray
    prob: np.ndarray
    log_thick: np.ndarray
    stem_border: np.ndarray
    links: dict
    unit_mm: float
    height_mm: float
    z0_mm: float

    @property
    def n(self) -> int:
        return len(self.moments)


def leaf_fragments(samples: SurfaceSamples, prob: np.ndarray, p: InstanceParams) -> Fragments:
    """Over-segment the leaf surface: cores of LEAF samples cut by creases, grown into the
    LEAF/EDGE samples around them; leaf-like parts no core reaches are fragments too."""
    n, pairs, u = samples.n, samples.pairs, samples.unit_mm
    half_area = samples.area / 2.0
    cls = prob.argmax(axis=1)
    leafish = (cls == LEAF) | (cls == EDGE)
    concave = samples.features[:, FEATURE_NAMES.index("concave_curvature")]
    core = geo.components(n, pairs, (cls == LEAF) & (concave > -CREASE))
    nc = int(core.max()) + 1
    big = np.bincount(core[core >= 0], half_area[core >= 0], nc) >= p.min_core_units2 * u * u
    frag = grow(_renumber(np.where((core >= 0) & big[np.maximum(core, 0)], core, -1)), pairs,
                leafish)
    rest = geo.components(n, pairs, leafish & (frag < 0))
    frag = np.where(rest >= 0, frag.max() + 1 + rest, frag)
    frag = _renumber(frag)
    g = int(frag.max()) + 1 if (frag >= 0).any() else 0
    on = frag >= 0
    moments = np.zeros((g, samples.moments.shape[1]))
    np.add.at(moments, frag[on], samples.moments[on])
    w = samples.area[on]
    area = np.maximum(np.bincount(frag[on], w, g), 1e-12)
    fprob = np.stack([np.bincount(frag[on], w * prob[on, c], g) for c in range(4)], 1)
    fprob /= area[:, None]
    thick = np.where(np.isfinite(samples.thickness_mm), samples.thickness_mm, np.nan)
    lt = np.log(np.maximum(np.nan_to_num(thick, nan=np.nanmedian(thick)), 1e-3))
    log_thick = np.bincount(frag[on], w * lt[on], g) / area
    a, b = pairs[:, 0], pairs[:, 1]
    fa, fb = frag[a], frag[b]
    stem = cls == STEM
    stem_border = (np.bincount(fa[(fa >= 0) & stem[b]], minlength=g)
                   + np.bincount(fb[(fb >= 0) & stem[a]], minlength=g))
    links: dict = {}
    x = (fa >= 0) & (fb >= 0) & (fa != fb)
    if x.any():
        lo, hi = np.minimum(fa[x], fb[x]), np.maximum(fa[x], fb[x])
        sep = (prob[a[x], EDGE] + prob[b[x], EDGE] + prob[a[x], STEM] + prob[b[x], STEM])
        cmin = np.minimum(concave[a[x]], concave[b[x]])
        key = lo * g + hi
        uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        sep_sum = np.bincount(inv, sep)
        cm = np.full(len(uk), np.inf)
        np.minimum.at(cm, inv, cmin)
        for k, c, ss, m in zip(uk, cnt, sep_sum, cm):
            links[(int(k // g), int(k % g))] = [float(c), float(ss), float(m), 0.0]
    z = samples.centroid[:, 2]
    frags = Fragments(frag, moments, fprob, log_thick, stem_border, links, u,
                      max(float(np.ptp(z)), 1e-9), float(z.min()))
    _gap_links(frags, samples)
    return frags


def _gap_links(frags: Fragments, samples: SurfaceSamples) -> None:
    """Links from fragments touching no other fragment and no stem (their own mesh piece, e.g.
    a blade tip the hull broke off) to the nearest other fragment within ``GAP_UNITS``."""
    from scipy.spatial import cKDTree

    touched = np.zeros(frags.n, bool)
    for f, g in frags.links:
        touched[f] = touched[g] = True
    lonely = np.flatnonzero(~touched & (frags.stem_border == 0))
    on = np.flatnonzero(frags.of_sample >= 0)
    if not len(lonely) or len(on) < 2:
        return
    tree = cKDTree(samples.centroid[on])
    for f in lonely:
        mine = np.flatnonzero(frags.of_sample == f)
        hits = tree.query_ball_point(samples.centroid[mine], GAP_UNITS * frags.unit_mm)
        best: dict[int, float] = {}
        for i, h in zip(mine, hits):
            for j in h:
                other = int(frags.of_sample[on[j]])
                if other != f:
                    d = float(np.linalg.norm(samples.centroid[i] - samples.centroid[on[j]]))
                    best[other] = min(best.get(other, np.inf), d)
        for other, d in best.items():
            key = (min(f, other), max(f, other))
            frags.links.setdefault(key, [0.0, 0.0, 0.0, d])


PAIR_FEATURES = ("log_small_area", "area_ratio", "border_per_size", "border_separation",
                 "border_concave", "gap", "normal_agreement", "axis_agreement",
                 "elongation_small", "elongation_large", "thickness_ratio", "height_small",
                 "height_large", "centroid_distance", "leaf_small", "leaf_large",
                 "stem_touch_small", "stem_touch_large")


def pair_features(frags: Fragments, keys: list[tuple[int, int]], moments: np.ndarray,
                  prob: np.ndarray, log_thick: np.ndarray, stem_border: np.ndarray
                  ) -> np.ndarray:
    """(len(keys), len(PAIR_FEATURES)) features of candidate merges, scale-free."""
    from plantscan_leaves.features import moment_shape

    if not keys:
        return np.zeros((0, len(PAIR_FEATURES)), np.float32)
    u = frags.unit_mm
    f = np.array([k[0] for k in keys])
    g = np.array([k[1] for k in keys])
    area = moments[:, 0] / 2.0
    swap = area[f] > area[g]
    small, large = np.where(swap, g, f), np.where(swap, f, g)
    normal, _, axis, ev_c = moment_shape(moments[np.r_[small, large]])
    m = len(keys)
    elong = np.sqrt(ev_c[:, 2] / np.maximum(ev_c[:, 1], 1e-12))
    mean = moments[:, 7:10] / np.maximum(moments[:, :1], 1e-12)
    link = np.array([frags.links[k] for k in keys])
    size_small = np.sqrt(np.maximum(area[small], 1e-12))
    out = np.stack([
        np.log(np.maximum(area[small], 1e-12) / (u * u)),
        area[small] / np.maximum(area[large], 1e-12),
        link[:, 0] * u / size_small,
        link[:, 1] / np.maximum(2.0 * link[:, 0], 1.0),
        np.where(np.isfinite(link[:, 2]), link[:, 2], 0.0),
        link[:, 3] / u,
        np.abs(np.einsum("ij,ij->i", normal[:m], normal[m:])),
        np.abs(np.einsum("ij,ij->i", axis[:m], axis[m:])),
        elong[:m], elong[m:],
        log_thick[small] - log_thick[large],
        (mean[small, 2] - frags.z0_mm) / frags.height_mm,
        (mean[large, 2] - frags.z0_mm) / frags.height_mm,
        np.linalg.norm(mean[small] - mean[large], axis=1) / np.sqrt(np.maximum(area[large], 1e-12)),
        prob[small, LEAF] + prob[small, EDGE], prob[large, LEAF] + prob[large, EDGE],
        stem_border[small] * u / size_small, stem_border[large] * u / np.sqrt(
            np.maximum(area[large], 1e-12)),
    ], axis=1)
    return out.astype(np.float32)


def agglomerate(frags: Fragments, merge_probability, threshold: float = 0.5,
                record=None, merged=None) -> np.ndarray:
    """(G,) leaf of every fragment after greedy merging, most likely pairs first.

    Merging goes in rounds: the pairs not scored yet (all at first, then those of the
    fragments merged in the last round) are scored in one call of
    ``merge_probability(features) -> (n,)``; then every pair at or above ``threshold``
    that is the most likely pair of both its fragments is merged.  A pair's features
    depend only on its two fragments and their link, so a round makes the merges that
    merging the single most likely pair at a time would make first, in one model call
    per round rather than one per merge (dicot development hull 9: 12 calls for 99
    merges, 4.8 -> 0.6 s).  The two orders can still part where a merge changes which
    pair comes next (same leaves on 4 of 5 development hulls, 53 vs 55 fragments left
    on the fifth).  The links of a merged fragment are combined (border counts and sums
    add, the sharpest crease and the smallest gap are kept).  ``record(keys, features,
    root)``, when given, sees every scored batch (training: the features a merge step
    really meets); ``merged(f, g, probability)`` every merge made.
    """
    moments = frags.moments.copy()
    prob = frags.prob * frags.moments[:, :1]  # area-weighted sums, so merged ones add
    log_thick = frags.log_thick * frags.moments[:, 0]
    stem_border = frags.stem_border.astype(float).copy()
    links = {k: list(v) for k, v in frags.links.items()}
    nbrs: dict[int, set[int]] = {}
    for f, g in links:
        nbrs.setdefault(f, set()).add(g)
        nbrs.setdefault(g, set()).add(f)
    root = np.arange(frags.n)
    p: dict[tuple[int, int], float] = {}
    while True:
        fresh = sorted(k for k in links if k not in p)
        if fresh:
            area = np.maximum(moments[:, :1], 1e-12)
            x = pair_features(_View(frags, links), fresh, moments, prob / area,
                              log_thick / area[:, 0], stem_border)
            if record is not None:
                record(fresh, x, root)
            p.update(zip(fresh, (float(q) for q in merge_probability(x))))
        busy: set[int] = set()
        batch = []
        for key in sorted(p, key=lambda k: (-p[k], k)):
            if p[key] < threshold:
                break
            if key[0] not in busy and key[1] not in busy:
                batch.append(key)
            busy.update(key)  # a pair is merged only if it is both fragments' best
        if not batch:
            return root
        for f, g in batch:
            if merged is not None:
                merged(f, g, p[(f, g)])
            for a in (f, g):  # every pair of the two is scored again next round
                for other in nbrs.get(a, ()):
                    p.pop((min(a, other), max(a, other)), None)
            root[root == g] = f
            for arr in (moments, prob):
                arr[f] += arr[g]
                arr[g] = 0.0
            log_thick[f] += log_thick[g]
            stem_border[f] += stem_border[g]
            links.pop((f, g))
            nbrs[f].discard(g)
            for other in nbrs.pop(g, set()) - {f}:
                old = links.pop((min(g, other), max(g, other)))
                nbrs[other].discard(g)
                new = (min(f, other), max(f, other))
                cur = links.get(new)
                links[new] = old if cur is None else [cur[0] + old[0], cur[1] + old[1],
                                                      min(cur[2], old[2]), min(cur[3], old[3])]
                nbrs[f].add(other)
                nbrs[other].add(f)


@dataclass
class _View:
    """``Fragments`` with other links (what ``pair_features`` reads during merging)."""

    base: Fragments
    links: dict

    def __getattr__(self, name):
        return getattr(self.base, name)


def sample_instances(samples: SurfaceSamples, prob: np.ndarray, frags: Fragments,
                     root: np.ndarray, p: InstanceParams) -> np.ndarray:
    """(S,) instance of every sample: 0..n-1 leaves (merged fragments big enough), ``-1`` stem,
    ``-2`` debris (pot remnants, and pieces too small for a leaf touching no stem)."""
    u2 = samples.unit_mm ** 2
    cls = prob.argmax(axis=1)
    out = np.where(cls == DEBRIS, -2, -1)
    leaf_of = np.where(frags.of_sample >= 0, root[np.maximum(frags.of_sample, 0)], -1)
    on = leaf_of >= 0
    g = frags.n
    area = np.bincount(leaf_of[on], samples.area[on] / 2.0, g)
    big = area >= p.min_leaf_units2 * u2
    keep = on & big[np.maximum(leaf_of, 0)]
    out[keep] = leaf_of[keep]
    small = np.where(on & ~keep, leaf_of, -1)
    if (small >= 0).any():
        stem = np.where(cls == STEM, 0, -1)
        touches_stem = _best_neighbour(samples.pairs, small, stem, g) >= 0
        sel = small >= 0
        out[sel] = np.where(touches_stem[small[sel]], -1, -2)
    leaves = out >= 0
    out[leaves] = _renumber(np.where(leaves, out, -1))[leaves]
    return out


def labelled_from_samples(mesh: Mesh, samples: SurfaceSamples, inst: np.ndarray
                          ) -> LabelledMesh:
    """The ``LabelledMesh`` of sample instances: 0 stem, 1..n leaves, n+1 debris (if any)."""
    face = inst[samples.face_sample]
    n = int(face.max()) + 1 if (face >= 0).any() else 0
    labels = np.where(face >= 0, face + 1, np.where(face == -1, 0, n + 1)).astype(np.int32)
    kinds = {i: "leaf" for i in range(1, n + 1)}
    kinds[0] = "stem"
    if (face == -2).any():
        kinds[n + 1] = "debris"
    return LabelledMesh(mesh, labels, kinds)


class LearnedOrgansParams(StageParams):
    """Parameters of ``learned-organs``: sizes in mesh units (``u``, the median edge length,
    about a voxel), so one recipe serves a 30 mm seedling and a 600 mm grass."""

    min_leaf_area_units2: float = Field(
        150.0, ge=0, description="smallest leaf, one side, in mesh units squared (at 1 mm "
                                 "voxels 150 mm², e.g. 20 x 10 mm); smaller pieces are stem "
                                 "where they touch it, else debris")
    min_core_area_units2: float = Field(
        30.0, ge=0, description="smallest connected core of leaf-inside samples that seeds a "
                                "leaf fragment, mesh units squared")
    merge_threshold: float = Field(
        0.5, gt=0, lt=1, description="two fragments are merged into one leaf while the merge "
                                     "model gives them at least this probability")
    model_dir: str | None = Field(
        None, description="a folder holding another organ model (the files "
                          "scripts/train_organ_model.py --out writes: a lab's own training); "
                          "None: the model shipped in the package")


def segment_organs(mesh: Mesh, params: LearnedOrgansParams | None = None,
                   model: OrganModel | None = None) -> tuple[LabelledMesh, StageReport]:
    """Label every face of ``mesh`` leaf *i*, stem or debris with the learned organ model.

    Returns the labelled mesh (0 stem, 1..n leaves, n+1 debris when there is any) and
    the report (counts ``samples``, ``fragments``, ``merges``, ``leaves``,
    ``debris_faces``; warnings).  ``labelled.evidence`` holds, per leaf label, what its
    trust is judged on (``phantom_share``: its area share the phantom model puts on
    phantom volume; ``fragments``: how many fragments were merged into it;
    ``weakest_merge``: the lowest merge probability among those merges).
    """
    p = params or LearnedOrgansParams()
    report = StageReport()
    if mesh.is_empty:
        report.warn("empty-mesh", "mesh is empty: no leaf to segment")
        return LabelledMesh(mesh, np.zeros(0, np.int32), {}), report
    model = model or load_model(p.model_dir)
    topo = geo.topology(mesh.faces)
    if topo.non_manifold_edges:
        report.warn("non-manifold", f"mesh has {topo.non_manifold_edges} non-manifold edges "
                    "(used by more than two faces); they are treated as ordinary connections")
    samples = surface_samples(mesh, topo)
    prob, phantom = model.predict(samples.features)
    ip = InstanceParams(p.min_core_area_units2, p.min_leaf_area_units2)
    frags = leaf_fragments(samples, prob, ip)
    merges: list[tuple[int, int, float]] = []
    root = agglomerate(frags, model.merge_probability, p.merge_threshold,
                       merged=lambda f, g, q: merges.append((f, g, q)))
    inst = sample_instances(samples, prob, frags, root, ip)
    labelled = labelled_from_samples(mesh, samples, inst)
    report.note({"samples": samples.n, "fragments": frags.n, "merges": len(merges),
                 "leaves": len(labelled.leaf_labels),
                 "debris_faces": int(np.count_nonzero(inst[samples.face_sample] == -2)),
                 "unit_mm": samples.unit_mm})
    labelled.evidence = _leaf_evidence(samples, inst, phantom, frags, root, merges)
    if not labelled.leaf_labels:
        report.warn("no-leaf", "no leaf found on the mesh (everything looks like stem or "
                    "debris)")
    return labelled, report


def _leaf_evidence(samples: SurfaceSamples, inst: np.ndarray, phantom: np.ndarray,
                   frags: Fragments, root: np.ndarray, merges: list) -> dict[int, dict]:
    """Per leaf label (1..n): phantom share, fragments merged into it, weakest merge."""
    out: dict[int, dict] = {}
    n = int(inst.max()) + 1 if (inst >= 0).any() else 0
    if not n:
        return out
    on = inst >= 0
    area = np.bincount(inst[on], samples.area[on], n)
    ph = np.bincount(inst[on], samples.area[on] * phantom[on], n) / np.maximum(area, 1e-12)
    # which fragment roots ended in which leaf
    leaf_of_root: dict[int, int] = {}
    for s_idx in np.flatnonzero(on & (frags.of_sample >= 0)):
        leaf_of_root.setdefault(int(root[frags.of_sample[s_idx]]), int(inst[s_idx]))
    pieces = np.zeros(n, int)
    weakest = np.ones(n)
    for r, leaf in leaf_of_root.items():
        pieces[leaf] += int(np.count_nonzero(root == r))
    for f, _g, q in merges:
        leaf = leaf_of_root.get(int(root[f]))
        if leaf is not None:
            weakest[leaf] = min(weakest[leaf], q)
    for i in range(n):
        out[i + 1] = {"phantom_share": round(float(ph[i]), 4), "fragments": int(pieces[i]),
                      "weakest_merge": round(float(weakest[i]), 4),
                      "area_units2": round(float(area[i]) / 2.0 / samples.unit_mm ** 2, 1)}
    return out

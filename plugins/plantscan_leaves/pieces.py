"""A learned judge of the pieces the curvature rules number as leaves.

The rules of ``curvature-regions`` (``plantscan_leaves.segment``) end with numbered
leaves; on other plants than the one they were tuned on, some of those are no whole
leaf: a leaf the creases cut in two gives two "leaves", and phantom hull volume or a
crumb of it over a young leaf gives a "leaf" that matches nothing.  With
``judge_pieces`` on, every numbered leaf (a *piece*) is judged by gradient-boosted
trees (LightGBM), trained on the virtual scanner's truth (``scripts/train_piece_model.py``),
as one of

* ``leaf``: a whole leaf (kept);
* ``join``: a fragment of a leaf: it joins its *partner*, the leaf piece it shares most
  border edges with (or, touching none, the nearest one within ``JOIN_REACH_UNITS``);
* ``debris``: phantom volume or crumbs: relabelled debris, kept in the labelled mesh,
  never counted in ``leaf_count`` or the total leaf area.

The features (``FEATURE_NAMES``) are scale-free: areas relative to the plant's largest
piece or to the mesh unit ``u`` squared (the median edge, about a voxel), lengths
relative to ``u`` or to the plant's height, shapes as eigenvalue ratios, curvature
times ``u``; so the judge says the same of a plant in millimetres and in centimetres.
"""

from __future__ import annotations

import gzip
import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from plantscan_leaves import geometry as geo

LEAF, JOIN, DEBRIS = 0, 1, 2
CLASS_NAMES = ("leaf", "join", "debris")
MODEL_FILE = "piece_model.json.gz"
FEATURE_NAMES = (
    "area_share_of_largest",  # one side, over the plant's largest piece's
    "log_area_units2",  # log of the area (one side) in mesh units squared
    "elongation",  # sqrt of 1st / 2nd eigenvalue of the faces' spread: a leaf 1.5-4
    "flatness",  # sqrt of 3rd / 2nd eigenvalue: a flat slab near 0, a blob near 1
    "length_share_of_height",  # 4 sigma along the long axis over the plant's height
    "thickness_units",  # median inward-ray thickness, mesh units: a hull leaf 2-4
    "thickness_share_of_plant",  # that over the median of all pieces' rays
    "thick_share",  # share of its rays over THICK_TIMES the plant's median: phantom volume
    "normal_spread",  # 2nd / 1st eigenvalue of the normal tensor: slab 0, tube or blob 0.5-1
    "border_leaf_share",  # share of the border edges shared with other leaf pieces
    "border_stem_share",  # share shared with the stem
    "border_per_size",  # border edges x u / sqrt(area): how much of it is cut, not rim
    "gap_units",  # distance to the nearest other leaf piece, mesh units (0: touching)
    "partner_area_ratio",  # area over the partner's (the piece it would join)
    "partner_normal_agreement",  # |cos| between the mean planes' normals of the two
    "height_share",  # mean height above the mesh's bottom over the plant's height
    "curvature_units",  # area-weighted mean of the rules' face curvature x u
    "concave_share",  # area share of faces more concave than CONCAVE_UNITS / u
)
THICK_TIMES = 3.0  # as the measurer's phantom warning: 3x the median thickness is no blade
CONCAVE_UNITS = 0.05  # a face whose curvature x u is below -0.05 is concave (a crease)
JOIN_REACH_UNITS = 6.0  # a piece touching no leaf joins one at most this far, mesh units
THICKNESS_FACES = 400  # inward rays per piece (every k-th face): a median, not a map
GAP_FACES = 3000  # faces per piece the nearest-piece distance is measured over


@dataclass
class PieceSurface:
    """What the judge reads of the mesh: per-face geometry of the rules' surface.

    ``centroids`` (F, 3) and ``normals`` (F, 3) in the mesh's unit and frame, ``areas`` (F,),
    ``pairs`` (E, 2) faces sharing an edge, ``curvature`` (F,) 1/unit (< 0 concave),
    ``unit`` the mesh unit (``geometry.mesh_unit``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    centroids: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    pairs: np.ndarray
    curvature: np.ndarray
    unit: float
    # the vertices the inward rays are cast at, when not ``vertices``: the plant as given,
    # where the segmenter works on it scaled to its reference unit (``vertices`` = these x
    # ``scene_scale``), so that the measurer, casting at the same plant, reuses the ray
    # scene (``geometry.raycasting_scene``: 1 s at 1.7 M faces) instead of building a second
    scene_vertices: np.ndarray | None = None
    scene_scale: float = 1.0


@dataclass
class Pieces:
    """The pieces of one plant: their features, partners and reach.

    ``features`` (n, len(FEATURE_NAMES)) of leaves 1..n (row i: label i + 1);
    ``partner`` (n,) label of the piece each would join (0: none in reach);
    ``area`` (n,) one side.
    """

    features: np.ndarray
    partner: np.ndarray
    area: np.ndarray


def surface_of(mesh, smoothing_units: float = 1.5 / 0.8) -> PieceSurface:
    """The judges' view of ``mesh`` on its own (outside the segmenter, which builds it from
    its passes' fields): curvature at ``smoothing_units`` mesh units (the rules'
    ``smoothing_mm`` 1.5 at 0.8 mm voxels)."""
    topo = geo.topology(mesh.faces)
    normals, areas = geo.face_normals_areas(mesh.vertices, mesh.faces)
    unit = geo.mesh_unit(mesh.vertices, mesh.faces)
    return PieceSurface(mesh.vertices, mesh.faces, geo.face_centroids(mesh.vertices, mesh.faces),
                        normals, areas, topo.face_pairs,
                        geo.face_curvature(mesh, topo, smoothing_units * unit), unit)


def _strided(idx: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` of ``idx``, evenly spaced (the same faces whatever the unit)."""
    return idx if len(idx) <= k else idx[np.linspace(0, len(idx) - 1, k).astype(np.int64)]


def piece_features(s: PieceSurface, labels: np.ndarray, n: int) -> Pieces:
    """The features of leaves 1..n of ``labels`` (F,) (0 stem), their partners and areas."""
    from plantscan_leaves.features import inward_thickness

    u = s.unit
    if n == 0:
        return Pieces(np.zeros((0, len(FEATURE_NAMES)), np.float32), np.zeros(0, np.int64),
                      np.zeros(0))
    lab = labels.astype(np.int64)
    m = n + 1
    # the pieces' own faces for their moments (the stem's row stays empty, and unused: the
    # same sums in the same order for every piece, a third of the work on a grass plant)
    own = (lab > 0) & (lab <= n)
    lp, w, cp, npf = lab[own], s.areas[own], s.centroids[own], s.normals[own]
    area2 = np.bincount(lab, s.areas, m)
    area = area2[1:] / 2.0
    safe = np.maximum(area2, 1e-30)
    _, mean, cov = geo.label_moments(lp, m, w, cp, 1e-30)  # a piece's own faces: area2's
    mean /= safe[:, None]
    nt = geo.label_moments(lp, m, w, npf)[2]
    ev_c = np.maximum(np.linalg.eigvalsh(cov / safe[:, None, None]), 0.0)  # ascending
    ev_n, vec_n = np.linalg.eigh(nt / safe[:, None, None])
    plane_normal = vec_n[:, :, 2]  # a slab's two sides share one sign-free normal
    z = s.vertices[:, 2]
    z0, height = float(z.min()), max(float(np.ptp(z)), 1e-12)

    # borders: edges between a piece and another label
    a, b = s.pairs[:, 0], s.pairs[:, 1]
    la, lb = lab[a], lab[b]
    cross = la != lb
    src = np.r_[la[cross], lb[cross]]
    dst = np.r_[lb[cross], la[cross]]
    on = src > 0
    src, dst = src[on], dst[on]
    border = np.bincount(src, minlength=m)[1:].astype(float)
    to_stem = np.bincount(src[dst == 0], minlength=m)[1:].astype(float)
    to_leaf = border - to_stem
    partner = np.zeros(n, np.int64)
    leafy = dst > 0
    if leafy.any():
        key, cnt = np.unique(src[leafy] * m + dst[leafy], return_counts=True)
        ks, kd = key // m, key % m
        order = np.lexsort((kd, -cnt, ks))  # most shared edges first, then the lower label
        first = order[np.r_[True, ks[order][1:] != ks[order][:-1]]]
        partner[ks[first] - 1] = kd[first]

    # the nearest other piece (touching pieces: 0)
    gap = np.zeros(n)
    nearest = np.zeros(n, np.int64)
    order = np.argsort(lab, kind="stable")  # each piece's faces in index order, one sort
    bounds = np.searchsorted(lab[order], np.arange(m + 1))
    faces_of = [order[bounds[i]:bounds[i + 1]] for i in range(1, m)]
    picked = [_strided(f, GAP_FACES) for f in faces_of]
    touching = to_leaf > 0
    nearest[touching] = partner[touching]
    lone = [i for i in range(n) if not touching[i]]
    if lone:
        gap[lone], nearest[lone] = _nearest_pieces([s.centroids[p] for p in picked], lone)
    reach = touching | (gap <= JOIN_REACH_UNITS * u)
    partner = np.where(reach, nearest, 0)

    thick = np.full(n, np.nan)
    thick_share = np.full(n, np.nan)
    rays = np.concatenate([_strided(f, THICKNESS_FACES) for f in faces_of])
    if len(rays):
        from plantscan_core.data import Mesh

        if s.scene_vertices is None:
            t = inward_thickness(Mesh(s.vertices, s.faces), rays)
        else:  # the same rays at the plant as given, their lengths scaled as the surface
            t = inward_thickness(Mesh(s.scene_vertices, s.faces), rays) * s.scene_scale
        owner = lab[rays]
        ok = np.isfinite(t)
        plant_median = float(np.median(t[ok])) if ok.any() else np.nan
        for i in range(n):
            ti = t[(owner == i + 1) & ok]
            if len(ti):
                thick[i] = float(np.median(ti))
                thick_share[i] = float(np.mean(ti > THICK_TIMES * plant_median))
    else:
        plant_median = np.nan
    cu = s.curvature[own] * u
    concave = np.bincount(lp, w * (cu < -CONCAVE_UNITS), m)[1:] / safe[1:]
    mean_curv = np.bincount(lp, w * np.clip(cu, -1.0, 1.0), m)[1:] / safe[1:]

    ev = ev_c[1:]
    has = partner > 0
    p_idx = np.maximum(partner, 0)
    out = np.stack([
        area / max(float(area.max()), 1e-30),
        np.log(np.maximum(area, 1e-30) / (u * u)),
        np.sqrt(ev[:, 2] / np.maximum(ev[:, 1], 1e-30)),
        np.sqrt(ev[:, 0] / np.maximum(ev[:, 1], 1e-30)),
        4.0 * np.sqrt(ev[:, 2]) / height,
        thick / u,
        thick / plant_median,
        thick_share,
        ev_n[1:, 1] / np.maximum(ev_n[1:, 2], 1e-30),
        to_leaf / np.maximum(border, 1.0),
        to_stem / np.maximum(border, 1.0),
        border * u / np.sqrt(np.maximum(area, 1e-30)),
        np.minimum(gap / u, 1e3),
        np.where(has, area / np.maximum(area2[p_idx] / 2.0, 1e-30), np.nan),
        np.where(has, np.abs(np.einsum("ij,ij->i", plane_normal[1:], plane_normal[p_idx])),
                 np.nan),
        (mean[1:, 2] - z0) / height,
        mean_curv,
        concave,
    ], axis=1)
    return Pieces(out.astype(np.float32), partner, area)


def _nearest_pieces(points: list[np.ndarray], which: list[int]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """For each piece in ``which`` (indices into ``points``, each piece's (k, 3) points):
    the least distance from its points to another piece's, and that piece's label
    (index + 1; inf and 0 with no other piece).

    Each piece's points are looked up in the other pieces' own trees, nearest box first;
    a piece whose box lies farther than the best distance so far cannot hold a nearer
    point and is skipped.  The same distances as one tree of all the others' points (a
    pair's distance does not depend on the tree), and the same closest pair: the first
    of the piece's points at the least distance.
    """
    from scipy.spatial import cKDTree

    lo = np.array([p.min(axis=0) if len(p) else np.full(3, np.inf) for p in points])
    hi = np.array([p.max(axis=0) if len(p) else np.full(3, -np.inf) for p in points])
    trees: dict[int, cKDTree] = {}
    gap = np.full(len(which), np.inf)
    label = np.zeros(len(which), np.int64)
    for w, i in enumerate(which):
        own = points[i]
        if not len(own):
            continue
        # box-to-box distance: a lower bound of any pair's
        sep = np.maximum(np.maximum(lo - hi[i], lo[i] - hi), 0.0)
        box = np.sqrt((sep * sep).sum(axis=1))
        best = np.full(len(own), np.inf)
        best_label = np.zeros(len(own), np.int64)
        for j in np.argsort(box, kind="stable"):
            if j == i or not len(points[j]):
                continue
            if box[j] > best.min():
                break
            if j not in trees:
                trees[j] = cKDTree(points[j])
            d, _ = trees[j].query(own)
            nearer = d < best
            best[nearer] = d[nearer]
            best_label[nearer] = j + 1
        k = int(np.argmin(best))
        gap[w], label[w] = best[k], best_label[k]
    return gap, label


@dataclass
class Verdict:
    """What the judge made of the pieces: ``labels`` (F,) 0 stem, 1..``n_leaves`` leaves,
    ``n_leaves + 1`` debris (when ``debris``); ``verdict`` (n,) class of every piece as
    judged; ``joined`` {new leaf label: (pieces, weakest join probability)} for leaves made
    of several pieces."""

    labels: np.ndarray
    n_leaves: int
    debris: bool
    verdict: np.ndarray
    joined: dict[int, tuple[int, float]]


def apply_verdict(labels: np.ndarray, pieces: Pieces, prob: np.ndarray,
                  parent: np.ndarray | None = None) -> Verdict:
    """New labels from the class probabilities ``prob`` (n, 3) of the pieces of ``labels``.

    Each piece takes its most likely class, except that a piece thicker than
    ``THICK_TIMES`` the plant's median (``thickness_share_of_plant``) is debris; the
    plant's largest piece is always a leaf
    (a plant has at least one leaf, and no truth leaf is smaller than a fragment of
    itself).  A ``join`` piece joins its partner unless the partner is debris or it has
    none in reach; then it is whichever of leaf and debris is more likely.  Joined
    groups (a leaf and the fragments joined to it, or fragments joined to each other)
    are one leaf each, numbered in the order of their lowest piece.  ``parent`` (n + 1,):
    the leaf each piece was before a tentative split (None: each its own); pieces of one
    parent joined count as one, and their join undoes the split: ``joined`` counts the
    parents and keeps the weakest join across parents (1 when there is none).
    """
    n = len(pieces.area)
    parent = np.arange(n + 1) if parent is None else np.asarray(parent)
    cls = prob.argmax(axis=1) if n else np.zeros(0, np.int64)
    # thicker than THICK_TIMES the plant's pieces is no blade (trees do not extrapolate to a
    # lump thicker than any they were shown; dev seeds 0-7: every leaf piece under 2.7x)
    thick = pieces.features[:, FEATURE_NAMES.index("thickness_share_of_plant")]
    cls = np.where(np.nan_to_num(thick) > THICK_TIMES, DEBRIS, cls)
    if n:
        cls[int(np.argmax(pieces.area))] = LEAF
    target = pieces.partner
    while True:  # a join whose partner became debris is stuck too, so again
        stuck = (cls == JOIN) & ((target == 0) | (cls[np.maximum(target - 1, 0)] == DEBRIS))
        if not stuck.any():
            break
        cls = np.where(stuck, np.where(prob[:, LEAF] >= prob[:, DEBRIS], LEAF, DEBRIS), cls)
    root = np.arange(n + 1)

    def find(i: int) -> int:
        while root[i] != i:
            i = root[i]
        return i

    for i in np.flatnonzero(cls == JOIN):
        ra, rb = find(i + 1), find(int(target[i]))
        if ra != rb:
            root[max(ra, rb)] = min(ra, rb)
    group = np.array([find(i) for i in range(n + 1)])
    new = np.zeros(n + 1, np.int64)
    n_leaves = 0
    joined: dict[int, tuple[int, float]] = {}
    for g in np.unique(group[1:][cls != DEBRIS]) if n else []:
        n_leaves += 1
        members = np.flatnonzero((group[1:] == g) & (cls != DEBRIS))
        new[members + 1] = n_leaves
        parents = len(set(parent[members + 1].tolist()))
        if parents > 1:
            fragments = members[cls[members] == JOIN]
            across = fragments[parent[fragments + 1] != parent[target[fragments]]]
            joined[n_leaves] = (parents, float(prob[across, JOIN].min()) if len(across)
                                else 1.0)
    debris = bool((cls == DEBRIS).any())
    new[np.flatnonzero(cls == DEBRIS) + 1] = n_leaves + 1
    return Verdict(new[labels], n_leaves, debris, cls, joined)


@dataclass
class PieceModel:
    """The shipped booster and what it was trained on (``config``, its ``config_sha256``)."""

    booster: object
    config: dict
    config_sha256: str

    def probabilities(self, pieces: Pieces) -> np.ndarray:
        """(n, 3) probability of leaf / join / debris of every piece."""
        x = np.asarray(pieces.features, dtype=np.float64)
        if not len(x):
            return np.zeros((0, len(CLASS_NAMES)))
        return np.asarray(self.booster.predict(x, num_threads=1)).reshape(len(x), -1)


@dataclass
class BinaryModel:
    """A shipped binary booster (the stem-part and pair judges) and what it was trained on
    (``config``, its ``config_sha256``)."""

    booster: object
    config: dict
    config_sha256: str

    def probabilities(self, rows) -> np.ndarray:
        """(k,) probability of the positive class of each row of ``rows.features``."""
        x = np.asarray(rows.features, dtype=np.float64)
        if not len(x):
            return np.zeros(0)
        return np.asarray(self.booster.predict(x, num_threads=1)).reshape(len(x))


def config_sha256(config: dict) -> str:
    """The hash a model file records of its training configuration."""
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def save_model(booster, config: dict, path: Path, feature_names=FEATURE_NAMES,
               class_names=CLASS_NAMES) -> None:
    """One gzip'd JSON file: the training config, its hash and the booster's text (the
    piece judge's features and classes unless given: ``stem_parts`` writes its own)."""
    body = {"config": config, "config_sha256": config_sha256(config),
            "feature_names": list(feature_names), "classes": list(class_names),
            "booster": booster.model_to_string()}
    path.parent.mkdir(parents=True, exist_ok=True)
    # mtime 0: the same model gives the same bytes
    path.write_bytes(gzip.compress(json.dumps(body, sort_keys=True).encode(), mtime=0))


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> PieceModel:
    """The piece model at ``path`` (``scripts/train_piece_model.py --out`` writes it): None,
    the one shipped in ``plantscan_leaves/models`` (``MODEL_FILE``); a file name without a
    folder, another model shipped there (as a recipe names one: ``piece_model_all.json.gz``);
    else a file path (``./my_model.json.gz`` in the working folder).  Loaded once per process
    and path."""
    booster, body = read_model(path, MODEL_FILE, FEATURE_NAMES, "piece model",
                               "plantscan_leaves.pieces", "scripts/train_piece_model.py")
    return PieceModel(booster, body["config"], body["config_sha256"])


def model_location(path: str | None, default: str):
    """Where a model file named as a recipe names it is: ``path`` None is ``default``
    shipped in ``plantscan_leaves/models``, a name without a folder another file shipped
    there, else a path."""
    shipped = resources.files("plantscan_leaves") / "models"
    return (shipped / default if path is None
            else shipped / path if "/" not in path else Path(path))


def check_model_name(value: str | None, script: str) -> str | None:
    """A recipe's model field checked when the recipe is read (before any motor moves): a
    file that is neither shipped nor on disk is a ``ValueError`` naming it and ``script``."""
    if value is not None and not model_location(value, value).is_file():
        raise ValueError(f"model file {value!r} not found (neither shipped in "
                         f"plantscan_leaves/models nor a file there); {script} writes one")
    return value


def read_model(path: str | None, default: str, feature_names: tuple[str, ...], what: str,
               module: str, script: str) -> tuple[object, dict]:
    """The LightGBM booster and the body of a model file ``save_model`` wrote: ``path``
    None is ``default`` shipped in ``plantscan_leaves/models``, a name without a folder
    another file shipped there, else a path.  A missing file, or one trained on other
    features than ``feature_names``, is a ``DataError`` naming it and ``script``."""
    import lightgbm as lgb

    from plantscan_core.errors import DataError

    where = model_location(path, default)
    try:
        body = json.loads(gzip.decompress(where.read_bytes()).decode())
    except (OSError, ValueError) as exc:
        raise DataError(f"{where}: {what} missing or unreadable ({exc}); {script} writes "
                        "it") from exc
    if tuple(body.get("feature_names", ())) != feature_names:
        raise DataError(f"{where}: trained on other features than {module} computes; "
                        f"retrain it ({script})")
    return lgb.Booster(model_str=body["booster"]), body


def judge(s: PieceSurface, labels: np.ndarray, n: int, model,
          parent: np.ndarray | None = None) -> tuple[Verdict, Pieces, np.ndarray]:
    """Judge leaves 1..n of ``labels``: the verdict, the pieces and their probabilities.

    ``model`` has ``probabilities(pieces) -> (n, 3)`` (a ``PieceModel``; training passes
    one that records the pieces); ``parent``: as ``apply_verdict``'s.
    """
    pieces = piece_features(s, labels, n)
    prob = model.probabilities(pieces)
    return apply_verdict(labels, pieces, prob, parent), pieces, prob


def verdict_labelled(mesh, verdict: Verdict):
    """The ``LabelledMesh`` of a verdict on ``mesh`` (what ``segment_leaves`` returns with the
    judge on; training re-judges the rules' labels with it without segmenting again)."""
    from plantscan_core.data import LabelledMesh

    kinds = {i: "leaf" for i in range(1, verdict.n_leaves + 1)}
    if (verdict.labels == 0).any() or not verdict.n_leaves:
        kinds[0] = "stem"
    if verdict.debris:
        kinds[verdict.n_leaves + 1] = "debris"
    return LabelledMesh(mesh, verdict.labels.astype(np.int32), kinds, joined_evidence(verdict))


def joined_evidence(verdict: Verdict) -> dict[int, dict[str, float]]:
    """Per joined leaf: how many pieces and the weakest join (``trust``'s ``rejoined``)."""
    return {leaf: {"fragments": k, "weakest_merge": round(q, 4)}
            for leaf, (k, q) in verdict.joined.items()}

"""A learned trust: how likely a measured leaf is wrong, from what the measurer can see.

The rule reasons of ``plantscan_leaves.trust`` (phantom share, short outline, weak merge,
few voxels, odd shape) each catch one way a leaf goes wrong; on grasses they marked 11-22 %
of the blades measured more than 10 % off (docs/benchmarks/population.md, session 15),
because most such blades fail in a way no single rule sees (a base left in the culm, two
blades fused in a tangle).  The **trust model** learns the whole picture from the virtual
scanner's exactly known leaves: for every leaf the measurer returns it computes
``FEATURE_NAMES`` (scale-free: ratios of the leaf's own traits, its share of the plant, its
place on the plant, what its edge touches, its thickness in voxels) and a LightGBM booster
trained on development plants (``scripts/train_trust_model.py``) gives ``p_bad``: the
probability that the leaf is not one truth leaf measured within 10 % on every trait (a
leaf off by more than 10 %, two leaves merged, a piece of a split leaf, or no leaf at all).

``measure``'s ``trust_model`` names a model (``trust_model_grass.json.gz`` ships, trained
on grass development seeds); its confidence is ``1 - p_bad`` and the leaf's confidence is
the lower of that and the rules', so a model can only add doubt, never clear a rule's
reason.  A model's low confidence comes with the reason ``model`` and the two features that
pushed ``p_bad`` up most (LightGBM's SHAP contributions), in words a scientist reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

FEATURE_NAMES = (
    "aspect",              # width / length
    "fill",                # area / (length x width)
    "outline",             # perimeter / length
    "compactness",         # perimeter^2 / area
    "outline_vs_ellipse",  # perimeter / the perimeter of the length x width ellipse
    "extent",              # the leaf's longest extent (principal axis) / length
    "base_to_stem",        # base point's distance to the nearest stem surface / length
    "chord",               # straight base-tip distance / length (how bent the midrib)
    "thick_share",         # the measurer's share of the area on thick hull
    "thickness_units",     # the leaf's median hull thickness, mesh units (voxels)
    "size_units",          # sqrt(area), mesh units: how many voxels across
    "area_vs_median",      # log(area / the plant's median leaf area)
    "area_share",          # area / the plant's total leaf area
    "length_vs_height",    # length / plant height
    "leaf_count",          # leaves measured on the plant
    "base_height",         # base height in the plant's height, 0 bottom - 1 top
    "tip_height",
    "base_radius",         # base distance from the plant's axis / the plant's radius
    "tip_radius",
    "contact_stem",        # share of the leaf's edge that touches stem faces
    "contact_leaf",        # ... other leaves
    "contact_debris",      # ... debris
    "fragments",           # pieces the judge joined into this leaf (1: none)
    "weakest_merge",       # the judge's weakest join probability (1: no join)
)
FEATURE_TEXT = {
    "aspect": "its width for its length",
    "fill": "its area for its length and width",
    "outline": "its perimeter for its length",
    "compactness": "its outline for its area",
    "outline_vs_ellipse": "its perimeter for its length and width",
    "extent": "its length against its size",
    "base_to_stem": "how far its base is from the stem",
    "chord": "how bent its midrib is",
    "thick_share": "thick hull (phantom volume) on it",
    "thickness_units": "its hull thickness",
    "size_units": "its size in voxels",
    "area_vs_median": "its size against the plant's other leaves",
    "area_share": "its share of the plant's leaf area",
    "length_vs_height": "its length against the plant's height",
    "leaf_count": "the number of leaves on the plant",
    "base_height": "where its base is on the plant",
    "tip_height": "where its tip is on the plant",
    "base_radius": "how far its base is from the stem",
    "tip_radius": "how far its tip reaches out",
    "contact_stem": "how much of its edge touches the stem",
    "contact_leaf": "how much of its edge touches other leaves",
    "contact_debris": "how much of its edge touches debris",
    "fragments": "the pieces it was joined from",
    "weakest_merge": "an uncertain join",
}
CLASS_NAMES = ("good", "bad")


@dataclass
class PlantContext:
    """What ``leaf_features`` reads of the labelled plant alone (not of the traits): its
    height range, the stem's axis and the plant's radius about it, the label borders'
    counts per kind, the stem's vertices, and each leaf's extent.  Worked out by
    ``plant_context`` (the measurer does it beside the leaves' measurement)."""

    z0: float
    height: float
    axis: np.ndarray
    radius: float
    edge: np.ndarray
    stem_tree: object | None
    extents: dict[int, float]


def plant_context(labelled, leaf_ids: list[int], stem: tuple | None = None) -> PlantContext:
    """``PlantContext`` of ``labelled`` for the leaves ``leaf_ids``; ``stem``:
    ``measure.stem_faces_and_tree(labelled)`` when the caller has it."""
    from plantscan_leaves import geometry as geo
    from plantscan_leaves.measure import stem_faces_and_tree

    mesh = labelled.mesh
    v = mesh.vertices
    z0, z1 = float(v[:, 2].min()), float(v[:, 2].max())
    kinds = labelled.kinds
    labels = labelled.face_labels
    on_stem_face, stem_tree = stem if stem is not None else stem_faces_and_tree(labelled)
    if stem_tree is not None:
        axis = v[mesh.faces[on_stem_face].ravel()][:, :2].mean(axis=0)
    else:
        axis = np.median(v[:, :2], axis=0)
    radius = max(float(np.hypot(*(v[:, :2] - axis).T).max()), 1e-9)
    # what each leaf's edge touches: face pairs across a label change
    pairs = geo.mesh_topology(mesh.faces).face_pairs
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    cross = la != lb
    la, lb = la[cross], lb[cross]
    top = int(max(labels.max(initial=0), max(kinds, default=0))) + 1
    kind_code = np.zeros(top, np.int64)  # 0 stem/other, 1 leaf, 2 debris
    for k, kind in kinds.items():
        if 0 <= k < top:
            kind_code[k] = 1 if kind == "leaf" else 2 if kind == "debris" else 0
    edge = np.zeros(3 * top)  # counts: whole numbers, exact in any order
    for a, b in ((la, lb), (lb, la)):
        ok = (a >= 0) & (b >= 0)
        edge += np.bincount(3 * a[ok] + kind_code[b[ok]], minlength=3 * top)
    extents = dict(zip(leaf_ids, _extents(mesh, labels, leaf_ids)))
    return PlantContext(z0, max(z1 - z0, 1e-9), axis, radius, edge.reshape(top, 3), stem_tree,
                        extents)


def leaf_features(traits, measurements, labelled, unit_mm: float,
                  context: PlantContext | None = None) -> np.ndarray:
    """(n, len(FEATURE_NAMES)) features of the measured leaves (``measurements`` order).

    ``traits``: the plant's ``Traits`` (its ``plant`` dict gives height and total leaf
    area); ``labelled``: the ``LabelledMesh`` measured; ``unit_mm``: its mesh unit;
    ``context``: ``plant_context(labelled, ...)`` of these leaves when the caller has it.
    """
    n = len(measurements)
    x = np.full((n, len(FEATURE_NAMES)), np.nan)
    if not n:
        return x
    ids = [m.traits.leaf_id for m in measurements]
    c = context if context is not None else plant_context(labelled, ids)
    z0, height, axis, radius, edge, stem_tree = (c.z0, c.height, c.axis, c.radius, c.edge,
                                                 c.stem_tree)
    top = len(edge)
    extents = np.array([c.extents[i] for i in ids], float)
    areas = np.array([m.traits.area_mm2 for m in measurements], float)
    total = float(traits.plant.get("total_leaf_area_mm2", areas.sum())) or float(areas.sum())
    median_area = float(np.median(areas)) if len(areas) else 1.0
    plant_height = float(traits.plant.get("height_mm", height)) or height
    for i, m in enumerate(measurements):
        t = m.traits
        length, width, area, perim = t.length_mm, t.width_mm, t.area_mm2, t.perimeter_mm
        ev = labelled.evidence.get(t.leaf_id) or {}
        e = edge[t.leaf_id] if 0 <= t.leaf_id < top else np.zeros(3)
        es = max(e.sum(), 1.0)
        base, tip = np.asarray(m.base, float), np.asarray(m.tip, float)
        x[i] = (
            width / length if length > 0 else np.nan,
            area / (length * width) if length * width > 0 else np.nan,
            perim / length if length > 0 else np.nan,
            perim * perim / area if area > 0 else np.nan,
            perim / _ellipse_perimeter(length, width) if length > 0 else np.nan,
            extents[i] / length if length > 0 else np.nan,
            (float(stem_tree.query(base)[0]) / length if stem_tree is not None and length > 0
             else np.nan),
            float(np.linalg.norm(tip - base)) / length if length > 0 else np.nan,
            t.thick_share,
            m.info.get("median_thickness_mm", np.nan) / unit_mm,
            np.sqrt(max(area, 0.0)) / unit_mm,
            np.log(area / median_area) if area > 0 and median_area > 0 else np.nan,
            area / total if total > 0 else np.nan,
            length / plant_height if plant_height > 0 else np.nan,
            n,
            (base[2] - z0) / height,
            (tip[2] - z0) / height,
            float(np.hypot(*(base[:2] - axis))) / radius,
            float(np.hypot(*(tip[:2] - axis))) / radius,
            e[0] / es, e[1] / es, e[2] / es,
            ev.get("fragments", 1),
            ev.get("weakest_merge", 1.0),
        )
    return x


def _ellipse_perimeter(length: float, width: float) -> float:
    """Ramanujan's perimeter of the ellipse with axes ``length`` and ``width``."""
    a, b = length / 2.0, width / 2.0
    h = ((a - b) / (a + b)) ** 2 if a + b > 0 else 0.0
    return float(np.pi * (a + b) * (1.0 + 3.0 * h / (10.0 + np.sqrt(4.0 - 3.0 * h))))


def _extents(mesh, labels: np.ndarray, leaf_ids: list[int]) -> np.ndarray:
    """Each leaf's range along its vertices' principal axis, mm."""
    out = np.full(len(leaf_ids), np.nan)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], [(i, i + 1) for i in leaf_ids])
    used = np.zeros(len(mesh.vertices), bool)
    for k, (lo, hi) in enumerate(bounds):
        if hi - lo < 3:
            continue
        used[:] = False
        used[mesh.faces[order[lo:hi]].ravel()] = True  # a mask, not np.unique: no sort
        pts = mesh.vertices[used]
        c = pts - pts.mean(axis=0)
        axis = np.linalg.eigh(c.T @ c)[1][:, 2]
        proj = c @ axis
        out[k] = float(proj.max() - proj.min())
    return out


@dataclass
class TrustModel:
    booster: object
    config: dict
    config_sha256: str

    def p_bad(self, x: np.ndarray) -> np.ndarray:
        """(n,) probability that each leaf's traits are wrong (``CLASS_NAMES[1]``)."""
        if not len(x):
            return np.zeros(0)
        return np.asarray(self.booster.predict(np.asarray(x, np.float64), num_threads=1))

    @property
    def cut(self) -> float:
        """The p_bad at which a leaf is low-confidence, chosen on the development plants
        (``scripts/train_trust_model.py``, ``choose_cut``); 0.5 for a model without one."""
        return float(self.config.get("cut", 0.5))

    def doubt(self, x: np.ndarray) -> np.ndarray:
        """(n,) ``p_bad`` rescaled so that the model's ``cut`` falls on 0.5 (piecewise
        linear, monotone, 0 and 1 kept): 1 - doubt is the leaf's confidence, low under 0.5
        when p_bad reaches the cut (the confidence is kept to 3 decimals: a p_bad within
        0.002 of the cut may round to 0.500, not low)."""
        p, c = self.p_bad(x), self.cut
        return np.where(p < c, 0.5 * p / c, 0.5 + 0.5 * (p - c) / (1.0 - c))

    def why(self, x: np.ndarray, top: int = 2) -> list[list[str]]:
        """Per leaf, the ``top`` features that raised ``p_bad`` most (SHAP contributions)."""
        if not len(x):
            return []
        c = np.asarray(self.booster.predict(np.asarray(x, np.float64), pred_contrib=True,
                                            num_threads=1))[:, :len(FEATURE_NAMES)]
        out = []
        for row in c:
            order = [j for j in np.argsort(-row)[:top] if row[j] > 0]
            out.append([FEATURE_NAMES[j] for j in order])
        return out


@lru_cache(maxsize=4)
def load_model(path: str) -> TrustModel:
    """The trust model ``path`` names (a file name: shipped in ``plantscan_leaves/models``;
    else a path).  Loaded once per process and path."""
    from plantscan_leaves.pieces import read_model

    booster, body = read_model(path, path, FEATURE_NAMES, "trust model",
                               "plantscan_leaves.trust_model", "scripts/train_trust_model.py")
    return TrustModel(booster, body["config"], body["config_sha256"])

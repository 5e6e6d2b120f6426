"""Leaf traits of a run against the virtual scanner's truth (``plantscan evaluate``).

Measured leaves are the leaf labels of ``run_dir/labelled.npz``; truth leaves
are the ``face_leaf_id`` groups of ``truth_dir/plant.npz`` (-1 = stem).  The
two meshes are in the same (turntable) frame but are different surfaces (the
hull encloses the true leaf), so overlap is measured by nearest faces:

* every truth face takes the label of the nearest measured face;
  ``cover[t, m]`` = fraction of truth leaf ``t``'s area whose nearest
  measured face belongs to measured leaf ``m``;
* truth and measured leaves are paired one to one maximising total cover
  (Hungarian algorithm); a pair counts when its cover is >= 0.5 (PAIR_COVER):
  the truth leaf is *found*, the measured leaf *matched*;
* a truth leaf is *missed* when it has no pair;
* a measured leaf is *merged* when it covers >= 0.3 (MERGE_COVER) of two or
  more truth leaves (one measured leaf holding two);
* a truth leaf is *split* when two or more measured leaves each cover >= 0.1
  (SPLIT_COVER) of it (found or not); an unpaired measured leaf covering
  >= 0.1 of some truth leaf is one of its *split pieces*;
* a measured leaf that is neither matched nor a split piece is *extra* (it
  matches no truth leaf); the measured area of the extra leaves is the
  *debris area*, said with where each lies (every measured face takes the
  truth organ of the nearest truth face: on a leaf, on the stem, or off the
  plant when that face is farther than ``OFF_PLANT_UNITS`` mesh units).

"12 of 12 found" thus stands beside the pieces that are no leaf: recall =
found / truth leaves, precision = matched / measured leaves.  Errors use the
seed's ε = mean(|truth − measured| / truth) over the pairs.

A calibration fixes the turntable frame only up to its gauge (a rotation about
the axis and a shift along it).  Whether the run's mesh is in the truth's frame
is judged from the truth's side: the median distance from the truth's surface
to the nearest mesh face, in units of the mesh's sampling (``mesh_unit``, about
a voxel).  In the right frame the hull encloses the true surface and touches it
where the views carve, so that median is a voxel or two; the other direction
(mesh to truth) is not used, because pot remnants, the uncarved cone over the
pot's opening or phantom volume put most of a small plant's mesh millimetres
off the plant in the right frame (seedling seed 1000 with the cone kept: 75 %
of the faces, median 7.9 mm, against 0.08 mm from the truth's side).  When the
median exceeds ``GAUGE_TOLERANCE_UNITS``, the rotation about +Z and the
shift that best bring the truth onto the mesh are searched (turns every
5 degrees, then ICP), and used only when they bring the truth clearly closer
(``GAUGE_GAIN``); the search and whether it was applied are reported as
``frame_alignment``.  Every length here is relative to the mesh unit or to the
truth plant's size, so a plant scaled down with its voxel is matched as at
full size.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from plantscan_core.data import TRAIT_NAMES, LabelledMesh, Traits, mean_relative_error, rotation_z
from plantscan_core.errors import DataError
from plantscan_leaves import geometry as geo
from plantscan_leaves.measure import warned

PAIR_COVER = 0.5  # more than half of a truth leaf must be in its measured leaf
MERGE_COVER = 0.3  # a measured leaf holding 30 % of each of two truth leaves merged them
SPLIT_COVER = 0.1  # a piece holding a tenth of a truth leaf is part of it, not debris
# a measured face this many mesh units from every truth face lies on no organ (5 mm at the
# population dicot's 0.77 mm unit, where the rule was set)
OFF_PLANT_UNITS = 6.5
# the truth's surface lies within a voxel or two of a hull in its frame (median over the
# truth's faces); past 4 units the frame is suspect and the gauge is searched
GAUGE_TOLERANCE_UNITS = 4.0
# the searched gauge replaces the run's frame only when it halves that median: a search
# that pulls the mesh's debris onto the plant instead leaves the truth farther away
GAUGE_GAIN = 0.5
# the turn search scores distances up to this share of the plant's size (far misses only
# need to count as far; the median decides); ICP pairs points up to a tenth of it
SEARCH_BOUND_SHARE = 0.25
ICP_PAIR_SHARE = 0.1


def align_gauge(points: np.ndarray, truth_points: np.ndarray) -> tuple[np.ndarray, dict]:
    """(4, 4) transform taking ``points`` onto ``truth_points`` within the turntable gauge.

    The truth is brought onto the mesh (``points``), not the other way: every
    true surface has hull nearby in the right frame, while the hull has surface
    that is no plant (pot remnants, phantom volume) which would otherwise be
    pulled onto the plant.  Tries rotations about +Z every 5 degrees and vertical
    shifts over the overlap of the two height ranges, keeps the best by median
    nearest distance, refines the rigid
    transform by point-to-point ICP (Open3D) and returns its inverse.  Distances
    are bounded relative to the truth plant's size (``SEARCH_BOUND_SHARE``,
    ``ICP_PAIR_SHARE``).

    Returns
    -------
    transform : (4, 4) float64 array, mesh frame -> truth frame
    info : dict with ``yaw_deg``, ``translation_mm`` (of ``transform``) and
        ``median_distance_mm`` (truth to the moved mesh, median).
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    sample = truth_points[rng.choice(len(truth_points), min(len(truth_points), 4000),
                                     replace=False)]
    size = float(np.linalg.norm(np.ptp(truth_points, axis=0)))
    bound = SEARCH_BOUND_SHARE * size
    tree = cKDTree(points)
    # vertical shifts over every overlap of the two height ranges, at half ICP's reach: no
    # single statistic of height is safe (pot remnants pull the mesh's low ones, an
    # off-plant piece its high ones)
    step = 0.5 * ICP_PAIR_SHARE * size
    lo = points[:, 2].min() - truth_points[:, 2].max()
    hi = points[:, 2].max() - truth_points[:, 2].min()
    shifts = np.arange(lo, hi + step, step)
    coarse = sample[:1000]  # the median of 1000 distances is plenty to rank the turns
    best = (np.inf, 0.0, 0.0)
    for deg in np.arange(0.0, 360.0, 5.0):
        turned = coarse @ rotation_z(deg).T
        for dz in shifts:
            d, _ = tree.query(turned + [0.0, 0.0, dz], distance_upper_bound=bound)
            best = min(best, (float(np.median(np.minimum(d, bound))), deg, dz))
    init = np.eye(4)
    init[:3, :3] = rotation_z(best[1])
    init[2, 3] = best[2]
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        points[rng.choice(len(points), min(len(points), 20000), replace=False)]))
    reg = o3d.pipelines.registration.registration_icp(
        src, dst, ICP_PAIR_SHARE * size, init,
        o3d.pipelines.registration.TransformationEstimationPointToPoint())
    truth_to_mesh = np.asarray(reg.transformation)
    t = np.linalg.inv(truth_to_mesh)
    residual = float(np.median(tree.query(sample @ truth_to_mesh[:3, :3].T
                                          + truth_to_mesh[:3, 3])[0]))
    return t, {"yaw_deg": float(np.degrees(np.arctan2(t[1, 0], t[0, 0]))),
               "translation_mm": t[:3, 3].round(3).tolist(), "median_distance_mm": residual}


def gauge_frame(mesh_points: np.ndarray, truth_points: np.ndarray, unit_mm: float
                ) -> tuple[np.ndarray, dict | None]:
    """``mesh_points`` in the truth's frame, and the ``frame_alignment`` report (None when
    the run's frame was in tolerance and no search was made); rules in the module docstring.

    ``mesh_points`` : (N, 3) float array, mm, the run's turntable frame; ``unit_mm`` the
    mesh unit (``geometry.mesh_unit``).
    """
    from scipy.spatial import cKDTree

    probe = truth_points[:: max(1, len(truth_points) // 4000)]
    before = float(np.median(cKDTree(mesh_points).query(probe)[0]))
    if before <= GAUGE_TOLERANCE_UNITS * unit_mm:
        return mesh_points, None
    transform, info = align_gauge(mesh_points, truth_points)
    moved = mesh_points @ transform[:3, :3].T + transform[:3, 3]
    after = float(np.median(cKDTree(moved).query(probe)[0]))
    applied = after <= GAUGE_GAIN * before
    info.update(applied=applied, median_distance_before_mm=before, unit_mm=unit_mm)
    return (moved if applied else mesh_points), info


def match_leaves(labelled: LabelledMesh, truth_vertices: np.ndarray, truth_faces: np.ndarray,
                 truth_leaf_id: np.ndarray) -> dict[str, Any]:
    """Pair measured leaves with truth leaves by surface overlap.

    Returns
    -------
    dict with ``pairs`` (list of (truth id, measured label, cover)),
    ``merged`` (measured labels holding several truth leaves), ``missed``
    (truth ids without a pair), ``split`` ({truth id: measured labels each
    covering >= SPLIT_COVER of it}, two or more), ``split_pieces`` (unpaired
    measured labels covering >= SPLIT_COVER of a truth leaf), ``extra``
    (measured leaves neither paired nor split pieces), ``lies_on`` ({measured
    label: shares of its mesh area on truth leaves, stem, off the plant}),
    ``cover`` (truth ids x measured labels matrix as nested lists); rules in
    the module docstring.
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    truth_ids = sorted(int(i) for i in np.unique(truth_leaf_id) if i >= 0)
    leaf_labels = labelled.leaf_labels
    out: dict[str, Any] = {"pairs": [], "merged": [], "missed": list(truth_ids),
                           "extra": list(leaf_labels), "split": {}, "split_pieces": [],
                           "lies_on": {}, "truth_ids": truth_ids,
                           "measured_labels": leaf_labels}
    if not truth_ids or not leaf_labels or labelled.mesh.is_empty:
        return out
    mc = geo.face_centroids(labelled.mesh.vertices, labelled.mesh.faces)
    tc = geo.face_centroids(truth_vertices, truth_faces)
    unit = geo.mesh_unit(labelled.mesh.vertices, labelled.mesh.faces)
    mc, alignment = gauge_frame(mc, tc, unit)
    if alignment is not None:
        out["frame_alignment"] = alignment
    v = truth_vertices[truth_faces]
    t_area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    _, nearest = cKDTree(mc).query(tc)
    label_of_truth_face = labelled.face_labels[nearest]
    col = {lab: j for j, lab in enumerate(leaf_labels)}
    cover = np.zeros((len(truth_ids), len(leaf_labels)))
    for i, tid in enumerate(truth_ids):
        sel = truth_leaf_id == tid
        total = t_area[sel].sum()
        labs, inv = np.unique(label_of_truth_face[sel], return_inverse=True)
        sums = np.bincount(inv, t_area[sel])
        for lab, s in zip(labs, sums):
            if int(lab) in col:
                cover[i, col[int(lab)]] = s / max(total, 1e-12)
    rows, cols = linear_sum_assignment(-cover)
    pairs = [(truth_ids[r], leaf_labels[c], float(cover[r, c]))
             for r, c in zip(rows, cols) if cover[r, c] >= PAIR_COVER]
    paired_t = {p[0] for p in pairs}
    paired_m = {p[1] for p in pairs}
    to_stem = ~np.isin(label_of_truth_face, leaf_labels)  # stem, pot or unlabelled
    split = {truth_ids[i]: [leaf_labels[j] for j in np.flatnonzero(cover[i] >= SPLIT_COVER)]
             for i in range(len(truth_ids)) if np.count_nonzero(cover[i] >= SPLIT_COVER) >= 2}
    pieces = [m for j, m in enumerate(leaf_labels)
              if m not in paired_m and cover[:, j].max() >= SPLIT_COVER]
    out.update(
        area_shares=_area_shares(truth_ids, truth_leaf_id, t_area, to_stem, cover, pairs,
                                 leaf_labels),
        pairs=pairs,
        merged=[leaf_labels[j] for j in range(len(leaf_labels))
                if np.count_nonzero(cover[:, j] >= MERGE_COVER) >= 2],
        missed=[t for t in truth_ids if t not in paired_t],
        split=split,
        split_pieces=pieces,
        extra=[m for m in leaf_labels if m not in paired_m and m not in pieces],
        lies_on=_lies_on(labelled, mc, tc, truth_leaf_id, leaf_labels, unit),
        cover=cover.round(4).tolist(),
    )
    return out


def _lies_on(labelled: LabelledMesh, mc: np.ndarray, tc: np.ndarray,
             truth_leaf_id: np.ndarray, leaf_labels: list[int], unit_mm: float
             ) -> dict[int, dict[str, float]]:
    """Shares of each measured leaf's mesh area on truth leaves, the stem, off the plant.

    Every measured face takes the organ of the nearest truth face (``mc`` and
    ``tc`` are face centroids in the truth's frame); off the plant beyond
    ``OFF_PLANT_UNITS`` mesh units (``unit_mm``).
    """
    from scipy.spatial import cKDTree

    dist, nearest = cKDTree(tc).query(mc)
    on_leaf = truth_leaf_id[nearest] >= 0
    off = dist > OFF_PLANT_UNITS * unit_mm
    area = labelled.mesh.face_areas()
    out = {}
    for m in leaf_labels:
        sel = labelled.face_labels == m
        total = max(float(area[sel].sum()), 1e-12)
        out[m] = {"leaf": float(area[sel & on_leaf & ~off].sum()) / total,
                  "stem": float(area[sel & ~on_leaf & ~off].sum()) / total,
                  "off_plant": float(area[sel & off].sum()) / total}
    return out


def instance_counts(match: dict[str, Any], measured: Traits) -> dict[str, Any]:
    """Found / missed / merged / split / extra counts, debris area, recall and precision.

    ``match`` is ``match_leaves``' result; ``measured`` the run's traits (its
    leaf areas are the debris area's unit: flat leaf area, mm², as in traits.csv).
    """
    area = {lf.leaf_id: lf.area_mm2 for lf in measured.leaves}
    n_truth, n_measured = len(match["truth_ids"]), len(match["measured_labels"])
    found = len(match["pairs"])
    debris = [{"measured_id": m, "area_mm2": round(float(area.get(m, 0.0)), 3),
               **{k: round(v, 4) for k, v in match["lies_on"].get(m, {}).items()}}
              for m in match["extra"]]
    debris_area = float(sum(d["area_mm2"] for d in debris))
    total = float(sum(area.get(m, 0.0) for m in match["measured_labels"]))
    return {
        "truth": n_truth, "measured": n_measured, "found": found,
        "missed": len(match["missed"]), "merged": len(match["merged"]),
        "split": len(match["split"]), "split_pieces": len(match["split_pieces"]),
        "extra": len(match["extra"]),
        "recall": found / n_truth if n_truth else float("nan"),
        "precision": found / n_measured if n_measured else float("nan"),
        "debris_area_mm2": debris_area,
        "debris_share": debris_area / total if total > 0 else 0.0,
        "missed_ids": list(match["missed"]),
        "merged_ids": list(match["merged"]),
        "split_ids": {str(t): ms for t, ms in match["split"].items()},
        "extra_pieces": debris,
    }


def _area_shares(truth_ids: list[int], truth_leaf_id: np.ndarray, t_area: np.ndarray,
                 to_stem: np.ndarray, cover: np.ndarray, pairs: list[tuple[int, int, float]],
                 leaf_labels: list[int]) -> list[dict[str, Any]]:
    """Where each truth leaf's surface went: its own (paired) leaf, the stem (any label
    that is not a leaf), other leaves.

    Shares of the truth leaf's area by the label of the nearest measured face
    (the same attribution as the pairing); they sum to 1.  A leaf measured too
    short usually shows a stem share (its base or petiole end went to the
    stem), a leaf that lost a piece to a neighbour an other-leaves share.
    """
    col = {lab: j for j, lab in enumerate(leaf_labels)}
    mate = {t: m for t, m, _ in pairs}
    rows = []
    for i, tid in enumerate(truth_ids):
        sel = truth_leaf_id == tid
        total = max(float(t_area[sel].sum()), 1e-12)
        own = float(cover[i, col[mate[tid]]]) if tid in mate else 0.0
        stem = float(t_area[sel & to_stem].sum()) / total
        other = float(cover[i].sum()) - own
        rows.append({"truth_id": tid, "measured_id": mate.get(tid), "own": round(own, 4),
                     "stem": round(stem, 4), "other_leaves": round(other, 4)})
    return rows


def trait_errors(truth: Traits, measured: Traits, pairs: list[tuple[int, int, float]]
                 ) -> dict[str, Any]:
    """Per-trait ε over the matched pairs, plus the per-leaf table."""
    t_by = {leaf.leaf_id: leaf for leaf in truth.leaves}
    m_by = {leaf.leaf_id: leaf for leaf in measured.leaves}
    used = [(t_by[t], m_by[m]) for t, m, _ in pairs if t in t_by and m in m_by]
    errors = {name: mean_relative_error([t.trait(name) for t, _ in used],
                                        [m.trait(name) for _, m in used])
              for name in TRAIT_NAMES}
    finite = [e for e in errors.values() if np.isfinite(e)]
    errors["all"] = float(np.mean(finite)) if finite else float("nan")
    per_leaf = [
        {"truth_id": t.leaf_id, "measured_id": m.leaf_id,
         **{f"{name}_truth": t.trait(name) for name in TRAIT_NAMES},
         **{f"{name}_measured": m.trait(name) for name in TRAIT_NAMES},
         "thick_share": None if np.isnan(m.thick_share) else m.thick_share}
        for t, m in used
    ]
    return {"mean_relative_error": errors, "per_leaf": per_leaf, "pairs_measured": len(used)}


def evaluate_traits(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    """The ``traits`` section of ``plantscan evaluate``, or None when either side is absent."""
    run_dir, truth_dir = Path(run_dir), Path(truth_dir)
    needed = [run_dir / "labelled.npz", run_dir / "traits.csv", truth_dir / "plant.npz",
              truth_dir / "traits.csv"]
    if not all(p.exists() for p in needed):
        return None
    try:
        labelled = LabelledMesh.load(run_dir / "labelled.npz")
        with np.load(truth_dir / "plant.npz") as z:
            tv, tf, tid = z["vertices"], z["faces"], z["face_leaf_id"]
        measured = Traits.load(run_dir / "traits.csv")
        truth = Traits.load(truth_dir / "traits.csv")
    except (KeyError, ValueError, OSError) as exc:
        raise DataError(f"{run_dir} / {truth_dir}: cannot read leaves or truth ({exc})") from exc
    m = match_leaves(labelled, tv, tf, tid)
    errs = trait_errors(truth, measured, m["pairs"])
    # the same over the leaves the measurer did not warn about (phantom volume, or a
    # perimeter too short for the length): what its warnings buy a user who sets them aside
    said = {lf.leaf_id for lf in measured.leaves if warned(lf)}
    unwarned = [p for p in m["pairs"] if p[1] not in said]
    quiet = trait_errors(truth, measured, unwarned)["mean_relative_error"]
    plant = plant_errors(run_dir / "plant_traits.json", truth_dir / "plant_traits.json",
                         from_rim=labelled.mesh.base_z_mm is not None)
    counts = instance_counts(m, measured)
    return {
        "traits": {
            "instances": counts,
            "mean_relative_error": errs["mean_relative_error"],
            "mean_relative_error_unwarned": quiet,
            "leaves_warned": len(m["pairs"]) - len(unwarned),
            "leaves_found": len(m["pairs"]),
            "leaves_truth": len(m["truth_ids"]),
            "leaves_measured": len(m["measured_labels"]),
            "leaves_merged": len(m["merged"]),
            "leaves_missed": len(m["missed"]),
            "leaves_split": len(m["split"]),
            "leaves_extra": len(m["extra"]),
            "debris_area_mm2": counts["debris_area_mm2"],
            **({"frame_alignment": m["frame_alignment"]} if "frame_alignment" in m else {}),
            "pairs": [{"truth_id": t, "measured_id": mm, "cover": c} for t, mm, c in m["pairs"]],
            "per_leaf": errs["per_leaf"],
            "area_shares": m.get("area_shares", []),
            **({"plant": plant} if plant else {}),
        }
    }


PLANT_TRAITS = ("height_mm", "total_leaf_area_mm2", "leaf_count")


def plant_errors(measured_path: Path, truth_path: Path,
                 from_rim: bool = False) -> dict[str, Any] | None:
    """Plant-level traits against the truth: measured, truth and relative error of each.

    The truth's ``height_mm`` is from the soil, which a hull cannot see inside an opaque
    pot.  ``from_rim``: the measured height is above the pot's rim (the mesher removed a
    pot), so it is compared with the truth's top above the truth pot's rim (``pot.yaml``
    beside ``truth_path``; without it, with the height from the soil).
    """
    try:
        measured = json.loads(measured_path.read_text())
        truth = json.loads(truth_path.read_text())
    except (OSError, ValueError):
        return None
    rim = _truth_rim_z(truth_path.parent / "pot.yaml") if from_rim else None
    if rim is not None and "top_z_mm" in truth:
        truth = {**truth, "height_mm": truth["top_z_mm"] - rim}
    out: dict[str, Any] = {}
    for name in PLANT_TRAITS:
        if name in measured and name in truth and truth[name]:
            out[name] = {"measured": measured[name], "truth": truth[name],
                         "error": measured[name] - truth[name],
                         "relative_error": (measured[name] - truth[name]) / truth[name]}
    return out or None


def _truth_rim_z(pot_path: Path) -> float | None:
    """The truth pot's rim height (mm) from the virtual scanner's ``pot.yaml``, or None."""
    try:
        import yaml

        return float(yaml.safe_load(pot_path.read_text())["pot"]["z_top_mm"])
    except (OSError, ValueError, KeyError, TypeError):
        return None

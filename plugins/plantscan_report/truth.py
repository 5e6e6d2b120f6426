"""Measured leaves against the virtual scanner's truth leaves (for the report's plots).

Leaf ids of a run are arbitrary, so measured leaves are matched to truth leaves
by geometry when both meshes exist: the centroid of each measured leaf's faces
against the centroid of each truth leaf (``ground_truth/plant.npz``, same
turntable frame), one-to-one by the Hungarian algorithm, a pair kept only when
the centroids are closer than half the truth leaf's length (a leaf further away
than that is not the same leaf).  Without meshes, leaves are paired by id.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from plantscan_core.data import LabelledMesh, LeafTraits, Traits


@dataclass
class LeafMatch:
    """Pairs of (measured, truth) leaves and how they were paired."""

    pairs: list[tuple[LeafTraits, LeafTraits]]
    method: str
    unmatched_measured: int
    unmatched_truth: int


def read_truth_traits(truth_dir: Path) -> Traits | None:
    """``ground_truth/traits.csv`` (+ ``plant_traits.json``) or None when absent."""
    path = Path(truth_dir) / "traits.csv"
    if not path.exists():
        return None
    return Traits.load(path, Path(truth_dir) / "plant_traits.json")


def _truth_leaf_centroids(truth_dir: Path) -> dict[int, np.ndarray] | None:
    path = Path(truth_dir) / "plant.npz"
    if not path.exists():
        return None
    with np.load(path) as z:
        vertices, faces, leaf_id = z["vertices"], z["faces"], z["face_leaf_id"]
    return _centroids(vertices, faces, leaf_id)


def _centroids(vertices: np.ndarray, faces: np.ndarray,
               labels: np.ndarray) -> dict[int, np.ndarray]:
    """Area-weighted centroid (3,) mm of each label's faces."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    centre = tri.mean(axis=1)
    out = {}
    for label in np.unique(labels):
        sel = labels == label
        w = area[sel]
        out[int(label)] = (centre[sel] * w[:, None]).sum(0) / max(w.sum(), 1e-12)
    return out


def match_leaves(measured: Traits, truth: Traits, labelled: LabelledMesh | None,
                 truth_dir: Path) -> LeafMatch:
    """Pair measured leaves with truth leaves (see the module docstring)."""
    truth_by_id = {leaf.leaf_id: leaf for leaf in truth.leaves}
    measured_by_id = {leaf.leaf_id: leaf for leaf in measured.leaves}
    truth_centroids = _truth_leaf_centroids(truth_dir) if labelled is not None else None
    if labelled is not None and truth_centroids is not None:
        ours = _centroids(labelled.mesh.vertices, labelled.mesh.faces, labelled.face_labels)
        m_ids = [i for i in measured_by_id if i in ours]
        t_ids = [i for i in truth_by_id if i in truth_centroids]
        if m_ids and t_ids:
            cost = np.array([[np.linalg.norm(ours[m] - truth_centroids[t]) for t in t_ids]
                             for m in m_ids])
            rows, cols = linear_sum_assignment(cost)
            pairs = [(measured_by_id[m_ids[r]], truth_by_id[t_ids[c]]) for r, c in zip(rows, cols)
                     if cost[r, c] < 0.5 * truth_by_id[t_ids[c]].length_mm]
            return LeafMatch(pairs, "nearest leaf centroid (Hungarian)",
                             len(measured.leaves) - len(pairs), len(truth.leaves) - len(pairs))
    pairs = [(measured_by_id[i], truth_by_id[i]) for i in sorted(measured_by_id)
             if i in truth_by_id]
    return LeafMatch(pairs, "same leaf id", len(measured.leaves) - len(pairs),
                     len(truth.leaves) - len(pairs))

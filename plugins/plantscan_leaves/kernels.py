"""Compiled (numba) loops of the leaf stages, each tested against its plain reference.

``fork_branches``: the persistence filtration of ``segment._split_forked_leaves`` (a
union-find over one leaf's faces, farthest from its base first).  The reference,
``fork_branches_reference``, keeps each part's member list and is the one to read; the
kernel records the merge tree instead (each union a new node, a branch a marked node, a
face's branch its lowest marked ancestor) and gives the same branches, numbered in the
same order (``tests/leaves/test_segment.py``).  On a grass plant's leaves (0.5-0.9 M
faces) the reference costs 3-9 s, the kernel a fraction of a second.  Without numba
the reference runs.
"""

from __future__ import annotations

import numpy as np

try:  # numba is optional: the reference is complete without it
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False


def fork_branches_reference(order: np.ndarray, dist: np.ndarray, indptr: np.ndarray,
                            indices: np.ndarray, centroids: np.ndarray, areas: np.ndarray,
                            min_area: float, min_reach: float) -> np.ndarray:
    """(N,) branch of every face (0: none), 1.. in the order the branches formed.

    Faces join in ``order`` (the others never do); a face joining two parts that each
    hold ``min_area`` (``areas`` summed), reach ``min_reach`` beyond its ``dist`` (their
    largest ``dist``) and lie the same way from it (their area-weighted centroids'
    offsets from its centroid have a positive dot product) makes each part's faces not
    yet in a branch a new branch.  The face graph is CSR (``indptr``, ``indices``)."""
    n = len(dist)
    parent = np.arange(n)
    size = areas.astype(np.float64).copy()
    reach = dist.astype(np.float64).copy()
    csum = centroids * areas[:, None]
    members: dict[int, list[int]] = {i: [i] for i in range(n)}
    added = np.zeros(n, bool)
    branch = np.zeros(n, np.int64)
    n_branch = 0

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for f in order:
        added[f] = True
        for g in indices[indptr[f]:indptr[f + 1]]:
            if not added[g]:
                continue
            rf, rg = find(f), find(g)
            if rf == rg:
                continue
            if (size[rf] >= min_area and size[rg] >= min_area
                    and min(reach[rf], reach[rg]) - dist[f] >= min_reach
                    and (csum[rf] / size[rf] - centroids[f])
                    @ (csum[rg] / size[rg] - centroids[f]) > 0):
                for r in (rf, rg):
                    m = np.asarray(members[r])
                    m = m[branch[m] == 0]
                    if len(m):
                        n_branch += 1
                        branch[m] = n_branch
            if len(members[rf]) < len(members[rg]):
                rf, rg = rg, rf
            parent[rg] = rf
            size[rf] += size[rg]
            reach[rf] = max(reach[rf], reach[rg])
            csum[rf] += csum[rg]
            members[rf].extend(members.pop(rg))
    return branch


if HAVE_NUMBA:
    @njit(cache=True)
    def _fork_branches_jit(order, dist, indptr, indices, centroids, areas, min_area,
                           min_reach):  # pragma: no cover - compiled
        n = dist.shape[0]
        parent = np.arange(n)
        count = np.ones(n, np.int64)  # faces per part (the union by size of the reference)
        node = np.arange(n)  # merge-tree node of every part's root
        tree_parent = np.full(2 * n, -1, np.int64)
        mark = np.zeros(2 * n, np.int64)  # the event that made a node a branch (0: none)
        size = areas.astype(np.float64).copy()
        reach = dist.astype(np.float64).copy()
        csum = np.empty((n, 3))
        for i in range(n):
            for k in range(3):
                csum[i, k] = centroids[i, k] * areas[i]
        added = np.zeros(n, np.bool_)
        n_nodes = n
        n_events = 0
        for f in order:
            added[f] = True
            for j in range(indptr[f], indptr[f + 1]):
                g = indices[j]
                if not added[g]:
                    continue
                rf = f
                while parent[rf] != rf:
                    parent[rf] = parent[parent[rf]]
                    rf = parent[rf]
                rg = g
                while parent[rg] != rg:
                    parent[rg] = parent[parent[rg]]
                    rg = parent[rg]
                if rf == rg:
                    continue
                if (size[rf] >= min_area and size[rg] >= min_area
                        and min(reach[rf], reach[rg]) - dist[f] >= min_reach):
                    dot = 0.0
                    for k in range(3):
                        dot += ((csum[rf, k] / size[rf] - centroids[f, k])
                                * (csum[rg, k] / size[rg] - centroids[f, k]))
                    if dot > 0:
                        n_events += 1
                        mark[node[rf]] = 2 * n_events - 1
                        mark[node[rg]] = 2 * n_events
                if count[rf] < count[rg]:
                    rf, rg = rg, rf
                tree_parent[node[rf]] = n_nodes
                tree_parent[node[rg]] = n_nodes
                node[rf] = n_nodes
                n_nodes += 1
                parent[rg] = rf
                count[rf] += count[rg]
                size[rf] += size[rg]
                reach[rf] = max(reach[rf], reach[rg])
                for k in range(3):
                    csum[rf, k] += csum[rg, k]
        # a face's branch: its lowest marked ancestor (parents are made after children)
        assign = np.zeros(n_nodes, np.int64)
        for v in range(n_nodes - 1, -1, -1):
            if mark[v] > 0:
                assign[v] = mark[v]
            elif tree_parent[v] >= 0:
                assign[v] = assign[tree_parent[v]]
        return assign[:n]


def fork_branches(order: np.ndarray, dist: np.ndarray, indptr: np.ndarray,
                  indices: np.ndarray, centroids: np.ndarray, areas: np.ndarray,
                  min_area: float, min_reach: float) -> np.ndarray:
    """``fork_branches_reference``, compiled when numba is there."""
    if not HAVE_NUMBA:
        return fork_branches_reference(order, dist, indptr, indices, centroids, areas,
                                       min_area, min_reach)
    raw = _fork_branches_jit(np.ascontiguousarray(order, np.int64),
                             np.ascontiguousarray(dist, np.float64),
                             np.ascontiguousarray(indptr, np.int64),
                             np.ascontiguousarray(indices, np.int64),
                             np.ascontiguousarray(centroids, np.float64),
                             np.ascontiguousarray(areas, np.float64),
                             float(min_area), float(min_reach))
    # events that found every face of a part already in a branch name no face: renumber
    # the branches that hold faces 1, 2, ... in the order they formed, as the reference
    present = np.unique(raw[raw > 0])
    out = np.zeros(len(raw), np.int64)
    out[raw > 0] = np.searchsorted(present, raw[raw > 0]) + 1
    return out


def grow_reference(labels: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Spread labels into unlabelled (-1) faces ring by ring until nothing changes.

    In each ring every unlabelled face with a labelled neighbour (over ``pairs`` (P, 2))
    takes the largest of its labelled neighbours' labels: the result does not depend on
    the order of the pairs.  The plain reference of ``grow``."""
    labels = labels.copy()
    a, b = pairs[:, 0], pairs[:, 1]
    while True:
        la, lb = labels[a], labels[b]
        # only pairs with an unlabelled face can ever change anything: the others leave
        # (a crease band is crossed in tens of steps, each then over the band's pairs alone)
        open_ = (la < 0) | (lb < 0)
        a, b, la, lb = a[open_], b[open_], la[open_], lb[open_]
        to_a = (la < 0) & (lb >= 0)
        to_b = (lb < 0) & (la >= 0)
        if not (to_a.any() or to_b.any()):
            return labels
        np.maximum.at(labels, a[to_a], lb[to_a])
        np.maximum.at(labels, b[to_b], la[to_b])


if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def _grow_jit(labels, pairs):  # pragma: no cover - compiled
        labels = labels.copy()
        a = pairs[:, 0].copy()
        b = pairs[:, 1].copy()
        reached = labels.copy()  # this ring's labels, read from the ring before
        n = a.shape[0]
        while True:
            changed = False
            k = 0
            for e in range(n):
                la, lb = labels[a[e]], labels[b[e]]
                if la >= 0 and lb >= 0:
                    continue  # closed: drops out, as the reference's
                if la < 0 and lb >= 0:
                    reached[a[e]] = max(reached[a[e]], lb)
                    changed = True
                elif lb < 0 and la >= 0:
                    reached[b[e]] = max(reached[b[e]], la)
                    changed = True
                a[k], b[k] = a[e], b[e]
                k += 1
            n = k
            if not changed:
                return labels
            for e in range(n):
                labels[a[e]] = reached[a[e]]
                labels[b[e]] = reached[b[e]]


def grow(labels: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``grow_reference``, compiled when numba is there (the same labels; a 2.7 M-face
    dicot from one face in a thousand: 2.0 -> 0.66 s; the segmenter's seed-region pass on
    it 0.87 -> 0.44 s)."""
    if not HAVE_NUMBA or not len(pairs):
        return grow_reference(labels, pairs)
    return _grow_jit(np.ascontiguousarray(labels, np.int64),
                     np.ascontiguousarray(pairs, np.int64)).astype(labels.dtype, copy=False)


def warm_up() -> str | None:
    """Compile the kernels now (``plantscan warm-up``): a four-face path, the argument
    types a real run passes (``segment._split_forked_leaves``), then both leaf stages on a
    small mock plant with every learned judge on (the per-face loops of
    ``plantscan_leaves.geometry`` and this module in the types a plant's mesh gives them:
    a few seconds of numba once, not in the first plant's run)."""
    if not HAVE_NUMBA:
        return None
    indptr = np.array([0, 1, 3, 5, 6], np.int64)
    indices = np.array([1, 0, 2, 1, 3, 2], np.int64)
    fork_branches(np.arange(4)[::-1], np.arange(4.0), indptr, indices, np.zeros((4, 3)),
                  np.ones(4), 1.0, 1.0)
    from plantscan_leaves import phantoms
    from plantscan_leaves.measure import measure_plant
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    mesh = phantoms.mock_plant(n_leaves=2).mesh(voxel_mm=1.0)
    params = CurvatureRegionsParams(reference_unit_mm=1.0, judge_pieces=True,
                                    judge_pairs=True, fork_branch_mm=20.0)
    labelled, _ = segment_leaves(mesh, params)
    measure_plant(labelled)
    return "leaf kernels compiled (fork branches, the leaf stages on a mock plant)"

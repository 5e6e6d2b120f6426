"""Vectorised mesh helpers: adjacency, smoothing, curvature, graph distances.

All arrays follow ``plantscan_core.data.Mesh``: vertices ``(V, 3)`` mm,
faces ``(F, 3)`` int64, counter-clockwise seen from outside.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy import sparse


@dataclass
class MeshTopology:
    """Edges and face adjacency of a triangle mesh.

    Attributes
    ----------
    edges : (E, 2) int64, vertex pairs (sorted within a row)
    face_edges : (F, 3) int64, edge index of each face side
    edge_face_count : (E,) int64, faces using each edge (2 = manifold, 1 = border)
    face_pairs : (P, 2) int64, faces sharing an edge (every pair once)
    pair_edge : (P,) int64, the shared edge of each pair
    """

    edges: np.ndarray
    face_edges: np.ndarray
    edge_face_count: np.ndarray
    face_pairs: np.ndarray
    pair_edge: np.ndarray

    @property
    def non_manifold_edges(self) -> int:
        return int(np.count_nonzero(self.edge_face_count > 2))

    @property
    def border_edges(self) -> int:
        return int(np.count_nonzero(self.edge_face_count == 1))


def sort_keys(key: np.ndarray, key_bound: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order, key[order])`` for non-negative int64 keys below ``key_bound``.

    Sorts the keys with each one's index packed into the low bits when they fit
    in 62 bits: a plain sort of one int64 array, about twice as fast as
    ``argsort``.  Equal keys come in any order.
    """
    n = len(key)
    shift = max(n, 1).bit_length()
    # "stable" is numpy's radix/tim sort: 3x faster than quicksort on the long sorted runs
    # of mesh keys (marching cubes emits neighbouring faces together), as fast on random ones
    if key_bound >= 2 ** (62 - shift):
        order = np.argsort(key, kind="stable")
        return order, key[order]
    packed = np.sort((key << shift) | np.arange(n, dtype=np.int64), kind="stable")
    return packed & ((1 << shift) - 1), packed >> shift


DENSE_KEYS_PER_ITEM = 4  # unique_inverse by a table when the key range is at most this x n


def unique_inverse(key: np.ndarray, key_bound: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(key, return_inverse=True)`` for int64 keys below ``key_bound``.

    Compiled by a table of the keys when it is not much longer than the keys (a cell grid's
    keys: 0.10 -> 0.01 s at 2.7 M faces), else one sort of the keys (``sort_keys``)."""
    if HAVE_NUMBA and len(key) and key_bound <= DENSE_KEYS_PER_ITEM * len(key):
        return _dense_unique_kernel(np.ascontiguousarray(key, np.int64), int(key_bound))
    order, k = sort_keys(key, key_bound)
    first = np.empty(len(k), bool)
    first[:1] = True
    first[1:] = k[1:] != k[:-1]
    inverse = np.empty(len(k), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return k[first], inverse


def topology(faces: np.ndarray) -> MeshTopology:
    """Edge list and face adjacency of ``faces`` (F, 3).

    Half-edges sorted by their edge ``(lo, hi)``, ties in half-edge order: edges come
    sorted, a face's pairs in that order.  Compiled (``_topology_kernel``: a counting sort
    by ``lo`` and a short insertion sort by ``hi`` per vertex, no comparison sort of the
    whole list: 1.3 -> 0.1 s at 1.7 M faces, the GIL released for the leaf threads) when
    numba is there; ``topology_reference`` otherwise, the same arrays.
    """
    f = np.asarray(faces, dtype=np.int64)
    if not HAVE_NUMBA or not len(f):
        return topology_reference(f)
    edges, face_edges, counts, pairs, pair_edge = _topology_kernel(np.ascontiguousarray(f))
    return MeshTopology(edges, face_edges, counts, pairs, pair_edge)


def topology_reference(faces: np.ndarray) -> MeshTopology:
    """``topology`` in numpy: one sort of the half-edges' keys (the plain reference the
    compiled kernel is tested against, and the path without numba)."""
    f = np.asarray(faces, dtype=np.int64)
    nf = len(f)
    # half-edge 3 i + k is side k of face i: (f[i, k], f[i, k + 1])
    nxt = np.empty_like(f)
    nxt[:, :2] = f[:, 1:]
    nxt[:, 2] = f[:, 0]
    lo, hi = np.minimum(f, nxt).ravel(), np.maximum(f, nxt).ravel()
    nv = int(f.max()) + 1 if nf else 0
    key = lo * nv + hi
    # one sort does it all: edge ids, each half-edge's edge, and faces grouped by edge
    order, k_sorted = sort_keys(key, nv * nv)  # faces of one edge may come in any order
    first = np.empty(len(k_sorted), bool)
    first[:1] = True
    first[1:] = k_sorted[1:] != k_sorted[:-1]
    e_sorted = np.cumsum(first) - 1
    uniq = k_sorted[first]
    counts = np.diff(np.append(np.flatnonzero(first), len(k_sorted)))
    inverse = np.empty_like(e_sorted)
    inverse[order] = e_sorted
    edges = np.stack([uniq // max(nv, 1), uniq % max(nv, 1)], axis=1)
    face_edges = inverse.reshape(nf, 3)
    f_sorted = order // 3  # the face of each sorted half-edge
    # pairs of consecutive half-edges on the same edge: manifold edges give one pair,
    # a non-manifold edge with k faces gives k-1 pairs (a chain, enough for connectivity)
    same = e_sorted[1:] == e_sorted[:-1]
    pairs = np.stack([f_sorted[:-1][same], f_sorted[1:][same]], axis=1)
    return MeshTopology(edges, face_edges, counts, pairs, e_sorted[1:][same])


try:
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba ships with the project's environment
    HAVE_NUMBA = False

if HAVE_NUMBA:

    @njit(cache=True, nogil=True)
    def _topology_kernel(f):
        """``topology``'s arrays: edges, face_edges, edge face counts, face pairs, pair edges."""
        nf = f.shape[0]
        n = 3 * nf
        nv = 0
        for i in range(nf):
            for k in range(3):
                nv = max(nv, f[i, k] + 1)
        lo = np.empty(n, np.int64)
        hi = np.empty(n, np.int64)
        for i in range(nf):
            for k in range(3):
                a, b = f[i, k], f[i, (k + 1) % 3]
                lo[3 * i + k] = min(a, b)
                hi[3 * i + k] = max(a, b)
        # counting sort by lo (stable), then each vertex's few half-edges by hi (stable)
        start = np.zeros(nv + 1, np.int64)
        for h in range(n):
            start[lo[h] + 1] += 1
        for v in range(nv):
            start[v + 1] += start[v]
        fill = start[:nv].copy()
        order = np.empty(n, np.int64)
        for h in range(n):
            order[fill[lo[h]]] = h
            fill[lo[h]] += 1
        for v in range(nv):
            for s in range(start[v] + 1, start[v + 1]):
                h = order[s]
                key = hi[h]
                t = s - 1
                while t >= start[v] and hi[order[t]] > key:
                    order[t + 1] = order[t]
                    t -= 1
                order[t + 1] = h
        edges = np.empty((n, 2), np.int64)
        counts = np.zeros(n, np.int64)
        face_edges = np.empty(n, np.int64)
        pairs = np.empty((n, 2), np.int64)
        pair_edge = np.empty(n, np.int64)
        ne = 0
        npairs = 0
        for s in range(n):
            h = order[s]
            if s == 0 or lo[h] != lo[order[s - 1]] or hi[h] != hi[order[s - 1]]:
                edges[ne, 0] = lo[h]
                edges[ne, 1] = hi[h]
                ne += 1
            else:  # consecutive half-edges of one edge: a chain of pairs
                pairs[npairs, 0] = order[s - 1] // 3
                pairs[npairs, 1] = h // 3
                pair_edge[npairs] = ne - 1
                npairs += 1
            counts[ne - 1] += 1
            face_edges[h] = ne - 1
        return (edges[:ne].copy(), face_edges.reshape(nf, 3), counts[:ne].copy(),
                pairs[:npairs].copy(), pair_edge[:npairs].copy())

    @njit(cache=True, nogil=True)
    def _averaging_kernel(n, links):
        """``averaging_operator``'s CSR arrays: indptr, indices (descending per row), data."""
        count = np.ones(n, np.int64)  # the identity
        for e in range(links.shape[0]):
            count[links[e, 0]] += 1
            count[links[e, 1]] += 1
        start = np.zeros(n + 1, np.int64)
        for r in range(n):
            start[r + 1] = start[r] + count[r]
        cols = np.empty(start[n], np.int64)
        fill = start[:n].copy()
        for r in range(n):
            cols[fill[r]] = r
            fill[r] += 1
        for e in range(links.shape[0]):
            a, b = links[e, 0], links[e, 1]
            cols[fill[a]] = b
            fill[a] += 1
            cols[fill[b]] = a
            fill[b] += 1
        indptr = np.zeros(n + 1, np.int64)
        indices = np.empty(start[n], np.int64)
        data = np.empty(start[n], np.float64)
        k = 0
        for r in range(n):
            s, e = start[r], start[r + 1]
            for t in range(s + 1, e):  # descending insertion sort of the row's few columns
                c = cols[t]
                u = t - 1
                while u >= s and cols[u] < c:
                    cols[u + 1] = cols[u]
                    u -= 1
                cols[u + 1] = c
            inv = 1.0 / (e - s)  # the degree counts repeated links: entries, not columns
            t = s
            while t < e:
                c = cols[t]
                mult = 0
                while t < e and cols[t] == c:
                    mult += 1
                    t += 1
                indices[k] = c
                data[k] = inv * mult
                k += 1
            indptr[r + 1] = k
        return indptr, indices[:k].copy(), data[:k].copy()

    @njit(cache=True, nogil=True)
    def _pair_csr_kernel(n, pairs):
        """``pair_graph``'s CSR structure: indptr, indices (ascending per row) and the pair
        of every entry."""
        indptr = np.zeros(n + 1, np.int64)
        for e in range(pairs.shape[0]):
            indptr[pairs[e, 0] + 1] += 1
            indptr[pairs[e, 1] + 1] += 1
        for r in range(n):
            indptr[r + 1] += indptr[r]
        fill = indptr[:n].copy()
        first = np.empty(indptr[n], np.int64)  # each row's columns in pair order
        first_of = np.empty(indptr[n], np.int64)
        for e in range(pairs.shape[0]):
            for a, b in ((pairs[e, 0], pairs[e, 1]), (pairs[e, 1], pairs[e, 0])):
                first[fill[a]] = b
                first_of[fill[a]] = e
                fill[a] += 1
        # the transpose, rows visited in ascending order, appends each row's columns in
        # ascending order; the graph is symmetric, so it is the graph again, sorted
        fill[:] = indptr[:n]
        indices = np.empty(indptr[n], np.int64)
        pair_of = np.empty(indptr[n], np.int64)
        for r in range(n):
            for t in range(indptr[r], indptr[r + 1]):
                b = first[t]
                indices[fill[b]] = r
                pair_of[fill[b]] = first_of[t]
                fill[b] += 1
        return indptr, indices, pair_of

    @njit(cache=True, nogil=True)
    def _root(parent, a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]  # path halving
            a = parent[a]
        return a

    @njit(cache=True, nogil=True)
    def _components_kernel(n, pairs, keep):
        """``components``: union-find with the lowest node as every root, then the roots
        numbered in node order (scipy's numbering)."""
        parent = np.arange(n)
        for e in range(pairs.shape[0]):
            a, b = pairs[e, 0], pairs[e, 1]
            if keep[a] and keep[b]:
                ra, rb = _root(parent, a), _root(parent, b)
                if ra < rb:
                    parent[rb] = ra
                elif rb < ra:
                    parent[ra] = rb
        number = np.full(n, -1, np.int64)
        label = np.empty(n, np.int64)
        count = 0
        for v in range(n):
            r = _root(parent, v)
            if number[r] < 0:
                number[r] = count
                count += 1
            label[v] = number[r] if keep[v] else -1
        return label

    @njit(cache=True, nogil=True)
    def _union_kernel(tri, h, w):
        """``triangle_union_mask``'s (H, W + 1) difference array, span by span."""
        diff = np.zeros((h, w + 1), np.int64)
        for t in range(tri.shape[0]):
            ymin = min(tri[t, 0, 1], tri[t, 1, 1], tri[t, 2, 1])
            ymax = max(tri[t, 0, 1], tri[t, 1, 1], tri[t, 2, 1])
            if not ymax > ymin:  # no height, no area
                continue
            r0 = np.int64(max(np.ceil(ymin), 0.0))
            r1 = np.int64(min(np.floor(ymax), float(h - 1)))
            for row in range(r0, r1 + 1):
                fr = float(row)
                lo, hi = np.inf, -np.inf
                for a in range(3):
                    b = (a + 1) % 3
                    xa, ya = tri[t, a, 0], tri[t, a, 1]
                    xb, yb = tri[t, b, 0], tri[t, b, 1]
                    dy = yb - ya
                    if dy != 0 and fr >= min(ya, yb) and fr <= max(ya, yb):
                        x = xa + (fr - ya) * (xb - xa) / dy
                        lo = min(lo, x)
                        hi = max(hi, x)
                if lo == np.inf or hi == -np.inf:
                    continue
                c0 = np.int64(max(np.ceil(lo), 0.0))
                c1 = np.int64(min(np.floor(hi), float(w - 1)))
                if c0 <= c1:
                    diff[row, c0] += 1
                    diff[row, c1 + 1] -= 1
        return diff

    @njit(cache=True, nogil=True)
    def _moments_kernel(lab, m, w, x, floor, centred):
        """``label_moments``: the same products summed in the same (face) order as
        ``np.bincount``, so the same bits, in one or two passes instead of ten."""
        s0 = np.zeros(m)
        s1 = np.zeros((m, 3))
        s2 = np.zeros((m, 3, 3))
        mean = np.zeros((m, 3))
        if centred:
            for i in range(lab.shape[0]):
                k = lab[i]
                s0[k] += w[i]
                for a in range(3):
                    s1[k, a] += w[i] * x[i, a]
            for k in range(m):
                for a in range(3):
                    mean[k, a] = s1[k, a] / max(s0[k], floor)
        for i in range(lab.shape[0]):
            k = lab[i]
            if not centred:
                s0[k] += w[i]
                for a in range(3):
                    s1[k, a] += w[i] * x[i, a]
            for a in range(3):
                da = x[i, a] - mean[k, a]
                for b in range(a, 3):
                    s2[k, a, b] += w[i] * da * (x[i, b] - mean[k, b])
        for k in range(m):
            for a in range(3):
                for b in range(a + 1, 3):
                    s2[k, b, a] = s2[k, a, b]
        return s0, s1, s2

    @njit(cache=True, nogil=True)
    def _face_cross_kernel(v, f):
        """``face_cross`` and its row norms, face by face (no (F, 3) temporaries)."""
        nf = f.shape[0]
        out = np.empty((nf, 3))
        norm = np.empty(nf)
        for i in range(nf):
            p, q, r = f[i, 0], f[i, 1], f[i, 2]
            a0, a1, a2 = v[q, 0] - v[p, 0], v[q, 1] - v[p, 1], v[q, 2] - v[p, 2]
            b0, b1, b2 = v[r, 0] - v[p, 0], v[r, 1] - v[p, 1], v[r, 2] - v[p, 2]
            c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            out[i, 0], out[i, 1], out[i, 2] = c0, c1, c2
            norm[i] = np.sqrt((c0 * c0 + c2 * c2) + c1 * c1)  # as row_norm's einsum
        return out, norm

    @njit(cache=True, nogil=True)
    def _centroids_kernel(v, f):
        """``face_centroids``: the three corners summed in the reference's order."""
        out = np.empty((f.shape[0], 3))
        for i in range(f.shape[0]):
            for k in range(3):
                out[i, k] = (v[f[i, 0], k] + v[f[i, 1], k] + v[f[i, 2], k]) / 3.0
        return out

    @njit(cache=True, nogil=True)
    def _cell_keys_kernel(p, cell):
        """``cell_normal_tensors``' grid: ``lo``, ``dims`` and each point's cell key, as its
        numpy lines compute them (the same numbers), in three passes without temporaries."""
        lo = np.empty(3)
        for k in range(3):
            m = p[0, k]
            for i in range(1, p.shape[0]):
                if p[i, k] < m:
                    m = p[i, k]
            lo[k] = m - cell
        ijk = np.empty((p.shape[0], 3), np.int64)
        dims = np.zeros(3, np.int64)
        for i in range(p.shape[0]):
            for k in range(3):
                ijk[i, k] = np.int64(np.floor((p[i, k] - lo[k]) / cell))
                dims[k] = max(dims[k], ijk[i, k])
        dims += 3
        key = np.empty(p.shape[0], np.int64)
        for i in range(p.shape[0]):
            key[i] = (ijk[i, 0] * dims[1] + ijk[i, 1]) * dims[2] + ijk[i, 2]
        return lo, dims, key

    @njit(cache=True, nogil=True)
    def _dense_unique_kernel(key, bound):
        """``unique_inverse`` by marking the keys in a table of ``bound`` (no sort)."""
        rank = np.zeros(bound, np.int64)
        for x in key:
            rank[x] = 1
        n = 0
        for b in range(bound):
            if rank[b]:
                rank[b] = n
                n += 1
            else:
                rank[b] = -1
        keys = np.empty(n, np.int64)
        inverse = np.empty(key.shape[0], np.int64)
        for i in range(key.shape[0]):
            inverse[i] = rank[key[i]]
            keys[inverse[i]] = key[i]
        return keys, inverse

    @njit(cache=True, nogil=True)
    def _block_sums_kernel(keys, t, offsets):
        """``block_sums_reference``: per offset a merge walk over the sorted keys (the
        needles are sorted too), the rows added in the same order."""
        nc, k = t.shape
        acc = np.zeros((nc, k))
        for off in offsets:
            j = 0
            for i in range(nc):
                q = keys[i] + off
                while j < nc and keys[j] < q:
                    j += 1
                if j < nc and keys[j] == q:
                    for c in range(k):
                        acc[i, c] += t[j, c]
                else:
                    for c in range(k):
                        acc[i, c] += 0.0  # the reference adds an empty cell's zeros
        return acc

    @njit(cache=True, nogil=True)
    def _dijkstra_kernel(indptr, indices, weights, source, limit):
        """``shortest_paths``: scipy's single-source Dijkstra (a node's value set when first
        reached, lowered only by a strictly shorter path, within ``limit``; its distance
        when scanned), on a binary heap with lazy deletion instead of a Fibonacci heap."""
        n = indptr.shape[0] - 1
        dist = np.full(n, np.inf)
        val = np.full(n, np.inf)
        pred = np.full(n, -9999, np.int64)
        state = np.zeros(n, np.int8)  # 0 not in heap, 1 in heap, 2 scanned
        cap = indices.shape[0] + 1
        hv = np.empty(cap)
        hn = np.empty(cap, np.int64)
        size = 0
        hv[0], hn[0], size = 0.0, source, 1
        val[source], state[source] = 0.0, 1
        while size:
            v, node = hv[0], hn[0]
            size -= 1
            hv[0], hn[0] = hv[size], hn[size]
            i = 0
            while True:  # sift down
                c = 2 * i + 1
                if c >= size:
                    break
                if c + 1 < size and hv[c + 1] < hv[c]:
                    c += 1
                if hv[c] < hv[i]:
                    hv[i], hv[c] = hv[c], hv[i]
                    hn[i], hn[c] = hn[c], hn[i]
                    i = c
                else:
                    break
            if state[node] == 2 or v != val[node]:
                continue  # stale: scanned already, or lowered since
            state[node] = 2
            dist[node] = v
            for k in range(indptr[node], indptr[node + 1]):
                u = indices[k]
                if state[u] == 2:
                    continue
                nv = v + weights[k]
                if not nv <= limit:
                    continue
                if state[u] == 0 or val[u] > nv:
                    state[u], val[u], pred[u] = 1, nv, node
                    i = size  # push, sift up
                    hv[i], hn[i] = nv, u
                    size += 1
                    while i > 0:
                        q = (i - 1) // 2
                        if hv[i] < hv[q]:
                            hv[i], hv[q] = hv[q], hv[i]
                            hn[i], hn[q] = hn[q], hn[i]
                            i = q
                        else:
                            break
        for i in range(n):  # scipy names no predecessor where no finite path arrives
            if not dist[i] < np.inf:
                pred[i] = -9999
        return dist, pred

    @njit(cache=True, nogil=True)
    def _segment_lengths_kernel(v, a, b):
        """``row_norm(v[a] - v[b])`` without the gathered copies."""
        out = np.empty(a.shape[0])
        for e in range(a.shape[0]):
            d0, d1, d2 = v[a[e], 0] - v[b[e], 0], v[a[e], 1] - v[b[e], 1], v[a[e], 2] - v[b[e], 2]
            out[e] = np.sqrt((d0 * d0 + d2 * d2) + d1 * d1)  # einsum's order, for its bits
        return out

    @njit(cache=True, nogil=True)
    def _edge_curvature_kernel(n, c, pairs, nf):
        """``face_curvature``'s last step: the smallest curvature across each face's edges."""
        kf = np.full(nf, np.inf)
        for e in range(pairs.shape[0]):
            i, j = pairs[e, 0], pairs[e, 1]
            d0, d1, d2 = c[j, 0] - c[i, 0], c[j, 1] - c[i, 1], c[j, 2] - c[i, 2]
            # summed in np.einsum's order (0 + 2, then 1), for the reference's bits
            num = ((n[j, 0] - n[i, 0]) * d0 + (n[j, 2] - n[i, 2]) * d2) + (n[j, 1] - n[i, 1]) * d1
            k = num / max((d0 * d0 + d2 * d2) + d1 * d1, 1e-12)
            if k < kf[i] or k != k:  # np.minimum's: a NaN stays
                kf[i] = k
            if k < kf[j] or k != k:
                kf[j] = k
        return kf


def row_norm(x: np.ndarray) -> np.ndarray:
    """(N,) Euclidean norm of each row of ``x`` (N, 3) (3-4x faster than ``np.linalg.norm``)."""
    return np.sqrt(np.einsum("ij,ij->i", x, x))


def face_centroids(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) centroid of each face, mm (compiled: 0.16 -> 0.06 s at 2.7 M faces, the bits
    of ``face_centroids_reference``)."""
    if _compiled(vertices, faces):
        return _centroids_kernel(vertices, faces)
    return face_centroids_reference(vertices, faces)


def face_centroids_reference(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``face_centroids`` in numpy (3x faster than ``vertices[faces].mean(axis=1)``)."""
    return (vertices[faces[:, 0]] + vertices[faces[:, 1]] + vertices[faces[:, 2]]) / 3.0


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (faster than ``np.cross`` on long arrays)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _compiled(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the compiled per-face loops apply: float64 vertices (the kernels write
    float64, as numpy does from them) and numba there."""
    return HAVE_NUMBA and vertices.dtype == np.float64 and len(faces) > 0


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) ``(v1 - v0) x (v2 - v0)`` of each face: outward for CCW faces, |.| = 2 area."""
    if _compiled(vertices, faces):
        return _face_cross_kernel(vertices, faces)[0]
    return face_cross_reference(vertices, faces)


def face_cross_reference(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``face_cross`` in numpy (the plain reference of ``_face_cross_kernel``)."""
    v0 = vertices[faces[:, 0]]
    return cross3(vertices[faces[:, 1]] - v0, vertices[faces[:, 2]] - v0)


def face_normals_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals ``(F, 3)`` (outward for CCW faces) and areas ``(F,)`` mm².
    Compiled: the same bits, 0.33 -> 0.09 s at 2.7 M faces."""
    if _compiled(vertices, faces):
        cross, norm = _face_cross_kernel(vertices, faces)
    else:
        cross = face_cross_reference(vertices, faces)
        norm = row_norm(cross)
    return cross / np.maximum(norm, 1e-300)[:, None], 0.5 * norm


def segment_lengths(vertices: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(E,) ``row_norm(vertices[a] - vertices[b])``: compiled without the gathered copies
    (same bits; 0.18 -> 0.02 s over a 2.7 M-face mesh's edges)."""
    if _compiled(vertices, a):
        return _segment_lengths_kernel(vertices, a, b)
    return row_norm(vertices[a] - vertices[b])


def label_moments(lab: np.ndarray, m: int, w: np.ndarray, x: np.ndarray,
                  floor: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per label ``0..m-1`` of the rows of ``x`` (N, 3) weighted by ``w`` (N,): the weight
    ``s0`` (m,), the weighted sum ``s1`` (m, 3) and the weighted outer products ``s2``
    (m, 3, 3), of the rows themselves or, with ``floor``, of their offsets from the
    label's mean ``s1 / max(s0, floor)``.  Compiled: one pass (two centred) summing the
    same products in the same order as ``label_moments_reference``'s ten ``np.bincount``,
    so the same bits (a 2.7 M-face plant's regions: 0.15-0.22 -> 0.02-0.03 s)."""
    if HAVE_NUMBA and len(lab) and x.dtype == np.float64 and w.dtype == np.float64:
        return _moments_kernel(np.ascontiguousarray(lab), m, w, x,
                               0.0 if floor is None else float(floor), floor is not None)
    return label_moments_reference(lab, m, w, x, floor)


def label_moments_reference(lab: np.ndarray, m: int, w: np.ndarray, x: np.ndarray,
                            floor: float | None = None
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``label_moments`` in numpy (the plain reference)."""
    s0 = np.bincount(lab, w, m)
    s1 = np.stack([np.bincount(lab, w * x[:, k], m) for k in range(3)], 1)
    d = x if floor is None else x - (s1 / np.maximum(s0, floor)[:, None])[lab]
    s2 = np.zeros((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            s2[:, a, b] = s2[:, b, a] = np.bincount(lab, w * d[:, a] * d[:, b], m)
    return s0, s1, s2


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)``."""
    cross = face_cross(vertices, faces)
    out = np.stack([sum(np.bincount(faces[:, k], cross[:, c], len(vertices)) for k in range(3))
                    for c in range(3)], axis=1)
    return out / np.maximum(row_norm(out), 1e-300)[:, None]


def face_adjacency_operator(nf: int, pairs: np.ndarray) -> sparse.csr_matrix:
    """Row-stochastic averaging operator over each face and its edge neighbours."""
    return averaging_operator(nf, pairs)


def shortest_paths(g: sparse.csr_matrix, source: int, limit: float = np.inf
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.sparse.csgraph.dijkstra(g, directed=True, indices=source,
    return_predecessors=True, limit=limit)``: distances from ``source`` (inf beyond
    ``limit`` or unreached) and predecessors (-9999 for none).  Compiled without the GIL
    (scipy's holds it, so the measurer's two leaf threads took turns); the same numbers
    but for the predecessor on an exact tie of two paths' lengths, which a Fibonacci heap
    and a binary heap may break differently (``shortest_paths_reference``: scipy's)."""
    if not HAVE_NUMBA:
        return shortest_paths_reference(g, source, limit)
    return _dijkstra_kernel(g.indptr, g.indices, g.data.astype(np.float64, copy=False),
                            int(source), float(limit))


def shortest_paths_reference(g: sparse.csr_matrix, source: int, limit: float = np.inf
                             ) -> tuple[np.ndarray, np.ndarray]:
    """``shortest_paths`` by scipy (the plain reference)."""
    from scipy.sparse.csgraph import dijkstra

    return dijkstra(g, directed=True, indices=source, return_predecessors=True, limit=limit)


def pair_graph(n: int, pairs: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The symmetric (n, n) graph of ``pairs`` (P, 2), both directions stored, in scipy's
    canonical form (each row's columns ascending), and the pair of every stored entry: its
    ``data`` is ``weights[pair_of]``.  ``pairs`` must not repeat a link.  Compiled: the
    arrays ``pair_graph_reference`` builds, without its sorts (a leaf of a 512³ dicot, 30 k
    points and 650 k pairs: about 0.08 -> 0.03 s)."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if not HAVE_NUMBA:
        return pair_graph_reference(n, pairs)
    indptr, indices, pair_of = _pair_csr_kernel(n, np.ascontiguousarray(pairs))
    g = sparse.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n))
    g.has_sorted_indices = True
    return g, pair_of


def pair_graph_reference(n: int, pairs: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """``pair_graph`` with scipy (the plain reference): each entry's data is its pair number
    + 1 until read back."""
    ids = np.arange(1.0, len(pairs) + 1)
    g = sparse.csr_matrix((np.concatenate([ids, ids]),
                           (np.concatenate([pairs[:, 0], pairs[:, 1]]),
                            np.concatenate([pairs[:, 1], pairs[:, 0]]))), shape=(n, n))
    pair_of = g.data.astype(np.int64) - 1
    g.data = np.ones(len(pair_of))
    return g, pair_of


def vertex_adjacency_operator(nv: int, edges: np.ndarray) -> sparse.csr_matrix:
    """Row-stochastic averaging operator over each vertex and its 1-ring."""
    return averaging_operator(nv, edges)


def averaging_operator(n: int, links: np.ndarray) -> sparse.csr_matrix:
    """``diags(1 / degree) @ A``, ``A`` the adjacency of ``links`` (L, 2) (a repeated link
    counts twice) plus the identity: the mean over each node and its neighbours.

    Compiled (``_averaging_kernel``: the rows filled by counting, each row's few columns
    sorted in place; faces of a 2.7 M-face mesh 0.47 -> 0.37 s, memory-bound) when numba
    is there, else
    ``averaging_operator_reference``: the same arrays, each row's columns in the order
    scipy's product leaves them (descending), so a smoothing sums every row in the same
    order and gives the same values to the bit.
    """
    links = np.asarray(links, dtype=np.int64).reshape(-1, 2)
    if not HAVE_NUMBA or n == 0:
        return averaging_operator_reference(n, links)
    indptr, indices, data = _averaging_kernel(n, np.ascontiguousarray(links))
    return sparse.csr_matrix((data, indices, indptr), shape=(n, n))


def averaging_operator_reference(n: int, links: np.ndarray) -> sparse.csr_matrix:
    """``averaging_operator`` with scipy: a sparse matrix of the links, its row sums, their
    inverse as a diagonal matrix times it (the plain reference the kernel is tested
    against)."""
    i = np.concatenate([links[:, 0], links[:, 1], np.arange(n)])
    j = np.concatenate([links[:, 1], links[:, 0], np.arange(n)])
    a = sparse.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    deg = np.asarray(a.sum(axis=1)).ravel()
    return (sparse.diags(1.0 / deg) @ a).tocsr()


def diffusion_steps(radius_mm: float, edge_mm: float, max_steps: int = 200) -> int:
    """Averaging steps whose diffusion reaches about ``radius_mm`` on edges of ``edge_mm``."""
    if radius_mm <= 0 or edge_mm <= 0:
        return 0
    return int(min(max_steps, max(1, round((radius_mm / edge_mm) ** 2))))


def smooth(op: sparse.csr_matrix, values: np.ndarray, steps: int) -> np.ndarray:
    out = values
    for _ in range(steps):
        out = op @ out
    return out


def taubin(vertices: np.ndarray, op: sparse.csr_matrix, steps: int,
           lam: float = 0.5, mu: float = -0.53) -> np.ndarray:
    """Taubin lambda/mu smoothing (removes voxel noise without shrinking the shape)."""
    v = vertices.copy()
    for _ in range(steps):
        v = v + lam * (op @ v - v)
        v = v + mu * (op @ v - v)
    return v


def polyline_length(points: np.ndarray) -> float:
    if len(points) < 2:
        return 0.0
    return float(row_norm(np.diff(points, axis=0)).sum())


def smoothing_shrinkage(points: np.ndarray, sigma_mm: float, closed: bool = False,
                        curve_sigma_mm: float | None = None) -> float:
    """Length (mm) a curve loses when smoothed by a Gaussian of ``sigma_mm`` (arclength).

    Smoothing a circle of radius ``R`` by a Gaussian of ``s`` in arclength
    shrinks it exactly to ``R exp(-s**2 / (2 R**2))`` (its one Fourier mode is
    damped so): to first order the heat equation's ``s**2 / 2 * kappa`` towards
    the centre of curvature, a length loss of ``s**2 / 2 * integral(kappa**2 ds)``.
    Each vertex of ``points`` is taken as such an arc, of the curve smoothed by
    ``curve_sigma_mm`` (default ``sigma_mm``): its radius there is the mean of its
    two segments over its turning angle; the true radius ``R`` is solved from it
    (monotonic: a few Newton steps) and the vertex's true arc, smoothed by
    ``sigma_mm``, loses ``1 - exp(-sigma**2 / (2 R**2))`` of itself.  Gentle
    outlines (``R >> sigma``) get the first-order loss back; a tip sharper than
    ``sigma`` gets what a circle of its size loses (the first-order term would
    over-correct it several times).  Measuring the curvature on a curve smoothed
    more than ``sigma_mm`` keeps wiggles a rough surface left in the line out of
    it (their curvature is not the outline's).
    """
    s_c = sigma_mm if curve_sigma_mm is None else curve_sigma_mm
    p = np.asarray(points, float)
    if closed:
        p = np.concatenate([p[-2:-1], p]) if np.allclose(p[0], p[-1]) else \
            np.concatenate([p[-1:], p, p[:1]])
    if len(p) < 3 or sigma_mm <= 0 or s_c <= 0:
        return 0.0
    d = np.diff(p, axis=0)
    seg = row_norm(d)
    ok = seg > 1e-12
    d, seg = d[ok], seg[ok]
    if len(d) < 2:
        return 0.0
    u = d / seg[:, None]
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", u[:-1], u[1:]), -1.0, 1.0))
    ds = 0.5 * (seg[:-1] + seg[1:])
    # a smoothed radius below what a circle of radius s_c becomes (s_c exp(-1/2)) is a
    # feature of the smoothing scale, the zig-zag or a speck smoothing is meant to remove:
    # nothing is given back there (the inverse is ill-posed: a speck would grow into a
    # circle of radius ~s_c)
    bent = (turn > 1e-12) & (turn * s_c * math.exp(-0.5) < ds)  # straight: nothing lost
    y = ds[bent] / turn[bent] / s_c  # radius on the curve smoothed by s_c, over s_c
    # solve ln x - 1 / (2 x^2) = ln y for x = R / s_c (increasing in x: Newton converges)
    x = np.maximum(y, 1.0)
    for _ in range(30):
        x = np.maximum(x - (np.log(x) - 0.5 / x**2 - np.log(y)) / (1.0 / x + 1.0 / x**3),
                       1.0)
    true_arc = ds[bent] * x / y
    radius = x * s_c
    return float(np.sum(true_arc * (1.0 - np.exp(-0.5 * (sigma_mm / radius) ** 2))))


def arclength(points: np.ndarray) -> np.ndarray:
    """(N,) distance along the polyline ``points`` from its first point to each point."""
    return np.concatenate([[0.0], np.cumsum(row_norm(np.diff(points, axis=0)))])


def points_at(points: np.ndarray, s: np.ndarray, t) -> np.ndarray:
    """The points at arclengths ``t`` along ``points`` (``s``: their ``arclength``),
    linearly between vertices."""
    return np.stack([np.interp(t, s, points[:, k]) for k in range(3)], axis=-1)


def smooth_polyline(points: np.ndarray, sigma_mm: float, closed: bool = False) -> np.ndarray:
    """Gaussian smoothing of a polyline by arclength (ends kept when open).

    A shortest path on a triangle mesh zig-zags across triangles and is a few
    percent longer than the geodesic it follows; smoothing at a scale well
    below the leaf's curvature radius removes the zig-zag and keeps the curve.
    """
    from scipy.ndimage import gaussian_filter1d

    if len(points) < 3 or sigma_mm <= 0:
        return points
    s = arclength(points)
    total = s[-1]
    if total <= 1e-9 * sigma_mm:  # a polyline of coincident points: nothing to smooth
        return points
    step = min(sigma_mm / 4.0, total / 8.0)
    n = max(int(np.ceil(total / step)) + 1, 4)
    t = np.linspace(0.0, total, n)
    res = points_at(points, s, t)
    # Beyond a few times the curve's own length a wider kernel changes nothing (the curve
    # is already flattened to its mean) but its size: cap it so a ~1e-7 mm curve cannot ask
    # scipy for a 1e15-sample kernel (seen on a hull leaf).
    sig = min(sigma_mm / (total / (n - 1)), 4.0 * n)
    if closed:
        return gaussian_filter1d(res[:-1], sig, axis=0, mode="wrap")
    # reflect about the end points ("odd" extension) so the ends stay where they are
    pad = int(min(n - 1, np.ceil(4 * sig)))
    head = 2 * res[0] - res[1:pad + 1][::-1]
    tail = 2 * res[-1] - res[-pad - 1:-1][::-1]
    ext = np.concatenate([head, res, tail])
    return gaussian_filter1d(ext, sig, axis=0, mode="nearest")[pad:pad + n]


def cell_normal_tensors(points: np.ndarray, normals: np.ndarray, weights: np.ndarray,
                        cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted normal tensors ``sum w n n^T`` over 3x3x3 blocks of cubic cells.

    Parameters
    ----------
    points, normals : (N, 3) arrays (mm; unit vectors)
    weights : (N,) array (e.g. face areas, mm²)
    cell : float, mm

    Returns
    -------
    keys : (C,) int64, sorted keys of the occupied cells
    tensors : (C, 3, 3), the sum over each cell and its 26 neighbours
    cell_of : (N,) int64, index into ``keys`` of each point's cell
    grid : (6,) float, ``lo`` (mm) and ``dims`` of the key layout
    """
    if HAVE_NUMBA and len(points) and points.dtype == np.float64:
        lo, dims, key = _cell_keys_kernel(points, float(cell))
    else:
        lo = points.min(axis=0) - cell
        ijk = np.floor((points - lo) / cell).astype(np.int64)
        dims = ijk.max(axis=0) + 3
        key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    keys, inv = unique_inverse(key, int(np.prod(dims)))
    nc = len(keys)
    comps = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    s2 = label_moments(inv, nc, weights, normals)[2]
    t = np.stack([s2[:, a, b] for a, b in comps], axis=1)
    # every occupied cell has a free cell on each side (lo and dims carry a margin), so a
    # neighbour's key is the cell's key plus a constant
    offsets = np.array([int((d[0] * dims[1] + d[1]) * dims[2] + d[2]) for d in
                        np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T])
    acc = (_block_sums_kernel(keys, np.ascontiguousarray(t), offsets) if HAVE_NUMBA
           else block_sums_reference(keys, t, offsets))
    m = np.zeros((nc, 3, 3))
    for c, (a, b) in enumerate(comps):
        m[:, a, b] = m[:, b, a] = acc[:, c]
    return keys, m, inv, np.concatenate([lo, dims.astype(float)])


def block_sums_reference(keys: np.ndarray, t: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(C, k) the sum of the rows of ``t`` (C, k) whose ``keys`` (sorted) are each key plus
    one of ``offsets``, added in ``offsets``' order (numpy: the plain reference of
    ``_block_sums_kernel``)."""
    nc = len(keys)
    t_ext = np.vstack([t, np.zeros((1, t.shape[1]))])  # row nc: an unoccupied cell's sum
    acc = np.zeros_like(t)
    for off in offsets:
        qk = keys + off
        pos = np.minimum(np.searchsorted(keys, qk), nc - 1)  # sorted needles: a fast search
        acc += t_ext[np.where(keys[pos] == qk, pos, nc)]
    return acc


def face_curvature(mesh, topo: MeshTopology, smoothing_mm: float,
                   face_op: Callable[[], sparse.csr_matrix] | None = None) -> np.ndarray:
    """(F,) smallest normal curvature across each face's edges, 1/mm (< 0 concave).

    Curvature across the edge shared by faces i, j is
    ``(n_j - n_i) . (c_j - c_i) / |c_j - c_i|^2`` with normals ``n`` and
    centroids ``c`` of the surface smoothed at ``smoothing_mm``; outward
    normals make convex edges positive.  ``face_op``, when given, returns the faces'
    ``face_adjacency_operator`` (built by another thread meanwhile: the segmenter's).
    """
    v, f = mesh.vertices, mesh.faces
    edge_mm = float(np.mean(segment_lengths(v, topo.edges[:, 0], topo.edges[:, 1])))
    vop = vertex_adjacency_operator(len(v), topo.edges)
    vs = taubin(v, vop, diffusion_steps(smoothing_mm / 2, edge_mm, 30))
    n, _ = face_normals_areas(vs, f)
    fop = face_op() if face_op is not None else face_adjacency_operator(len(f), topo.face_pairs)
    n = smooth(fop, n, diffusion_steps(smoothing_mm, edge_mm * 0.6))
    n /= np.maximum(row_norm(n), 1e-12)[:, None]
    c = face_centroids(vs, f)
    if HAVE_NUMBA and len(f):
        kf = _edge_curvature_kernel(n, c, topo.face_pairs, len(f))
    else:
        kf = edge_curvature_reference(n, c, topo.face_pairs, len(f))
    kf[~np.isfinite(kf)] = 0.0
    return kf


def edge_curvature_reference(n: np.ndarray, c: np.ndarray, pairs: np.ndarray, nf: int
                             ) -> np.ndarray:
    """(nf,) the smallest ``(n_j - n_i) . (c_j - c_i) / |c_j - c_i|^2`` over each face's
    ``pairs`` (inf where it has none): ``face_curvature``'s last step in numpy (the plain
    reference of ``_edge_curvature_kernel``: 0.46 -> 0.07 s at 2.7 M faces)."""
    i, j = pairs[:, 0], pairs[:, 1]
    dc = c[j] - c[i]
    k = np.einsum("ij,ij->i", n[j] - n[i], dc) / np.maximum(np.einsum("ij,ij->i", dc, dc), 1e-12)
    kf = np.full(nf, np.inf)
    np.minimum.at(kf, i, k)
    np.minimum.at(kf, j, k)
    return kf


def components(n: int, pairs: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(n,) connected component of each node in ``keep`` over ``pairs`` (P, 2); -1 elsewhere.

    Components are numbered as scipy's ``connected_components`` numbers them over all
    ``n`` nodes (the nodes off ``keep`` alone each): in the order of their lowest node.
    Compiled (``_components_kernel``, union-find: 0.15-0.25 -> 0.03 s at 1.7 M faces) when
    numba is there, else ``components_reference``, the same numbers.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if not HAVE_NUMBA:
        return components_reference(n, pairs, keep)
    return _components_kernel(n, np.ascontiguousarray(pairs), np.asarray(keep, bool))


def components_reference(n: int, pairs: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``components`` with scipy (the plain reference the kernel is tested against)."""
    from scipy.sparse.csgraph import connected_components

    sel = keep[pairs[:, 0]] & keep[pairs[:, 1]]
    p = pairs[sel]
    g = sparse.csr_matrix((np.ones(len(p), np.int8), (p[:, 0], p[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    lab = lab.astype(np.int64)
    lab[~keep] = -1
    return lab


def dilate_faces(mask: np.ndarray, pairs: np.ndarray, rings: int) -> np.ndarray:
    """(n,) ``mask`` grown by ``rings`` rings of neighbours over ``pairs`` (P, 2); a copy."""
    out = np.asarray(mask, bool).copy()
    a, b = pairs[:, 0], pairs[:, 1]
    for _ in range(rings):
        grown = out.copy()
        grown[a[out[b]]] = True
        grown[b[out[a]]] = True
        out = grown
    return out


_KEY_LOCK = threading.Lock()
_KEY_SCOPES = [0]  # stages running inside ``meshes_unchanged``
_KNOWN_KEYS: dict[tuple[int, int], tuple[bytes, np.ndarray, np.ndarray]] = {}


@contextmanager
def meshes_unchanged():
    """Within, ``mesh_key`` remembers the digest of each (vertices, faces) pair of arrays it
    was given, by identity: a leaf stage asks for the same plant's key a dozen times (its
    unit, topology, ray scene: 0.06 s each at 2.7 M faces) and changes no
    array in place.  The arrays are held until the last scope ends, so no identity is
    reused meanwhile."""
    with _KEY_LOCK:
        _KEY_SCOPES[0] += 1
    try:
        yield
    finally:
        with _KEY_LOCK:
            _KEY_SCOPES[0] -= 1
            if not _KEY_SCOPES[0]:
                _KNOWN_KEYS.clear()


def mesh_key(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A digest of a mesh's arrays (SHA-256 of their bytes, dtypes and shapes): the key of the
    per-mesh caches below, so two stages given the same surface share its work (0.03 s at
    1.7 M faces, against 0.3 s for the unit and 1 s for a ray-casting scene).  Inside
    ``meshes_unchanged`` each pair of arrays is digested once."""
    if _KEY_SCOPES[0]:
        known = _KNOWN_KEYS.get((id(vertices), id(faces)))
        if known is not None and known[1] is vertices and known[2] is faces:
            return known[0]
        key = _digest(vertices, faces)
        with _KEY_LOCK:
            if _KEY_SCOPES[0]:
                _KNOWN_KEYS[(id(vertices), id(faces))] = (key, vertices, faces)
        return key
    return _digest(vertices, faces)


def _digest(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    h = hashlib.sha256()
    for a in (vertices, faces):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return h.digest()


class _MeshCache:
    """The last ``size`` values of a function of a mesh, keyed by ``mesh_key``."""

    def __init__(self, size: int) -> None:
        self.size, self.values = size, OrderedDict()

    def get(self, vertices: np.ndarray, faces: np.ndarray, make):
        key = mesh_key(vertices, faces)
        if key in self.values:
            self.values.move_to_end(key)
            return self.values[key]
        value = self.values[key] = make()
        while len(self.values) > self.size:
            _close(self.values.popitem(last=False)[1])
        return value

    def clear(self) -> None:
        for value in self.values.values():
            _close(value)
        self.values.clear()


def _close(value) -> None:
    """A cached value that holds a resource (a ray scene's helper process) lets it go."""
    close = getattr(value, "close", None)
    if close is not None:
        close()


_UNITS = _MeshCache(8)
_SCENES = _MeshCache(1)  # an Embree scene of a 1.7 M-face plant holds a few hundred MB
_TOPOLOGIES = _MeshCache(1)  # ~250 MB at 1.7 M faces
_NO_VERTICES = np.zeros((1, 3))  # the key of a topology: its faces alone


def forget_meshes() -> None:
    """Empty the per-mesh caches (``mesh_unit``, ``raycasting_scene``): a benchmark times
    every round from scratch."""
    _UNITS.clear()
    _SCENES.clear()
    _TOPOLOGIES.clear()


def mesh_topology(faces: np.ndarray) -> MeshTopology:
    """``topology(faces)`` remembered for the last mesh (keyed by the faces alone, as
    ``mesh_key``): the segmenter and the measurer's trust features ask for the same plant's
    (0.18 s at 1.7 M faces, against 0.02 s for the key).  Its arrays are read-only: they
    are shared."""
    def make() -> MeshTopology:
        topo = topology(faces)
        for a in (topo.edges, topo.face_edges, topo.edge_face_count, topo.face_pairs,
                  topo.pair_edge):
            a.setflags(write=False)
        return topo

    return _TOPOLOGIES.get(_NO_VERTICES, faces, make)


def mesh_unit(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The median edge length of a mesh, mm: the unit the leaf stages count sizes in (about
    a voxel for a marching-cubes mesh; on a closed mesh every edge is two faces' side, so
    the median over the faces' sides is the median over the edges).  Remembered for the
    last few meshes (``mesh_key``): the segmenter and the measurer both ask."""
    if not len(faces):
        return 1.0
    return _UNITS.get(vertices, faces, lambda: _median_side(vertices, faces))


def _median_side(v: np.ndarray, faces: np.ndarray) -> float:
    sides = np.concatenate([segment_lengths(v, faces[:, a], faces[:, b])
                            for a, b in ((0, 1), (1, 2), (2, 0))])
    return float(np.median(sides))


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    """The ray-casting scene of a mesh (``rays.make_scene``: ``t_hit(rays)``, float32),
    shared with the last caller of the same mesh (``mesh_key``): the piece judge and the
    measurer's thickness both cast inward rays at the whole plant, and building the
    scene is most of their cost (1.7 s at 2.7 M faces; its hits do not depend on who
    built it).  Asking early starts the build: a large mesh's in a helper process
    (``rays.HelperScene``), on the core the caller leaves idle.  One scene serves
    threads one at a time."""
    from plantscan_leaves import rays

    return _SCENES.get(vertices, faces, lambda: rays.make_scene(vertices, faces))


def triangle_union_mask(triangles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels whose centre lies in (or on) any of ``triangles``.

    ``triangles`` (T, 3, 2) float, pixel coordinates (x = column, y = row: pixel
    ``[r, c]`` has its centre at ``(c, r)``); ``shape`` (H, W).  The *union*: a pixel
    under several triangles is set once.  ``cv2.fillPoly`` given many polygons fills by
    parity instead, so where two triangles overlap (a leaf over a leaf, seen from above)
    their overlap is left empty.  Scanline per triangle row: each triangle's span on each
    pixel row it crosses is added to a per-row difference array, whose running sum counts
    the triangles over every pixel.  Compiled (``_union_kernel``, the same spans from the
    same float expressions: 1.4 -> 0.1 s for a 1.7 M-face plant's shadow) when numba is
    there, else ``triangle_union_mask_reference``.
    """
    h, w = shape
    tri = np.asarray(triangles, float)
    if not HAVE_NUMBA or not len(tri):
        return triangle_union_mask_reference(tri, shape)
    diff = _union_kernel(np.ascontiguousarray(tri), int(h), int(w))
    return np.cumsum(diff, axis=1)[:, :w] > 0


def triangle_union_mask_reference(triangles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``triangle_union_mask`` in numpy, every (triangle, row) span at once (the plain
    reference the kernel is tested against)."""
    h, w = shape
    tri = np.asarray(triangles, float)
    if not len(tri):
        return np.zeros((h, w), bool)
    y = tri[:, :, 1]
    r0 = np.maximum(np.ceil(y.min(axis=1)), 0).astype(np.int64)
    r1 = np.minimum(np.floor(y.max(axis=1)), h - 1).astype(np.int64)
    # a triangle with no height covers no area (its edge belongs to its neighbours)
    rows = np.where(y.max(axis=1) > y.min(axis=1), r1 - r0 + 1, 0)
    keep = rows > 0
    tri, r0, rows = tri[keep], r0[keep], rows[keep]
    # one (triangle, row) pair per span
    owner = np.repeat(np.arange(len(tri)), rows)
    row = r0[owner] + (np.arange(len(owner)) - np.repeat(np.cumsum(rows) - rows, rows))
    lo = np.full(len(owner), np.inf)
    hi = np.full(len(owner), -np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        xa, ya = tri[owner, a, 0], tri[owner, a, 1]
        xb, yb = tri[owner, b, 0], tri[owner, b, 1]
        dy = yb - ya
        crosses = (dy != 0) & (row >= np.minimum(ya, yb)) & (row <= np.maximum(ya, yb))
        with np.errstate(divide="ignore", invalid="ignore"):
            x = xa + (row - ya) * (xb - xa) / dy
        lo = np.where(crosses, np.minimum(lo, x), lo)
        hi = np.where(crosses, np.maximum(hi, x), hi)
    c0 = np.maximum(np.ceil(lo), 0).astype(np.int64)
    c1 = np.minimum(np.floor(hi), w - 1).astype(np.int64)
    span = c0 <= c1
    row, c0, c1 = row[span], c0[span], c1[span]
    diff = np.bincount(row * (w + 1) + c0, minlength=h * (w + 1))
    diff -= np.bincount(row * (w + 1) + c1 + 1, minlength=h * (w + 1))
    return np.cumsum(diff.reshape(h, w + 1), axis=1)[:, :w] > 0

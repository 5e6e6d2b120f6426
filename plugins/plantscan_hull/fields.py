"""The mesher's reads and edits of a hull's field, dense array or ``BlockField`` alike.

Pot removal, speck removal and marching cubes read boxes, columns and points of
the field and edit a few boxes and voxels; on a ``BlockField`` each of these
touches only the blocks concerned, so a 1024^3 hull is never densified.  Edits
made in the caller's field are recorded in an ``undo`` list and put back by
:func:`restore` (the mesher leaves the volume as it found it).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plantscan_core.data import BlockField

Field = np.ndarray | BlockField


def read_box(field: Field, lo: Sequence[int], hi: Sequence[int]) -> np.ndarray:
    """Dense float32 copy of the voxels ``[lo, hi)`` (per axis), -1 beyond the grid."""
    if isinstance(field, BlockField):
        return field.read(lo, hi)
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    out = np.full(tuple(hi - lo), -1.0, dtype=np.float32)
    a = np.maximum(lo, 0)
    b = np.minimum(hi, field.shape)
    if np.all(b > a):
        out[tuple(slice(x - y, z - y) for x, y, z in zip(a, lo, b, strict=True))] = \
            field[tuple(slice(x, z) for x, z in zip(a, b, strict=True))]
    return out


def write_box(field: Field, lo: Sequence[int], data: np.ndarray,
              undo: list | None = None) -> None:
    """``field[lo:lo + data.shape] = data`` (the box within the grid), recorded in ``undo``.

    On a ``BlockField`` an implicit block (wholly -1 or +1) that the box changes is
    given a row first; one it leaves as it was stays implicit.
    """
    lo = np.asarray(lo, dtype=np.int64)
    hi = lo + np.asarray(data.shape)
    if not isinstance(field, BlockField):
        box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
        if undo is not None:
            undo.append((box, field[box].copy()))
        field[box] = data
        return
    B = field.block
    blocks = np.array(list(np.ndindex(*((hi - 1) // B - lo // B + 1)))) + lo // B
    _snapshot(field, undo)
    changed = []
    for blk in blocks:
        g0, g1 = np.maximum(blk * B, lo), np.minimum(blk * B + B, hi)
        part = data[tuple(slice(a - b, c - b) for a, b, c in zip(g0, lo, g1, strict=True))]
        row = int(field.index[tuple(blk)])
        implicit = {BlockField.OUTSIDE: -1.0, BlockField.INSIDE: 1.0}.get(row)
        if implicit is not None and np.all(part == implicit):
            continue
        changed.append(blk)
    if not changed:
        return
    changed = np.array(changed)
    field.materialise(changed)
    for blk in changed:
        row = int(field.index[tuple(blk)])
        if undo is not None and row < undo[0][2]:  # a row that existed before the edit
            undo.append(("row", row, field.values[row].copy()))
        g0, g1 = np.maximum(blk * B, lo), np.minimum(blk * B + B, hi)
        src = tuple(slice(a - b, c - b) for a, b, c in zip(g0, lo, g1, strict=True))
        dst = tuple(slice(a - b, c - b) for a, b, c in zip(g0, blk * B, g1, strict=True))
        field.values[row][dst] = data[src]


def set_voxels(field: Field, flat: np.ndarray, value: float, undo: list | None = None) -> None:
    """Voxels with linear (C order) indices ``flat`` take ``value``, recorded in ``undo``."""
    if not isinstance(field, BlockField):
        out = field.reshape(-1)
        if undo is not None:
            undo.append((flat, out[flat]))
        out[flat] = value
        return
    idx = np.stack(np.unravel_index(flat, field.shape), axis=1)
    B = field.block
    blocks = np.unique(idx // B, axis=0)
    _snapshot(field, undo)
    field.materialise(blocks)
    rows = field.index[idx[:, 0] // B, idx[:, 1] // B, idx[:, 2] // B]
    if undo is not None:
        for row in np.unique(rows[rows < undo[0][2]]):
            undo.append(("row", int(row), field.values[row].copy()))
    q = idx % B
    field.values[rows, q[:, 0], q[:, 1], q[:, 2]] = value


def _snapshot(field: BlockField, undo: list | None) -> None:
    # The block map and row count before the first edit: implicit blocks given rows go
    # back to implicit, and the appended rows are dropped, by ``restore``.
    if undo is not None and not undo:
        undo.append(("index", field.index.copy(), len(field.values)))


def restore(field: Field, undo: list) -> None:
    """Undo the edits recorded in ``undo`` (last first) and clear it."""
    if isinstance(field, BlockField):
        for entry in reversed(undo):
            if entry[0] == "row":
                field.values[entry[1]] = entry[2]
            else:
                field.index[...] = entry[1]
                field.values = field.values[:entry[2]]
        undo.clear()
        return
    flat = field.reshape(-1)
    for where, values in reversed(undo):
        if isinstance(where, tuple):
            field[where] = values
        else:
            flat[where] = values
    undo.clear()


def faces_inside(field: Field) -> list[str]:
    """Names of the grid faces (``x-``, ``x+``...) with a voxel of ``field > 0``."""
    n = np.asarray(field.shape)
    faces = []
    for axis, name in enumerate("xyz"):
        for side, hi_end in (("-", False), ("+", True)):
            lo = np.zeros(3, np.int64)
            hi = n.copy()
            if hi_end:
                lo[axis] = n[axis] - 1
            else:
                hi[axis] = 1
            if np.any(read_box(field, lo, hi) > 0):
                faces.append(f"{name}{side}")
    return faces


def values_at(field: Field, idx: np.ndarray) -> np.ndarray:
    """(N,) float32 values at voxel indices ``idx`` (N, 3); -1 beyond the grid."""
    idx = np.asarray(idx, dtype=np.int64)
    ok = np.all((idx >= 0) & (idx < np.asarray(field.shape)), axis=1)
    out = np.full(len(idx), -1.0, dtype=np.float32)
    if isinstance(field, BlockField):
        out[ok] = field.values_at(idx[ok])
    else:
        flat = np.ascontiguousarray(field).reshape(-1)
        i = idx[ok]
        out[ok] = flat[(i[:, 0] * field.shape[1] + i[:, 1]) * field.shape[2] + i[:, 2]]
    return out


def z_profile(field: Field) -> np.ndarray:
    """(NZ,) float32: the largest value of each z slice."""
    if not isinstance(field, BlockField):
        return field.max(axis=(0, 1))  # no (NX, NY, NZ) temporary
    B, nz = field.block, field.shape[2]
    out = np.full(field.index.shape[2] * B, -1.0, dtype=np.float32)
    inside = np.any(field.index == BlockField.INSIDE, axis=(0, 1))
    for bz in np.flatnonzero(inside):
        out[bz * B:(bz + 1) * B] = 1.0
    rows = field.index[field.index >= 0]
    bz = np.nonzero(field.index >= 0)[2]
    if rows.size:
        per_row = field.values[rows].max(axis=(1, 2))  # (R, B) over x, y
        for b in np.unique(bz):
            out[b * B:(b + 1) * B] = np.maximum(out[b * B:(b + 1) * B],
                                                per_row[bz == b].max(axis=0))
    return out[:nz]


def chunk_max(field: Field, block: int) -> np.ndarray:
    """The largest value of each ``block``^3 chunk of voxels (chunks from the origin)."""
    if isinstance(field, BlockField) and field.block == block:
        return field.block_max()
    if isinstance(field, BlockField):
        field = field.dense()
    out = field
    for ax in range(3):
        out = np.maximum.reduceat(out, np.arange(0, field.shape[ax], block), axis=ax)
    return out


def inside_indices(field: Field, slab_voxels: int = 1 << 23) -> np.ndarray:
    """Sorted linear (C order) indices of the voxels with ``field > 0`` ((N,) int64).

    A dense field is read slab by slab (about ``slab_voxels`` each) along the
    first axis: ``np.flatnonzero(field > 0)`` makes an (NX, NY, NZ) bool
    temporary first (106 MB of fresh pages at 512^3).  A ``BlockField`` is
    read block by block.
    """
    if isinstance(field, BlockField):
        return _inside_indices_blocks(field)
    field = np.ascontiguousarray(field)
    plane = int(np.prod(field.shape[1:]))
    step = max(1, slab_voxels // max(plane, 1))
    return np.concatenate([np.flatnonzero(field[x:x + step] > 0) + x * plane
                           for x in range(0, field.shape[0], step)] or [np.zeros(0, np.int64)])


def _inside_indices_blocks(field: BlockField) -> np.ndarray:
    B = field.block
    shape = np.asarray(field.shape)
    parts = []
    r = np.arange(B)
    cube = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    for blk in np.argwhere(field.index != BlockField.OUTSIDE):
        row = int(field.index[tuple(blk)])
        local = cube if row == BlockField.INSIDE else np.argwhere(field.values[row] > 0)
        idx = local + blk * B
        idx = idx[np.all(idx < shape, axis=1)]
        parts.append((idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2])
    if not parts:
        return np.zeros(0, np.int64)
    out = np.concatenate(parts)
    out.sort()
    return out

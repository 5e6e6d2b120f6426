"""Leaf colours shared by every exporter, so the report's 3D view, the PLY/GLB/OBJ
files and the traits table use the same colour for the same leaf."""

from __future__ import annotations

import numpy as np

from plantscan_core.data import LabelledMesh, Mesh

# Colour-blind-friendly qualitative palette (Okabe-Ito first, then Tableau), RGB 0..1.
_LEAF_PALETTE = np.array(
    [
        (0.902, 0.624, 0.000),
        (0.337, 0.706, 0.914),
        (0.000, 0.620, 0.451),
        (0.941, 0.894, 0.259),
        (0.000, 0.447, 0.698),
        (0.835, 0.369, 0.000),
        (0.800, 0.475, 0.655),
        (0.580, 0.404, 0.741),
        (0.549, 0.337, 0.294),
        (0.090, 0.745, 0.812),
        (0.737, 0.741, 0.133),
        (0.839, 0.153, 0.157),
    ]
)
STEM_RGB = np.array((0.30, 0.55, 0.20))
POT_RGB = np.array((0.55, 0.45, 0.40))
UNASSIGNED_RGB = np.array((0.75, 0.75, 0.75))
PLAIN_RGB = np.array((0.35, 0.65, 0.35))


def leaf_colour(rank: int) -> np.ndarray:
    """(3,) RGB 0..1 of the ``rank``-th leaf (ranks follow ``LabelledMesh.leaf_labels``)."""
    return _LEAF_PALETTE[rank % len(_LEAF_PALETTE)]


def label_colours(labelled: LabelledMesh) -> dict[int, np.ndarray]:
    """Label -> (3,) RGB 0..1 for every label in ``kinds`` (leaves by rank, stem, pot)."""
    out: dict[int, np.ndarray] = {}
    leaf_rank = {label: i for i, label in enumerate(labelled.leaf_labels)}
    for label, kind in labelled.kinds.items():
        if kind == "leaf":
            out[label] = leaf_colour(leaf_rank[label])
        elif kind == "stem":
            out[label] = STEM_RGB
        else:
            out[label] = POT_RGB
    return out


def face_colours(labelled: LabelledMesh) -> np.ndarray:
    """(F, 3) float64 RGB 0..1 of every face; unassigned faces (-1) light grey."""
    colours = np.tile(UNASSIGNED_RGB, (len(labelled.face_labels), 1))
    for label, rgb in label_colours(labelled).items():
        colours[labelled.face_labels == label] = rgb
    return colours


def hex_colour(rgb: np.ndarray) -> str:
    """``#rrggbb`` of an RGB 0..1 triple."""
    r, g, b = (int(round(float(c) * 255)) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def split_by_face_colour(mesh: Mesh, colours: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """A mesh whose vertices carry the colour of their faces exactly.

    Mesh formats store colour per vertex; a vertex shared by two leaves would
    blend them.  Every vertex is duplicated once per distinct face colour that
    uses it, so each face's three vertices carry that face's colour.

    Parameters
    ----------
    mesh : Mesh
    colours : (F, 3) float array, RGB 0..1 per face

    Returns
    -------
    mesh : Mesh with (V', 3) vertices, V <= V' <= 3 F, same faces in the same order
    vertex_colours : (V', 3) float64 array, RGB 0..1
    """
    colours = np.asarray(colours, dtype=float).reshape(-1, 3)
    if len(colours) != len(mesh.faces):
        raise ValueError(f"{len(colours)} face colours for {len(mesh.faces)} faces")
    if mesh.is_empty:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)), np.zeros((0, 3))
    # Colours to one integer key each (16 bits per channel: palette colours differ far
    # more than 1/65535); a 1-D unique is ~10x faster than np.unique(axis=0) on 1 M rows.
    q = np.round(np.clip(colours, 0.0, 1.0) * 65535).astype(np.int64)
    key = (q[:, 0] << 32) | (q[:, 1] << 16) | q[:, 2]
    # A stable sort runs through the long runs of one colour (faces come leaf by leaf,
    # 3x faster than np.unique's quicksort); then a few distinct values to look up.
    ordered = np.sort(key, kind="stable")
    distinct = ordered[np.r_[True, ordered[1:] != ordered[:-1]]]
    colour_id = np.searchsorted(distinct, key)
    n_colours = int(colour_id.max()) + 1
    keys = (mesh.faces.astype(np.int64) * n_colours + colour_id[:, None]).reshape(-1)
    # The keys are dense (< V x colours): number the used ones by a table, not a sort.
    used = np.zeros(len(mesh.vertices) * n_colours, bool)
    used[keys] = True
    unique_keys = np.flatnonzero(used)
    number = np.cumsum(used) - 1
    inverse = number[keys]
    vertices = mesh.vertices[unique_keys // n_colours]
    vertex_colours = np.empty((len(unique_keys), 3))
    vertex_colours[inverse] = np.repeat(colours, 3, axis=0)
    return Mesh(vertices, inverse.reshape(-1, 3)), vertex_colours

"""Leaf colours shared by every exporter, so the report's 3D view, the PLY/GLB/OBJ
files and the traits table use the same colour for the same leaf."""

from __future__ import annotations

import functools

import numpy as np

from plantscan_core.data import LabelledMesh, Mesh

# Colour-blind-friendly qualitative palette (Okabe-Ito first, then Tableau), RGB 0..1: the
# first twelve leaves.  Leaves beyond get colours picked as far as possible (CIELAB) from
# every colour already in use, so no two labels of a plant share a colour (``leaf_palette``).
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
DEBRIS_RGB = np.array((0.40, 0.40, 0.40))
UNASSIGNED_RGB = np.array((0.75, 0.75, 0.75))
PLAIN_RGB = np.array((0.35, 0.65, 0.35))
KIND_RGB = {"stem": STEM_RGB, "pot": POT_RGB, "debris": DEBRIS_RGB}
# Extra leaf colours come from sRGB colours of medium lightness and chroma, the range of the
# fixed palette (legible as a swatch on white and as a shaded surface, not neon): CIELAB
# L* 35-85, chroma 30-75.
_EXTRA_LIGHTNESS = (35.0, 85.0)
_EXTRA_CHROMA = (30.0, 75.0)


def _lab(rgb: np.ndarray) -> np.ndarray:
    from skimage.color import rgb2lab

    return rgb2lab(np.asarray(rgb, dtype=float).reshape(-1, 1, 3)).reshape(-1, 3)


@functools.lru_cache(maxsize=8)
def _palette(n: int) -> np.ndarray:
    fixed = _LEAF_PALETTE[:n]
    if n <= len(_LEAF_PALETTE):
        return fixed
    steps = np.linspace(0.0, 1.0, 18)
    grid = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    lab = _lab(grid)
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    keep = ((lab[:, 0] >= _EXTRA_LIGHTNESS[0]) & (lab[:, 0] <= _EXTRA_LIGHTNESS[1])
            & (chroma >= _EXTRA_CHROMA[0]) & (chroma <= _EXTRA_CHROMA[1]))
    grid, lab = grid[keep], lab[keep]
    # Greedy farthest point: each new colour is the candidate farthest (Delta E 1976) from
    # all colours in use: the fixed palette, the organ kinds and the unassigned grey.
    used = [*_LEAF_PALETTE, *KIND_RGB.values(), UNASSIGNED_RGB, PLAIN_RGB]
    nearest = np.min(np.linalg.norm(lab[:, None, :] - _lab(np.array(used))[None], axis=2), 1)
    extra = []
    for _ in range(n - len(_LEAF_PALETTE)):
        i = int(np.argmax(nearest))
        extra.append(grid[i])
        nearest = np.minimum(nearest, np.linalg.norm(lab - lab[i], axis=1))
    return np.vstack([fixed, np.array(extra)])


def leaf_palette(n: int) -> np.ndarray:
    """(n, 3) RGB 0..1: ``n`` leaf colours, all different from each other and from the stem,
    pot, debris and unassigned colours.

    The first twelve are the fixed palette (a leaf keeps its colour whatever the
    plant's leaf count); the others are chosen greedily, each the farthest in
    CIELAB from every colour already used (deterministic).
    """
    return _palette(max(int(n), 0))


def leaf_colour(rank: int, n_leaves: int | None = None) -> np.ndarray:
    """(3,) RGB 0..1 of the ``rank``-th leaf of a plant of ``n_leaves`` leaves (ranks follow
    ``LabelledMesh.leaf_labels``)."""
    return leaf_palette(max(rank + 1, n_leaves or 0))[rank]


def label_colours(labelled: LabelledMesh) -> dict[int, np.ndarray]:
    """Label -> (3,) RGB 0..1 for every label in ``kinds``: leaves by rank (never two the
    same), stem, pot, debris by kind."""
    leaves = labelled.leaf_labels
    palette = leaf_palette(len(leaves))
    out: dict[int, np.ndarray] = {label: palette[i] for i, label in enumerate(leaves)}
    for label, kind in labelled.kinds.items():
        if kind != "leaf":
            out[label] = KIND_RGB.get(kind, UNASSIGNED_RGB)
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

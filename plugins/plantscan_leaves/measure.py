"""Flat-leaf measurement of visual-hull leaves (length, width, area, perimeter).

A leaf from a visual hull is a thin *closed slab* (a few voxels thick, lens
or stadium shaped in cross-section), not a sheet.  The flat-leaf traits are
those of its **mid-surface**, measured without building it:

* **sheet axis** ``N``: the leaf's local normal direction, the principal
  axis of the area-weighted normal tensor ``sum n n^T`` over cells of
  ``sheet_scale_units`` (sign-free, so both sides of the slab agree; cells are
  then oriented consistently by a walk over neighbouring cells).  The two
  *sides* of the slab are where ``n . N > 0`` and ``< 0``; the *rim crest*
  (the leaf outline) is where ``n . N = 0``.
* **area** = ``1/2 sum_f A_f |n_f . N_f|``: each side of the slab projected
  on the local leaf plane covers the leaf once, so half of the projected
  area of the whole closed surface is the planform area; it is exact for a
  flat slab of any thickness and edge profile, and exact to first order in
  ``thickness / bend radius`` for a bent one.
* **perimeter** = length of the ``n . N = 0`` iso-line (marching triangles on
  a lightly smoothed surface, chained and smoothed by ``outline_smoothing_units``);
  where the leaf was cut from the stem or petiole the line is open, and is
  closed by the straight chord between its ends.
* **length**: base (where the leaf meets the stem, or one end of the leaf's
  geodesic diameter when there is no stem) to tip (the geodesically
  farthest point): the shortest path over each side of the slab, smoothed
  of its zig-zag along the mesh, averaged over the two sides (a bent slab's
  inner side is shorter and its outer side longer than the mid-surface, by
  the same amount to first order).
* **width**: the outline (lightly smoothed) and the crest points are binned in
  stations along the smoothed midrib; at the stations of largest lateral
  extent (across the midrib, in the local leaf plane; the outline's where it
  crosses the station) the same two-side shortest path runs from the left rim
  to the right rim.  The width is the largest such path, or the lateral
  extent where the path is implausible (shorter than it, or > 1.25 x longer).

Paths over a side run from crest to crest over the rounded rim, a little
longer than the mid-surface would be (``(pi/2 - 1) r`` per end for a
semicircular rim of radius ``r``); with ``rim_correction`` that amount is
removed with ``r`` half the measured slab thickness: by default from the width
only (a rim-to-rim path; a length path starts at the cut base, see docs).
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from scipy import sparse
from scipy.sparse.csgraph import (
    breadth_first_order,
    connected_components,
    depth_first_order,
    minimum_spanning_tree,
)

from plantscan_core.data import LabelledMesh, LeafTraits, Mesh, Traits
from plantscan_core.parallel import keep_heap_memory, thread_map
from plantscan_core.stages import StageParams, StageReport, StageWarning
from plantscan_leaves import geometry as geo
from plantscan_leaves import tips

log = logging.getLogger(__name__)

# the crest line of n . N is the outline when one piece holds this share of it (a clean rim)
CLEAN_OUTLINE_SHARE = 0.95
# the top-view shadow is rasterised at a quarter of a mesh unit (0.25 mm at 1 mm voxels)
PROJECTION_PIXEL_UNITS = 0.25
# a leaf whose open border is at most this share of its outline was only cut at its base
CUT_BORDER_SHARE = 0.25
# hull more than this many times the leaf's median thickness is not a leaf slab: phantom volume
# of the visual hull, or an organ fused with the leaf (docs/leaves.md, "thick share")
THICK_FACTOR = 3.0
# faces per leaf whose inward thickness is cast: the share to about +-1 %
THICK_SAMPLE = 4000
# a leaf with more of its area that thick is named in a warning: on the virtual dicot scans
# the two leaves grown into phantom volume hold 17-26 % in every run (measured 3-20 % off in
# length), the other ten at most 7 %; wheat blades fused with tillers hold 6-17 %
# (docs/benchmarks/leaves.md, session 8)
THICK_WARN_SHARE = 0.12
# an outline runs from base to tip and back, each way at least the base-to-tip geodesic the
# length follows: a perimeter under this many lengths means one of the two is wrong (10 %
# below 2 for the smoothing of both; the leaves of the virtual scans measure 1.9-2.4 unless
# their length ran into another organ or their outline broke)
MIN_PERIMETER_PER_LENGTH = 1.8


class LeafGeometryParams(StageParams):
    """Parameters of ``leaf-geometry``: lengths in mesh units (``u``, the plant mesh's median
    edge, about a voxel: ``geometry.mesh_unit``), so the same plant in centimetres, or
    scaled with its voxel size, is measured the same (docs/leaves.md, "Scale-free
    parameters", for how the defaults were chosen on development and validation hulls)."""

    sheet_scale_units: float = Field(
        3.0, gt=0,
        description="size of the cells over which the leaf plane is estimated, mesh units: "
                    "well above the slab thickness, well below the leaf's bend radius",
    )
    smoothing_units: float = Field(
        0.8, ge=0, description="surface smoothing before measuring, mesh units")
    path_smoothing_units: float = Field(
        3.0, ge=0, description="smoothing of midrib/width paths (removes mesh zig-zag), mesh "
                               "units")
    outline_smoothing_units: float = Field(
        2.5, ge=0,
        description="smoothing of the rim crest line (perimeter), mesh units: above the "
                    "voxel zig-zag of a hull's sharp rim, below the outline's smallest "
                    "radius of curvature")
    width_stations: int = Field(3, ge=1, description="widest stations whose width is traced")
    graph_spacing_units: float = Field(
        1.0, gt=0, description="spacing of the points geodesic paths run through, mesh units")
    graph_points_per_size: float = Field(
        200.0, gt=0,
        description="the spacing of path points is at least the leaf's bounding-box diagonal "
                    "over this (big leaves: fewer points, same relative accuracy)")
    rim_correction: bool | Literal["width"] = Field(
        "width",
        description="remove the rounded-rim excess of over-the-side paths (see docs): True "
                    "for length and width, 'width' for the width only (rim-to-rim paths "
                    "cross two rims, a length path starts at the cut base)")
    min_leaf_faces: int = Field(20, ge=1, description="leaves with fewer faces are skipped")
    tip_taper_units: float = Field(
        0.0, ge=0,
        description="width, mesh units, below which a tapering tip is lost to the hull "
                    "(3 at the grass family's 1296x864 and 512^3): the blade's taper, from "
                    "the last station at 0.9 of its width to its measured end, is "
                    "continued to zero width (docs/leaves.md, \"Lost tips\"); 1 for the "
                    "dicot family's; 0: off")
    tip_model: str | None = Field(
        None,
        description="a learned tip model (scripts/train_tip_model.py writes one): the lost "
                    "tip's length predicted from the leaf's width profile instead of the "
                    "straight taper (needs tip_taper_units, the width it reads the profile "
                    "against; docs/leaves.md, \"Lost tips\"); a file name without a folder "
                    "is a model shipped in the package (tip_model_grass.json.gz), else a "
                    "path; None: the taper rule")
    base_taper_units: float = Field(
        0.0, ge=0,
        description="the same at the leaf's base: width, mesh units, below which a blade "
                    "narrowing into its petiole is lost to the hull and the cut from the "
                    "petiole; the taper from the first station at 0.9 of the width back to "
                    "the measured base is continued to zero width (1 at the dicot family's "
                    "1296x864 and 512^3); 0: off")
    stalk_width_units: float = Field(
        0.0, ge=0,
        description="width, mesh units, below which the stations at the leaf's base are a "
                    "stalk (a leaflet's petiolule the segmentation left on it), not blade: "
                    "the base is put where the blade's taper, fitted from the first two "
                    "stations at least this wide to the first at half the width, reaches "
                    "zero width, and the stalk's length, area and edges are left out "
                    "(docs/leaves.md, \"Stalks\"; 2.5 at the branched family's 1296x864 and "
                    "512^3); 0: off")
    outline_offset_units: float = Field(
        0.0, ge=-10.0, le=10.0,
        description="mesh units by which the hull's outline of a thin leaf lies inside the "
                    "leaf's (what is left after the mesher's thin rims): the area gains "
                    "this band along the seen outline (0.1 at the grass family's 1296x864 "
                    "and 512^3, chosen on its virtual twin's development plants; "
                    "docs/leaves.md, \"Outline offset\"); negative where the outline lies "
                    "outside (a band of phantom volume the views cannot carve around leaves "
                    "lying low in a dense rosette): the area loses the band; 0: off")
    width_offset_units: float = Field(
        0.0, ge=-10.0, le=10.0,
        description="the same for the width: mesh units by which each side of the hull's "
                    "outline lies inside the leaf's at its widest (the width gains twice "
                    "this), negative where it lies outside (-2 at the rosette family's "
                    "1296x864 and 512^3; docs/leaves.md, \"Outline offset\"); 0: off")
    min_plant_views: int = Field(
        0, ge=0, description="plant views this recipe's plants need (the family's protocol): "
                             "fewer flag the plant 'check', fewer than half 'fail' "
                             "(docs/leaves.md, Trust); 0: no check")
    max_stem_share: float = Field(
        0.0, ge=0, le=1,
        description="the most of a plant's surface (one side) this recipe's plants hold in "
                    "the stem: more flags the plant 'check', twice as much 'fail' (leaves "
                    "labelled stem are missed; docs/leaves.md, Trust); 0: no check")
    trust_model: str | None = Field(
        None, description="a learned trust model (scripts/train_trust_model.py writes one): "
                          "each leaf's confidence is also at most 1 - the model's probability "
                          "that its traits are wrong (docs/leaves.md, Trust); a file name "
                          "without a folder is a model shipped in the package "
                          "(trust_model_grass.json.gz), else a path; None: the rules alone")

    @field_validator("trust_model")
    @classmethod
    def _trust_model_exists(cls, value: str | None) -> str | None:
        from plantscan_leaves.pieces import check_model_name

        return check_model_name(value, "scripts/train_trust_model.py")

    @field_validator("tip_model")
    @classmethod
    def _tip_model_exists(cls, value: str | None) -> str | None:
        from plantscan_leaves.pieces import check_model_name

        return check_model_name(value, "scripts/train_tip_model.py")

    @model_validator(mode="after")
    def _tip_model_needs_width(self) -> LeafGeometryParams:
        if self.tip_model is not None and self.tip_taper_units <= 0:
            raise ValueError("tip_model needs tip_taper_units > 0 (the width the model reads "
                             "the leaf's profile against)")
        return self

    def scales(self, unit_mm: float) -> LeafScales:
        """These parameters with their lengths in mm for a mesh unit of ``unit_mm``."""
        u = float(unit_mm)
        return LeafScales(
            self.sheet_scale_units * u, self.smoothing_units * u, self.path_smoothing_units * u,
            self.outline_smoothing_units * u,
            self.graph_spacing_units * u, u, self.width_stations, self.graph_points_per_size,
            self.rim_correction, self.min_leaf_faces, self.tip_taper_units * u,
            self.base_taper_units * u, self.outline_offset_units * u,
            self.stalk_width_units * u, self.width_offset_units * u, self.tip_model)


@dataclass(frozen=True)
class LeafScales:
    """``LeafGeometryParams`` resolved for one mesh: lengths in mm (``unit_mm`` = 1 unit)."""

    sheet_scale_mm: float
    smoothing_mm: float
    path_smoothing_mm: float
    outline_smoothing_mm: float
    graph_spacing_mm: float
    unit_mm: float
    width_stations: int
    graph_points_per_size: float
    rim_correction: bool | str
    min_leaf_faces: int
    tip_taper_mm: float = 0.0
    base_taper_mm: float = 0.0
    outline_offset_mm: float = 0.0
    stalk_width_mm: float = 0.0
    width_offset_mm: float = 0.0
    tip_model: str | None = None


@dataclass
class LeafMeasurement:
    traits: LeafTraits
    thickness_mm: float
    base: np.ndarray
    tip: np.ndarray
    midrib: np.ndarray
    info: dict = field(default_factory=dict)


def _cell_sheet_axes(points: np.ndarray, normals: np.ndarray, weights: np.ndarray,
                     cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Oriented sheet axis per occupied cell.

    Returns ``keys`` (C,) sorted cell keys, ``axes`` (C, 3) unit vectors and
    the grid description ``(lo, dims)`` packed as an array of 6 floats.
    """
    keys, m, _, grid = geo.cell_normal_tensors(points, normals, weights, cell)
    nc = len(keys)
    dims = grid[3:].astype(np.int64)
    nbr_of = []
    for d in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T:
        if not np.any(d != 0):
            continue
        # occupied cells have a free margin: a neighbour's key is the key plus a constant
        qk = keys + int((d[0] * dims[1] + d[1]) * dims[2] + d[2])
        pos = np.minimum(np.searchsorted(keys, qk), nc - 1)
        nbr_of.append(np.where(keys[pos] == qk, pos, -1))
    ev, vec = np.linalg.eigh(m)
    axes = vec[:, :, 2].copy()
    # orient the sign-free axes consistently: propagate signs along the minimum spanning tree
    # of neighbouring cells weighted by how much their axes disagree (Hoppe et al. 1992), so a
    # flip is only ever decided between cells that agree well (never across a rim cell or a
    # lump whose axis is uncertain, as a plain breadth-first walk may)
    nbrs = np.stack(nbr_of, axis=1)
    i, j = np.nonzero(nbrs >= 0)
    j = nbrs[i, j]
    keep = i < j
    i, j = i[keep], j[keep]
    w = 1.0 + 1e-6 - np.abs(np.einsum("ij,ij->i", axes[i], axes[j]))
    tree = minimum_spanning_tree(sparse.csr_matrix((w, (i, j)), shape=(nc, nc)))
    tree = tree + tree.T
    # each piece of the tree hangs from its strongest cell (the first of its cells by
    # decreasing eigenvalue); one walk from a hub node joined to every such root gives each
    # cell its parent (a tree's path to its root is unique, so any walk gives the same)
    _, piece = connected_components(tree, directed=False)
    by_strength = np.argsort(-ev[:, 2])
    roots = by_strength[np.unique(piece[by_strength], return_index=True)[1]]
    t = tree.tocoo()
    hub = np.full(len(roots), nc)
    walk = sparse.csr_matrix((np.ones(len(t.row) + 2 * len(roots)),
                              (np.concatenate([t.row, hub, roots]),
                               np.concatenate([t.col, roots, hub]))), shape=(nc + 1, nc + 1))
    parent = breadth_first_order(walk, nc, directed=False)[1][:nc]
    # a cell flips when its axis opposes its parent's once the parent is oriented: its sign
    # is its parent's times the sign of their dot product; a cell edge-on to its parent
    # (dot 0) keeps its axis and starts afresh, as a root does
    child = np.flatnonzero(parent < nc)
    dot = np.zeros(nc)
    dot[child] = np.einsum("ij,ij->i", axes[child], axes[parent[child]])
    fresh = ~(dot != 0)
    sign = np.where(fresh | (dot > 0), 1, -1)
    up = np.where(fresh, -1, parent)
    while (up >= 0).any():  # signs multiplied along the paths by pointer jumping
        live = np.flatnonzero(up >= 0)
        sign[live] = sign[live] * sign[up[live]]
        up[live] = up[up[live]]
    return keys, axes * sign[:, None], grid


def _axes_at(points: np.ndarray, keys: np.ndarray, axes: np.ndarray, grid: np.ndarray,
             cell: float) -> np.ndarray:
    """Trilinear interpolation of the oriented cell axes at ``points`` (unit vectors)."""
    lo, dims = grid[:3], grid[3:].astype(np.int64)
    # a dense key -> cell table (the grid is a leaf's box in cells of several mm: small);
    # an unoccupied or outside corner reads a zero axis (row nc), which adds nothing
    nc = len(keys)
    lut = np.full(int(np.prod(dims)), nc, np.int64)
    lut[keys] = np.arange(nc)
    axes0 = np.vstack([axes, np.zeros((1, 3))])
    u = (points - lo) / cell - 0.5
    base = np.floor(u).astype(np.int64)
    frac = u - base
    weight = (1.0 - frac, frac)  # per corner offset 0 / 1, per axis
    inside = tuple((base + c >= 0) & (base + c < dims) for c in (0, 1))
    stride = np.array([dims[1] * dims[2], dims[2], 1])
    key0 = base @ stride
    out = np.zeros_like(points)
    for corner in np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T:
        cx, cy, cz = corner
        ok = inside[cx][:, 0] & inside[cy][:, 1] & inside[cz][:, 2]
        pos = np.where(ok, lut[np.where(ok, key0 + int(corner @ stride), 0)], nc)
        w = weight[cx][:, 0] * weight[cy][:, 1] * weight[cz][:, 2]
        out += w[:, None] * axes0[pos]
    norm = geo.row_norm(out)
    missing = norm < 1e-9
    if missing.any():  # fall back to the own cell's axis (every point's cell is occupied)
        own = np.floor((points[missing] - lo) / cell).astype(np.int64)
        ok = np.all((own >= 0) & (own < dims), axis=1)
        pos = np.where(ok, lut[np.where(ok, own @ stride, 0)], nc)
        out[missing] = axes[np.where(pos < nc, pos, 0)]
        norm[missing] = 1.0
    return out / norm[:, None]


def _path(pred: np.ndarray, target: int) -> list[int]:
    out = [target]
    while pred[out[-1]] >= 0:
        out.append(int(pred[out[-1]]))
    return out[::-1]


def _two_side_length(graphs: list[sparse.csr_matrix], vertices: np.ndarray, a: int, b: int,
                     sigma: float, limit: float = np.inf) -> float:
    """Mean over the slab's sides of the smoothed shortest-path length from ``a`` to ``b``."""
    lengths = []
    for g in graphs:
        dist, pred = geo.shortest_paths(g, a, limit)
        if not np.isfinite(dist[b]):
            continue
        pts = vertices[_path(pred, b)]
        lengths.append(geo.polyline_length(geo.smooth_polyline(pts, sigma)))
    return float(np.mean(lengths)) if lengths else float("nan")


@dataclass
class _Slab:
    """One leaf's closed slab as the measurement steps share it.

    ``v`` (V, 3) smoothed vertices, ``f`` faces with the hole caps appended after the
    first ``n_leaf`` (the leaf's own faces), ``topo`` the capped slab's topology (None
    until the outline needs it), ``leaf_topo`` the leaf faces' own, ``edge_mm`` the mean
    edge, ``detached`` the other pieces of the label (vertices, faces) or None.
    """

    v: np.ndarray
    f: np.ndarray
    n_leaf: int
    topo: geo.MeshTopology | None
    leaf_topo: geo.MeshTopology
    edge_mm: float
    border_length: float
    detached: tuple[np.ndarray, np.ndarray] | None

    @property
    def leaf(self) -> slice:
        return slice(0, self.n_leaf)


@dataclass
class _Sides:
    """Geodesic graphs over resampled points of each side of the slab (see ``_side_graphs``)."""

    nodes: np.ndarray
    q: np.ndarray
    crest: np.ndarray
    g_all: sparse.csr_matrix
    g_a: sparse.csr_matrix
    g_b: sparse.csr_matrix
    spacing: float


def measure_leaf(mesh: Mesh, leaf_id: int, params: LeafGeometryParams,
                 base_hint: np.ndarray | None = None, unit_mm: float | None = None
                 ) -> LeafMeasurement | None:
    """Flat-leaf traits of one leaf surface (a closed or nearly closed slab).

    Parameters
    ----------
    mesh : Mesh
        The faces of this leaf only (mm, turntable frame).
    base_hint : (3,) mm, optional
        Where the leaf attaches (e.g. the nearest stem point): of the two ends
        of the leaf's geodesic diameter, the one nearer to it is the base.
    unit_mm : float, optional
        The mesh unit the parameters are counted in (the whole plant mesh's median
        edge, ``geometry.mesh_unit``); default: this leaf's own.
    """
    if len(mesh.faces) < params.min_leaf_faces:
        return None
    p = params.scales(unit_mm if unit_mm is not None else geo.mesh_unit(mesh.vertices,
                                                                        mesh.faces))
    slab = _closed_slab(mesh, p)
    sheet = _cell_sheet_axes(*_leaf_faces_geometry(slab), p.sheet_scale_mm)
    vert_axis = _axes_at(slab.v, *sheet, p.sheet_scale_mm)
    face_side, fa = _face_sides(slab, vert_axis)
    area = 0.5 * float(np.sum((fa * np.abs(face_side))[slab.leaf]))
    rim_length, outline_kind, outline_lines = _outline(slab, vert_axis, face_side, fa, p)
    perimeter = rim_length
    # mean slab thickness: enclosed volume over planform area (exact for a flat slab; an
    # open cut at the stem leaves this an estimate, used only by the rim correction)
    thickness = _enclosed_volume(slab.v, slab.f) / max(area, 1e-9)
    area += p.outline_offset_mm * rim_length  # the band along the outline the hull lost
    sides = _side_graphs(slab, face_side, p)
    base, tip, dist_b, pred_b = _base_and_tip(sides, base_hint)
    midrib_idx = np.array(_path(pred_b, tip))
    sigma = p.path_smoothing_mm
    rim_excess = (math.pi / 2 - 1) * thickness if p.rim_correction else 0.0
    length, mid_pts = _midrib_length(sides, base, tip, dist_b, midrib_idx, sigma,
                                     rim_excess if p.rim_correction is True else 0.0)
    tip_extension_mm, ext_tip = 0.0, None
    if slab.detached is not None:
        tip_extension_mm, ext_area, ext_tip = _detached_tips(sides, base, tip, slab.detached,
                                                             sigma, base_hint is None)
        length += tip_extension_mm
        perimeter += 2.0 * tip_extension_mm  # both edges of the tip
        area += ext_area
    width, extent = _width(sides, mid_pts, dist_b, outline_lines, sheet, slab.edge_mm,
                           rim_excess, p)
    seen_mm = geo.polyline_length(mid_pts) + tip_extension_mm
    d_length, d_perimeter, d_area, ends = _end_corrections(extent, seen_mm, p)
    width = max(width + 2.0 * p.width_offset_mm, 0.0)  # the outline's offset on both sides
    traits = LeafTraits(leaf_id, float(length + d_length), float(width), area + d_area,
                        perimeter + d_perimeter)
    base_v, tip_v = sides.nodes[base], sides.nodes[tip]
    base_point = slab.v[base_v]
    if ends["stalk_mm"] > 0:  # the blade's base, up the midrib past the stalk
        base_point = geo.points_at(mid_pts, geo.arclength(mid_pts), ends["stalk_mm"])
    tip_point = slab.v[tip_v] if ext_tip is None else ext_tip
    return LeafMeasurement(traits, thickness, base_point, tip_point,
                           slab.v[sides.nodes[midrib_idx]],
                           {"rim_length_mm": rim_length, "outline": outline_kind,
                            "border_length_mm": slab.border_length,
                            "tip_extension_mm": tip_extension_mm, **ends})


def _end_corrections(extent: np.ndarray, seen_mm: float, p: LeafScales
                     ) -> tuple[float, float, float, dict[str, float]]:
    """What the leaf's two ends add to its length, perimeter and area (mm, mm, mm²): a tip
    or a base the hull lost (``_lost_tip``), a stalk at the base that is not blade
    (``_stalk``, negative); and those lengths by name."""
    taper_mm = base_taper_mm = stalk_mm = stalk_area = 0.0
    features = None
    if p.tip_taper_mm > 0:
        taper_mm = _lost_tip(extent, seen_mm, p.tip_taper_mm)
        features = tips.tip_features(extent, seen_mm, p.tip_taper_mm, taper_mm)
        if p.tip_model is not None and features is not None:
            taper_mm = tips.load_model(p.tip_model).lost_mm(features, seen_mm)
    if p.stalk_width_mm > 0:
        stalk_mm, stalk_area = _stalk(extent, seen_mm, p.stalk_width_mm)
    if p.base_taper_mm > 0 and stalk_mm <= 0:  # the same taper read from the other end
        base_taper_mm = _lost_tip(extent[::-1], seen_mm, p.base_taper_mm)
    d_length, d_perimeter, d_area = -stalk_mm, -2.0 * stalk_mm, -stalk_area
    for lost_width, lost_mm in ((p.tip_taper_mm, taper_mm), (p.base_taper_mm, base_taper_mm)):
        d_length += lost_mm
        d_perimeter += 2.0 * lost_mm  # both edges of the lost end
        d_area += 0.5 * lost_width * lost_mm  # the lost triangle
    return d_length, d_perimeter, d_area, {"lost_tip_mm": taper_mm, "lost_base_mm": base_taper_mm,
                                           "stalk_mm": stalk_mm, "tip_features": features,
                                           "seen_mm": seen_mm}


# the blade's base taper is fitted up to the first station this share of the leaf's width:
# a blade widening with a rounded shoulder (its taper concave) would pull a longer fit's zero
# toward the stalk
STALK_RISE_SHARE = 0.5


def _stalk(extent: np.ndarray, length_mm: float, stalk_width_mm: float) -> tuple[float, float]:
    """Length and area of a stalk at the leaf's base (0, 0 without one).

    ``extent`` is the leaf's width at stations from base to tip, ``length_mm`` long in all.
    The blade begins at the first two stations at least ``stalk_width_mm`` wide; its base
    taper (those stations up to the first at ``STALK_RISE_SHARE`` of the leaf's width) is
    fitted with a straight line, and the blade's base is where the line reaches zero width,
    between the measured base and the blade's first station.  What lies before it is
    stalk: a leaflet's petiolule, narrower than any blade station, carried by the label.
    A blade that widens from its first station has no stalk.
    """
    n = len(extent)
    wide = extent >= stalk_width_mm
    starts = np.flatnonzero(wide[:-1] & wide[1:])
    if n < 3 or not len(starts) or starts[0] == 0:
        return 0.0, 0.0
    first, step = int(starts[0]), length_mm / n
    x = (np.arange(n) + 1.0) * step  # a station's extent is its widest: on a rise, its end
    width = float(np.percentile(extent[extent > 0], 95))
    risen = np.flatnonzero(extent[first:] >= STALK_RISE_SHARE * width)
    rise = np.arange(first, first + (int(risen[0]) if len(risen) else n - first) + 1)
    rise = rise[rise < n]
    base_mm = first * step  # no fit: the blade's first station's start
    if len(rise) >= 2:
        slope, offset = np.polyfit(x[rise], extent[rise], 1)
        if slope > 0:
            base_mm = -offset / slope
    base_mm = float(np.clip(base_mm, 0.0, x[first]))
    stalk = x <= base_mm
    return base_mm, float(np.sum(extent[stalk]) * step)


def _closed_slab(mesh: Mesh, p: LeafScales) -> _Slab:
    """The label's largest connected piece, lightly smoothed, every hole capped.

    A leaf label may also hold stray crumbs (left by the segmentation): the largest
    piece is measured; the others may carry a blade tip the hull broke off a voxel or
    two from the blade (``_detached_tips``).  A leaf cut from the stem, or holed where
    the segmentation gave a patch to a neighbour, is closed again by a fan over each
    hole; its outline then crosses each cap instead of ending there (caps are not leaf
    surface: no area, no side).
    """
    v0, f = mesh.vertices, mesh.faces
    topo = geo.topology(f)
    detached = None
    piece = geo.components(len(f), topo.face_pairs, np.ones(len(f), bool))
    if piece.max() > 0:  # the areas only to pick the largest of several pieces
        main = piece == np.argmax(np.bincount(piece, mesh.face_areas()))
        detached = (v0, f[~main])
        used, f = np.unique(f[main], return_inverse=True)
        v0, f = v0[used], f.reshape(-1, 3)
        topo = geo.topology(f)
    edge_mm = float(np.mean(geo.row_norm(v0[topo.edges[:, 0]] - v0[topo.edges[:, 1]])))
    vop = geo.vertex_adjacency_operator(len(v0), topo.edges)
    v = geo.taubin(v0, vop, geo.diffusion_steps(p.smoothing_mm, edge_mm, 50))
    border = topo.edges[topo.edge_face_count == 1]
    border_length = float(geo.row_norm(v[border[:, 0]] - v[border[:, 1]]).sum())
    n_leaf, leaf_topo, capped_topo = len(f), topo, topo
    if topo.border_edges:
        v, f = close_holes(v, f, topo, 2.0 * edge_mm)
        capped_topo = None  # the capped slab's topology, built only if the outline needs it
    return _Slab(v, f, n_leaf, capped_topo, leaf_topo, edge_mm, border_length, detached)


def _leaf_faces_geometry(slab: _Slab) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids, normals and areas of the leaf's own faces (not the caps)."""
    fn, fa = geo.face_normals_areas(slab.v, slab.f[slab.leaf])
    return geo.face_centroids(slab.v, slab.f[slab.leaf]), fn, fa


def _face_sides(slab: _Slab, vert_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) ``n . N`` of every face (caps included; > 0 side A, < 0 side B) and (F,) areas."""
    fn, fa = geo.face_normals_areas(slab.v, slab.f)
    face_axis = vert_axis[slab.f].sum(axis=1)  # cells are oriented: corner axes agree in sign
    face_axis /= np.maximum(geo.row_norm(face_axis), 1e-12)[:, None]
    return np.einsum("ij,ij->i", fn, face_axis), fa


def _outline(slab: _Slab, vert_axis: np.ndarray, face_side: np.ndarray, fa: np.ndarray,
             p: LeafScales) -> tuple[float, str, list[np.ndarray]]:
    """The rim crest's length, which line it is, and its pieces (``_outline_length``): the
    crest on the leaf as it is (an outline open at the stem cut is closed by its chord),
    the two sides' border on the capped slab."""
    sigma = p.outline_smoothing_mm
    vertex_side = np.einsum("ij,ij->i", geo.vertex_normals(slab.v, slab.f[slab.leaf]),
                            vert_axis)
    return _outline_length(slab, vertex_side, face_side, fa, sigma)


SIDE_CREST = 0.35  # a vertex with a face this close to edge-on (|n . N|) is on both sides


def _side_graphs(slab: _Slab, face_side: np.ndarray, p: LeafScales) -> _Sides:
    """Geodesic graphs on a resampled copy of each side of the slab.

    A shortest path along mesh edges of a marching-cubes grid is a staircase (up to
    ~40 % too long on a diagonal); joining every pair of points closer than 3 spacings
    makes the path directions dense enough.  A vertex is on side A (B) when one of its
    faces faces A (B) or is a rim face; the crest is the vertices on both, and its
    points are shared by both sides' graphs, so paths of both sides end on them.
    Points a 200th of the leaf's size apart give paths as exact as denser ones (their
    error scales with spacing / length), and far cheaper on a big leaf.
    """
    v, f, n = slab.v, slab.f, slab.n_leaf
    fmax = np.full(len(v), -np.inf)
    fmin = np.full(len(v), np.inf)
    for c in range(3):  # leaf faces only: a cap's normal says nothing about the sides
        np.maximum.at(fmax, f[:n, c], face_side[:n])
        np.minimum.at(fmin, f[:n, c], face_side[:n])
    on_a, on_b = fmax > -SIDE_CREST, fmin < SIDE_CREST
    spacing = max(p.graph_spacing_mm, slab.edge_mm,
                  float(np.linalg.norm(np.ptp(v, axis=0))) / p.graph_points_per_size)
    pts = [_downsample(np.flatnonzero(sel), v, spacing)
           for sel in (on_a & on_b, on_a & ~on_b, on_b & ~on_a)]
    nodes = np.concatenate(pts)
    q = v[nodes]
    kind = np.repeat([0, 1, 2], [len(x) for x in pts])
    g_all, g_a, g_b = _radius_graphs(q, kind, 3.0 * spacing)
    crest = np.arange(len(pts[0])) if len(pts[0]) else np.arange(len(nodes))
    return _Sides(nodes, q, crest, g_all, g_a, g_b, spacing)


def _base_and_tip(sides: _Sides, base_hint: np.ndarray | None
                  ) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Base, tip (node indices), distances and predecessors from the base over the surface.

    Base and tip are the two ends of the leaf's geodesic diameter (double sweep); the
    base is the end nearer to where the leaf attaches.  (The crest point nearest to the
    stem is not used directly: a drooping blade's tip may hang close to another stem.)
    """
    crest, g = sides.crest, sides.g_all
    d0 = geo.shortest_paths(g, int(crest[0]))[0]
    end1 = int(crest[np.argmax(np.where(np.isfinite(d0[crest]), d0[crest], -1))])
    d1, pred1 = geo.shortest_paths(g, end1)
    end2 = int(crest[np.argmax(np.where(np.isfinite(d1[crest]), d1[crest], -1))])
    if base_hint is not None:
        hint = np.asarray(base_hint, float)
        if np.linalg.norm(sides.q[end2] - hint) < np.linalg.norm(sides.q[end1] - hint):
            d2, pred2 = geo.shortest_paths(g, end2)
            return end2, end1, d2, pred2
    return end1, end2, d1, pred1


def _midrib_length(sides: _Sides, base: int, tip: int, dist_b: np.ndarray,
                   midrib_idx: np.ndarray, sigma: float, rim_excess: float
                   ) -> tuple[float, np.ndarray]:
    """Base-to-tip length over the two sides (``_two_side_length``) and the smoothed midrib.

    A path over one side is never twice the shortest path over both (the limit is for
    speed).  Where neither side joins base and tip on its own (a side broken by phantom
    volume or the segmentation): the shortest path over the whole surface.
    """
    q = sides.q
    length = _two_side_length([sides.g_a, sides.g_b], q, base, tip, sigma,
                              2.0 * dist_b[tip]) - rim_excess
    mid_pts = geo.smooth_polyline(q[midrib_idx], sigma) if len(midrib_idx) > 2 else q[midrib_idx]
    if not np.isfinite(length):
        length = geo.polyline_length(mid_pts)
    return float(length), mid_pts


def _detached_tips(sides: _Sides, base: int, tip: int, detached, sigma: float,
                   both_ends: bool) -> tuple[float, float, np.ndarray | None]:
    """Length, area and new tip point the label's other pieces add beyond the tip (beyond
    the base too when nothing says where the leaf attaches: with a stem, a piece beyond
    the base is a crumb between leaf and stem)."""
    total, area, ext_tip = 0.0, 0.0, None
    for start, end in [(base, tip)] + ([(tip, base)] if both_ends else []):
        ext, ext_area, ext_end = _tip_extension(sides.q, sides.g_all, start, end, detached,
                                                sides.spacing, sigma)
        if ext > 0:
            total += ext
            area += ext_area
            if end == tip:
                ext_tip = ext_end
    return total, area, ext_tip


WIDTH_PATH_SLACK = 1.25  # a rim-to-rim path longer than this x the lateral extent went astray
WIDTH_MAX_BINS = 60  # the widest lateral extent is read in at most this many bins along the
# midrib (each at least two path-point spacings long): finer bins only add noise to the max


def _width(sides: _Sides, mid_pts: np.ndarray, dist_b: np.ndarray, outline_lines: list,
           sheet: tuple, edge_mm: float, rim_excess: float, p: LeafScales
           ) -> tuple[float, np.ndarray]:
    """The widest station's rim-to-rim width (``_station_extents``, then the two-side path),
    and the lateral extent at every station (base to tip).

    At the ``width_stations`` stations of largest lateral extent the same two-side path
    runs rim to rim (right for a leaf curled across); a path shorter than the extent, or
    more than ``WIDTH_PATH_SLACK`` x longer, went round a gap or a misplaced rim point:
    the extent is used there.
    """
    extent, station, valid, lateral = _station_extents(sides, mid_pts, dist_b, outline_lines,
                                                       sheet, edge_mm, p)
    width = 0.0
    for st in np.argsort(-extent)[: p.width_stations]:
        if extent[st] <= 0:
            break
        in_st = np.flatnonzero(station == st)
        if not len(in_st):  # the outline crosses this station, no crest node does
            width = max(width, float(extent[st]))
            continue
        li = valid[in_st[np.argmax(lateral[in_st])]]
        ri = valid[in_st[np.argmin(lateral[in_st])]]
        w = _two_side_length([sides.g_a, sides.g_b], sides.q, int(li), int(ri),
                             p.path_smoothing_mm,
                             1.5 * extent[st] + 10 * sides.spacing) - rim_excess
        if not (np.isfinite(w) and extent[st] <= w <= WIDTH_PATH_SLACK * extent[st]):
            w = float(extent[st])
        width = max(width, w)
    return width, extent


# the taper starts at the last station this share of the leaf's width wide: below 1, a
# parallel-sided blade's station-to-station jitter does not move it to mid-blade
TAPER_START_SHARE = 0.9


# the lost tip is at most this share of the seen length: where the taper's slope is near
# zero (a blade parallel-sided to its measured end) the extrapolation has no bound
# (grass development seeds 0-29: 0.2 and 0.3 alike, 37 of 344 blades reach it)
LOST_TIP_MAX_SHARE = 0.3
# the taper's slope is fitted over at least this many stations, else read from two
# (the taper's start and the measured end, the drop at least half the leaf's width)
TAPER_FIT_STATIONS = 3


def taper_stations(extent: np.ndarray, lost_width_mm: float) -> tuple[float, int, np.ndarray]:
    """``(width, last, taper)`` of a leaf with some width: the 95th percentile of its
    station extents, the last station ``TAPER_START_SHARE`` of that wide (where the taper
    starts), and the taper's stations from there still ``lost_width_mm`` wide (what
    ``_lost_tip`` and the tip model's features fit the taper to)."""
    width = float(np.percentile(extent[extent > 0], 95))
    last = int(np.flatnonzero(extent >= TAPER_START_SHARE * width)[-1])
    taper = np.arange(last, len(extent))
    return width, last, taper[extent[taper] >= lost_width_mm]


def _lost_tip(extent: np.ndarray, length_mm: float, lost_width_mm: float) -> float:
    """Length of the tip the hull lost where the leaf is narrower than ``lost_width_mm``.

    The leaf's width is the 95th percentile of its station extents (one station swollen
    by phantom volume does not set it); the taper runs from the last station
    ``TAPER_START_SHARE`` of that wide to the measured end.  Its slope is the straight
    line fitted to the extents of the taper's stations still ``lost_width_mm`` wide (the
    hull's rounded end is narrower, and left out), and the tip reaches zero width
    ``lost_width_mm / slope`` beyond where the hull cut it, at most
    ``LOST_TIP_MAX_SHARE`` of the seen length.  With fewer than ``TAPER_FIT_STATIONS``
    such stations, or no fall along them, the slope is read from the taper's start to
    the measured end as if it were ``lost_width_mm`` wide there.
    Session 23, grass development seeds 0-29 (344 matched blades, labels as segmented,
    rims put out): ε median length 5.4 -> 4.3 % against the slope read from two points
    alone (session 20), which blew up where a narrow blade's width is near
    ``lost_width_mm`` (+100-230 mm on 60-190 mm blades); dicot development seeds 0-29
    (1 unit): 1.47 -> 1.54 % (docs/leaves.md, "Lost tips").
    """
    seen = extent[extent > 0]
    if not len(seen) or length_mm <= 0:
        return 0.0
    width, last, taper = taper_stations(extent, lost_width_mm)
    start_width = TAPER_START_SHARE * width
    n = len(extent)
    run = length_mm * (1.0 - (last + 0.5) / n)
    cap = LOST_TIP_MAX_SHARE * length_mm
    if len(taper) >= TAPER_FIT_STATIONS:
        slope = -np.polyfit((taper + 0.5) / n * length_mm, extent[taper], 1)[0]
        if slope > 0:
            return float(min(lost_width_mm / slope, cap))
    drop = max(start_width - lost_width_mm, 0.5 * width)
    return float(min(lost_width_mm * run / drop, cap))


def _station_extents(sides: _Sides, mid_pts: np.ndarray, dist_b: np.ndarray,
                     outline_lines: list, sheet: tuple, edge_mm: float, p: LeafScales):
    """Lateral extent of the leaf at stations along the smoothed midrib.

    Crest points (of the base's piece) are binned in stations along the midrib and
    their lateral offset measured across it in the local leaf plane (exact for a leaf
    flat across).  Where the outline passes a station, its lateral extent is the one
    used: the crest nodes at a station's extremes sit on the peaks of the rough rim's
    zig-zag (+0.3…+2 mm on 512^3 dicot hulls), the outline smoothed at the zig-zag's
    scale (two mean edges: a marching-cubes rim zig-zags over a few voxels) does not,
    and at leaf-scale curvature (radius >= 30 mm) that smoothing moves it by < 0.03 mm.
    Returns (extent per station, station of each crest point, the crest nodes, their
    lateral offsets).
    """
    from scipy.spatial import cKDTree

    q, crest = sides.q, sides.crest
    mid_axis = _axes_at(mid_pts, *sheet, p.sheet_scale_mm)
    tangent = np.gradient(mid_pts, axis=0) if len(mid_pts) > 1 else np.zeros((1, 3))
    across = np.cross(tangent, mid_axis)
    unit_across = across / np.maximum(geo.row_norm(across), 1e-12)[:, None]
    valid = crest[np.isfinite(dist_b[crest])]
    tree = cKDTree(mid_pts)
    _, k = tree.query(q[valid])
    lateral = np.einsum("ij,ij->i", q[valid] - mid_pts[k], unit_across[k])
    mid_len = geo.polyline_length(mid_pts)
    nbins = max(int(mid_len / max(2.0 * sides.spacing, mid_len / WIDTH_MAX_BINS)), 1)

    def extents(ks: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = np.minimum((ks * nbins) // len(mid_pts), nbins - 1)
        hi = np.full(nbins, -np.inf)
        lo = np.full(nbins, np.inf)
        np.maximum.at(hi, st, lat)
        np.minimum.at(lo, st, lat)
        return st, hi, lo

    station, u_max, u_min = extents(k, lateral)
    extent = np.where(np.isfinite(u_max) & np.isfinite(u_min), u_max - u_min, 0.0)
    pieces = [geo.smooth_polyline(line, 2.0 * edge_mm) for line in outline_lines
              if len(line) > 2]
    if pieces:
        op = np.concatenate(pieces)
        _, ko = tree.query(op)
        _, o_max, o_min = extents(ko, np.einsum("ij,ij->i", op - mid_pts[ko], unit_across[ko]))
        seen = np.isfinite(o_max) & np.isfinite(o_min) & (o_max > 0) & (o_min < 0)
        extent = np.where(seen, o_max - o_min, extent)
    return extent, station, valid, lateral


def thick_shares(mesh: Mesh, face_labels: np.ndarray, leaf_labels: list[int],
                 unit_mm: float | None = None) -> dict[int, tuple[float, float]]:
    """``{leaf: (share, median mm)}``: the share of each leaf's area where the mesh is over
    ``THICK_FACTOR`` x the leaf's median thickness there, and that median.

    The thickness at a face is how far a ray from it along its inward normal runs
    before it leaves the closed surface of the whole plant (Open3D's ray casting),
    read at ``THICK_SAMPLE`` faces of the leaf drawn at random, weighted by area.  A
    leaf's slab is about as thick everywhere (the hull of a thin sheet); where the
    surface is several times thicker it is not the leaf's own: phantom volume the
    views could not carve (a young leaf folded against its neighbours) or another
    organ fused with it, and the traits measured there carry it.  Rays that leave
    through nothing (a numerically open spot) are not counted.  ``unit_mm``: the
    mesh's ``geometry.mesh_unit`` when the caller has it (a median over every edge).
    """
    v, f = mesh.vertices, mesh.faces
    out: dict[int, tuple[float, float]] = {}
    if not len(f) or not leaf_labels:
        return out
    scene = geo.raycasting_scene(v, f)
    rng = np.random.default_rng(0)  # the same figure from the same mesh
    eps = 1e-3 * (unit_mm or geo.mesh_unit(v, f))  # off the face, well inside any slab
    for label in leaf_labels:
        ids = np.flatnonzero(face_labels == label)
        if not len(ids):
            continue
        # faces drawn uniformly, weighted by their area: the area share without the areas
        # of all faces (a marching-cubes mesh's faces differ in area by a few times only)
        pick = ids[rng.integers(0, len(ids), THICK_SAMPLE)]
        fn, fa = geo.face_normals_areas(v, f[pick])
        centre = geo.face_centroids(v, f[pick])
        rays = np.hstack([centre - eps * fn, -fn]).astype(np.float32)
        t = scene.t_hit(rays)
        hit = np.isfinite(t)
        if hit.any() and fa[hit].sum() > 0:
            median = float(np.median(t[hit]))
            thick = t[hit] > THICK_FACTOR * median
            out[label] = (float(fa[hit][thick].sum() / fa[hit].sum()), median)
    return out


def in_phantom(leaf: LeafTraits) -> bool:
    """Whether ``leaf``'s ``thick_share`` reaches ``THICK_WARN_SHARE``."""
    return bool(leaf.thick_share >= THICK_WARN_SHARE)


def short_outline(leaf: LeafTraits) -> bool:
    """Whether ``leaf``'s perimeter is under ``MIN_PERIMETER_PER_LENGTH`` x its length."""
    return leaf.length_mm > 0 and leaf.perimeter_mm < MIN_PERIMETER_PER_LENGTH * leaf.length_mm


def warned(leaf: LeafTraits) -> bool:
    """Whether the measurer warns about ``leaf``: phantom volume (``thick_share``) or a
    perimeter too short for its length."""
    return in_phantom(leaf) or short_outline(leaf)


def inconsistent_leaves(leaves: list[LeafTraits]) -> list[StageWarning]:
    """Warnings for leaves whose perimeter is under ``MIN_PERIMETER_PER_LENGTH`` x their length.

    Whatever its shape, a leaf's outline goes from base to tip along one edge and back
    along the other, and neither edge is shorter than the shortest path from base to tip
    that the length follows; a perimeter much under twice the length says that the
    length ran on into another organ or that the outline was traced wrong (a leaf holed
    by the segmentation).  The traits are kept: which of the two is wrong is not known.
    """
    out = []
    for lf in leaves:
        if short_outline(lf):
            out.append(StageWarning(
                "short-outline", f"leaf {lf.leaf_id}: perimeter {lf.perimeter_mm:.1f} mm is "
                f"under {MIN_PERIMETER_PER_LENGTH:g}x its length {lf.length_mm:.1f} mm; an "
                "outline runs base to tip and back, so one of the two is wrong (a length "
                "run into another organ, or an outline of a holed leaf)", lf.leaf_id))
    return out


def _tip_extension(q: np.ndarray, g: sparse.csr_matrix, base: int, tip: int,
                   detached: tuple[np.ndarray, np.ndarray], spacing: float, sigma: float
                   ) -> tuple[float, float, np.ndarray]:
    """How far the leaf's other pieces carry its midrib beyond the measured tip.

    Where a blade's tip is narrower than about a voxel the hull breaks it off (grasses:
    10-25 mm pieces 0.7-2 mm from the blade); the segmentation gives such a piece to
    its leaf (``tips_to_leaf``), and here the path graph of the main piece (``q``
    points, graph ``g`` joining points closer than 3 ``spacing``) is extended by the
    detached pieces' points, joined the same way.  If the point farthest from ``base``
    then lies on a detached piece, the leaf is longer by the smoothed path to it less
    the smoothed path to ``tip``; pieces beside the blade change nothing.

    Returns the extension (mm, 0 if none), the planform area of the detached pieces
    the path reaches (mm², their surface projected on their own sheet axis, halved: one
    side) and the new tip point (3,).
    """
    from scipy.spatial import cKDTree

    v_all, f_det = detached
    used = np.unique(f_det)
    pts = v_all[_downsample(used, v_all, spacing)]
    n = len(q)
    allp = np.concatenate([q, pts])
    radius = 3.0 * spacing
    # only the new edges (to or among detached points): the main graph is reused
    pairs = cKDTree(allp).query_pairs(radius, output_type="ndarray")
    pairs = pairs[pairs[:, 1] >= n]  # i < j, so every new edge has j on a detached piece
    if not len(pairs):
        return 0.0, 0.0, q[tip]
    w = np.maximum(geo.row_norm(allp[pairs[:, 0]] - allp[pairs[:, 1]]), 1e-9)
    m = len(allp)
    g_new = sparse.csr_matrix((np.concatenate([w, w]),
                               (np.concatenate([pairs[:, 0], pairs[:, 1]]),
                                np.concatenate([pairs[:, 1], pairs[:, 0]]))), shape=(m, m))
    g_old = sparse.csr_matrix((g.data, g.indices,
                               np.concatenate([g.indptr, np.full(m - n, g.indptr[-1])])),
                              shape=(m, m))
    dist, pred = geo.shortest_paths((g_old + g_new).tocsr(), base)
    reach = np.isfinite(dist)
    far = int(np.argmax(np.where(reach, dist, -1.0)))
    if far < n:
        return 0.0, 0.0, q[tip]
    to_far = geo.polyline_length(geo.smooth_polyline(allp[_path(pred, far)], sigma))
    to_tip = geo.polyline_length(geo.smooth_polyline(allp[_path(pred, tip)], sigma))
    ext = to_far - to_tip
    if ext <= 0:
        return 0.0, 0.0, q[tip]
    # area of the detached faces near a reached point
    reached = allp[n:][reach[n:]]
    fc = v_all[f_det].mean(axis=1)
    near = cKDTree(reached).query(fc, distance_upper_bound=spacing)[0] < np.inf
    fn, fa = geo.face_normals_areas(v_all, f_det[near])
    # projected on the pieces' own sheet axis (principal axis of their normal tensor), as
    # the leaf's area is: half the surface would count the rim and the cut faces of a piece
    # as thick as it is narrow
    axis = np.linalg.eigh(np.einsum("i,ij,ik->jk", fa, fn, fn))[1][:, 2]
    return float(ext), 0.5 * float(np.sum(fa * np.abs(fn @ axis))), allp[far]


def close_holes(v: np.ndarray, f: np.ndarray, topo: geo.MeshTopology, min_loop_mm: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Cap every border loop at least ``min_loop_mm`` long by a fan around its centroid.

    Returns the vertices ``(V + H, 3)`` (one centroid per hole appended) and
    faces ``(F + B, 3)`` (one cap face per border edge, wound to match the
    face on the other side of that edge).
    """
    border = topo.edge_face_count[topo.face_edges] == 1  # (F, 3) side k = (f[k], f[k+1])
    fi, k = np.nonzero(border)
    a, b = f[fi, k], f[fi, (k + 1) % 3]
    nv = len(v)
    g = sparse.csr_matrix((np.ones(len(a)), (a, b)), shape=(nv, nv))
    _, comp = connected_components(g, directed=False)
    loops, loop_of = np.unique(comp[a], return_inverse=True)
    # seams of coincident vertices (a closed truth mesh may have them) are not holes
    loop_len = np.bincount(loop_of, geo.row_norm(v[a] - v[b]), len(loops))
    real = loop_len[loop_of] >= min_loop_mm
    a, b, loop_of = a[real], b[real], loop_of[real]
    if len(a) == 0:
        return v, f
    loops, loop_of = np.unique(loop_of, return_inverse=True)
    count = np.bincount(loop_of, minlength=len(loops)).astype(float)
    centre = np.stack([np.bincount(loop_of, 0.5 * (v[a, c] + v[b, c]), len(loops))
                       for c in range(3)], axis=1) / count[:, None]
    caps = np.stack([b, a, nv + loop_of], axis=1)
    return np.vstack([v, centre]), np.vstack([f, caps])


def _largest_piece(nf: int, pairs: np.ndarray, member: np.ndarray, area: np.ndarray
                   ) -> np.ndarray:
    """(F,) bool: the connected piece of ``member`` faces with the largest area."""
    sel = member[pairs[:, 0]] & member[pairs[:, 1]]
    g = sparse.csr_matrix((np.ones(int(sel.sum()), np.int8), (pairs[sel, 0], pairs[sel, 1])),
                          shape=(nf, nf))
    _, comp = connected_components(g, directed=False)
    piece_area = np.bincount(comp[member], area[member], comp.max() + 1)
    return member & (comp == np.argmax(piece_area))


def _outline_length(slab: _Slab, vertex_side: np.ndarray, face_side: np.ndarray,
                    area: np.ndarray, sigma: float) -> tuple[float, str, list[np.ndarray]]:
    """Length (mm) of the rim crest of a slab, smoothed by ``sigma`` mm, how it was traced,
    and its raw pieces (each ``(P, 3)`` mm, in order along the line).

    ``slab.v, slab.f, slab.topo`` is the capped slab (``topo`` None: not built yet),
    its first ``n_leaf`` faces (topology ``leaf_topo``) the leaf's own.  ``"crest"``: the
    zero line of
    ``vertex_side`` (n . N at the vertices), exact where the rim is clean, over
    the leaf's own faces when its open border is short (a cut at the base,
    closed by its chord) and over the capped slab otherwise; used when it is
    one outline (one piece holding
    ``CLEAN_OUTLINE_SHARE`` of its length).  Otherwise (islands where a rough
    surface turns edge-on, phantom hull volume, a leaf holed by the segmentation)
    ``"sides"``: side A is the largest piece of the faces with ``face_side > 0``,
    side B the largest piece of the rest, everything else joins A, and the
    outline is the zero line of their ±area summed at the vertices: one loop
    between the two sides, placed within a triangle (so coarse triangles make it
    a little short: -1 % to -4 % on the truth meshes' 4 mm triangles).
    """
    v, f, topo, leaf_topo = slab.v, slab.f, slab.topo, slab.leaf_topo
    leaf_faces = f[slab.leaf]
    nf = len(f)
    e = leaf_topo.edges[leaf_topo.edge_face_count == 1]
    border = float(geo.row_norm(v[e[:, 0]] - v[e[:, 1]]).sum())
    # a cut at the base is closed well by its chord (the leaf as it is); a leaf with a long
    # open border (holed by the segmentation) is traced on its capped slab
    lines: list[np.ndarray] = []
    crest = _iso_line_lengths(v, leaf_faces, leaf_topo, vertex_side, sigma, lines)
    total = sum(crest)
    clean = total > 0 and max(crest) >= CLEAN_OUTLINE_SHARE * total
    if clean and border <= CUT_BORDER_SHARE * max(crest):
        return _longest_crest(crest, lines)
    if len(f) > len(leaf_faces):
        topo = topo if topo is not None else geo.topology(f)
        lines = []
        crest = _iso_line_lengths(v, f, topo, vertex_side, sigma, lines)
        total = sum(crest)
        if total > 0 and max(crest) >= CLEAN_OUTLINE_SHARE * total:
            return _longest_crest(crest, lines)
    elif clean:
        return _longest_crest(crest, lines)
    topo = topo if topo is not None else leaf_topo
    side_a = face_side > 0
    if nf == 0 or not side_a.any() or side_a.all():
        return _longest_crest(crest, lines) if crest else (0.0, "crest", [])
    a_main = _largest_piece(nf, topo.face_pairs, side_a, area)
    b_main = _largest_piece(nf, topo.face_pairs, ~a_main, area)
    face_val = np.where(b_main, -area, area)
    val = sum(np.bincount(f[:, k], face_val, len(v)) for k in range(3))
    lines = []
    pieces = _iso_line_lengths(v, f, topo, val, sigma, lines)
    # one loop in principle; a pinch where the two sides touch at a vertex may split it
    return float(sum(pieces)), "sides", lines


def _longest_crest(crest: list[float], lines: list[np.ndarray]
                   ) -> tuple[float, str, list[np.ndarray]]:
    """``_outline_length``'s answer from the longest crest piece (``lines`` in step)."""
    i = int(np.argmax(crest))
    return crest[i], "crest", [lines[i]]


def _iso_line_lengths(v: np.ndarray, f: np.ndarray, topo: geo.MeshTopology, value: np.ndarray,
                      sigma: float, lines: list[np.ndarray] | None = None) -> list[float]:
    """Lengths (mm) of the pieces of the zero iso-line of the vertex field ``value``.

    Crossing points sit on mesh edges; each face with a sign change links two
    of them.  Chains are walked into polylines (closed when they close; specks
    left out, see ``_chains``) and smoothed by ``sigma`` mm of arclength before
    measuring; an open chain with both ends on the mesh border (a leaf cut from
    the stem) is closed by its chord.
    """
    pos = value > 0
    e = topo.edges
    crossing = pos[e[:, 0]] != pos[e[:, 1]]
    if not crossing.any():
        return []
    ce = np.flatnonzero(crossing)
    t = value[e[ce, 0]] / (value[e[ce, 0]] - value[e[ce, 1]])
    point_of_edge = np.full(len(e), -1)
    point_of_edge[ce] = np.arange(len(ce))
    pts = v[e[ce, 0]] + t[:, None] * (v[e[ce, 1]] - v[e[ce, 0]])
    on_border = topo.edge_face_count[ce] == 1
    fe = point_of_edge[topo.face_edges]  # (F, 3) crossing point on each side or -1
    two = (fe >= 0).sum(axis=1) == 2
    links = np.sort(fe[two], axis=1)[:, 1:]  # the two crossing points of each such face
    chains: list[float] = []
    raw_links = geo.row_norm(pts[links[:, 0]] - pts[links[:, 1]])
    for chain, closed in _chains(links, len(pts), raw_links):
        if lines is not None:  # the raw line of each piece, in step with the lengths
            lines.append(pts[chain])
        # smoothing removes the zig-zag but also shrinks the curve by sigma^2/2 of its
        # curvature: that length is added back (geometry.smoothing_shrinkage), with the
        # curvature of the line smoothed twice as much (a wiggle of wavelength l left by
        # sigma is damped as exp(-2 pi^2 sigma^2 / l^2), by 2 sigma four times as hard
        # in the exponent; the outline's own curvature barely changes)
        if closed:
            loop = pts[chain]
            chains.append(geo.polyline_length(_closed_smooth(loop, sigma))
                          + geo.smoothing_shrinkage(_closed_smooth(loop, 2.0 * sigma), sigma,
                                                    closed=True, curve_sigma_mm=2.0 * sigma))
            continue
        poly = pts[chain]
        length = (geo.polyline_length(geo.smooth_polyline(poly, sigma))
                  + geo.smoothing_shrinkage(geo.smooth_polyline(poly, 2.0 * sigma), sigma,
                                            curve_sigma_mm=2.0 * sigma))
        chord = float(np.linalg.norm(poly[-1] - poly[0]))
        if on_border[chain[0]] and on_border[chain[-1]] and chord < 0.5 * length:
            # an outline broken where the leaf was cut from the stem: close it by the chord
            length += chord
        chains.append(length)
    return chains



def _chains(links: np.ndarray, n: int, link_length: np.ndarray, walk_share: float = 0.05
            ) -> list[tuple[np.ndarray, bool]]:
    """Walk the graph of ``links`` (L, 2) over ``n`` nodes into chains ``(nodes, closed)``.

    Iso-lines and outlines are unions of paths and cycles (every node has one
    or two links): a depth-first order from an end (or any node of a cycle)
    walks each piece in sequence.  Pieces shorter than ``walk_share`` of the
    longest (sum of ``link_length``) are left out: specks where a rough surface
    turns edge-on, which smoothing by a few mm would shrink to nothing anyway.
    """
    if len(links) == 0:
        return []
    g = sparse.csr_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n))
    g = ((g + g.T) > 0).astype(np.int8)
    degree = np.diff(g.indptr)
    ncomp, comp = connected_components(g, directed=False)
    raw = np.bincount(comp[links[:, 0]], link_length, ncomp)
    small = raw < walk_share * raw.max()
    out = []
    # start each piece at an end if it has one (an open chain), else anywhere (a loop)
    ends = np.flatnonzero(degree == 1)
    start = np.full(ncomp, -1)
    start[comp[ends[::-1]]] = ends[::-1]
    anywhere = np.flatnonzero(degree > 0)
    first = np.full(ncomp, -1)
    first[comp[anywhere[::-1]]] = anywhere[::-1]
    for c in np.flatnonzero(~small):
        s0 = start[c] if start[c] >= 0 else first[c]
        if s0 < 0:
            continue  # an unlinked node
        order, pred = depth_first_order(g, int(s0), directed=False)
        # where a node has three links (a non-manifold edge) the search backtracks: cut there
        jump = np.flatnonzero(pred[order[1:]] != order[:-1]) + 1
        for piece in np.split(order, jump):
            closed = len(piece) > 2 and g[piece[-1], piece[0]] > 0
            out.append((piece, bool(closed)))
    return out


def _closed_smooth(loop: np.ndarray, sigma: float) -> np.ndarray:
    sm = geo.smooth_polyline(np.concatenate([loop, loop[:1]]), sigma, closed=True)
    return np.concatenate([sm, sm[:1]])


def _downsample(idx: np.ndarray, v: np.ndarray, spacing: float) -> np.ndarray:
    """One vertex of ``idx`` per cubic cell of ``spacing`` mm."""
    if len(idx) == 0:
        return idx
    cell = np.floor((v[idx] - v[idx].min(axis=0)) / spacing).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]  # cells in x, y, z order
    # per cell keep the vertex farthest from the leaf's centre: in rim cells that is the
    # outermost crest vertex, so the base, tip and widest points are not pulled inwards
    far = -geo.row_norm(v[idx] - v[idx].mean(axis=0))
    order = np.lexsort((far, key))
    k = key[order]
    first = np.concatenate([[True], k[1:] != k[:-1]])
    return idx[np.sort(order[first])]


def _radius_graphs(q: np.ndarray, kind: np.ndarray, radius: float
                   ) -> tuple[sparse.csr_matrix, sparse.csr_matrix, sparse.csr_matrix]:
    """Graphs joining points closer than ``radius``: all, side A + crest, side B + crest.

    ``kind`` is 0 for crest points, 1 for side A, 2 for side B.  Symmetric (each edge
    stored both ways): search them with ``directed=True``.
    """
    from scipy.spatial import cKDTree

    pairs = cKDTree(q).query_pairs(radius, output_type="ndarray")
    w = np.maximum(geo.segment_lengths(q, pairs[:, 0], pairs[:, 1]), 1e-9)
    # built once: the side graphs share its structure, with the other side's edges made
    # impassable (infinite); both directions stored (pairs are i < j, so none is summed
    # twice): a dijkstra with directed=False would build this symmetric copy on every call
    g_all, pair_of = geo.pair_graph(len(q), pairs)
    g_all.data = w[pair_of]
    ka, kb = kind[pairs[:, 0]], kind[pairs[:, 1]]
    g_a, g_b = g_all.copy(), g_all.copy()
    g_a.data = np.where(((ka != 2) & (kb != 2))[pair_of], g_all.data, np.inf)
    g_b.data = np.where(((ka != 1) & (kb != 1))[pair_of], g_all.data, np.inf)
    return g_all, g_a, g_b


def _enclosed_volume(v: np.ndarray, f: np.ndarray) -> float:
    """Volume (mm³) enclosed by a closed, outward-oriented surface (divergence theorem)."""
    p = v[f]
    return float(abs(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum()) / 6.0)


def plant_traits(mesh: Mesh, leaves: list[LeafTraits], pixel_mm: float | None = None,
                 geometry: dict[str, float] | None = None) -> dict[str, float]:
    """Plant-level traits of the whole mesh (stem and leaves).

    ``height_mm`` (above the pot's rim, ``mesh.base_z_mm``; without it the vertical
    extent), ``total_leaf_area_mm2``, ``leaf_count``,
    ``convex_hull_volume_mm3`` and ``projected_area_mm2`` (area of the top
    view shadow, rasterised at ``pixel_mm``; default a quarter of the mesh unit).
    ``geometry``: ``plant_geometry(mesh, pixel_mm)`` when the caller has it.
    """
    out: dict[str, float] = {
        "height_mm": 0.0,
        "total_leaf_area_mm2": float(sum(x.area_mm2 for x in leaves)),
        "leaf_count": len(leaves),
    }
    out.update(geometry if geometry is not None else plant_geometry(mesh, pixel_mm))
    return out


def plant_geometry(mesh: Mesh, pixel_mm: float | None = None) -> dict[str, float]:
    """The plant traits of ``plant_traits`` that need the mesh alone (``height_mm``,
    ``convex_hull_volume_mm3``, ``projected_area_mm2``): ``measure_plant`` works them out
    while the leaves are measured."""
    out = {"height_mm": 0.0, "convex_hull_volume_mm3": 0.0, "projected_area_mm2": 0.0}
    if mesh.is_empty:
        return out
    v = mesh.vertices
    base = v[:, 2].min() if mesh.base_z_mm is None else mesh.base_z_mm
    out["height_mm"] = float(v[:, 2].max() - base)
    pixel_mm = pixel_mm or PROJECTION_PIXEL_UNITS * geo.mesh_unit(v, mesh.faces)
    try:
        from scipy.spatial import ConvexHull

        out["convex_hull_volume_mm3"] = float(ConvexHull(v).volume)
    except Exception as exc:  # flat or degenerate point sets have no hull volume
        log.warning("convex hull volume not measured: %s", exc)
    lo = v[:, :2].min(axis=0) - 2 * pixel_mm
    size = np.ceil((v[:, :2].max(axis=0) + 2 * pixel_mm - lo) / pixel_mm).astype(int) + 1
    # the top-view shadow of a closed surface is covered by its up-facing triangles alone
    up = mesh.faces[geo.face_cross(v, mesh.faces)[:, 2] >= 0]
    shadow = geo.triangle_union_mask((v[up][:, :, :2] - lo) / pixel_mm,
                                     (int(size[1]), int(size[0])))
    out["projected_area_mm2"] = float(shadow.sum()) * pixel_mm * pixel_mm
    return out


class _LeafMeshes:
    """``labelled.submesh(label)`` of any label, cut when asked (one sort of the labels for
    all; each cut writes only its own arrays, so threads may cut at once)."""

    def __init__(self, labelled: LabelledMesh) -> None:
        lab = labelled.face_labels
        self.mesh = labelled.mesh
        self.order = np.argsort(lab, kind="stable")  # keeps each label's faces in mesh order
        self.sorted = lab[self.order]

    def _range(self, label: int) -> slice:
        return slice(np.searchsorted(self.sorted, label),
                     np.searchsorted(self.sorted, label, side="right"))

    def face_count(self, label: int) -> int:
        r = self._range(label)
        return r.stop - r.start

    def submesh(self, label: int) -> Mesh:
        vertices = self.mesh.vertices
        f = self.mesh.faces[self.order[self._range(label)]]
        used = np.zeros(len(vertices), bool)
        used[f.ravel()] = True
        idx = np.flatnonzero(used)
        lut = np.empty(len(vertices), np.int64)  # read only where written
        lut[idx] = np.arange(len(idx))
        return Mesh(vertices[idx], lut[f])


@geo.meshes_unchanged()  # its mesh arrays' digests taken once
def measure_plant(labelled: LabelledMesh, params: LeafGeometryParams | None = None,
                  plant_views: int | None = None
                  ) -> tuple[Traits, list[LeafMeasurement], StageReport]:
    """Traits of every leaf of ``labelled`` and of the whole plant, and the warnings.

    Every leaf gets a confidence and the plant a quality flag (``plantscan_leaves.trust``);
    ``plant_views`` (the views the hull was carved from, when known) is checked against
    ``min_plant_views``.  A mesh with ``rim_vertices`` (the mesher's ``thin_rims:
    measure``) is measured on them: the labels are the segmenter's, the surface the one
    with the thin rims put out.
    """
    p = params or LeafGeometryParams()
    report = StageReport()
    keep_heap_memory()  # as the segmenter: big arrays reuse freed memory
    if labelled.mesh.rim_vertices is not None:
        labelled = LabelledMesh(labelled.mesh.measured(), labelled.face_labels, labelled.kinds,
                                labelled.evidence)
    mesh = labelled.mesh
    if mesh.is_empty:
        msg = "mesh is empty: traits table left empty"
        log.warning(msg)
        report.warn("empty-mesh", msg)
        traits = Traits([], plant_traits(mesh, []))
        _judge(traits, [], labelled, p, plant_views, report)
        return traits, [], report
    leaf_labels = labelled.leaf_labels
    if leaf_labels:  # the thick shares' scene builds while the leaves are measured
        geo.raycasting_scene(mesh.vertices, mesh.faces)
    else:
        msg = "no leaf in the labelled mesh: traits table left empty"
        log.warning(msg)
        report.warn("no-leaf", msg)
    unit = geo.mesh_unit(mesh.vertices, mesh.faces)  # one unit for every leaf of the plant
    geometry, parts, done = _measure_parts(labelled, leaf_labels, p, unit)
    measurements = [m for m, _ in done if m is not None]
    report.warnings += [w for _, w in done if w is not None]
    _thick_and_outline_checks(labelled, measurements, report, unit)
    leaves = [m.traits for m in measurements]
    traits = Traits(leaves, plant_traits(mesh, leaves, geometry=geometry))
    _judge(traits, measurements, labelled, p, plant_views, report, unit, parts)
    return traits, measurements, report


def _measure_parts(labelled: LabelledMesh, leaf_labels: list[int], p: LeafGeometryParams,
                   unit: float):
    """``measure_plant``'s work on both cores: the plant's geometry, (the stem's and
    debris' areas, the trust model's plant context or None), and per leaf of
    ``leaf_labels`` (measurement or None, warning or None)."""
    mesh = labelled.mesh
    stem = _Once(lambda: stem_faces_and_tree(labelled))  # one tree for hints and context
    hints = _Once(lambda: _base_hints(labelled, stem.get()))
    leaf_meshes = _LeafMeshes(labelled)

    def one(leaf_id: int) -> tuple[LeafMeasurement | None, StageWarning | None]:
        sub = leaf_meshes.submesh(leaf_id)
        if len(sub.faces) < p.min_leaf_faces:  # also a leaf label no face carries
            return None, StageWarning("leaf-too-small", f"leaf {leaf_id}: {len(sub.faces)} "
                                      f"faces (fewer than {p.min_leaf_faces}), skipped", leaf_id)
        try:
            m = measure_leaf(sub, leaf_id, p, hints.get()(leaf_id, sub), unit)
        except Exception as exc:  # one odd leaf must not lose the others
            msg = f"leaf {leaf_id}: not measured ({type(exc).__name__}: {exc})"
            log.warning(msg)
            return None, StageWarning("leaf-not-measured", msg, leaf_id)
        if m is None:
            return None, StageWarning("leaf-too-small", f"leaf {leaf_id}: fewer than "
                                      f"{p.min_leaf_faces} faces, skipped", leaf_id)
        return m, None

    def task(item):
        if item == "geometry":
            return plant_geometry(mesh, PROJECTION_PIXEL_UNITS * unit)
        if item == "plant":  # what the plant flag reads of the labels
            hints.get()  # first, while the geometry runs: every leaf waits for them
            return _kind_areas(labelled)
        if item == "context":  # what the trust model reads of the labels
            from plantscan_leaves import trust_model as tm

            return tm.plant_context(labelled, leaf_labels, stem.get())
        return one(item)

    # Leaves are measured independently, on both cores: their numpy/scipy work releases
    # the GIL for most of the time (1.2 M-face dicot hull, 12 leaves: 5.6 -> 3.5 s wall,
    # same CPU, same traits).  The plant's own geometry (hull, top-view shadow: 1 s at
    # 1.7 M faces) goes first; beside it the base hints every leaf needs (found once, with
    # the stem's k-d tree the trust model's plant context reuses) and the stem's and
    # debris' areas; then the leaves largest first, so that no big leaf is left alone on
    # one core at the end, with the trust model's plant context (needed only after them)
    # half-way (rosette 1001, 2.9 M faces: measure 5.6-5.8 s wall against 5.9 s when the
    # context went first and the first leaf found the hints).  Results come back in the
    # leaves' order.
    order = sorted(leaf_labels, key=lambda leaf: -leaf_meshes.face_count(leaf))
    half = len(order) // 2
    items = ["geometry", "plant", *order[:half], *(["context"] if p.trust_model else []),
             *order[half:]]
    out = dict(zip(items, thread_map(task, items)))  # leaf labels are ints, the rest names
    return out["geometry"], (out["plant"], out.get("context")), [out[k] for k in leaf_labels]


class _Once:
    """``make()``'s value, made by the first thread that asks (the others wait for it)."""

    def __init__(self, make) -> None:
        self._make, self._lock, self._value = make, threading.Lock(), None

    def get(self):
        with self._lock:
            if self._make is not None:
                self._value, self._make = self._make(), None
            return self._value


def stem_faces_and_tree(labelled: LabelledMesh):
    """The faces labelled stem ((F,) bool) and a ``cKDTree`` of their vertices (None without
    any): what the base hints and the trust model's plant context look up."""
    mesh = labelled.mesh
    stem_labels = [k for k, kind in labelled.kinds.items() if kind == "stem"]
    stem_faces = (np.isin(labelled.face_labels, stem_labels) if stem_labels
                  else np.zeros(len(labelled.face_labels), bool))
    if not stem_faces.any():
        return stem_faces, None
    from scipy.spatial import cKDTree

    used = np.zeros(len(mesh.vertices), bool)
    used[mesh.faces[stem_faces].ravel()] = True  # a mask, not np.unique: no sort
    return stem_faces, cKDTree(mesh.vertices[used])


def _base_hints(labelled: LabelledMesh, stem: tuple | None = None):
    """``hint(leaf_id, leaf_mesh)``: where the leaf attaches, for ``measure_leaf`` (its stem
    contact, ``_stem_contacts``; else its point nearest to the stem; None without a stem).
    ``stem``: ``stem_faces_and_tree(labelled)`` when the caller has it."""
    stem_faces, tree = stem if stem is not None else stem_faces_and_tree(labelled)
    contacts = _stem_contacts(labelled, stem_faces)

    def hint(leaf_id: int, sub: Mesh) -> np.ndarray | None:
        if leaf_id in contacts or tree is None:
            return contacts.get(leaf_id)
        probe = sub.vertices[:: max(1, len(sub.vertices) // 5000)]  # 5000 are plenty
        d, _ = tree.query(probe)
        return probe[int(np.argmin(d))]

    return hint


def _stem_contacts(labelled: LabelledMesh, stem_faces: np.ndarray) -> dict[int, np.ndarray]:
    """Where each leaf meets the stem: the centroid (``Mesh.label_centroids``) of its faces
    sharing an edge with a stem face (mm), for the leaves that have any.

    The base hint of ``measure_leaf``.  The leaf's point nearest to any stem vertex (the
    hint without a contact) is as often the tip of a blade drooping past another tiller:
    on grass development seeds 0-29 it lay nearer the truth's tip than its base for 63 of
    344 matched blades, the contact for 26 of the 277 that have one (session 23).
    """
    if not stem_faces.any():
        return {}
    labels = labelled.face_labels
    pairs = geo.mesh_topology(labelled.mesh.faces).face_pairs
    a, b = pairs[:, 0], pairs[:, 1]
    contact = np.zeros(len(labels), bool)
    contact[a[~stem_faces[a] & stem_faces[b]]] = True
    contact[b[~stem_faces[b] & stem_faces[a]]] = True
    centres = labelled.mesh.label_centroids(np.where(contact, labels, -1))
    return {k: c for k, c in centres.items() if labelled.kinds.get(k) == "leaf"}


def _thick_and_outline_checks(labelled: LabelledMesh, measurements: list[LeafMeasurement],
                              report: StageReport, unit_mm: float | None = None) -> None:
    """Each leaf's ``thick_share`` (and a warning at ``THICK_WARN_SHARE``), and the
    perimeter-against-length warnings."""
    mesh = labelled.mesh
    shares = thick_shares(mesh, labelled.face_labels, [m.traits.leaf_id for m in measurements],
                          unit_mm)
    for m in measurements:
        if m.traits.leaf_id not in shares:
            continue
        share, median = shares[m.traits.leaf_id]
        m.traits.thick_share = share
        m.info["median_thickness_mm"] = median
        if in_phantom(m.traits):
            msg = (f"leaf {m.traits.leaf_id}: {100 * share:.0f} % of its area lies where the "
                   f"surface is more than {THICK_FACTOR:g}x its median thickness "
                   f"({median:.1f} mm): phantom volume or a fused organ, which its traits "
                   "carry (more views or tilts carve phantom volume)")
            log.warning(msg)
            report.warn("thick-leaf", msg, leaf=m.traits.leaf_id)
    for w in inconsistent_leaves([m.traits for m in measurements]):
        log.warning(w.message)
        report.warnings.append(w)


def _kind_area(labelled: LabelledMesh, kind: str) -> float:
    """One-side area of the faces labelled ``kind`` (their area over two).  Only those
    faces are summed (the whole plant's areas cost 0.3-0.9 s at 1.7 M faces)."""
    labels = [k for k, name in labelled.kinds.items() if name == kind]
    faces = labelled.mesh.faces[np.isin(labelled.face_labels, labels)]
    return float(Mesh(labelled.mesh.vertices, faces).face_areas().sum()) / 2.0


def _kind_areas(labelled: LabelledMesh) -> dict[str, float]:
    """``_kind_area`` of the debris and the stem, what the plant's flag reads."""
    return {kind: _kind_area(labelled, kind) for kind in ("debris", "stem")}


def stem_share(labelled: LabelledMesh, other_area_mm2: float,
               stem_area_mm2: float | None = None) -> float:
    """The stem's share of the plant's surface, one side: the stem's one-side area
    (``stem_area_mm2`` when known) over that plus ``other_area_mm2`` (the leaves' and the
    debris' one-side area)."""
    area = _kind_area(labelled, "stem") if stem_area_mm2 is None else stem_area_mm2
    total = area + other_area_mm2
    return area / total if total > 0 else 0.0


def _judge(traits: Traits, measurements: list[LeafMeasurement], labelled: LabelledMesh,
           p: LeafGeometryParams, plant_views: int | None, report: StageReport,
           unit_mm: float | None = None, parts: tuple | None = None) -> None:
    """Each leaf's confidence and the plant's quality flag, into ``traits`` and ``report``.
    ``parts``: (the stem's and debris' areas, the trust model's plant context or None),
    ``_measure_parts``' when the caller has them."""
    from plantscan_leaves.trust import leaf_trust, model_trust, plant_quality, reason_text

    kind_areas, context = parts or (None, None)
    trusts = [leaf_trust(m.traits, labelled.evidence.get(m.traits.leaf_id))
              for m in measurements]
    if p.trust_model and measurements:
        from plantscan_leaves import trust_model as tm

        model = tm.load_model(p.trust_model)
        x = tm.leaf_features(traits, measurements, labelled, unit_mm
                             or geo.mesh_unit(labelled.mesh.vertices, labelled.mesh.faces),
                             context)
        trusts = [model_trust(t, pb, why)
                  for t, pb, why in zip(trusts, model.doubt(x), model.why(x))]
    for m, t in zip(measurements, trusts):
        leaf = m.traits
        leaf.confidence, leaf.confidence_reasons = t.confidence, ";".join(t.reasons)
        leaf.quality_flag = "check" if t.low else "ok"
        if t.low:
            report.warn("low-confidence", f"leaf {leaf.leaf_id}: confidence {t.confidence:.2f}: "
                        + "; ".join(reason_text(r, t) for r in t.reasons), leaf=leaf.leaf_id)
    kind_areas = kind_areas or _kind_areas(labelled)
    debris_area = kind_areas["debris"]
    leaf_area = float(traits.plant.get("total_leaf_area_mm2", 0.0))
    share = debris_area / leaf_area if leaf_area > 0 else (1.0 if debris_area > 0 else 0.0)
    stem_area = kind_areas["stem"]
    stem = stem_share(labelled, leaf_area + debris_area, stem_area)
    flag, reasons = plant_quality(trusts, share, plant_views, p.min_plant_views,
                                  stem, p.max_stem_share)
    traits.plant.update(quality_flag=flag, quality_reasons=reasons,
                        debris_area_mm2=debris_area, stem_area_mm2=stem_area,
                        low_confidence_leaves=sum(t.low for t in trusts))
    if flag != "ok":
        report.warn("plant-quality", f"plant flagged '{flag}': " + "; ".join(reasons))

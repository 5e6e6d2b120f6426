"""Leaf/stem segmentation of a plant surface by curvature-constrained region growing.

The plant surface from a visual hull is one closed mesh: a stem (a tube) with
leaves (thin closed slabs) growing out of it.  Where a leaf meets the stem,
or where two leaves touch, the union of the two solids has a *concave
crease*; across a leaf (flat, bent, or over its convex rim) the surface is
never sharply concave.  So (after Paproki et al. 2012, simplified), the
passes of ``PASSES``, in order, over one labels record (``_Labels``):

1. *seed regions*: the curvature of the surface at a scale of ``smoothing_mm``
   (Taubin-smoothed vertices, diffused face normals, normal curvature across
   every edge); faces sharper than ``concave_curvature_per_mm`` in the
   concave direction are crease faces, the connected components of the
   others are seed regions (smaller than ``min_region_area_mm2``: dropped),
   and labels grow from them into the crease bands, one ring of faces per
   step, until every face of every connected part is labelled;
2. *region kinds*: each region is a leaf or stem: stem pieces are tubes
   (``_tubes``: their normals turn all round an axis that is also their long
   axis), leaves are everything else with at least ``min_leaf_area_mm2``
   (one side); smaller non-tube pieces join the neighbour they share most
   edges with;
3. *blade tips* (``tips_to_leaf``) and 4. *stem sheets* (``stem_sheet_ratio``):
   grass blade tips called tubes and flat blade bases in stem regions go back
   to their leaf;
5. *tubes to stem*: tube-like parts of leaves go to the stem: petioles
   touching it (at ``petiole_scale_mm``) and stretches of main stem grown
   into a leaf (at ``stem_scale_mm``);
6. *leaf pieces*, 7. *stem and ground pieces*, 8. *blade pieces joined*, 9.
   *numbered leaves*: a leaf that lost a petiole may fall apart; its pieces
   that are tubes or lie on the ground go to the stem, pieces of one cut blade
   are joined (``join_gap_mm``), small ones join their neighbour, the rest are
   leaves 1..n;
10. *touching leaves split* (``split_curvature_per_mm``), 11. *forked leaves split*
    (``fork_branch_mm``), 12. *broken blades joined* (``join_gap_mm``), 13. *bases off
    culms* (``base_reach_mm``), 14. *stem parts judged* (``judge_stem_parts``);
15. *pieces judged* (``judge_pieces``): a learned judge calls every numbered leaf a
    leaf, a fragment to join to its neighbour, or debris (``plantscan_leaves.pieces``);
16. *pairs judged* (``judge_pairs``): a learned judge merges two leaves sharing a border
    that it calls one leaf (``plantscan_leaves.pairs``).

Every number that decides a label is a parameter above or a named module
constant with its reason (``TUBE_AXIS_COS``, ``TIP_*``, ``JOIN_*``, ``CULM_*``...).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from concurrent.futures import Future

import numpy as np
from pydantic import Field, field_validator
from scipy import sparse
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from plantscan_core.data import LabelledMesh, Mesh
from plantscan_core.parallel import keep_heap_memory, thread_map
from plantscan_core.stages import StageParams, StageReport
from plantscan_leaves import geometry as geo
from plantscan_leaves import kernels
from plantscan_leaves.geometry import face_curvature

log = logging.getLogger(__name__)

STEM_LABEL = 0
TIP_GAP_EDGES = 6.0  # a broken-off blade tip within this many mean mesh edges of its blade


class CurvatureRegionsParams(StageParams):
    """Parameters of ``curvature-regions`` (defaults: broad dicot leaves, 0.3–1 mm voxels).

    With ``reference_unit_mm`` set, every length, area and curvature below (and every
    module constant in mm) is relative to the voxel size: the ``_mm`` values hold on a
    mesh whose unit (``geometry.mesh_unit``, the median edge, about a voxel) is
    ``reference_unit_mm``, and a mesh of another unit is segmented as if scaled to it
    (docs/leaves.md, "Scale-free segmentation").
    """

    reference_unit_mm: float | None = Field(
        None, gt=0,
        description="the mesh unit (median edge, about a voxel), mm, at which the _mm "
                    "parameters hold: a mesh of unit u is segmented scaled by this / u, so "
                    "every length is in voxels (times this), areas in voxels², curvatures "
                    "per voxel; the same plant in centimetres, or scaled with its voxel "
                    "size, gets the same labels; None: absolute millimetres")

    smoothing_mm: float = Field(1.5, gt=0, description="scale of the curvature estimate, mm")
    concave_curvature_per_mm: float = Field(
        0.08, gt=0,
        description="faces more concave than this (1/mm) separate regions (leaf-stem and "
                    "leaf-leaf creases); lower splits more",
    )
    min_region_area_mm2: float = Field(
        20.0, ge=0, description="smaller seed regions are re-grown from their neighbours, mm²")
    min_leaf_area_mm2: float = Field(
        500.0, ge=0, description="smallest leaf (one side, i.e. half its surface), mm²")
    stem_tube_ratio: float = Field(
        0.35, gt=0, le=1,
        description="a region whose normals spread around its long axis this much "
                    "(2nd/1st eigenvalue of the normal tensor; 1 = cylinder, 0 = flat) is a stem",
    )
    stem_min_elongation: float = Field(
        2.5, gt=0, description="a stem piece is at least this many times longer than thick")
    petiole_scale_mm: float = Field(
        2.0, gt=0,
        description="cell size of the tube test that moves petioles and stem pieces grown "
                    "into a leaf back to the stem (tested over 3x3x3 cells), mm; about the "
                    "petiole/stem diameter")
    petiole_tube_ratio: float = Field(
        0.45, gt=0, le=1,
        description="faces whose neighbourhood's normals spread this much around one axis "
                    "(2nd/1st eigenvalue) are tube-like; tube-like parts of a leaf touching "
                    "the stem are stem (petioles); 1 disables")
    stem_scale_mm: float | None = Field(
        3.0, gt=0,
        description="cell size of a second tube test, at the main stem's scale (its diameter "
                    "/ 3), mm: connected parts of a leaf region that are tube-like at this "
                    "scale, hold min_leaf_area_mm2 of surface and are a tube along their long "
                    "axis are stem grown into the leaf (a stem thicker than a petiole is only "
                    "patchily tube-like at petiole_scale_mm); None: off (grasses: sheaths and "
                    "blade bases around the stem are tubes at this scale)")
    crumb_merge_rounds: int = Field(
        1, ge=1,
        description="rounds of merging small regions into their neighbours: 1 joins only "
                    "crumbs touching a leaf or stem region; more also joins chains of crumbs "
                    "(narrow grass blade tips; on broad leaves the chains are mostly phantom "
                    "hull volume, so 1)")
    split_curvature_per_mm: float | None = Field(
        0.06, gt=0,
        description="a leaf holding two big regions separated by creases sharper than this "
                    "(1/mm, below concave_curvature_per_mm) is split in two (touching "
                    "leaves); None: off")
    split_crease_rings: int = Field(
        0, ge=0, le=8,
        description="the touching-leaf split (split_curvature_per_mm) widens the creases by "
                    "this many rings of faces: two touching leaves whose crease has a gap (a "
                    "few faces where the hull is smooth) come apart; a leaf it cuts that is "
                    "one is joined back by the piece and pair judges, and that join is not "
                    "counted as one (trust's rejoined); 0: the creases as they are")
    fork_branch_mm: float | None = Field(
        None, gt=0,
        description="a leaf whose surface forks, going out from where it meets the stem "
                    "nearest the plant's axis, into branches of at least min_leaf_area_mm2 "
                    "that each reach this far beyond the fork and go the same way, is one "
                    "leaf per branch (grass blades fused at their common base); None: off")
    stem_sheet_ratio: float = Field(
        0.0, ge=0, le=1,
        description="faces of stem regions whose neighbourhood (petiole_scale_mm cells) is "
                    "this flat (2nd/1st eigenvalue of the normal tensor below it) are blade, "
                    "not stem: they go back to the leaf they touch (grass blades fused with "
                    "their stem in the hull: 0.25); 0 disables (broad leaves: the flat parts of "
                    "their stem regions are phantom hull volume)")
    petiole_within_leaf: bool = Field(
        False,
        description="the petiole test takes tube-like parts of one leaf region at a time "
                    "(grasses: true; crossing blades' tube-like patches otherwise join into "
                    "one part that touches the stem somewhere and goes whole)")
    tips_to_leaf: bool = Field(
        False,
        description="blade tips go to their leaf: tube regions whose only neighbour is one "
                    "leaf, and small pieces the hull broke off within a few voxels of a leaf "
                    "(a narrow grass tip is as thick as it is wide in the hull, so its normals "
                    "turn all round; grasses: true; broad leaves: false, a stem top hanging "
                    "off a leaf that grabbed the stem below it would go to the leaf)")
    join_gap_mm: float | None = Field(
        None, gt=0,
        description="a grass blade cut in two where it crosses a stem (its hull fuses with "
                    "the stem there) is joined again: two leaves whose ends lie within this "
                    "many mm, continue each other (outward directions opposite within "
                    "~30°) and are both wide there (a blade's own base tapers) become one, "
                    "with the stem faces between the ends; about the stem's diameter in the "
                    "hull plus a margin (grasses: 12); None: off (broad leaves)")
    base_reach_mm: float | None = Field(
        None, gt=0,
        description="a grass blade whose base runs through the tangle of tillers is fused "
                    "with them in the hull, and its base is labelled stem: the stem faces "
                    "off the straight culms (found by RANSAC) that lie along the blade's "
                    "continuation, within its width at the cut + 1 mm and up to this many "
                    "mm from the cut, go back to the blade (grasses: 80); None: off (broad "
                    "leaves)")
    judge_pieces: bool = Field(
        False,
        description="after the rules, a learned judge (plantscan_leaves.pieces, trained on "
                    "the virtual scanner's truth) calls every numbered leaf a whole leaf, a "
                    "fragment (joined to the leaf piece it borders most) or debris (phantom "
                    "volume, crumbs: labelled debris, never counted as leaf)")
    piece_model: str | None = Field(
        None, description="another piece model (scripts/train_piece_model.py --out writes "
                          "one): a file name without a folder is a model shipped in the "
                          "package (piece_model_all.json.gz: trained on every family), else "
                          "a path; None: the shipped dicot model (piece_model.json.gz)")
    judge_stem_parts: bool = Field(
        False,
        description="before the piece judge, a learned judge (plantscan_leaves.stem_parts) "
                    "looks at the parts of the stem off the straight culms and makes those it "
                    "calls blades leaf pieces (narrow grass blades are tubes to the rules)")
    stem_part_model: str | None = Field(
        None, description="another stem-part model (scripts/train_stem_part_model.py --out "
                          "writes one): a file name without a folder is a model shipped in "
                          "the package, else a path; None: the shipped one")
    judge_pairs: bool = Field(
        False,
        description="after the piece judge, a learned judge (plantscan_leaves.pairs) looks at "
                    "every two leaves sharing a border and merges those it calls one leaf (a "
                    "leaf a crease cut into two halves that each look whole)")
    pair_model: str | None = Field(
        None, description="another pair model (scripts/train_pair_model.py --out writes "
                          "one): a file name without a folder is a model shipped in the "
                          "package, else a path; None: the shipped one (pair_model.json.gz)")
    ground_band_mm: float = Field(
        12.0, ge=0,
        description="leaf-like pieces lying entirely this close to the bottom of the mesh are "
                    "remnants of the pot cut / soil, not leaves (0 for rosettes lying on the "
                    "soil), mm")

    @field_validator("piece_model", "stem_part_model", "pair_model")
    @classmethod
    def _model_exists(cls, value: str | None, info) -> str | None:
        from plantscan_leaves.pieces import check_model_name

        script = {"piece_model": "scripts/train_piece_model.py",
                  "pair_model": "scripts/train_pair_model.py"}.get(
                      info.field_name, "scripts/train_stem_part_model.py")
        return check_model_name(value, script)


def _regions_of(nf: int, pairs: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Connected components of the faces ``keep`` over ``pairs``; -1 elsewhere."""
    return geo.components(nf, pairs, keep)


def _relabel(labels: np.ndarray) -> np.ndarray:
    """Labels renumbered 0..n-1 in order (-1 stays -1); a lookup table, not a sort."""
    ok = labels >= 0
    if not ok.any():
        return np.full_like(labels, -1)
    present = np.zeros(int(labels.max()) + 1, bool)
    present[labels[ok]] = True
    new_id = np.cumsum(present) - 1
    return np.where(ok, new_id[np.maximum(labels, 0)], -1)


def _region_shape(c: np.ndarray, normals: np.ndarray, areas: np.ndarray, labels: np.ndarray,
                  nlab: int) -> dict[str, np.ndarray]:
    """Per-region area, normal-tensor spread, long axis alignment, elongation.

    ``c`` (F, 3) face centroids, ``normals`` (F, 3), ``areas`` (F,), ``labels`` (F,) < nlab.
    """
    tot, _, cov = geo.label_moments(labels, nlab, areas, c, 1e-12)
    nt = geo.label_moments(labels, nlab, areas, normals)[2]
    safe = np.maximum(tot, 1e-12)[:, None, None]
    ev_c, vec_c = np.linalg.eigh(cov / safe)  # ascending
    ev_n, vec_n = np.linalg.eigh(nt / safe)
    long_axis = vec_c[:, :, 2]
    null_normal = vec_n[:, :, 0]  # direction the normals never point to (tube axis)
    return {
        "area": tot,
        "spread": ev_n[:, 1] / np.maximum(ev_n[:, 2], 1e-12),
        "axis_alignment": np.abs(np.einsum("ij,ij->i", long_axis, null_normal)),
        "elongation": np.sqrt(ev_c[:, 2] / np.maximum(ev_c[:, 1], 1e-12)),
    }


# A tube: normals spread round one axis (``stem_tube_ratio``) that is also the long axis
# (|cos| between the two above this, within ~37°), and elongated (``stem_min_elongation``).
TUBE_AXIS_COS = 0.8


def _tubes(shape: dict[str, np.ndarray], p: CurvatureRegionsParams) -> np.ndarray:
    """Which regions of ``_region_shape`` are tubes (stem pieces): the one tube test."""
    return ((shape["spread"] > p.stem_tube_ratio) & (shape["axis_alignment"] > TUBE_AXIS_COS)
            & (shape["elongation"] > p.stem_min_elongation))


class _Surface:
    """What every pass reads of the mesh: per-face geometry, curvature, the parameters."""

    def __init__(self, mesh: Mesh, topo: geo.MeshTopology, p: CurvatureRegionsParams,
                 report: StageReport) -> None:
        self.mesh, self.topo, self.p, self.report = mesh, topo, p, report
        self.pairs = topo.face_pairs  # (E, 2) faces sharing an edge
        self.nf = len(mesh.faces)
        v, f = mesh.vertices, mesh.faces
        # (F,) how tube-like each face's neighbourhood is at petiole_scale_mm and at
        # stem_scale_mm (None where no pass asks)
        self.spread: np.ndarray | None = None
        self.stem_spread: np.ndarray | None = None

        face_op: Future = Future()  # the curvature's smoothing operator, built by per_face

        def curvature() -> None:
            self.curvature = face_curvature(mesh, topo, p.smoothing_mm,  # (F,) 1/mm, < 0 concave
                                            face_op.result)

        def per_face() -> None:
            try:
                face_op.set_result(geo.face_adjacency_operator(self.nf, topo.face_pairs))
            except BaseException as exc:  # the curvature waits for it: never in vain
                face_op.set_exception(exc)
                raise
            self.normals, self.areas = geo.face_normals_areas(v, f)
            self.centroids = geo.face_centroids(v, f)
            if p.petiole_tube_ratio < 1 or p.stem_sheet_ratio > 0:
                self.spread = _neighbourhood_spread(self.centroids, self.normals, self.areas,
                                                    p.petiole_scale_mm)
            if p.petiole_tube_ratio < 1 and p.stem_scale_mm is not None:
                self.stem_spread = _neighbourhood_spread(self.centroids, self.normals,
                                                         self.areas, p.stem_scale_mm)
            if p.judge_pieces or p.judge_stem_parts or p.judge_pairs:
                geo.mesh_unit(v, f)  # remembered (geometry.mesh_key) for the judges

        # the label-free fields on both cores, in two halves of about equal work (dicot
        # 1009, 2.72 M faces: 1.2 and 1.0 s); both release the GIL most of the time.
        # per_face goes first: on one worker it runs whole before the curvature waits
        thread_map(lambda task: task(), [per_face, curvature])
        self.piece_model = None  # the judge of judge_pieces when not the params' file
        self.stem_part_model = None  # the judge of judge_stem_parts when not the params' file
        self.pair_model = None  # the judge of judge_pairs when not the params' file
        # (vertices as given, scale) when the passes see them scaled to the reference unit
        self.given: tuple[np.ndarray, float] | None = None

    @functools.cached_property
    def piece_surface(self):
        """The surface as the learned judges read it (``pieces.PieceSurface``)."""
        from plantscan_leaves import pieces

        given, scale = self.given if self.given is not None else (None, 1.0)
        return pieces.PieceSurface(self.mesh.vertices, self.mesh.faces, self.centroids,
                                   self.normals, self.areas, self.pairs, self.curvature,
                                   geo.mesh_unit(self.mesh.vertices, self.mesh.faces),
                                   given, scale)


@dataclasses.dataclass
class _Labels:
    """The labels record the passes refine, one after the other (``PASSES``).

    ``regions`` (F,) region per face and the region kinds ``tube`` / ``leafy`` (R,);
    ``leaf_face`` / ``stem_face`` (F,) what each face is now; ``pieces`` (F,) the
    connected leaf piece of each leaf face (-1 elsewhere) and ``small`` (P,) the
    pieces below a leaf's area; ``out`` (F,) the labels (0 stem, 1..``n_leaves``).
    """

    regions: np.ndarray
    nlab: int = 0
    tube: np.ndarray | None = None
    leafy: np.ndarray | None = None
    leaf_face: np.ndarray | None = None
    stem_face: np.ndarray | None = None
    pieces: np.ndarray | None = None
    n_pieces: int = 0
    small: np.ndarray | None = None
    out: np.ndarray | None = None
    n_leaves: int = 0
    debris: bool = False
    evidence: dict = dataclasses.field(default_factory=dict)
    # (F,) each face's leaf before the touching-leaf split at widened creases, when it split
    # any (the judges' joins that only undo it are not joins of broken pieces)
    split_from: np.ndarray | None = None

    def faces_from_regions(self) -> None:
        self.leaf_face, self.stem_face = self.leafy[self.regions], self.tube[self.regions]

    def piece_areas(self, s: _Surface) -> None:
        """``small`` from the pieces' areas (one side)."""
        on = self.leaf_face
        area = np.bincount(self.pieces[on], s.areas[on], self.n_pieces) / 2.0
        self.small = area < s.p.min_leaf_area_mm2


def _seed_regions(s: _Surface, lab: _Labels) -> None:
    """Crease faces part the surface; seed regions grow into the creases (steps 1-4)."""
    p, pairs = s.p, s.pairs
    crease = s.curvature < -p.concave_curvature_per_mm
    s.report.counts["crease_faces"] = int(crease.sum())
    seeds = _regions_of(s.nf, pairs, ~crease)
    seed_area = np.bincount(seeds[seeds >= 0], s.areas[seeds >= 0])
    small = seed_area < p.min_region_area_mm2
    seeds[(seeds >= 0) & small[np.maximum(seeds, 0)]] = -1
    labels = kernels.grow(_relabel(seeds), pairs)
    # parts of the mesh with no seed at all (crumbs, all-crease bits) are their own region
    if (labels < 0).any():
        rest = _regions_of(s.nf, pairs, labels < 0)
        labels[labels < 0] = labels.max() + 1 + rest[labels < 0]
    lab.regions = _relabel(labels)
    lab.nlab = int(lab.regions.max()) + 1
    s.report.counts["regions"] = lab.nlab


def _region_kinds(s: _Surface, lab: _Labels) -> None:
    """Each region a tube (stem) or a leaf; smaller non-tube regions (crumbs) join the
    neighbour they share most edges with (step 5)."""
    p = s.p
    shape = _region_shape(s.centroids, s.normals, s.areas, lab.regions, lab.nlab)
    lab.tube = _tubes(shape, p)
    lab.leafy = ~lab.tube & (shape["area"] / 2.0 >= p.min_leaf_area_mm2)
    crumbs = ~lab.tube & ~lab.leafy
    if crumbs.any():
        lab.regions = _merge_crumbs(lab.regions, crumbs, s.pairs, lab.nlab, p.crumb_merge_rounds)
    lab.faces_from_regions()


def _blade_tips(s: _Surface, lab: _Labels) -> None:
    """Blade tips called tubes, or broken off by the hull, go to their leaf (``tips_to_leaf``)."""
    if not s.p.tips_to_leaf:
        return
    v, edges = s.mesh.vertices, s.topo.edges
    # a broken-off tip lies within a few voxels of its blade; mesh edges are 0.5-0.8 voxel
    edge_mm = float(np.mean(geo.row_norm(v[edges[:, 0]] - v[edges[:, 1]])))
    lab.regions, n_tips = _tips_to_leaves(lab.regions, lab.tube, lab.leafy, s.pairs, lab.nlab,
                                          s.centroids, TIP_GAP_EDGES * edge_mm)
    s.report.counts["tips_to_leaf"] = n_tips
    lab.faces_from_regions()


def _stem_sheets(s: _Surface, lab: _Labels) -> None:
    """Flat parts of stem regions go back to the leaves (``stem_sheet_ratio``)."""
    p = s.p
    if p.stem_sheet_ratio <= 0:
        return
    lab.regions, recovered = _sheets_of_stem(lab.regions, s.spread < p.stem_sheet_ratio,
                                             lab.leaf_face, lab.stem_face, s.areas, s.pairs,
                                             p.min_leaf_area_mm2)
    s.report.counts["sheet_faces_from_stem"] = int(np.count_nonzero(recovered))
    lab.leaf_face |= recovered
    lab.stem_face &= ~recovered


def _tubes_to_stem(s: _Surface, lab: _Labels) -> None:
    """Tube-like parts of leaves go to the stem: petioles and main stem grown in (step 6)."""
    p = s.p
    moved = np.zeros(s.nf, bool)
    if p.petiole_tube_ratio < 1:
        moved = _petioles_to_stem(s.spread, s.pairs, lab.leaf_face, lab.stem_face, s.areas,
                                  p.petiole_tube_ratio, p.min_leaf_area_mm2,
                                  lab.regions if p.petiole_within_leaf else None)
        if p.stem_scale_mm is not None:
            # after the petiole test, not before: run against the recovered stem, the petiole
            # test cuts further into blade bases the hull has fattened into rods
            stem_in_leaf = _stems_in_leaves(s.stem_spread, s.pairs, lab.leaf_face, s.centroids,
                                            s.normals, s.areas, p)
            s.report.counts["stem_faces_from_leaves"] = int(np.count_nonzero(stem_in_leaf
                                                                             & ~moved))
            moved |= stem_in_leaf
    s.report.counts["petiole_faces"] = int(np.count_nonzero(moved))
    lab.stem_face |= moved
    lab.leaf_face &= ~moved


def _leaf_pieces(s: _Surface, lab: _Labels) -> None:
    """A leaf region that lost its petiole or a stem piece may fall apart: its connected
    pieces, each a leaf when big enough and a crumb of its neighbour otherwise."""
    leaf_lab = np.where(lab.leaf_face, lab.regions, -1)
    a, b = s.pairs[:, 0], s.pairs[:, 1]
    same = (leaf_lab[a] == leaf_lab[b]) & (leaf_lab[a] >= 0)
    lab.pieces = _relabel(_regions_of(s.nf, s.pairs[same], lab.leaf_face))
    lab.n_pieces = int(lab.pieces.max()) + 1 if lab.leaf_face.any() else 0
    lab.piece_areas(s)


def _stem_and_ground_pieces(s: _Surface, lab: _Labels) -> None:
    """Leaf pieces that are stem pieces (a thick stem is not tube-like at the petiole
    scale) or remnants of the pot cut near the ground go to the stem."""
    p, n, leaf_face = s.p, lab.n_pieces, lab.leaf_face
    if not n:
        return
    at = np.where(leaf_face, lab.pieces, n)  # faces off leaves: piece n
    drop = _tubes(_region_shape(s.centroids, s.normals, s.areas, at, n + 1), p)[:n]
    z = s.mesh.vertices[:, 2]
    if p.ground_band_mm > 0 and lab.stem_face.any():  # a plant on a pot, not a lone leaf
        zmax = np.full(n + 1, -np.inf)
        np.maximum.at(zmax, at, z[s.mesh.faces].max(axis=1))
        drop |= zmax[:n] < z.min() + p.ground_band_mm
    if p.tips_to_leaf:
        # a small piece that is a mesh component of its own was given to its leaf on
        # purpose (a broken-off blade tip, tube-like at that size): not a stem piece
        alone = np.ones(n + 1, bool)
        a, b = s.pairs[:, 0], s.pairs[:, 1]
        diff = at[a] != at[b]
        alone[at[a][diff]] = False
        alone[at[b][diff]] = False
        drop &= ~(alone[:n] & lab.small)
    if drop.any():
        s.report.counts["stem_or_ground_pieces"] = int(drop.sum())
        to_stem = leaf_face & drop[np.maximum(lab.pieces, 0)]
        lab.leaf_face &= ~to_stem
        lab.stem_face |= to_stem
        lab.pieces = np.where(lab.leaf_face, lab.pieces, -1)
        lab.small |= drop


def _blade_pieces_joined(s: _Surface, lab: _Labels) -> None:
    """Pieces of one blade the petiole test cut apart across a tiller, joined before small
    pieces merge into whatever they touch most (the stem) (``join_gap_mm``)."""
    p = s.p
    if p.join_gap_mm is None or lab.n_pieces <= 1:
        return
    lab.pieces, n_joined = _join_blade_pieces(lab.pieces, lab.leaf_face, lab.small, s.centroids,
                                              s.areas, p.join_gap_mm, p.min_leaf_area_mm2)
    if n_joined:
        lab.leaf_face = lab.pieces >= 0
        lab.n_pieces = int(lab.pieces.max()) + 1
        lab.piece_areas(s)
    s.report.counts["blade_pieces_joined"] = n_joined


def _numbered_leaves(s: _Surface, lab: _Labels) -> None:
    """Small pieces join the piece they share most edges with; the rest are leaves 1..n."""
    small, n = lab.small, lab.n_pieces
    if small.any() and (~small).any():
        merged = _merge_crumbs(np.where(lab.leaf_face, lab.pieces, n), np.append(small, False),
                               s.pairs, n + 1)
        lab.pieces = np.where(lab.leaf_face, merged, -1)
        if s.p.tips_to_leaf:
            lab.pieces = _strays_to_region(lab.pieces, small, lab.regions, s.centroids)
    lab.out = np.full(s.nf, STEM_LABEL, np.int32)
    leaf_pieces = [r for r in range(n) if not small[r]]
    for new, r in enumerate(leaf_pieces, start=1):
        lab.out[lab.pieces == r] = new
    lab.n_leaves = len(leaf_pieces)


def _touching_leaves_split(s: _Surface, lab: _Labels) -> None:
    """A leaf of two big regions at a finer crease threshold is two (``split_curvature_per_mm``)."""
    p = s.p
    if p.split_curvature_per_mm is None or not lab.n_leaves:
        return
    crease = geo.dilate_faces(s.curvature < -p.split_curvature_per_mm, s.pairs,
                              p.split_crease_rings)
    before = lab.out
    lab.out, n_split = _split_joined_leaves(lab.out, crease, s.areas, s.pairs,
                                            p.min_leaf_area_mm2)
    if n_split and p.split_crease_rings:
        lab.split_from = before  # a tentative split: the judges may undo it
    s.report.counts["leaves_split"] = n_split
    lab.n_leaves = int(lab.out.max())


def _forked_leaves_split(s: _Surface, lab: _Labels) -> None:
    """A leaf that forks into branches going the same way is one leaf each (``fork_branch_mm``)."""
    p = s.p
    if p.fork_branch_mm is None or not lab.n_leaves:
        return
    lab.out, n_split = _split_forked_leaves(lab.out, s.centroids, s.areas, s.pairs,
                                            p.min_leaf_area_mm2, p.fork_branch_mm)
    s.report.counts["forked_leaves_split"] = n_split
    lab.n_leaves = int(lab.out.max())


def _broken_blades_joined(s: _Surface, lab: _Labels) -> None:
    """Two leaves that are pieces of one blade cut at a stem are one (``join_gap_mm``)."""
    if s.p.join_gap_mm is None or lab.n_leaves <= 1:
        return
    lab.out, n_joined = _join_broken_blades(lab.out, s.centroids, s.areas, s.p.join_gap_mm)
    s.report.counts["blades_joined"] = n_joined
    lab.n_leaves = int(lab.out.max())


def _bases_off_culms(s: _Surface, lab: _Labels) -> None:
    """Stem faces along a blade's continuation, off the culms, go to it (``base_reach_mm``)."""
    p = s.p
    if p.base_reach_mm is None or not lab.n_leaves:
        return
    ground_z = float(s.mesh.vertices[:, 2].min()) + p.ground_band_mm
    lab.out, n_claimed = _blade_bases_off_culms(lab.out, s.centroids, s.normals, s.pairs,
                                                ground_z, p.base_reach_mm)
    s.report.counts["base_faces_from_stem"] = n_claimed


def _pieces_judged(s: _Surface, lab: _Labels) -> None:
    """Every numbered leaf judged a leaf, a fragment to join, or debris (``judge_pieces``)."""
    if not s.p.judge_pieces or not lab.n_leaves:
        return
    from plantscan_leaves import pieces

    model = s.piece_model or pieces.load_model(s.p.piece_model)
    verdict, _, _ = pieces.judge(s.piece_surface, lab.out, lab.n_leaves, model,
                                 _split_parents(lab))
    for k, name in enumerate(pieces.CLASS_NAMES):
        s.report.counts[f"pieces_{name}"] = int(np.count_nonzero(verdict.verdict == k))
    lab.out = verdict.labels.astype(np.int32)
    lab.n_leaves, lab.debris = verdict.n_leaves, verdict.debris
    lab.evidence = pieces.joined_evidence(verdict)


def _pairs_judged(s: _Surface, lab: _Labels) -> None:
    """Two leaves sharing a border that a learned judge calls one leaf merged (``judge_pairs``)."""
    if not s.p.judge_pairs or lab.n_leaves < 2:
        return
    from plantscan_leaves import pairs

    model = s.pair_model or pairs.load_model(s.p.pair_model)
    found = pairs.pair_features(s.piece_surface, lab.out, lab.n_leaves)
    prob = model.probabilities(found)
    out, n, merged, new_of_old = pairs.merge_pairs(lab.out, lab.n_leaves, found, prob,
                                                   parent=_split_parents(lab))
    s.report.counts["pairs_touching"] = len(found.pairs)
    s.report.counts["pairs_merged"] = lab.n_leaves - n
    evidence: dict[int, dict] = {}
    for old in range(1, lab.n_leaves + 1):  # the piece judge's joins carry over
        new, ev = int(new_of_old[old]), lab.evidence.get(old, {})
        if new not in merged:
            if ev:
                evidence[new] = ev
            continue
        # the pieces: one per parent merged (``merge_pairs``), plus those joined before
        cur = evidence.setdefault(new, {"fragments": merged[new][0],
                                        "weakest_merge": merged[new][1]})
        cur["fragments"] += int(ev.get("fragments", 1)) - 1
        cur["weakest_merge"] = round(min(cur["weakest_merge"], ev.get("weakest_merge", 1.0)), 4)
    lab.out = out.astype(np.int32)
    lab.evidence = {k: ev for k, ev in evidence.items() if ev["fragments"] > 1}
    lab.n_leaves = n


def _split_parents(lab: _Labels) -> np.ndarray | None:
    """(n + 1,) the leaf each leaf 1..n of ``lab.out`` was before the touching-leaf split at
    widened creases (the one most of its faces were; None when it cut none): the judges'
    joins among leaves of one parent undo that split and are no joins of their own."""
    if lab.split_from is None:
        return None
    n = lab.n_leaves
    on = (lab.out >= 1) & (lab.out <= n)
    width = int(lab.split_from.max()) + 1
    keys, counts = np.unique(lab.out[on].astype(np.int64) * width + lab.split_from[on],
                             return_counts=True)
    # a leaf with no faces that were a leaf (all stem before): a parent of its own
    parent = np.arange(n + 1) + width
    most = np.zeros(n + 1, np.int64)
    for key, c in zip(keys.tolist(), counts.tolist()):
        leaf, was = divmod(key, width)
        if was != STEM_LABEL and c > most[leaf]:
            most[leaf], parent[leaf] = c, was
    return parent


def _stem_parts_judged(s: _Surface, lab: _Labels) -> None:
    """Parts of the stem off the culms that are blades become leaf pieces (``judge_stem_parts``)."""
    if not s.p.judge_stem_parts:
        return
    from plantscan_leaves import stem_parts

    model = s.stem_part_model or stem_parts.load_model(s.p.stem_part_model)
    ground_z = float(s.mesh.vertices[:, 2].min()) + s.p.ground_band_mm
    parts = stem_parts.stem_parts(s.piece_surface, lab.out, lab.n_leaves, ground_z)
    lab.out, lab.n_leaves, n_blades = stem_parts.blades_from_stem(
        lab.out, lab.n_leaves, parts, model.probabilities(parts))
    s.report.counts["stem_parts"] = parts.m
    s.report.counts["stem_parts_to_leaf"] = n_blades


PASSES = (
    ("seed regions", _seed_regions),
    ("region kinds", _region_kinds),
    ("blade tips", _blade_tips),
    ("stem sheets", _stem_sheets),
    ("tubes to stem", _tubes_to_stem),
    ("leaf pieces", _leaf_pieces),
    ("stem and ground pieces", _stem_and_ground_pieces),
    ("blade pieces joined", _blade_pieces_joined),
    ("numbered leaves", _numbered_leaves),
    ("touching leaves split", _touching_leaves_split),
    ("forked leaves split", _forked_leaves_split),
    ("broken blades joined", _broken_blades_joined),
    ("bases off culms", _bases_off_culms),
    ("stem parts judged", _stem_parts_judged),
    ("pieces judged", _pieces_judged),
    ("pairs judged", _pairs_judged),
)
"""The passes of ``segment_leaves``, in order, each ``(name, fn(surface, labels))``."""


@geo.meshes_unchanged()  # its mesh arrays' digests taken once
def segment_leaves(mesh: Mesh, params: CurvatureRegionsParams | None = None,
                   piece_model=None, stem_part_model=None, pair_model=None,
                   _given: tuple[np.ndarray, float] | None = None
                   ) -> tuple[LabelledMesh, StageReport]:
    """Label every face of ``mesh`` as one leaf or the stem (``PASSES`` in turn).

    ``piece_model``: the judge of ``judge_pieces`` (anything with ``probabilities(pieces)
    -> (n, 3)``, ``plantscan_leaves.pieces``; None: the params' file or the shipped one);
    ``stem_part_model`` likewise the judge of ``judge_stem_parts`` (``probabilities(parts)
    -> (m,)``, ``plantscan_leaves.stem_parts``), ``pair_model`` of ``judge_pairs``
    (``probabilities(pairs) -> (k,)``, ``plantscan_leaves.pairs``).  ``_given``: internal
    (the vertices as given and their scale, when ``reference_unit_mm`` scales the mesh).

    Returns
    -------
    labelled : LabelledMesh
        ``face_labels`` 0 = stem (kind ``"stem"``), 1..n = leaves
        (kind ``"leaf"``), n + 1 = debris (kind ``"debris"``, only from the piece
        judge), every face labelled.  An empty mesh gives an empty labelled mesh.
    report : StageReport
        Work counts (``regions``, ``crease_faces``...) and warnings.
    """
    p = params or CurvatureRegionsParams()
    report = StageReport()
    keep_heap_memory()  # arrays of tens of MB, freed and allocated again: reuse the memory
    if not mesh.is_empty and p.reference_unit_mm is not None:
        unit = geo.mesh_unit(mesh.vertices, mesh.faces)
        scale = p.reference_unit_mm / unit
        # scaling the surface, not each parameter, makes every length, area and curvature
        # that decides a label (parameters and module constants alike) relative to the voxel
        # at once; labels are per face, so they carry back to the mesh as it was
        scaled, report = segment_leaves(Mesh(mesh.vertices * scale, mesh.faces),
                                        p.model_copy(update={"reference_unit_mm": None}),
                                        piece_model, stem_part_model, pair_model,
                                        _given=(mesh.vertices, scale))
        report.figures.update(mesh_unit_mm=round(unit, 6), scale_to_reference_unit=round(scale, 6))
        return LabelledMesh(mesh, scaled.face_labels, scaled.kinds, scaled.evidence), report
    if mesh.is_empty:
        msg = "mesh is empty: no leaf to segment"
        log.warning(msg)
        report.warn("empty-mesh", msg)
        return LabelledMesh(mesh, np.zeros(0, np.int32), {}), report
    topo = geo.mesh_topology(mesh.faces)
    if topo.non_manifold_edges:
        msg = (f"mesh has {topo.non_manifold_edges} non-manifold edges (used by more than two "
               "faces); they are treated as ordinary connections")
        log.warning(msg)
        report.warn("non-manifold", msg)
    surface = _Surface(mesh, topo, p, report)
    surface.piece_model = piece_model
    surface.stem_part_model = stem_part_model
    surface.pair_model = pair_model
    surface.given = _given
    lab = _Labels(regions=np.zeros(surface.nf, np.int64))
    if p.judge_pieces:
        # the piece judge's rays are cast at the plant as given: its scene starts building
        # now, a large mesh's in a helper process on the core the passes leave idle (the
        # surface's fields above keep both busy), and is ready when the judge comes
        geo.raycasting_scene(mesh.vertices if _given is None else _given[0], mesh.faces)
    for _name, run_pass in PASSES:
        run_pass(surface, lab)
    kinds: dict[int, str] = {new: "leaf" for new in range(1, lab.n_leaves + 1)}
    if (lab.out == STEM_LABEL).any() or not lab.n_leaves:
        kinds[STEM_LABEL] = "stem"
    if lab.debris:
        kinds[lab.n_leaves + 1] = "debris"
    if not lab.n_leaves:
        msg = "no leaf-like region found on the mesh (everything looks like stem or crumbs)"
        log.warning(msg)
        report.warn("no-leaf", msg)
    report.counts["leaves"] = lab.n_leaves
    report.counts["stem_pieces"] = int(lab.tube.sum())
    return LabelledMesh(mesh, lab.out, kinds, lab.evidence), report


def _petioles_to_stem(spread: np.ndarray, pairs: np.ndarray, leaf_face: np.ndarray,
                      stem_face: np.ndarray, areas: np.ndarray, ratio: float, min_area: float,
                      labels: np.ndarray | None = None) -> np.ndarray:
    """Faces of leaf regions that belong to tubes touching the stem (petioles, stem tops).

    A petiole meets its blade without a concave crease (the blade narrows into
    it), so region growing gives it to the leaf.  Its surface is a tube: over a
    few millimetres its normals turn all round one axis, while a slab's normals
    stay near +-N even at its rounded rim (the rim is a small part of any
    neighbourhood).  Tube-like parts of leaves that touch the stem, or are
    big (``min_area`` of surface: a stem grown into a leaf), go to the stem;
    small ones elsewhere (narrow blade tips) stay.
    """
    tube_face = (spread > ratio) & leaf_face
    if not tube_face.any():
        return tube_face
    within = pairs if labels is None else pairs[labels[pairs[:, 0]] == labels[pairs[:, 1]]]
    comp = _regions_of(len(leaf_face), within, tube_face)  # tube-like parts
    a, b = pairs[:, 0], pairs[:, 1]
    touch = np.zeros(int(comp.max()) + 1, bool)
    touch[comp[a[(comp[a] >= 0) & stem_face[b]]]] = True
    touch[comp[b[(comp[b] >= 0) & stem_face[a]]]] = True
    big = np.bincount(comp[comp >= 0], areas[comp >= 0], len(touch)) >= min_area
    return (comp >= 0) & (touch | big)[np.maximum(comp, 0)]


def _stems_in_leaves(spread: np.ndarray, pairs: np.ndarray, leaf_face: np.ndarray,
                     centroids: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                     p: CurvatureRegionsParams) -> np.ndarray:
    """Faces of leaf regions that are a stretch of main stem grown into the leaf.

    Where no concave crease parts a petiole from the stem (the petiole leaves
    the stem at a shallow angle, or hull volume fills the angle), region
    growing runs from the blade down the petiole into the stem, and the whole
    region, mostly blade, is judged a leaf.  The petiole test at
    ``petiole_scale_mm`` sees a stem thicker than its 3-cell block only in
    patches.  At ``stem_scale_mm`` the stem is tube-like throughout: a
    connected tube-like part holding ``min_leaf_area_mm2`` of surface that is,
    as a whole, a tube along its long axis (the stem test of whole regions) is
    stem, with the petioles it carries.  ``spread`` (F,): ``_neighbourhood_spread`` at
    ``stem_scale_mm``.
    """
    thick = (spread > p.petiole_tube_ratio) & leaf_face
    if not thick.any():
        return thick
    comp = _relabel(_regions_of(len(leaf_face), pairs, thick))
    ncomp = int(comp.max()) + 1
    big = np.bincount(comp[thick], areas[thick], ncomp) >= p.min_leaf_area_mm2
    shape = _region_shape(centroids, normals, areas, np.where(thick, comp, ncomp), ncomp + 1)
    tube = _tubes(shape, p)[:ncomp]
    return thick & (big & tube)[np.maximum(comp, 0)]


def _neighbourhood_spread(centroids: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                          scale: float) -> np.ndarray:
    """(F,) how tube-like each face's neighbourhood is: 2nd/1st eigenvalue of the normal tensor.

    Over the 3x3x3 block of ``scale`` mm cells around the face's cell: about 0.5-1 on a
    tube of that diameter, near 0 on a slab (its two sides share one sign-free normal).
    """
    _, tens, cell_of, _ = geo.cell_normal_tensors(centroids, normals, areas, scale)
    ev = np.linalg.eigvalsh(tens)  # ascending
    return (ev[:, 1] / np.maximum(ev[:, 2], 1e-12))[cell_of]


def _sheets_of_stem(labels: np.ndarray, sheet_face: np.ndarray, leaf_face: np.ndarray,
                    stem_face: np.ndarray, areas: np.ndarray, pairs: np.ndarray,
                    min_area: float) -> tuple[np.ndarray, np.ndarray]:
    """Slab-like parts of stem regions given back to the leaves.

    Region growing follows a blade that leaves its stem without a crease (grasses: a
    steep blade base fused with its stem in the hull) into the stem region, and the
    whole region is then judged a tube.  Its connected slab-like parts (``sheet_face``)
    join the leaf region they share most edges with, or are a leaf of their own when
    they hold ``min_area`` mm² on one side.  Returns the new labels (leaves of their
    own get labels above the current ones) and the faces given back.
    """
    cand = sheet_face & stem_face
    if not cand.any():
        return labels, cand
    comp = _regions_of(len(labels), pairs, cand)
    ncomp = int(comp.max()) + 1
    a, b = pairs[:, 0], pairs[:, 1]
    # component -> leaf label edges, both directions
    src = np.concatenate([comp[a], comp[b]])
    dst = np.concatenate([np.where(leaf_face[b], labels[b], -1),
                          np.where(leaf_face[a], labels[a], -1)])
    ok = (src >= 0) & (dst >= 0)
    src, dst = src[ok], dst[ok]
    nlab = int(labels.max()) + 1
    target = np.full(ncomp, -1)
    if len(src):
        uk, cnt = np.unique(src * nlab + dst, return_counts=True)
        s_, d_ = uk // nlab, uk % nlab
        order = np.lexsort((-cnt, s_))
        s_, d_ = s_[order], d_[order]
        first = np.concatenate([[True], s_[1:] != s_[:-1]])
        target[s_[first]] = d_[first]
    big = np.bincount(comp[cand], areas[cand], ncomp) / 2.0 >= min_area
    alone = (target < 0) & big
    target[alone] = nlab + np.arange(int(alone.sum()))
    back = cand & (target[np.maximum(comp, 0)] >= 0)
    labels = labels.copy()
    labels[back] = target[comp[back]]
    return labels, back


TIP_CHAIN_ROUNDS = 3  # a tip the creases cut into a chain of up to this many tubes joins whole
TIP_FAR_END_SHARE = 0.5  # a tip meets its leaf at least this share of the leaf's stem distance


def _tips_to_leaves(labels: np.ndarray, tube: np.ndarray, leafy: np.ndarray,
                    pairs: np.ndarray, nlab: int, centroids: np.ndarray, gap: float,
                    rounds: int = TIP_CHAIN_ROUNDS) -> tuple[np.ndarray, int]:
    """Blade tips the tube test called stem, or the hull cut off, given to their leaf.

    A grass blade narrows to its tip over a few centimetres; there the hull's slab is
    about as thick as it is wide, its normals turn all round its axis, and the crease
    where the blade bends cuts it off as a region the tube test calls stem.  Where
    the tip is narrower than about a voxel the hull breaks it off altogether: a
    separate mesh component a voxel or two from the blade.  A piece is a tip of leaf
    L when it touches (or lies within ``gap`` mm of) L and nothing else, **at L's far
    end**: at least ``TIP_FAR_END_SHARE`` of L's greatest distance from the stem,
    measured over L's surface from the faces L shares with stem regions.  (A stalk's
    top hanging off the top leaf that wraps it touches that leaf at its base; a leaf
    touching no stem has no far end, and gets nothing.)  So

    * a tube region whose only neighbour is one leaf, at its far end, joins it;
      ``rounds`` rounds, so a tip cut into a short chain of tubes joins too;
    * a non-leaf region with no neighbour at all (its own mesh component) whose
      nearest leaf face lies within ``gap`` mm and at that leaf's far end joins it.

    ``labels`` (F,) regions < ``nlab`` after the crumb merge; ``tube``/``leafy``
    (nlab,) region kinds; ``centroids`` (F, 3) mm.  Returns the new labels and the
    number of regions given to a leaf.
    """
    pruned, parent = _hanging_tubes(labels, tube, pairs, nlab, rounds)
    far = _FarEnd(labels, leafy[labels], (tube & ~pruned)[labels], pairs, centroids, nlab)
    if far.dist is None:
        return labels.copy(), 0
    labels, n_chains = _chains_to_leaves(labels, leafy, pairs, pruned, parent, far, rounds)
    labels, n_lonely = _lonely_to_leaves(labels, leafy, pairs, centroids, far, gap)
    return labels, n_chains + n_lonely


def _hanging_tubes(labels: np.ndarray, tube: np.ndarray, pairs: np.ndarray, nlab: int,
                   rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """Tube regions dangling off one neighbour, pruned ``rounds`` times like a tree's
    leaves (the tips themselves): ``(pruned, parent)`` (nlab,), ``parent`` the region
    each pruned tube hung from (-1 for the others)."""
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    cross = la != lb
    uk = np.unique(np.concatenate([la[cross] * nlab + lb[cross], lb[cross] * nlab + la[cross]]))
    r_s, r_d = uk // nlab, uk % nlab
    pruned = np.zeros(nlab, bool)
    parent = np.full(nlab, -1)
    for _ in range(rounds):
        alive = ~pruned[r_s] & ~pruned[r_d]
        deg = np.bincount(r_s[alive], minlength=nlab)
        dangling = tube & ~pruned & (deg == 1)
        if not dangling.any():
            break
        hang = alive & dangling[r_s]
        parent[r_s[hang]] = r_d[hang]
        pruned |= dangling
    return pruned, parent


class _FarEnd:
    """Distance from the stem over each leaf's surface (``dist`` (F,), face centroids
    over shared edges, from the leaf faces next to ``stem_face``) and each leaf's
    greatest (``far_end`` (nlab,)); ``dist`` is None when no leaf touches the stem."""

    def __init__(self, labels: np.ndarray, leaf_face: np.ndarray, stem_face: np.ndarray,
                 pairs: np.ndarray, centroids: np.ndarray, nlab: int) -> None:
        from scipy.sparse.csgraph import dijkstra

        nf = len(labels)
        a, b = pairs[:, 0], pairs[:, 1]
        inner = leaf_face[a] & leaf_face[b] & (labels[a] == labels[b])
        w = geo.row_norm(centroids[a[inner]] - centroids[b[inner]])
        g = sparse.csr_matrix((np.concatenate([w, w]), (np.concatenate([a[inner], b[inner]]),
                                                        np.concatenate([b[inner], a[inner]]))),
                              shape=(nf, nf))
        src = np.unique(np.concatenate([a[leaf_face[a] & stem_face[b]],
                                        b[leaf_face[b] & stem_face[a]]]))
        self.dist: np.ndarray | None = None
        self.far_end = np.zeros(nlab)
        if len(src):
            self.dist = dijkstra(g, directed=True, indices=src, min_only=True)
            ok = np.isfinite(self.dist) & leaf_face
            np.maximum.at(self.far_end, labels[ok], self.dist[ok])

    def at(self, face: np.ndarray, leaf: np.ndarray) -> np.ndarray:
        """Whether each ``face`` lies at the far end of its ``leaf``."""
        d, end = self.dist[face], self.far_end[leaf]
        return np.isfinite(d) & (d >= TIP_FAR_END_SHARE * end) & (end > 0)


def _chains_to_leaves(labels: np.ndarray, leafy: np.ndarray, pairs: np.ndarray,
                      pruned: np.ndarray, parent: np.ndarray, far: _FarEnd,
                      rounds: int) -> tuple[np.ndarray, int]:
    """A chain of dangling tubes hanging from a leaf at its far end joins the leaf."""
    nlab = len(leafy)
    a, b = pairs[:, 0], pairs[:, 1]
    la, lb = labels[a], labels[b]
    root = parent.copy()
    for _ in range(rounds):
        up = (root >= 0) & pruned[np.maximum(root, 0)]
        root[up] = parent[root[up]]
    first = pruned & (parent >= 0) & leafy[np.maximum(parent, 0)]  # hangs from the leaf
    # every face of the leaf touching a first link must be at the far end
    to_leaf = first[la] & (lb == parent[la]) | first[lb] & (la == parent[lb])
    link = np.where(first[la], la, lb)[to_leaf]
    leaf_side = np.where(first[la], b, a)[to_leaf]
    bad = np.zeros(nlab, bool)
    bad[link[~far.at(leaf_side, labels[leaf_side])]] = True
    good_first = first & ~bad
    ok_chain = pruned & (root >= 0) & leafy[np.maximum(root, 0)]
    # the link of each chain that touches the leaf: follow parents up to it
    top = np.arange(nlab)
    for _ in range(rounds):
        up = pruned[top] & (parent[top] >= 0) & pruned[np.maximum(parent[top], 0)]
        top[up] = parent[top[up]]
    move = ok_chain & good_first[top]
    target = np.arange(nlab)
    target[move] = root[move]
    moved_face = move[labels]
    labels = target[labels]
    far.dist[moved_face] = far.far_end[labels[moved_face]]  # a joined tip: its leaf's far end
    return labels, int(np.count_nonzero(move))


def _lonely_to_leaves(labels: np.ndarray, leafy: np.ndarray, pairs: np.ndarray,
                      centroids: np.ndarray, far: _FarEnd, gap: float) -> tuple[np.ndarray, int]:
    """Non-leaf regions with no neighbour (their own mesh component) whose nearest leaf
    face lies within ``gap`` mm, at that leaf's far end, join that leaf."""
    nlab = len(leafy)
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    cross = la != lb
    has_nbr = np.zeros(nlab, bool)
    has_nbr[la[cross]] = True
    has_nbr[lb[cross]] = True
    present = np.bincount(labels, minlength=nlab) > 0
    lonely = present & ~has_nbr & ~leafy
    leaf_face = leafy[labels]
    if not (lonely.any() and leaf_face.any()):
        return labels, 0
    cand = np.flatnonzero(lonely[labels])
    leaf_idx = np.flatnonzero(leaf_face)
    d, idx = cKDTree(centroids[leaf_idx]).query(centroids[cand], distance_upper_bound=gap)
    hit = np.isfinite(d)
    reg = labels[cand]
    # each lonely region: its face nearest to any leaf decides
    order = np.lexsort((d, reg))
    first = order[np.concatenate([[True], reg[order][1:] != reg[order][:-1]])]
    first = first[hit[first]]
    near = leaf_idx[idx[first]]
    good = far.at(near, labels[near])
    target = np.arange(nlab)
    target[reg[first[good]]] = labels[near[good]]
    return target[labels], int(np.count_nonzero(good))


def _strays_to_region(pieces: np.ndarray, small: np.ndarray, regions: np.ndarray,
                      centroids: np.ndarray) -> np.ndarray:
    """Small leaf pieces that no merge reached join the nearest big piece of their region.

    ``pieces`` (F,) leaf piece per face (-1 off leaves, P merged into the stem side),
    ``small`` (P,) pieces below a leaf's area, ``regions`` (F,) the region labels the
    pieces were cut from, ``centroids`` (F, 3) mm.  A piece with no neighbour (a blade
    tip the hull broke off, given to its leaf by ``_tips_to_leaves``) keeps its leaf
    instead of falling to the stem.  The *nearest* piece, not the biggest: one region
    may hold several blades until the petiole test cuts them apart (18 MP wheat,
    paper-360: the broken-off tips of three blades all went to the biggest blade of
    their region, each blade 6-9 % short).
    """
    from scipy.spatial import cKDTree

    npc = len(small)
    on = (pieces >= 0) & (pieces < npc)  # npc: faces merged into the stem side
    stray = on & small[np.clip(pieces, 0, npc - 1)]
    if not stray.any():
        return pieces
    big_face = on & ~stray
    if not big_face.any():
        return pieces
    out = pieces.copy()
    for reg in np.unique(regions[stray]):
        cand = np.flatnonzero(big_face & (regions == reg))
        if not len(cand):
            continue
        tree = cKDTree(centroids[cand])
        for piece in np.unique(pieces[stray & (regions == reg)]):
            faces = np.flatnonzero(stray & (regions == reg) & (pieces == piece))
            dist, nearest = tree.query(centroids[faces])
            out[faces] = pieces[cand[nearest[np.argmin(dist)]]]
    return out


def _split_joined_leaves(labels: np.ndarray, crease: np.ndarray, areas: np.ndarray,
                         pairs: np.ndarray, min_area: float) -> tuple[np.ndarray, int]:
    """Leaves that hold two or more big regions at a finer crease threshold, split.

    Two leaves that touch in the hull (a drooping leaf lying on one below it) may meet
    along a crease shallower than ``concave_curvature_per_mm``; a lower threshold
    everywhere would cut leaves' own edges off (creases of phantom volume).  Within
    each leaf, the connected non-``crease`` faces with ``min_area`` mm² on one side are
    seeds; a leaf with two or more is regrown from them (faces reached by none stay
    with the biggest).  Returns labels 0 (stem), 1..n and the number of leaves split.
    """
    nf = len(labels)
    same = labels[pairs[:, 0]] == labels[pairs[:, 1]]
    inner = pairs[same & (labels[pairs[:, 0]] > 0)]
    seeds = _regions_of(nf, inner, (labels > 0) & ~crease)
    if not (seeds >= 0).any():
        return labels, 0
    n_seeds = int(seeds.max()) + 1
    seed_area = np.bincount(seeds[seeds >= 0], areas[seeds >= 0], n_seeds) / 2.0
    seed_label = np.zeros(n_seeds, np.int64)
    seed_label[seeds[seeds >= 0]] = labels[seeds >= 0]
    big = seed_area >= min_area
    n_big = np.bincount(seed_label[big], minlength=int(labels.max()) + 1)
    split = n_big >= 2
    if not split.any():
        return labels, 0
    in_split = split[labels]
    init = np.where(in_split & (seeds >= 0) & big[np.maximum(seeds, 0)], seeds, -1)
    grown = kernels.grow(init, inner[in_split[inner[:, 0]]])
    # faces of a split leaf no seed reaches (cut off by creases) join its biggest seed
    biggest = np.full(len(split), -1)
    big_ids = np.flatnonzero(big)  # few: most seeds are crumbs between creases
    order = big_ids[np.argsort(seed_area[big_ids], kind="stable")]
    biggest[seed_label[order]] = order  # ascending: a label's biggest seed is written last
    lost = in_split & (grown < 0)
    grown[lost] = biggest[labels[lost]]
    # renumber: unsplit leaves keep one id each, each seed of a split leaf gets its own
    key = np.where(in_split, n_seeds + labels.max() + 1 + grown, labels)
    key[labels == 0] = 0
    _, new = geo.unique_inverse(key, 2 * n_seeds + int(labels.max()) + 1)
    out = new.reshape(labels.shape).astype(np.int32)
    if (labels > 0).all():  # no stem at all: ids start at 1 anyway
        out += 1
    return out, int(split.sum())


def _leaf_bases(labels: np.ndarray, centroids: np.ndarray, pairs: np.ndarray
                ) -> dict[int, np.ndarray]:
    """Each leaf's base: of the places where it meets the stem (``_cut_places``), the one
    with the smallest median distance from the plant's axis (the turntable axis, z through
    x = y = 0; a blade's base is at its culm, its tip out, and a blade lying across another
    culm touches it farther out); its faces, by leaf label.  A leaf with no such place
    (no stem contact) has none."""
    best: dict[int, tuple[float, np.ndarray]] = {}
    for lab, faces in _cut_places(labels, _stem_border(labels, pairs), centroids):
        r = float(np.median(np.hypot(centroids[faces, 0], centroids[faces, 1])))
        if int(lab) not in best or r < best[int(lab)][0]:
            best[int(lab)] = (r, faces)
    return {lab: np.flatnonzero(faces) for lab, (_, faces) in best.items()}


def _split_forked_leaves(labels: np.ndarray, centroids: np.ndarray, areas: np.ndarray,
                         pairs: np.ndarray, min_area: float, min_reach: float
                         ) -> tuple[np.ndarray, int]:
    """Leaves that fork into branches, one leaf per branch (``fork_branch_mm``).

    Grass blades that leave their culm together share a fused base in the hull and
    arrive as one leaf: no crease parts them where they join, because they do not touch
    along a line but grow out of one surface.  Seen from the leaf's base
    (``_leaf_bases``), such a leaf forks; one blade does not.  Per leaf: geodesic distance
    over its face graph from the base (edge length between face centroids), the branches
    of ``kernels.fork_branches`` (a persistence filtration, as in watershed and
    mode-seeking segmentation: the superlevel sets of the distance grow face by face,
    and where two parts of ``min_area`` one side, each reaching ``min_reach`` mm beyond
    the joining face and lying the same way from it, meet, each becomes a branch: two
    blades diverging from a common base, not the two ends of one blade whose base-most
    stem contact sits in its middle; a lobe or a hole never makes two big parts), and
    the trunk (the faces below the fork, both blades' fused bases) given to the nearest
    branch along the surface.  A leaf with no stem contact, or with fewer than two
    branches, is left as it is.  Returns the labels (new leaves numbered after the
    others) and the number of leaves split.
    """
    out = labels.copy()
    a, b = pairs[:, 0], pairs[:, 1]
    inner = (labels[a] == labels[b]) & (labels[a] > 0)
    one_side = areas / 2.0
    leaf_area = np.bincount(labels[labels > 0], one_side[labels > 0])
    bases = _leaf_bases(labels, centroids, pairs)
    next_label, n_split = int(labels.max()) + 1, 0
    for lab in np.flatnonzero(leaf_area >= 2 * min_area):
        base = bases.get(int(lab))
        if base is None:
            continue
        idx = np.flatnonzero(labels == lab)
        loc = np.full(len(labels), -1)
        loc[idx] = np.arange(len(idx))
        e = inner & (labels[a] == lab)
        ia, ib = loc[a[e]], loc[b[e]]
        w = geo.row_norm(centroids[a[e]] - centroids[b[e]]) + 1e-9
        graph = sparse.csr_matrix((np.r_[w, w], (np.r_[ia, ib], np.r_[ib, ia])),
                                  shape=(len(idx), len(idx)))
        dist = dijkstra(graph, indices=loc[base], min_only=True)
        reached = np.isfinite(dist)
        order = np.flatnonzero(reached)[np.argsort(-dist[reached], kind="stable")]
        branch = kernels.fork_branches(order, np.where(reached, dist, 0.0), graph.indptr,
                                       graph.indices, centroids[idx], one_side[idx],
                                       min_area, min_reach)
        n_branch = int(branch.max())
        if n_branch < 2:
            continue
        # the trunk (and faces the base does not reach) to the nearest branch on the surface
        _, _, src = dijkstra(graph, indices=np.flatnonzero(branch > 0), min_only=True,
                             return_predecessors=True)
        rest = branch == 0
        branch[rest] = np.where(src[rest] >= 0, branch[np.maximum(src[rest], 0)], 1)
        new = np.r_[lab, np.arange(next_label, next_label + n_branch - 1)]
        out[idx] = new[branch - 1]
        next_label += n_branch - 1
        n_split += 1
    return out, n_split


# A broken blade's two pieces: their facing ends point at each other within ~30° and
# are at least this share of each piece's widest station wide (a blade's own base tapers,
# so two blades meeting base to base across a stem are not joined).
JOIN_END_COS = 0.85
JOIN_END_WIDTH_SHARE = 0.6
JOIN_END_MM = 5.0  # the end zone whose width is read (a tapered base is narrow there)
JOIN_DIRECTION_MM = 30.0  # the end zone whose principal axis is the end's direction
JOIN_END_WIDTH_PERCENTILE = 95  # an end's half width: this percentile of its lateral offsets
JOIN_STATION_MM = 10.0  # a piece's widest station: the widest of its slices this long
JOIN_MIN_FACES = 10  # a piece of fewer faces has no ends to read (no direction, no width)
JOIN_BRIDGE_MARGIN_MM = 2.0  # stem faces within half the wider end + this join the blade


def _principal_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and unit principal axis (its sign arbitrary) of ``points`` (N, 3)."""
    mu = points.mean(axis=0)
    return mu, np.linalg.svd(points - mu, full_matrices=False)[2][0]


def _blade_ends(q: np.ndarray, w: np.ndarray) -> tuple[list[tuple[np.ndarray, np.ndarray,
                                                                     float]], float]:
    """Both ends of a leaf piece: (point, outward direction, width) each, mm.

    Ends are the last ``JOIN_END_MM`` along the piece's principal axis (area-weighted;
    the point is their mean, not the single extreme face, a corner of the cut); the
    direction is the principal axis of the last ``JOIN_DIRECTION_MM``, pointing out;
    the width is twice the ``JOIN_END_WIDTH_PERCENTILE``th percentile of the lateral
    distance over the last ``JOIN_END_MM``.  Also returns the widest ``JOIN_STATION_MM``
    station across the second principal axis.
    """
    mu = np.average(q, axis=0, weights=w)
    _, _, vt = np.linalg.svd((q - mu) * np.sqrt(w)[:, None], full_matrices=False)
    s = (q - mu) @ vt[0]
    across = (q - mu) @ vt[1]
    station = np.floor((s - s.min()) / JOIN_STATION_MM).astype(np.int64)
    lo = np.full(int(station.max()) + 1, np.inf)
    hi = np.full(int(station.max()) + 1, -np.inf)
    np.minimum.at(lo, station, across)
    np.maximum.at(hi, station, across)
    widest = float(np.max(hi - lo))
    ends = []
    for sign in (1.0, -1.0):
        ss = sign * s
        top = ss.max()
        _, d = _principal_axis(q[ss > top - JOIN_DIRECTION_MM])
        d = d if d @ (sign * vt[0]) > 0 else -d  # pointing out of the blade
        tip = q[ss > top - JOIN_END_MM]
        rel = tip - tip.mean(axis=0)
        width = 2.0 * float(np.percentile(geo.row_norm(rel - np.outer(rel @ d, d)),
                                          JOIN_END_WIDTH_PERCENTILE))
        ends.append((tip.mean(axis=0), d, width))
    return ends, widest


def _join_broken_blades(labels: np.ndarray, centroids: np.ndarray, areas: np.ndarray,
                        gap_mm: float) -> tuple[np.ndarray, int]:
    """Leaves that are two pieces of one blade cut where it crosses a stem, joined.

    Where a grass blade lies against a stem or tiller it crosses, the hull fuses
    them and the concave creases on both sides of the stem cut the blade in two;
    the outer piece then measures as an extra leaf and the blade as far too short
    (18 MP wheat, paper-72: one blade −51 % length).  Two leaf pieces are one blade
    when an end of each lies within ``gap_mm`` of the other, the two ends point at
    each other (outward directions opposite within ~30°) and both are wide there
    (``JOIN_END_WIDTH_SHARE`` of the piece's widest station: a blade's own base
    tapers, so blades meeting base to base across a stem stay apart).  The stem
    faces between the ends (within half the wider end + 2 mm of the segment
    joining them) join too, so the blade is one connected surface.  Returns
    labels 0 (stem), 1..n and the number of joins.
    """
    n = int(labels.max())
    ends: dict[int, list] = {}
    widest: dict[int, float] = {}
    for lab in range(1, n + 1):
        sel = labels == lab
        if np.count_nonzero(sel) >= JOIN_MIN_FACES:
            ends[lab], widest[lab] = _blade_ends(centroids[sel], areas[sel])
    root = np.arange(n + 1)

    def find(a: int) -> int:
        while root[a] != a:
            a = root[a]
        return a

    out = labels.copy()
    joined = 0
    keys = sorted(ends)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            for pa, da, wa in ends[a]:
                for pb, db, wb in ends[b]:
                    gap = float(np.linalg.norm(pb - pa))
                    if (gap > gap_mm or float(da @ -db) < JOIN_END_COS
                            or wa < JOIN_END_WIDTH_SHARE * widest[a]
                            or wb < JOIN_END_WIDTH_SHARE * widest[b]):
                        continue
                    u = (pb - pa) / max(gap, 1e-9)
                    rel = centroids - pa
                    t = rel @ u
                    r = 0.5 * max(wa, wb) + JOIN_BRIDGE_MARGIN_MM
                    bridge = ((labels == STEM_LABEL) & (t > -r) & (t < gap + r)
                              & (geo.row_norm(rel - np.outer(t, u)) < r))
                    ra, rb = find(a), find(b)
                    if ra != rb:
                        root[max(ra, rb)] = min(ra, rb)
                        joined += 1
                    out[bridge] = min(ra, rb)
    if not joined:
        return labels, 0
    final = np.array([find(k) for k in range(n + 1)])
    out = np.where(out > 0, final[out], 0)
    _, new = np.unique(out, return_inverse=True)  # 0 stays 0 when a stem face exists
    new = new.reshape(out.shape).astype(np.int32)
    if (out > 0).all():
        new += 1
    return new, joined


CULM_MIN_LENGTH_MM = 100.0  # a culm axis: a straight tube at least this long ...
CULM_MIN_STEEPNESS = 0.5  # ... and steeper than 30 degrees (|axis z| > sin 30°)
CULM_INLIER_MM = 6.0  # stem faces within this of a candidate line are its inliers
CULM_MARGIN_MM = 1.5  # faces beyond a culm's radius + this are off the culm
CULM_SAMPLE = 30_000  # stem faces the RANSAC looks at
CULM_TRIALS = 400
CULM_MAX_LINES = 16
CULM_MIN_POOL = 200  # fewer stem faces left than this: no further culm to find
CULM_MIN_TRIAL_MM = 15.0  # a trial line's two points at least this far apart (a direction)
CULM_REFINE_ROUNDS = 4  # PCA refinements of the best trial line over its inliers
CULM_POOL_DROP = 2.0  # after each line, faces within this x CULM_INLIER_MM leave the pool
CULM_MIN_ROUNDNESS = 0.4  # a culm is round: its normals turn all round its axis (below)
CULM_ROUND_STEP_MM = 10.0  # ... judged per stretch of this length along the axis
CULM_ROUND_MIN_FACES = 20  # ... of at least this many inliers
BASE_DIRECTION_MM = 30.0  # a blade's direction at its cut: its faces within this of the cut
BASE_MARGIN_MM = 1.0  # the corridor: the cut's half width (90th percentile) + this
CUT_LINK_MM = 3.0  # cut faces this close are one place where a leaf meets the stem
CUT_MIN_FACES = 3  # a place of fewer cut faces is a corner touching the stem, not a cut
BASE_MIN_FACES = 10  # a blade with fewer faces near its cut has no direction to follow
BASE_HALF_WIDTH_PERCENTILE = 90  # the cut's half width: this percentile of its lateral offsets


def _culm_axes(points: np.ndarray, normals: np.ndarray, rng: np.random.Generator
               ) -> list[tuple[np.ndarray, np.ndarray, float, float, float]]:
    """Straight culm axes through stem points: ``(origin, direction, s0, s1, radius)`` each.

    Sequential RANSAC lines (two random points; inliers within
    ``CULM_INLIER_MM``), each refined by the PCA of its inliers (a tube's
    surface points average onto its axis); a line is a culm when its inliers
    span ``CULM_MIN_LENGTH_MM`` (2nd-98th percentile along it), it is
    steeper than 30° and it is round (``_roundness`` of the inliers' unit
    ``normals`` at least ``CULM_MIN_ROUNDNESS``: a narrow straight blade the
    tube test called stem is a slab, whose normals point two ways); ``radius``
    is the inliers' median distance from it.  Points within twice the inlier
    distance leave the pool after every line, culm or not (the soil disc's
    edge, fused blade bases, blades).
    """
    axes = []
    pool = np.ones(len(points), bool)
    for _ in range(CULM_MAX_LINES):
        idx = np.flatnonzero(pool)
        if len(idx) < CULM_MIN_POOL:
            break
        pairs = [rng.choice(idx, 2, replace=False) for _t in range(CULM_TRIALS)]
        o_t = points[[i for i, _ in pairs]]
        d_t = points[[j for _, j in pairs]] - o_t
        length = geo.row_norm(d_t)
        keep = length >= CULM_MIN_TRIAL_MM
        if not keep.any():
            break
        o_t, d_t = o_t[keep], d_t[keep] / length[keep, None]
        # squared distance of every point from every trial line, |w|^2 - (w.d)^2 with
        # w = p - o, in two matrix products (one pass over the points for all trials)
        n_in = np.zeros(len(o_t), np.int64)
        od, oo = np.einsum("ij,ij->i", o_t, d_t), np.einsum("ij,ij->i", o_t, o_t)
        for k in range(0, len(idx), 8192):  # ~25 MB per block at 400 trials
            q = points[idx[k:k + 8192]]
            along = q @ d_t.T - od
            w2 = np.einsum("ij,ij->i", q, q)[:, None] - 2.0 * (q @ o_t.T) + oo
            n_in += np.count_nonzero(w2 - along * along < CULM_INLIER_MM ** 2, axis=0)
        t = int(np.argmax(n_in))
        o, d = o_t[t], d_t[t]
        for _r in range(CULM_REFINE_ROUNDS):
            w = points[idx] - o
            q = points[idx][geo.row_norm(w - np.outer(w @ d, d)) < CULM_INLIER_MM]
            o, d = _principal_axis(q)
        w = points[idx] - o
        s = w @ d
        r = geo.row_norm(w - np.outer(s, d))
        inl = r < CULM_INLIER_MM
        pool[idx[r < CULM_POOL_DROP * CULM_INLIER_MM]] = False
        if (np.percentile(s[inl], 98) - np.percentile(s[inl], 2) >= CULM_MIN_LENGTH_MM
                and abs(d[2]) > CULM_MIN_STEEPNESS
                and _roundness(normals[idx[inl]], s[inl], d) >= CULM_MIN_ROUNDNESS):
            axes.append((o, d, float(np.percentile(s[inl], 1)), float(np.percentile(s[inl], 99)),
                         float(np.median(r[inl]))))
    return axes


def _roundness(normals: np.ndarray, along: np.ndarray, d: np.ndarray) -> float:
    """How evenly unit ``normals`` turn round the axis direction ``d``: per stretch of
    ``CULM_ROUND_STEP_MM`` along it (``along``: each face's position on the axis), the
    smaller over the larger eigenvalue of the normals' tensor across the axis; the median
    over the stretches with ``CULM_ROUND_MIN_FACES``.  A tube gives ~1, a slab (a blade,
    whose two sides share one normal up to sign) ~0; a blade twisting along its length
    still reads as a slab in every stretch.  1 when no stretch has enough faces (nothing
    to say against the line)."""
    across = normals - np.outer(normals @ d, d)
    ratios = []
    k = np.floor((along - along.min()) / CULM_ROUND_STEP_MM).astype(np.int64)
    for b in np.flatnonzero(np.bincount(k) >= CULM_ROUND_MIN_FACES):
        t = across[k == b]
        ev = np.linalg.eigvalsh(t.T @ t)  # 3x3; the smallest ~0 (along d)
        ratios.append(ev[1] / max(ev[2], 1e-12))
    return float(np.median(ratios)) if ratios else 1.0


def _stem_culms(stem: np.ndarray, centroids: np.ndarray, normals: np.ndarray) -> list:
    """``_culm_axes`` of the ``stem`` (F,) faces, at most ``CULM_SAMPLE`` of them, drawn
    with a fixed seed (the same culms from the same mesh); [] without stem."""
    si = np.flatnonzero(stem)
    if not len(si):
        return []
    rng = np.random.default_rng(0)
    sample = si if len(si) <= CULM_SAMPLE else rng.choice(si, CULM_SAMPLE, replace=False)
    return _culm_axes(centroids[sample], normals[sample], rng)


def _stem_border(labels: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(F,) the leaf faces (label > 0) sharing an edge with a stem face."""
    a, b = pairs[:, 0], pairs[:, 1]
    stem = labels == STEM_LABEL
    cut = np.zeros(len(labels), bool)
    cut[a[(labels[a] > 0) & stem[b]]] = True
    cut[b[(labels[b] > 0) & stem[a]]] = True
    return cut


def _axis_distance(points: np.ndarray, axes: list) -> np.ndarray:
    """(N,) distance of every point from the nearest culm axis segment (inf without axes)."""
    best = np.full(len(points), np.inf)
    for o, d, s0, s1, _ in axes:
        w = points - o
        s = np.clip(w @ d, s0, s1)
        best = np.minimum(best, geo.row_norm(w - np.outer(s, d)))
    return best


def _cut_places(labels: np.ndarray, cut: np.ndarray, centroids: np.ndarray):
    """``(label, faces)`` for every place a leaf meets the stem: its cut faces grouped by
    single linkage within ``CUT_LINK_MM`` (a border's faces touch at vertices, not
    edges), groups of at least ``CUT_MIN_FACES`` faces."""
    for lab in np.unique(labels[cut]):
        ids = np.flatnonzero(cut & (labels == lab))
        if len(ids) < CUT_MIN_FACES:
            continue
        links = cKDTree(centroids[ids]).query_pairs(CUT_LINK_MM, output_type="ndarray")
        g = sparse.csr_matrix((np.ones(len(links), np.int8), (links[:, 0], links[:, 1])),
                              shape=(len(ids), len(ids)))
        _, group = connected_components(g, directed=False)
        for k in np.flatnonzero(np.bincount(group) >= CUT_MIN_FACES):
            faces = np.zeros(len(labels), bool)
            faces[ids[group == k]] = True
            yield lab, faces


def _blade_bases_off_culms(labels: np.ndarray, centroids: np.ndarray, normals: np.ndarray,
                           pairs: np.ndarray, ground_z: float, reach_mm: float
                           ) -> tuple[np.ndarray, int]:
    """Stem faces along a blade's continuation into the tangle of tillers, given to the blade.

    A wheat blade's base often runs across the neighbouring tillers to its own
    node; the 2-camera hull fuses blade and tillers there, the region growing
    and the petiole test call that stretch stem, and the blade measures a third
    short (18 MP wheat paper-72: two blades −31 / −35 % length, 37-40 % of their
    area in the stem label).  The culms themselves are straight tubes
    (``_culm_axes``); the fused blade bases lie off them.  For every leaf
    touching the stem: its direction is the principal axis of its faces within
    ``BASE_DIRECTION_MM`` of the cut (the leaf faces next to stem faces),
    pointing into the stem; the stem faces off every culm (beyond its radius +
    ``CULM_MARGIN_MM``), above ``ground_z``, ahead of the cut up to
    ``reach_mm`` and within the cut's half width + ``BASE_MARGIN_MM`` of that
    ray are claimed; a face two rays claim goes to the nearer ray; a leaf keeps
    only the claimed faces connected to it.  A leaf meeting the stem in several
    places (``_cut_places``) gets a corridor from each.  Returns the labels and
    the number of faces moved.
    """
    stem = labels == STEM_LABEL
    axes = _stem_culms(stem, centroids, normals)
    if not axes:
        return labels, 0
    off = _axis_distance(centroids, axes) > np.median([a[4] for a in axes]) + CULM_MARGIN_MM
    cand = stem & off & (centroids[:, 2] > ground_z)
    cut = _stem_border(labels, pairs)
    best = np.full(len(labels), np.inf)
    claim = np.zeros(len(labels), labels.dtype)
    ids_all = np.flatnonzero(cand)
    for lab, cf in _cut_places(labels, cut, centroids):
        c0 = centroids[cf].mean(axis=0)
        q = centroids[(labels == lab) & (geo.row_norm(centroids - c0) < BASE_DIRECTION_MM)]
        if len(q) < BASE_MIN_FACES:
            continue
        mu, d = _principal_axis(q)
        d = d if d @ (c0 - mu) >= 0 else -d  # into the stem
        w = centroids[cf] - c0
        half = float(np.percentile(geo.row_norm(w - np.outer(w @ d, d)),
                                   BASE_HALF_WIDTH_PERCENTILE)) + BASE_MARGIN_MM
        w = centroids[ids_all] - c0
        t = w @ d
        lat = geo.row_norm(w - np.outer(t, d))
        ok = (t > -BASE_MARGIN_MM) & (t < reach_mm) & (lat < half)
        ids, lat = ids_all[ok], lat[ok]
        nearer = lat < best[ids]
        best[ids[nearer]] = lat[nearer]
        claim[ids[nearer]] = lab
    out = labels.copy()
    for lab in np.unique(claim[claim > 0]):
        comp = _regions_of(len(labels), pairs, (claim == lab) | (labels == lab))
        main = np.bincount(comp[labels == lab]).argmax()
        out[(claim == lab) & (comp == main)] = lab
    return out, int(np.count_nonzero(out != labels))


JOIN_MIN_PIECE_SHARE = 0.25  # of min_leaf_area_mm2: smaller pieces are crumbs, not blade parts


def _join_blade_pieces(pieces: np.ndarray, leaf_face: np.ndarray, small: np.ndarray,
                       centroids: np.ndarray, areas: np.ndarray, gap_mm: float,
                       min_area: float) -> tuple[np.ndarray, int]:
    """Leaf pieces of one blade cut apart at a stem, joined (``_join_broken_blades``' rule).

    ``pieces`` (F,) piece per face, -1 off leaves; ``small`` (P,) pieces below a leaf's
    area.  Candidates are the pieces with ``JOIN_MIN_PIECE_SHARE`` of a leaf's area (a
    blade's base cut off where it crosses a tiller is often less than a leaf, more than
    a crumb); the faces bridging a joined pair become leaf faces of the joined piece.
    Returns the pieces renumbered 0..n-1 (-1 off leaves) and the number of joins.
    """
    npc = len(small)
    on = leaf_face & (pieces >= 0)
    area = np.bincount(pieces[on], areas[on], npc) / 2.0
    cand = area >= JOIN_MIN_PIECE_SHARE * min_area
    cand_face = on & cand[np.maximum(pieces, 0)]
    lab = np.where(cand_face, pieces + 1, 0).astype(np.int32)
    joined, n = _join_broken_blades(lab, centroids, areas, gap_mm)
    if not n:
        return pieces, 0
    # joined candidates (and their bridges) keep their new ids; other leaf pieces follow
    m = int(joined.max())
    out = np.where(joined > 0, joined - 1, -1)
    rest = on & ~cand_face & (joined == 0)
    out[rest] = m + pieces[rest]
    return _relabel(out), n


def _merge_crumbs(labels: np.ndarray, crumbs: np.ndarray, pairs: np.ndarray, nlab: int,
                  rounds: int = 1) -> np.ndarray:
    """Give each crumb region the label of the non-crumb region it shares most edges with.

    With ``rounds`` > 1, crumbs that touch only other crumbs (a narrow blade tip cut off
    by a chain of small regions) join in later rounds, once a crumb next to them has
    joined a region.
    """
    crumbs = crumbs.copy()
    # only edges between different regions matter; they are few compared to all face pairs
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    cross = la != lb
    la, lb = la[cross], lb[cross]
    mapping = np.arange(nlab)
    for _ in range(rounds):
        ma, mb = mapping[la], mapping[lb]
        both = np.concatenate([np.stack([ma, mb], 1), np.stack([mb, ma], 1)])
        both = both[crumbs[both[:, 0]] & ~crumbs[both[:, 1]] & (both[:, 0] != both[:, 1])]
        if len(both) == 0:
            break
        key = both[:, 0] * nlab + both[:, 1]
        uk, cnt = np.unique(key, return_counts=True)
        src, dst = uk // nlab, uk % nlab
        order = np.lexsort((-cnt, src))
        src, dst = src[order], dst[order]
        first = np.concatenate([[True], src[1:] != src[:-1]])
        src, dst = src[first], dst[first]
        step = np.arange(nlab)
        step[src] = dst
        mapping = step[mapping]
        crumbs[src] = False
    return mapping[labels]

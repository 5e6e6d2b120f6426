"""Procedural plants (and external meshes) with exact flat-leaf truth.

A plant is built in the world (turntable) frame, standing in its pot: the pot's
soil surface is at ``soil_z`` (mm above the turntable plate).  ``build_plant``
makes a plant of one of the five families (``families.FAMILIES``: seeded,
varied, growing with ``age``) or of a fixed preset: ``plastic-dicot`` (a member
of the dicot family: the seed's plastic plant), ``wheat`` and ``sorghum``
(members of the grass family, kept so their old figures can be re-measured) and
``mesh`` (any labelled mesh).  Every face carries a leaf id (-1: not leaf) and
an organ (``families.ORGANS``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plantscan_core.data import LeafTraits, Traits
from plantscan_core.errors import DataError
from plantscan_sim.families import (
    DRAW,
    FAMILIES,
    ORGAN_CODE,
    Ground,
    build,
    resolve_crossings,
)
from plantscan_sim.geometry import (
    LeafOutline,
    LeafPlacement,
    TriMesh,
    leaf_outline,
    leaf_solid,
    mesh_area,
    tube,
)

PRESETS = ("plastic-dicot", "wheat", "sorghum", "mesh")
# the family each fixed preset belongs to (what a population figure of it is compared with)
PRESET_FAMILY = {"plastic-dicot": "dicot", "wheat": "grass", "sorghum": "grass", "mesh": None}
PLANTS = FAMILIES + PRESETS  # every value of scan.scene.params.preset

# The seed's large plastic plant (Table of dissected leaves): length, width mm; perimeter mm;
# area mm².
PLASTIC_DICOT_LEAVES = {
    "B": dict(length=152.6, width=74.5, perimeter=350.89, area=8535.6, count=4),
    "C": dict(length=186.9, width=96.6, perimeter=436.16, area=13303.4, count=2),
    "D": dict(length=221.0, width=115.6, perimeter=519.1, area=18868.0, count=6),
}


@dataclass
class Leaf:
    leaf_id: int
    kind: str
    outline: LeafOutline
    placement: LeafPlacement
    colour: tuple[float, float, float]
    group: int = -1                  # tiller / shoot / compound leaf (families)
    growth: float = 1.0              # share of its final size at the plant's age
    appear_day: float | None = None  # day the leaf appeared (families)

    def traits(self) -> LeafTraits:
        o = self.outline
        return LeafTraits(self.leaf_id, o.length, o.width, o.area, o.perimeter)


@dataclass
class Plant:
    """Geometry of a plant: ``mesh.face_attr`` is the leaf id (-1 stem/petioles),
    ``face_organ`` the organ of every face (a code of ``families.ORGANS``)."""

    preset: str
    mesh: TriMesh
    leaves: list[Leaf]
    leaf_colours: dict[int, tuple[float, float, float]]
    stem_colour: tuple[float, float, float]
    soil_z: float
    info: dict = field(default_factory=dict)
    surface_traits: list[LeafTraits] | None = None  # external meshes: measured, not flat
    face_organ: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.face_organ is None:  # a leaf id is a blade, everything else stem
            self.face_organ = np.where(self.mesh.face_attr >= 0, ORGAN_CODE["blade"],
                                       ORGAN_CODE["stem"]).astype(np.int8)

    def leaf_records(self) -> list[dict]:
        """One record per leaf: id, kind, group, growth, appearance day, base and tip (mm)."""
        out = []
        for lf in self.leaves:
            pts, _ = lf.placement.midrib(np.array([0.0, lf.outline.length]))
            out.append({"leaf_id": lf.leaf_id, "kind": lf.kind, "group": lf.group,
                        "growth": round(float(lf.growth), 6), "appear_day": lf.appear_day,
                        "base_mm": np.round(pts[0], 4).tolist(),
                        "tip_mm": np.round(pts[1], 4).tolist()})
        return out

    def traits(self) -> Traits:
        leaves = self.surface_traits if self.surface_traits is not None else [
            leaf.traits() for leaf in self.leaves]
        top = float(self.mesh.vertices[:, 2].max())
        plant = {
            "height_mm": top - self.soil_z,
            "top_z_mm": top,
            "soil_z_mm": self.soil_z,
            "total_leaf_area_mm2": float(sum(t.area_mm2 for t in leaves)),
            "leaf_count": len(leaves),
        }
        return Traits(leaves, plant)


def _green(rng: np.random.Generator, base=(0.10, 0.36, 0.07)) -> tuple[float, float, float]:
    j = rng.uniform(0.85, 1.15)
    return (base[0] * rng.uniform(0.8, 1.2), base[1] * j, base[2] * rng.uniform(0.8, 1.2))


def _assemble(preset, leaves, stems, soil_z, rng, thickness, info, stem_colour,
              stem_organs=None) -> Plant:
    parts = [leaf_solid(lf.outline, lf.placement, thickness, attr=lf.leaf_id) for lf in leaves]
    parts += [s.with_attr(-1) for s in stems]
    organs = ["blade"] * len(leaves) + list(stem_organs or ["stem"] * len(stems))
    face_organ = np.concatenate([np.full(len(p.faces), ORGAN_CODE[o], np.int8)
                                 for p, o in zip(parts, organs, strict=True)])
    info = {"family": PRESET_FAMILY[preset], **info}
    return Plant(preset, TriMesh.concat(parts), leaves, {lf.leaf_id: lf.colour for lf in leaves},
                 stem_colour, soil_z, info, face_organ=face_organ)


@functools.lru_cache(maxsize=32)
def _mature_plan(family: str, seed: int, soil_z: float, thickness: float, ground: Ground):
    """The seed's plan with its crossings fixed (cached: a growth series builds it once)."""
    plan = DRAW[family](np.random.default_rng(seed))
    return resolve_crossings(plan, seed, soil_z, thickness, ground)


def family_plant(family: str, seed: int, soil_z: float, thickness: float = 0.5,
                 age: float | None = None, ground: Ground | None = None) -> Plant:
    """The plant of ``family`` drawn from ``seed``, at ``age`` days (None: mature).

    The plan (every random draw) depends on the seed only; the crossing fixes are
    made on the mature plant, so every age of one seed is the same plant growing.
    """
    if family not in DRAW:
        raise ValueError(f"unknown plant family {family!r}; valid: {', '.join(FAMILIES)}")
    if age is not None and age < 0:
        raise ValueError(f"age {age} days: must be >= 0")
    ground = ground or Ground.default(soil_z)
    plan, crossings_left = _mature_plan(family, int(seed), float(soil_z), float(thickness), ground)
    mature = plan.mature_age()
    at = mature if age is None else min(float(age), mature)
    built = build(plan, at, soil_z, thickness, ground)
    leaves = []
    for i, _, outline, place, growth in built.leaves:
        lp = plan.leaves[i]
        leaves.append(Leaf(i, lp.kind, outline, place, lp.colour, lp.group, growth, lp.appear))
    # leaf ids are the plan's indices: stable over ages (a leaf keeps its id as it grows)
    faces, organs = [], []
    for part in built.parts:
        attr = part.mesh.face_attr
        if part.key[0] == "leaf":
            attr = np.full(len(part.mesh.faces), part.key[1], np.int64)
        faces.append(TriMesh(part.mesh.vertices, part.mesh.faces, attr if part.organ == "blade"
                             else np.full(len(part.mesh.faces), -1, np.int64)))
        organs.append(np.full(len(part.mesh.faces), ORGAN_CODE[part.organ], np.int8))
    info = {"family": family, "variant": plan.variant, "age_days": at,
            "mature_age_days": mature, "crossings": crossings_left, **built.info,
            "leaves_planned": len(plan.leaves),
            "petioles_mm": [round(plan.leaves[i].petiole_mm * g, 4) for i, *_, g in built.leaves]}
    return Plant(family, TriMesh.concat(faces), leaves, {lf.leaf_id: lf.colour for lf in leaves},
                 plan.stem_colour, soil_z, info, face_organ=np.concatenate(organs))


def plastic_dicot(rng: np.random.Generator, soil_z: float, thickness: float = 0.5) -> Plant:
    """The seed's plastic dicot: 12 leaves (6 D at the bottom, 2 C, 4 B at the top)
    on a single stem, spiral phyllotaxis (137.5°)."""
    kinds = ["D"] * 6 + ["C"] * 2 + ["B"] * 4
    outlines = {k: leaf_outline(v["length"], v["width"], v["area"])
                for k, v in PLASTIC_DICOT_LEAVES.items()}
    stem_top = soil_z + 215.0
    stem_pts = np.stack([np.zeros(12), np.zeros(12), np.linspace(soil_z - 8.0, stem_top, 12)], 1)
    stems = [tube(stem_pts, np.linspace(4.5, 2.5, 12), n=12)]
    leaves = []
    for i, kind in enumerate(kinds):
        z = soil_z + 30.0 + 14.0 * i
        az = i * 137.5 + rng.uniform(-6.0, 6.0)
        a = math.radians(az)
        radial = np.array([math.cos(a), math.sin(a), 0.0])
        pet_len = {"D": 42.0, "C": 34.0, "B": 26.0}[kind]
        pet_elev = math.radians(25.0 + 3.0 * i)
        start = np.array([0.0, 0.0, z]) + 3.0 * radial
        end = start + pet_len * (math.cos(pet_elev) * radial + np.array([0, 0, math.sin(pet_elev)]))
        stems.append(tube(np.linspace(start, end, 6), 1.6, n=8))
        incl = 18.0 + 3.5 * i + rng.uniform(-4.0, 4.0)
        bend = 55.0 + rng.uniform(-8.0, 8.0)
        place = LeafPlacement.with_total_bend(end, az, incl, outlines[kind].length, bend,
                                              rng.uniform(-10.0, 10.0))
        leaves.append(Leaf(i, kind, outlines[kind], place, _green(rng)))
    info = {"shape": {k: o.shape for k, o in outlines.items()}, "stem_top_z_mm": stem_top}
    return _assemble("plastic-dicot", leaves, stems, soil_z, rng, thickness, info,
                     (0.12, 0.30, 0.08), ["stem"] + ["petiole"] * (len(stems) - 1))


def wheat(rng: np.random.Generator, soil_z: float, thickness: float = 0.5) -> Plant:
    """Wheat: several tillers, each with long narrow drooping leaves (distichous)."""
    n_tillers = int(rng.integers(3, 6))
    leaves, stems = [], []
    lid = 0
    for k in range(n_tillers):
        az0 = k * 360.0 / n_tillers + rng.uniform(-15, 15)
        lean = math.radians(rng.uniform(4.0, 12.0))
        a0 = math.radians(az0)
        axis = np.array([math.sin(lean) * math.cos(a0), math.sin(lean) * math.sin(a0),
                         math.cos(lean)])
        height = rng.uniform(190.0, 260.0)
        base = np.array([3.0 * math.cos(a0), 3.0 * math.sin(a0), soil_z - 5.0])
        pts = base + np.linspace(0.0, height, 10)[:, None] * axis
        stems.append(tube(pts, np.linspace(2.6, 1.6, 10), n=10))
        n_leaves = int(rng.integers(3, 5))
        for j in range(n_leaves):
            frac = 0.2 + 0.6 * j / max(1, n_leaves - 1)
            node = base + frac * height * axis
            length = rng.uniform(150.0, 240.0) * (1.0 - 0.25 * frac)
            width = rng.uniform(9.0, 14.0)
            fill = rng.uniform(0.70, 0.76)
            outline = leaf_outline(length, width, fill * length * width, p=4.0, warp=0.7)
            az = az0 + (0.0 if j % 2 == 0 else 180.0) + rng.uniform(-20, 20)
            incl = rng.uniform(45.0, 70.0)
            bend = rng.uniform(95.0, 135.0)
            a = math.radians(az)
            start = node + 2.0 * np.array([math.cos(a), math.sin(a), 0.0])
            place = LeafPlacement.with_total_bend(start, az, incl, length, bend,
                                                  rng.uniform(-15.0, 15.0), tip_share=0.8)
            leaves.append(Leaf(lid, "blade", outline, place, _green(rng, (0.12, 0.40, 0.08))))
            lid += 1
    return _assemble("wheat", leaves, stems, soil_z, rng, thickness,
                     {"tillers": n_tillers}, (0.16, 0.38, 0.10))


def sorghum(rng: np.random.Generator, soil_z: float, thickness: float = 0.5) -> Plant:
    """Sorghum: one stalk, long broad arching leaves, nearly distichous."""
    n_leaves = int(rng.integers(6, 9))
    height = rng.uniform(200.0, 240.0)
    pts = np.stack([np.zeros(10), np.zeros(10), np.linspace(soil_z - 8.0, soil_z + height, 10)], 1)
    stems = [tube(pts, np.linspace(8.0, 4.5, 10), n=14)]
    leaves = []
    for i in range(n_leaves):
        frac = 0.12 + 0.8 * i / max(1, n_leaves - 1)
        z = soil_z + frac * height
        az = i * 180.0 + i * 12.0 + rng.uniform(-10, 10)
        a = math.radians(az)
        length = rng.uniform(230.0, 320.0) * (1.0 - 0.3 * frac)
        width = rng.uniform(38.0, 55.0) * (1.0 - 0.2 * frac)
        fill = rng.uniform(0.70, 0.75)
        outline = leaf_outline(length, width, fill * length * width, p=3.0, warp=0.8)
        r_stalk = 8.0 - 3.5 * frac
        start = np.array([0.0, 0.0, z]) + (r_stalk + 0.5) * np.array([math.cos(a), math.sin(a), 0])
        place = LeafPlacement.with_total_bend(start, az, rng.uniform(45.0, 65.0), length,
                                              rng.uniform(70.0, 100.0), rng.uniform(-8.0, 8.0),
                                              tip_share=0.6)
        leaves.append(Leaf(i, "blade", outline, place, _green(rng, (0.09, 0.33, 0.07))))
    return _assemble("sorghum", leaves, stems, soil_z, rng, thickness, {"stalk_height_mm": height},
                     (0.15, 0.34, 0.09))


def external_mesh(path: Path, labels_path: Path | None, scale: float, soil_z: float) -> Plant:
    """A plant mesh from another generator (PLY/OBJ, units x ``scale`` = mm).

    Per-face leaf labels come from ``labels_path`` (one integer per face, text or
    ``.npy``; -1 = stem); without it every face is stem.  The mesh is placed with
    its lowest point on the soil surface, centred on the turntable axis.
    """
    import open3d as o3d

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: plant mesh file not found (scan.scene.params.mesh_path)")
    m = o3d.io.read_triangle_mesh(str(path))
    v = np.asarray(m.vertices, dtype=float) * scale
    f = np.asarray(m.triangles, dtype=np.int64)
    if len(f) == 0:
        raise DataError(f"{path}: no triangles could be read (PLY/OBJ expected)")
    if labels_path is not None:
        lp = Path(labels_path)
        if not lp.exists():
            raise DataError(f"{lp}: leaf label file not found (scan.scene.params.mesh_labels_path)")
        labels = np.load(lp) if lp.suffix == ".npy" else np.loadtxt(lp, dtype=np.int64, ndmin=1)
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        if len(labels) != len(f):
            raise DataError(f"{lp}: {len(labels)} labels for {len(f)} faces of {path}")
    else:
        labels = np.full(len(f), -1, np.int64)
    centre = 0.5 * (v[:, :2].min(0) + v[:, :2].max(0))
    v = v - np.array([centre[0], centre[1], v[:, 2].min() - soil_z])
    mesh = TriMesh(v, f, labels)
    rng = np.random.default_rng(0)
    ids = sorted(int(x) for x in np.unique(labels) if x >= 0)
    surface = []
    for lid in ids:
        sel = f[labels == lid]
        area = mesh_area(v, sel)
        # Boundary edges (used by one face) give the perimeter of an open leaf surface.
        e = np.sort(np.concatenate([sel[:, [0, 1]], sel[:, [1, 2]], sel[:, [2, 0]]]), axis=1)
        uniq, counts = np.unique(e, axis=0, return_counts=True)
        b = uniq[counts == 1]
        perim = float(np.linalg.norm(v[b[:, 0]] - v[b[:, 1]], axis=1).sum())
        pts = v[np.unique(sel)]
        c = pts - pts.mean(0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        ext = c @ vt.T
        surface.append(LeafTraits(lid, float(np.ptp(ext[:, 0])), float(np.ptp(ext[:, 1])), area,
                                  perim))
    plant = Plant("mesh", mesh, [], {lid: _green(rng) for lid in ids}, (0.15, 0.34, 0.09),
                  soil_z, {"source": str(path), "scale": scale})
    plant.surface_traits = surface
    return plant


def build_plant(preset: str, seed: int, soil_z: float, thickness: float = 0.5,
                mesh_path: str | None = None, mesh_labels_path: str | None = None,
                mesh_scale: float = 1.0, age: float | None = None,
                ground: Ground | None = None) -> Plant:
    """The plant of ``preset`` (a family or one of ``PRESETS``), reproducible from ``seed``.

    ``age`` (days, families only) grows the plant; ``ground`` is the soil and pot
    rim its blades must clear (default: the sim scene's default pot).
    """
    if preset in FAMILIES:
        return family_plant(preset, seed, soil_z, thickness, age, ground)
    if age is not None:
        raise ValueError(f"preset {preset!r} does not grow (age applies to the families: "
                         f"{', '.join(FAMILIES)})")
    rng = np.random.default_rng(seed)
    if preset == "plastic-dicot":
        return plastic_dicot(rng, soil_z, thickness)
    if preset == "wheat":
        return wheat(rng, soil_z, thickness)
    if preset == "sorghum":
        return sorghum(rng, soil_z, thickness)
    if preset == "mesh":
        if not mesh_path:
            raise DataError("scan.scene.params.mesh_path: the 'mesh' preset needs a PLY/OBJ file")
        return external_mesh(Path(mesh_path), Path(mesh_labels_path) if mesh_labels_path else None,
                             mesh_scale, soil_z)
    raise ValueError(f"unknown plant preset {preset!r}; valid: {', '.join(PLANTS)}")

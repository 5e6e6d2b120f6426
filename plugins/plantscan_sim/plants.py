"""Procedural plants (and external meshes) with exact flat-leaf truth.

A plant is built in the world (turntable) frame, standing in its pot: the pot's
soil surface is at ``soil_z`` (mm above the turntable plate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plantscan_core.data import LeafTraits, Traits
from plantscan_core.errors import DataError
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

    def traits(self) -> LeafTraits:
        o = self.outline
        return LeafTraits(self.leaf_id, o.length, o.width, o.area, o.perimeter)


@dataclass
class Plant:
    """Geometry of a plant: ``mesh.face_attr`` is the leaf id (-1 stem/petioles)."""

    preset: str
    mesh: TriMesh
    leaves: list[Leaf]
    leaf_colours: dict[int, tuple[float, float, float]]
    stem_colour: tuple[float, float, float]
    soil_z: float
    info: dict = field(default_factory=dict)
    surface_traits: list[LeafTraits] | None = None  # external meshes: measured, not flat

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


def _assemble(preset, leaves, stems, soil_z, rng, thickness, info, stem_colour) -> Plant:
    parts = [leaf_solid(lf.outline, lf.placement, thickness, attr=lf.leaf_id) for lf in leaves]
    parts += [s.with_attr(-1) for s in stems]
    return Plant(preset, TriMesh.concat(parts), leaves, {lf.leaf_id: lf.colour for lf in leaves},
                 stem_colour, soil_z, info)


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
                     (0.12, 0.30, 0.08))


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
                mesh_scale: float = 1.0) -> Plant:
    """The plant of ``preset`` (one of ``PRESETS``), reproducible from ``seed``."""
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
    raise ValueError(f"unknown plant preset {preset!r}; valid: {', '.join(PRESETS)}")

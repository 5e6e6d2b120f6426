"""Plant families: seeded parametric generators with growth, exact truth and organ labels.

Five families (``FAMILIES``) cover the plants a turntable lab scans:

* ``dicot`` -- one stem, 6-20 simple leaves (ovate to lanceolate, 40-250 mm) on
  petioles of 0-80 mm, spiral, opposite (decussate) or distichous phyllotaxy;
* ``rosette`` -- Arabidopsis-like: 8-30 leaves of 10-70 mm on petioles, on a
  very short axis, near-horizontal and overlapping; sometimes a flowering stem;
* ``branched`` -- tomato/pepper-like: a main stem and side shoots, 200-600 mm
  tall; compound leaves (tomato-like plants) whose *leaflets* are the measured
  leaves (rachis and petiolules are organs of their own, not leaf), or simple
  leaves (pepper-like plants);
* ``grass`` -- wheat-, sorghum- and maize-like, 100-600 mm (models of tall
  grasses at 1:2-1:4 scale): culms (tillers), sheaths wrapping the culm from a
  node to the collar, long arching and twisted blades (the measured leaf is the
  blade: the sheath is not leaf);
* ``seedling`` -- two cotyledons and 0-2 first true leaves, 10-40 mm, 30-80 mm tall.

Every generator draws a *plan* from its seed once (every random number, in
the same order whatever the age), then builds the plant at an ``age`` (days
after emergence).  Each leaf appears on a day and expands over some days
along a smooth, non-decreasing curve (``expansion``): its outline is scaled by
that factor (length and width with it, area with its square), its petiole and
the internode below it elongate with it.  ``age=None`` is the mature plant:
every organ fully grown (``info["mature_age_days"]`` is the first day of it).
A leaf is part of the plant (and of the truth) once it has reached
``VISIBLE_SHARE`` of its final length.

Leaves do not pass through each other or through stems: at the mature age,
a leaf whose blade crosses another organ is turned (azimuth, inclination, bend
and roll, from its own seeded sub-stream) and the plant rebuilt, a few rounds;
what is left is counted in ``info["crossings"]``.  A blade never goes into
the soil or through the pot rim (``Ground``): its bend, then its inclination,
is eased until it clears them, at every age (bending preserves every trait).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from plantscan_sim.geometry import (
    LeafOutline,
    LeafPlacement,
    TriMesh,
    grid_faces,
    leaf_outline,
    leaf_solid,
    tube,
)

FAMILIES = ("dicot", "rosette", "branched", "grass", "seedling")
# Bump when a change makes a seed give another plant: cached renders of the old plants
# (benchmarks/population.py) are then not reused.
GENERATOR_VERSION = 1
ORGANS = ("stem", "petiole", "blade", "sheath", "rachis", "inflorescence")
ORGAN_CODE = {name: code for code, name in enumerate(ORGANS)}
VISIBLE_SHARE = 0.15  # a leaf below 15 % of its final length is still hidden in the bud
CROSSING_ROUNDS = 12
SOIL_CLEARANCE_MM = 1.0
FINE_SAMPLES = 601  # tangent-integral grid of family blades (presets keep 4001)

# What the generators promise over seeds (mature plants); tests check them on 50 seeds.
FAMILY_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "dicot": {"leaf_count": (6, 20), "length_mm": (40, 250), "petiole_mm": (0, 80),
              "height_mm": (60, 450)},
    "rosette": {"leaf_count": (8, 30), "length_mm": (10, 70), "height_mm": (1, 130)},
    "branched": {"leaf_count": (6, 120), "length_mm": (15, 130), "height_mm": (200, 600)},
    "grass": {"leaf_count": (3, 30), "length_mm": (45, 500), "height_mm": (100, 600)},
    "seedling": {"leaf_count": (2, 4), "length_mm": (10, 40), "height_mm": (30, 80)},
}


def expansion(age: float, appear: float, duration: float) -> float:
    """Share (0-1) of its final size an organ has at ``age`` (smoothstep, non-decreasing)."""
    u = min(max((age - appear) / duration, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


@dataclass(frozen=True)
class Ground:
    """Where a blade may not go: the soil, and the pot's rim (mm, turntable frame).

    Inside the soil disc a blade stays ``SOIL_CLEARANCE_MM`` above the soil; over
    the pot wall (between the inner wall at the soil and the outer rim) above the
    rim; outside the pot above ``floor_z`` (the pot's foot).
    """

    soil_z: float
    rim_z: float
    r_soil: float
    r_rim: float
    floor_z: float

    @staticmethod
    def default(soil_z: float) -> Ground:
        """The sim scene's default pot (r 52 -> 68 mm, 3 mm wall, soil 8 mm below the rim)."""
        return Ground(soil_z, soil_z + 8.0, 63.9, 68.0, 30.0)

    def min_z(self, r: np.ndarray) -> np.ndarray:
        c = SOIL_CLEARANCE_MM
        return np.where(r < self.r_soil - c, self.soil_z + c,
                        np.where(r <= self.r_rim + c, self.rim_z + c, self.floor_z + c))


# --------------------------------------------------------------------------- plans
@dataclass
class AxisPlan:
    """A stem, tiller, side shoot, hypocotyl or flowering stem: nodes along a line."""

    organ: str
    direction: np.ndarray          # (3,) unit
    internodes: np.ndarray         # (K,) mature lengths mm; node k ends internode k
    appear: np.ndarray             # (K,) day each internode starts to elongate
    expand: np.ndarray             # (K,) days it elongates
    radius: tuple[float, float]    # mature radius at the base, at the top, mm
    parent: int | None = None      # axis it branches from (None: from the soil)
    parent_node: int = 0
    base_xy: tuple[float, float] = (0.0, 0.0)  # from the soil (parent None), mm
    depth_mm: float = 6.0          # starts this far below the soil (hidden)
    tip_mm: float = 0.0            # apex beyond the last node, grows with the last internode


@dataclass
class LeafPlan:
    """A blade (simple leaf, leaflet, cotyledon, grass blade) and what carries it."""

    kind: str
    outline: LeafOutline           # mature outline
    axis: int                      # axis it sits on
    node: int                      # node index on that axis
    azimuth_deg: float             # around the axis / leaflet spread angle (compound)
    inclination_deg: float
    bend_deg: float
    roll_deg: float
    twist_deg: float
    tip_share: float
    appear: float
    expand: float
    colour: tuple[float, float, float]
    group: int = -1                # tiller, shoot or compound leaf it belongs to
    petiole_mm: float = 0.0
    petiole_elev_deg: float = 30.0
    petiole_radius: float = 1.0
    sheath_mm: float = 0.0         # grass: sheath up the culm from the node to the collar
    compound: int | None = None    # index into Plan.compounds (leaflets)
    rachis_at: float = 1.0         # position along the rachis (share of its length)
    side: int = 0                  # -1 / +1 lateral leaflet, 0 terminal


@dataclass
class CompoundPlan:
    """The petiole + rachis of a compound leaf (a bent midrib-like tube)."""

    axis: int
    node: int
    azimuth_deg: float
    elevation_deg: float
    length_mm: float               # petiole + rachis
    petiole_share: float           # first share without leaflets
    bend_deg: float
    radius: float
    appear: float
    expand: float


@dataclass
class Plan:
    family: str
    variant: str
    axes: list[AxisPlan]
    leaves: list[LeafPlan]
    compounds: list[CompoundPlan] = field(default_factory=list)
    stem_colour: tuple[float, float, float] = (0.15, 0.34, 0.09)
    extra: dict = field(default_factory=dict)  # inflorescence etc.
    fix_scale: dict = field(default_factory=lambda: {"azimuth": 25.0, "inclination": 12.0,
                                                      "bend": 0.8, "roll": 10.0})

    def mature_age(self) -> float:
        ends = [float(np.max(a.appear + a.expand)) for a in self.axes if len(a.appear)]
        ends += [lf.appear + lf.expand for lf in self.leaves]
        ends += [c.appear + c.expand for c in self.compounds]
        fl = self.extra.get("flower")
        if fl:
            ends.append(fl["appear"] + fl["expand"])
        return float(max(ends))


# --------------------------------------------------------------------------- helpers
def _green(rng: np.random.Generator, base=(0.10, 0.36, 0.07)) -> tuple[float, float, float]:
    j = rng.uniform(0.85, 1.15)
    return (base[0] * rng.uniform(0.8, 1.2), base[1] * j, base[2] * rng.uniform(0.8, 1.2))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _dir(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def _outline(rng: np.random.Generator, length: float, ratio: float, warp: float,
             fill: float, p: float | None = None) -> LeafOutline:
    width = ratio * length
    if p is None:
        p = float(rng.uniform(1.7, 3.0))
    return leaf_outline(length, width, fill * length * width, p=p, warp=warp, n=81)


def _scaled(o: LeafOutline, s: float) -> LeafOutline:
    return LeafOutline(o.x * s, o.half_width * s, o.shape)


def placement_along(base: np.ndarray, e1: np.ndarray, up: np.ndarray, length: float,
                    bend_deg: float, roll_deg: float = 0.0, twist_deg: float = 0.0,
                    tip_share: float = 0.7) -> LeafPlacement:
    """A blade leaving ``base`` along ``e1`` with its upper side towards ``up`` (then rolled)."""
    e1 = _unit(np.asarray(e1, float))
    az = math.degrees(math.atan2(e1[1], e1[0]))
    incl = math.degrees(math.asin(max(-1.0, min(1.0, e1[2]))))
    place = LeafPlacement.with_total_bend(base, az, incl, length, bend_deg, 0.0, tip_share,
                                          twist_deg)
    place.fine_samples = FINE_SAMPLES
    _, e2, e3 = place.frame()
    u = np.asarray(up, float) - (np.asarray(up, float) @ e1) * e1
    roll0 = math.degrees(math.atan2(u @ e3, u @ e2)) if np.linalg.norm(u) > 1e-9 else 0.0
    place.roll_deg = roll0 + roll_deg
    return place


# --------------------------------------------------------------------------- build
@dataclass
class Part:
    mesh: TriMesh | None           # face_attr = leaf id (-1 not leaf); None: not built
    organ: str
    key: tuple                     # ("leaf", i), ("axis", a), ("petiole", i), ...
    ignore: tuple = ()             # keys this part may touch (where it is attached)


@dataclass
class Built:
    parts: list[Part]
    leaves: list                   # (plan index, leaf id, outline, placement, growth)
    info: dict


def _axis_nodes(plan: Plan, age: float, soil_z: float):
    """Per axis: node positions (K+1, 3) (base first), radii, growth of each internode."""
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for a in plan.axes:
        s = np.array([expansion(age, ap, ex) for ap, ex in zip(a.appear, a.expand, strict=True)])
        if a.parent is None:
            base = np.array([a.base_xy[0], a.base_xy[1], soil_z - a.depth_mm])
            lengths = a.internodes * s
            lengths[0] += a.depth_mm  # the hidden part below the soil is always there
        else:
            pn, pr, _ = out[a.parent]
            base = pn[min(a.parent_node + 1, len(pn) - 1)]
            lengths = a.internodes * s
        cum = np.concatenate([[0.0], np.cumsum(lengths)])
        nodes = base + cum[:, None] * a.direction
        f = np.linspace(0.0, 1.0, len(nodes))
        plant_s = float(s.max()) if len(s) else 0.0
        radii = (a.radius[0] + f * (a.radius[1] - a.radius[0])) * (0.45 + 0.55 * plant_s)
        out.append((nodes, radii, s))
    return out


def _radial(direction: np.ndarray, azimuth_deg: float) -> np.ndarray:
    """Unit vector perpendicular to ``direction`` pointing towards world ``azimuth_deg``."""
    r = _dir(azimuth_deg, 0.0)
    r = r - (r @ direction) * direction
    if np.linalg.norm(r) < 1e-6:
        r = np.array([1.0, 0.0, 0.0])
    return _unit(r)


def _leaf_base(plan: Plan, lp: LeafPlan, nodes, s: float):
    """Attachment point, petiole polyline (or None) and sheath polyline of a simple leaf."""
    a = plan.axes[lp.axis]
    pn, pr, _ = nodes[lp.axis]
    k = min(lp.node + 1, len(pn) - 1)
    radial = _radial(a.direction, lp.azimuth_deg)
    node = pn[k]
    r_axis = pr[k]
    sheath = None
    if lp.sheath_mm > 0:
        top = node + lp.sheath_mm * s * a.direction
        sheath = (np.linspace(node, top, 6), r_axis + 0.8)
        node, r_axis = top, r_axis + 0.8
    start = node + r_axis * radial
    if lp.petiole_mm * s < 0.5:
        return start, radial, None, sheath
    up = a.direction
    e = math.radians(lp.petiole_elev_deg)
    pdir = _unit(math.cos(e) * radial + math.sin(e) * up)
    end = start + lp.petiole_mm * s * pdir
    return end, radial, np.linspace(start, end, 6), sheath


def _rachis(plan: Plan, c: CompoundPlan, nodes, s: float) -> LeafPlacement:
    a = plan.axes[c.axis]
    pn, pr, _ = nodes[c.axis]
    k = min(c.node + 1, len(pn) - 1)
    radial = _radial(a.direction, c.azimuth_deg)
    start = pn[k] + pr[k] * radial
    e = math.radians(c.elevation_deg)
    e1 = math.cos(e) * radial + math.sin(e) * a.direction
    return placement_along(start, e1, np.array([0.0, 0.0, 1.0]), max(c.length_mm * s, 1e-3),
                           c.bend_deg, tip_share=0.5)


def _blade_placement(plan: Plan, i: int, lp: LeafPlan, nodes, s: float, rachis) -> tuple:
    """(placement, petiole polyline | None, sheath | None, ignore keys) of leaf ``i``."""
    length = lp.outline.length * s
    up_world = np.array([0.0, 0.0, 1.0])
    if lp.compound is not None:
        c = plan.compounds[lp.compound]
        rp, rs = rachis[lp.compound]
        at = (c.petiole_share + (1.0 - c.petiole_share) * lp.rachis_at) * c.length_mm * rs
        pts, normal = rp.midrib(np.array([max(at - 1e-3, 0.0), at]))
        tangent = _unit(pts[1] - pts[0]) if at > 1e-3 else rp.frame()[0]
        across = _unit(np.cross(tangent, normal[1]))
        if lp.side == 0:
            e1 = tangent
        else:
            sp = math.radians(lp.azimuth_deg)
            e1 = _unit(math.cos(sp) * tangent + lp.side * math.sin(sp) * across)
        e1 = _unit(e1 + math.tan(math.radians(lp.inclination_deg)) * normal[1])
        base = pts[1]
        pet = None
        if lp.petiole_mm * s >= 0.5:
            end = base + lp.petiole_mm * s * e1
            pet = np.linspace(base, end, 4)
            base = end
        place = placement_along(base, e1, normal[1], length, lp.bend_deg, lp.roll_deg,
                                lp.twist_deg, lp.tip_share)
        return place, pet, None, (("rachis", lp.compound), ("petiole", i))
    base, radial, pet, sheath = _leaf_base(plan, lp, nodes, s)
    incl = math.radians(lp.inclination_deg)
    axis_dir = plan.axes[lp.axis].direction
    e1 = _unit(math.cos(incl) * radial + math.sin(incl) * axis_dir)
    place = placement_along(base, e1, up_world, length, lp.bend_deg, lp.roll_deg, lp.twist_deg,
                            lp.tip_share)
    # a grass blade's base wraps its culm: touching the sheaths above it is no crossing
    own = tuple(("sheath", j) for j, other in enumerate(plan.leaves)
                if other.axis == lp.axis and other.sheath_mm > 0)
    return place, pet, sheath, (("axis", lp.axis), ("petiole", i), ("sheath", i)) + own


def _coarse_blade(o: LeafOutline, place: LeafPlacement, rows: int | None = None):
    """A coarse mid-surface grid (rows x 5 points) of a placed blade, for the checks."""
    n = rows or max(6, int(o.length / 5.0) + 2)
    x = np.linspace(0.0, o.length, n)
    h = np.interp(x, o.x, o.half_width)
    y = h[:, None] * np.linspace(-1.0, 1.0, 5)[None, :]
    pts, _ = place.surface(np.broadcast_to(x[:, None], y.shape), y)
    return pts  # (n, 5, 3)


def _clear_ground(o: LeafOutline, place: LeafPlacement, ground: Ground, bend_deg: float,
                  lp: LeafPlan) -> tuple[LeafPlacement, int]:
    """Ease the bend, then raise the blade, until it clears soil and rim (0 = no change)."""
    def clears(pl):
        g = _coarse_blade(o, pl).reshape(-1, 3)
        return bool(np.all(g[:, 2] >= ground.min_z(np.hypot(g[:, 0], g[:, 1]))))

    if clears(place):
        return place, 0
    e1, _, _ = place.frame()
    tries = [(f, 0.0) for f in (0.6, 0.3, 0.0)] + [(0.0, d) for d in (10.0, 20.0, 35.0, 50.0)]
    for k, (f, lift) in enumerate(tries, start=1):
        horiz = np.hypot(e1[0], e1[1])
        el = math.degrees(math.atan2(e1[2], horiz)) + lift
        el = min(el, 85.0)
        az = math.degrees(math.atan2(e1[1], e1[0]))
        new = LeafPlacement.with_total_bend(place.base, az, el, o.length, bend_deg * f,
                                            0.0, lp.tip_share, lp.twist_deg)
        new.roll_deg = place.roll_deg
        new.fine_samples = FINE_SAMPLES
        if clears(new):
            return new, k
    return new, len(tries)


def build(plan: Plan, age: float, soil_z: float, thickness: float, ground: Ground,
          solids: bool = True) -> Built:
    """The plant of ``plan`` at ``age`` days: parts with organ labels, leaves with growth.

    ``solids=False`` leaves the blades' meshes out (None): the crossing check
    needs only their placements.
    """
    nodes = _axis_nodes(plan, age, soil_z)
    parts: list[Part] = []
    for ai, (a, (pn, pr, s)) in enumerate(zip(plan.axes, nodes, strict=True)):
        if len(pn) < 2 or float(np.linalg.norm(pn[-1] - pn[0])) < 0.5:
            continue
        pts = pn
        if a.tip_mm > 0:
            pts = np.concatenate([pn, [pn[-1] + a.tip_mm * float(s[-1]) * a.direction]])
        pts = _densify(pts, 12.0)
        radii = np.interp(np.linspace(0, 1, len(pts)), np.linspace(0, 1, len(pr)), pr)
        if a.tip_mm > 0:
            radii[-1] *= 0.5
        parts.append(Part(tube(pts, radii, n=10 if radii.max() < 3 else 14), a.organ,
                          ("axis", ai), (("axis", a.parent),) if a.parent is not None else ()))
    rachis = {}
    for ci, c in enumerate(plan.compounds):
        cs = expansion(age, c.appear, c.expand)
        if cs < VISIBLE_SHARE:
            continue
        rp = _rachis(plan, c, nodes, cs)
        pts, _ = rp.midrib(np.linspace(0.0, c.length_mm * cs, 12))
        rachis[ci] = (rp, cs)
        parts.append(Part(tube(pts, np.linspace(c.radius, 0.5 * c.radius, 12) * (0.5 + 0.5 * cs),
                               n=8), "rachis", ("rachis", ci), (("axis", c.axis),)))
    leaves = []
    fixes = 0
    for i, lp in enumerate(plan.leaves):
        s = expansion(age, lp.appear, lp.expand)
        if s < VISIBLE_SHARE or (lp.compound is not None and lp.compound not in rachis):
            continue
        o = _scaled(lp.outline, s)
        place, pet, sheath, ignore = _blade_placement(plan, i, lp, nodes, s, rachis)
        place, k = _clear_ground(o, place, ground, lp.bend_deg, lp)
        fixes += k > 0
        if pet is not None:
            parts.append(Part(tube(pet, lp.petiole_radius * (0.5 + 0.5 * s), n=8), "petiole",
                              ("petiole", i), (("axis", lp.axis), ("leaf", i), ("sheath", i),
                                               ("rachis", lp.compound))))
        if sheath is not None:
            parts.append(Part(tube(sheath[0], sheath[1], n=14), "sheath", ("sheath", i),
                              (("axis", lp.axis), ("leaf", i))))
        leaf_id = len(leaves)
        solid = leaf_solid(o, place, thickness, attr=leaf_id) if solids else None
        parts.append(Part(solid, "blade", ("leaf", i), ignore))
        leaves.append((i, leaf_id, o, place, s))
    fl = plan.extra.get("flower")
    if fl:
        parts += _flower(plan, fl, age, nodes)
    return Built(parts, leaves, {"ground_fixes": fixes})


def _densify(pts: np.ndarray, step: float) -> np.ndarray:
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out += [a + (b - a) * t for t in np.linspace(0, 1, n + 1)[1:]]
    return np.array(out)


def _flower(plan: Plan, fl: dict, age: float, nodes) -> list[Part]:
    """A flowering stem's buds: short thin branches at its top (organ inflorescence)."""
    s = expansion(age, fl["appear"], fl["expand"])
    if s < VISIBLE_SHARE:
        return []
    pn, pr, _ = nodes[fl["axis"]]
    top = pn[-1]
    parts = []
    for j, (az, el, ln) in enumerate(fl["buds"]):
        d = _dir(az, el)
        pts = np.linspace(top, top + ln * s * d, 4)
        parts.append(Part(tube(pts, np.array([0.5, 0.6, 0.8, 1.2]) * (0.5 + 0.5 * s), n=8),
                          "inflorescence", ("bud", j), (("axis", fl["axis"]),)))
    return parts


# --------------------------------------------------------------------------- crossings
def crossings(built: Built) -> list[tuple[tuple, tuple]]:
    """(blade key, other organ key) for every blade that passes through another organ.

    The blade's mid-surface (a coarse grid) is cast as segments against every
    other part; hits on the parts it is attached to are not crossings.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    keys = []
    coarse = {}
    for part in built.parts:
        if part.key[0] == "leaf":
            idx = [lf for lf in built.leaves if lf[0] == part.key[1]][0]
            g = _coarse_blade(idx[2], idx[3])
            coarse[part.key] = g
            n, m = g.shape[:2]
            v, f = g.reshape(-1, 3), grid_faces(n, m)
        else:
            v, f = part.mesh.vertices, part.mesh.faces
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                            o3d.core.Tensor(f.astype(np.uint32)))
        keys.append(part)
    found: list[tuple[tuple, tuple]] = []
    for key, g in coarse.items():
        a = np.concatenate([g[:-1].reshape(-1, 3), g[:, :-1].reshape(-1, 3)])
        b = np.concatenate([g[1:].reshape(-1, 3), g[:, 1:].reshape(-1, 3)])
        rays = np.concatenate([a, b - a], axis=1).astype(np.float32)
        hit = scene.list_intersections(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy()
        gid = hit["geometry_ids"].numpy()[(t > 1e-4) & (t < 1.0 - 1e-4)]
        me = [p for p in keys if p.key == key][0]
        others = set()
        for g_i in np.unique(gid):
            other = keys[int(g_i)]
            if other.key == key or other.key in me.ignore or key in other.ignore:
                continue
            others.add(other.key)
        found += [(key, o) for o in sorted(others, key=str)]
    return found


def resolve_crossings(plan: Plan, seed: int, soil_z: float, thickness: float,
                      ground: Ground) -> tuple[Plan, int]:
    """Turn crossing blades (younger one of a pair) until none cross; rounds are bounded.

    Returns the adjusted plan and the number of crossings left.
    """
    age = plan.mature_age()
    fs = plan.fix_scale
    tries: dict[int, int] = {}
    for _ in range(CROSSING_ROUNDS):
        built = build(plan, age, soil_z, thickness, ground, solids=False)
        found = crossings(built)
        if not found:
            return plan, 0
        movers = set()
        for key, other in found:
            i = key[1]
            if other[0] == "leaf":
                i = max(i, other[1])
            movers.add(i)
        leaves = list(plan.leaves)
        for i in sorted(movers):
            t = tries.get(i, 0) + 1
            tries[i] = t
            r = np.random.default_rng([seed, 104729, i, t])
            lp = leaves[i]
            grow = 1.0 + 0.5 * (t - 1)  # a blade that keeps crossing is turned further
            turn = r.choice([-1, 1]) * r.uniform(0.4, 1.0) * fs["azimuth"] * grow
            leaves[i] = replace(
                lp,
                azimuth_deg=lp.azimuth_deg + turn,
                inclination_deg=min(lp.inclination_deg + r.uniform(0.3, 1.0) * fs["inclination"],
                                    85.0),
                bend_deg=lp.bend_deg * fs["bend"],
                roll_deg=lp.roll_deg + r.uniform(-1, 1) * fs["roll"],
                petiole_elev_deg=min(lp.petiole_elev_deg + r.uniform(0.0, 0.5)
                                     * fs["inclination"], 80.0))
        plan = replace(plan, leaves=leaves)
    return plan, len(crossings(build(plan, age, soil_z, thickness, ground, solids=False)))


# --------------------------------------------------------------------------- families
def _lean(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    return _dir(rng.uniform(0.0, 360.0), 90.0 - rng.uniform(0.0, max_deg))


def _split(rng: np.random.Generator, total: float, n: int, spread=(0.6, 1.4)) -> np.ndarray:
    w = rng.uniform(*spread, n)
    return total * w / w.sum()


def draw_dicot(rng: np.random.Generator) -> Plan:
    """One stem, 6-20 simple leaves; spiral, opposite (decussate) or distichous."""
    n = int(rng.integers(6, 21))
    phyllotaxy = str(rng.choice(["spiral", "opposite", "distichous"], p=[0.5, 0.35, 0.15]))
    per_node = 2 if phyllotaxy == "opposite" else 1
    m = math.ceil(n / per_node)
    stem_h = rng.uniform(60.0, 230.0)
    first = rng.uniform(0.08, 0.25) * stem_h
    internodes = np.concatenate([[first], _split(rng, stem_h - first, m - 1)]) if m > 1 \
        else np.array([stem_h])
    phyllochron = rng.uniform(1.5, 4.0) * per_node
    appear = 1.0 + np.arange(m) * phyllochron
    expand = rng.uniform(10.0, 18.0, m)
    r0 = rng.uniform(2.0, 5.0)
    axis = AxisPlan("stem", _lean(rng, 6.0), internodes, appear, expand,
                    (r0, r0 * rng.uniform(0.4, 0.6)), tip_mm=rng.uniform(5.0, 15.0))
    l_base = rng.uniform(70.0, 250.0)
    l_top = rng.uniform(40.0, l_base)
    gamma = rng.uniform(0.5, 2.0)
    ratio, warp = rng.uniform(0.2, 0.6), rng.uniform(0.65, 1.25)
    sessile = rng.random() < 0.2
    pf = 0.0 if sessile else rng.uniform(0.08, 0.45)
    div = 137.5 if rng.random() < 0.8 else 144.0
    az0 = rng.uniform(0.0, 360.0)
    leaves = []
    for i in range(n):
        k, j = divmod(i, per_node)
        f = k / max(1, m - 1)
        length = float(np.clip((l_top + (l_base - l_top) * (1.0 - f) ** gamma)
                               * rng.uniform(0.92, 1.08), 40.0, 250.0))
        if phyllotaxy == "spiral":
            az = az0 + k * div
        elif phyllotaxy == "opposite":
            az = az0 + 90.0 * k + 180.0 * j
        else:
            az = az0 + 180.0 * k
        az += rng.uniform(-8.0, 8.0)
        o = _outline(rng, length, float(np.clip(ratio * rng.uniform(0.9, 1.1), 0.18, 0.65)),
                     float(np.clip(warp * rng.uniform(0.92, 1.08), 0.6, 1.3)),
                     rng.uniform(0.62, 0.74))
        pet = min(80.0, pf * length * rng.uniform(0.8, 1.2))
        leaves.append(LeafPlan(
            "leaf", o, 0, k, az, rng.uniform(-5.0, 30.0) + 15.0 * f, rng.uniform(15.0, 80.0),
            rng.uniform(-15.0, 15.0), rng.uniform(-8.0, 8.0), rng.uniform(0.5, 0.85),
            float(appear[k]), float(expand[k] * rng.uniform(0.9, 1.1)), _green(rng),
            petiole_mm=pet, petiole_elev_deg=15.0 + 35.0 * f + rng.uniform(-8.0, 8.0),
            petiole_radius=0.8 + 0.006 * length))
    return Plan("dicot", phyllotaxy, [axis], leaves, stem_colour=_green(rng, (0.12, 0.30, 0.08)),
                extra={"sessile": sessile})


def draw_rosette(rng: np.random.Generator) -> Plan:
    """Arabidopsis-like: 8-30 leaves on a very short axis; sometimes a flowering stem."""
    n = int(rng.integers(8, 31))
    phyllochron = rng.uniform(0.9, 2.0)
    appear = 1.0 + np.arange(n) * phyllochron
    expand = rng.uniform(6.0, 12.0, n)
    internodes = np.concatenate([[1.0], np.full(n - 1, rng.uniform(0.08, 0.18))])
    axes = [AxisPlan("stem", np.array([0.0, 0.0, 1.0]), internodes, appear, expand, (1.2, 0.8),
                     depth_mm=3.0, tip_mm=1.0)]
    l_first = rng.uniform(10.0, 18.0)
    l_max = rng.uniform(max(l_first + 5.0, 25.0), 70.0)
    ratio, warp = rng.uniform(0.45, 0.8), rng.uniform(1.05, 1.6)
    pf = rng.uniform(0.2, 0.7)
    az0 = rng.uniform(0.0, 360.0)
    leaves = []
    for k in range(n):
        f = k / (n - 1)
        length = float(np.clip((l_first + (l_max - l_first) * f ** 0.6) * rng.uniform(0.9, 1.1),
                               10.0, 70.0))
        o = _outline(rng, length, float(np.clip(ratio * rng.uniform(0.9, 1.1), 0.4, 0.85)),
                     float(np.clip(warp * rng.uniform(0.93, 1.07), 1.0, 1.7)),
                     rng.uniform(0.66, 0.76))
        leaves.append(LeafPlan(
            "leaf", o, 0, k, az0 + 137.5 * k + rng.uniform(-4.0, 4.0),
            rng.uniform(-8.0, 12.0) + 10.0 * f, rng.uniform(-20.0, 25.0), rng.uniform(-12.0, 12.0),
            rng.uniform(-5.0, 5.0), rng.uniform(0.4, 0.8), float(appear[k]), float(expand[k]),
            _green(rng, (0.11, 0.33, 0.08)), petiole_mm=pf * length * rng.uniform(0.8, 1.2),
            petiole_elev_deg=8.0 + 35.0 * f + rng.uniform(-5.0, 5.0),
            petiole_radius=0.4 + 0.006 * length))
    extra: dict = {}
    variant = "vegetative"
    if rng.random() < 0.3:
        variant = "flowering"
        h = rng.uniform(30.0, 110.0)
        start = float(appear[-1] + rng.uniform(2.0, 6.0))
        axes.append(AxisPlan("inflorescence", _lean(rng, 10.0), np.array([h]), np.array([start]),
                             np.array([rng.uniform(8.0, 14.0)]), (0.9, 0.6), parent=0,
                             parent_node=n - 1))
        buds = [(rng.uniform(0, 360), rng.uniform(30, 70), rng.uniform(3.0, 10.0))
                for _ in range(int(rng.integers(3, 7)))]
        extra["flower"] = {"axis": 1, "appear": start, "expand": float(axes[1].expand[0]),
                           "buds": buds}
    return Plan("rosette", variant, axes, leaves, stem_colour=(0.14, 0.32, 0.09), extra=extra,
                fix_scale={"azimuth": 12.0, "inclination": 8.0, "bend": 0.7, "roll": 8.0})


def draw_branched(rng: np.random.Generator) -> Plan:
    """Tomato-like (compound leaves, leaflets measured) or pepper-like (simple leaves)."""
    tomato = rng.random() < 0.7
    height = rng.uniform(170.0, 440.0)
    m = int(rng.integers(5, 10))
    first = rng.uniform(0.1, 0.25) * height
    internodes = np.concatenate([[first], _split(rng, height - first, m - 1)])
    phyllochron = rng.uniform(2.5, 4.5)
    appear = 2.0 + np.arange(m) * phyllochron
    expand = rng.uniform(12.0, 20.0, m)
    r0 = rng.uniform(3.0, 6.0)
    axes = [AxisPlan("stem", _lean(rng, 6.0), internodes, appear, expand,
                     (r0, r0 * rng.uniform(0.35, 0.5)), tip_mm=rng.uniform(5.0, 15.0))]
    div = 137.5 if rng.random() < 0.7 else 144.0
    az0 = rng.uniform(0.0, 360.0)
    main_az = [az0 + div * k + rng.uniform(-8.0, 8.0) for k in range(m)]
    # (axis, node, azimuth, size factor, appear, expand, group)
    sites = [(0, k, main_az[k], 1.0 - 0.45 * (k / (m - 1)) ** 1.5, float(appear[k]),
              float(expand[k]), 0) for k in range(m)]
    n_shoots = int(rng.integers(1, 4))
    shoot_nodes = sorted(rng.choice(np.arange(1, max(2, (2 * m) // 3)), size=min(
        n_shoots, max(1, (2 * m) // 3 - 1)), replace=False).tolist())
    for si, k in enumerate(shoot_nodes):
        ln = rng.uniform(0.25, 0.5) * height
        ks = int(rng.integers(2, 4))
        az = main_az[k] + rng.uniform(-30.0, 30.0)
        start = float(appear[k] + rng.uniform(6.0, 14.0))
        s_app = start + np.arange(ks) * phyllochron
        s_exp = rng.uniform(12.0, 20.0, ks)
        axes.append(AxisPlan("stem", _dir(az, rng.uniform(40.0, 65.0)), _split(rng, ln, ks),
                             s_app, s_exp, (0.6 * r0, 0.3 * r0), parent=0, parent_node=k,
                             tip_mm=rng.uniform(3.0, 8.0)))
        for j in range(ks):
            sites.append((len(axes) - 1, j, az + 137.5 * (j + 1) + rng.uniform(-10, 10),
                          rng.uniform(0.5, 0.8), float(s_app[j]), float(s_exp[j]), si + 1))
    leaves: list[LeafPlan] = []
    compounds: list[CompoundPlan] = []
    colour_base = (0.09, 0.32, 0.07)
    for axis_i, node, az, size, ap, ex, group in sites:
        if tomato:
            total = rng.uniform(110.0, 250.0) * size
            c = CompoundPlan(axis_i, node, az, rng.uniform(25.0, 60.0), total,
                             rng.uniform(0.15, 0.3), rng.uniform(20.0, 70.0),
                             rng.uniform(1.0, 1.8), ap, ex)
            compounds.append(c)
            ci = len(compounds) - 1
            pairs = int(rng.integers(1, 4))
            lt = float(np.clip(rng.uniform(0.28, 0.45) * total, 15.0, 120.0))
            specs = [(1.0, 0, lt, rng.uniform(0.0, 5.0))]
            for j in range(pairs):
                at = (j + 0.6) / (pairs + 0.4)
                ll = float(np.clip(lt * rng.uniform(0.55, 0.95) * (0.7 + 0.3 * at), 15.0, 120.0))
                for side in (-1, 1):
                    specs.append((at, side, float(np.clip(ll * rng.uniform(0.93, 1.07), 15.0,
                                                          120.0)), rng.uniform(2.0, 10.0)))
            for at, side, ll, pet in specs:
                o = _outline(rng, ll, rng.uniform(0.38, 0.6), rng.uniform(0.7, 1.0),
                             rng.uniform(0.62, 0.72))
                leaves.append(LeafPlan(
                    "leaflet", o, axis_i, node, rng.uniform(45.0, 75.0), rng.uniform(-5.0, 20.0),
                    rng.uniform(5.0, 35.0), rng.uniform(-15.0, 15.0), rng.uniform(-6.0, 6.0),
                    rng.uniform(0.5, 0.8), ap, ex, _green(rng, colour_base), group=group,
                    petiole_mm=pet, petiole_radius=0.6, compound=ci, rachis_at=at, side=side))
        else:
            length = float(np.clip(rng.uniform(60.0, 130.0) * (0.6 + 0.4 * size), 40.0, 130.0))
            o = _outline(rng, length, rng.uniform(0.3, 0.5), rng.uniform(0.7, 1.0),
                         rng.uniform(0.62, 0.72))
            leaves.append(LeafPlan(
                "leaf", o, axis_i, node, az, rng.uniform(-5.0, 30.0), rng.uniform(15.0, 60.0),
                rng.uniform(-15.0, 15.0), rng.uniform(-8.0, 8.0), rng.uniform(0.5, 0.85), ap, ex,
                _green(rng, colour_base), group=group,
                petiole_mm=rng.uniform(0.2, 0.5) * length, petiole_elev_deg=rng.uniform(20.0, 55.0),
                petiole_radius=0.8 + 0.006 * length))
    return Plan("branched", "tomato" if tomato else "pepper", axes, leaves, compounds,
                stem_colour=(0.15, 0.33, 0.09))


GRASS_VARIANTS = {
    # tillers, leaves per culm, culm height, culm radius, blade length, width, inclination,
    # bend, twist, sheath (all mm / deg ranges); models of tall grasses at 1:2-1:4
    "wheat": dict(tillers=(2, 7), leaves=(3, 6), culm=(70.0, 240.0), radius=(1.2, 2.2),
                  length=(60.0, 250.0), width=(4.0, 13.0), incl=(55.0, 80.0),
                  bend=(70.0, 150.0), twist=(5.0, 25.0), sheath=(15.0, 50.0)),
    "sorghum": dict(tillers=(1, 3), leaves=(5, 10), culm=(140.0, 330.0), radius=(4.0, 7.0),
                    length=(150.0, 400.0), width=(25.0, 60.0), incl=(40.0, 70.0),
                    bend=(60.0, 110.0), twist=(0.0, 15.0), sheath=(30.0, 80.0)),
    "maize": dict(tillers=(1, 2), leaves=(6, 13), culm=(180.0, 360.0), radius=(6.0, 10.0),
                  length=(200.0, 480.0), width=(35.0, 80.0), incl=(35.0, 65.0),
                  bend=(50.0, 100.0), twist=(5.0, 20.0), sheath=(40.0, 90.0)),
}


def draw_grass(rng: np.random.Generator) -> Plan:
    """Wheat-, sorghum- or maize-like: culms with sheaths and long arching, twisted blades."""
    variant = str(rng.choice(list(GRASS_VARIANTS), p=[0.45, 0.3, 0.25]))
    v = GRASS_VARIANTS[variant]
    n_tillers = int(rng.integers(*v["tillers"]))
    axes: list[AxisPlan] = []
    leaves: list[LeafPlan] = []
    phyllochron = rng.uniform(3.0, 6.0)
    for t in range(n_tillers):
        main = t == 0
        az_t = t * 360.0 / n_tillers + rng.uniform(-20.0, 20.0)
        height = rng.uniform(*v["culm"]) * (1.0 if main else rng.uniform(0.7, 1.0))
        nl = int(rng.integers(*v["leaves"]))
        first = rng.uniform(0.05, 0.15) * height
        internodes = np.concatenate([[first], _split(rng, height - first, nl - 1, (0.4, 1.6))])
        internodes = np.sort(internodes[1:]) if nl > 1 else internodes[1:]
        internodes = np.concatenate([[first], internodes])  # internodes lengthen upwards
        start = 0.0 if main else rng.uniform(4.0, 10.0) * t
        appear = start + np.arange(nl) * phyllochron
        expand = rng.uniform(10.0, 16.0, nl)
        r0 = rng.uniform(*v["radius"]) * (1.0 if main else 0.8)
        lean = 0.0 if (main and n_tillers > 1) else rng.uniform(0.0, 6.0)
        if not main:
            lean = rng.uniform(3.0, 18.0)
        d = _dir(az_t, 90.0 - lean)
        # tillers stand beside the main culm, not in it
        off = 0.0 if main else axes[0].radius[0] + r0 + rng.uniform(1.0, 4.0)
        axes.append(AxisPlan("stem", d, internodes, appear, expand, (r0, 0.6 * r0),
                             base_xy=(off * math.cos(math.radians(az_t)),
                                      off * math.sin(math.radians(az_t))),
                             tip_mm=rng.uniform(3.0, 10.0)))
        side = rng.uniform(0.0, 360.0)
        if n_tillers > 1:  # blades in the plane across the line to the neighbouring culm
            side = (az_t if not main else 360.0 / n_tillers) + 90.0 + rng.uniform(-20.0, 20.0)
        for j in range(nl):
            f = j / max(1, nl - 1)
            length = rng.uniform(*v["length"]) * (1.0 - 0.3 * abs(f - 0.35))
            width = rng.uniform(*v["width"]) * (1.0 - 0.2 * f)
            o = _outline(rng, length, width / length, rng.uniform(0.6, 0.8),
                         rng.uniform(0.68, 0.76), p=rng.uniform(3.0, 5.0))
            sheath = min(rng.uniform(*v["sheath"]), 0.9 * float(internodes[min(j + 1, nl - 1)]))
            leaves.append(LeafPlan(
                "blade", o, t, j, side + (0.0 if j % 2 == 0 else 180.0) + rng.uniform(-20, 20),
                rng.uniform(*v["incl"]), rng.uniform(*v["bend"]), rng.uniform(-4.0, 4.0),
                rng.choice([-1.0, 1.0]) * rng.uniform(*v["twist"]), rng.uniform(0.6, 0.85),
                float(appear[j]), float(expand[j]), _green(rng, (0.12, 0.40, 0.08)), group=t,
                sheath_mm=sheath))
    return Plan("grass", variant, axes, leaves, stem_colour=(0.16, 0.38, 0.10),
                fix_scale={"azimuth": 15.0, "inclination": 6.0, "bend": 0.85, "roll": 2.0})


def draw_seedling(rng: np.random.Generator) -> Plan:
    """Two cotyledons and 0-2 first true leaves on a hypocotyl, 30-80 mm tall."""
    n_true = int(rng.integers(0, 3))
    az0 = rng.uniform(0.0, 360.0)
    cot_l = rng.uniform(10.0, 25.0)
    true_appear = rng.uniform(5.0, 9.0)
    leaves = []
    for j in range(2):
        o = _outline(rng, cot_l * rng.uniform(0.95, 1.05), rng.uniform(0.45, 0.75),
                     rng.uniform(0.9, 1.15), rng.uniform(0.7, 0.78))
        leaves.append(LeafPlan(
            "cotyledon", o, 0, 0, az0 + 180.0 * j + rng.uniform(-8, 8), rng.uniform(-5.0, 25.0),
            rng.uniform(-10.0, 25.0), rng.uniform(-10.0, 10.0), 0.0, 0.6, 0.0,
            rng.uniform(3.0, 6.0), _green(rng, (0.18, 0.42, 0.08)),
            petiole_mm=rng.uniform(1.0, 8.0), petiole_elev_deg=rng.uniform(10.0, 35.0),
            petiole_radius=0.5))
    for j in range(n_true):
        length = rng.uniform(12.0, 40.0)
        o = _outline(rng, length, rng.uniform(0.35, 0.6), rng.uniform(0.7, 1.0),
                     rng.uniform(0.64, 0.74))
        leaves.append(LeafPlan(
            "leaf", o, 0, 1, az0 + 90.0 + 180.0 * j + rng.uniform(-15, 15),
            rng.uniform(15.0, 50.0), rng.uniform(5.0, 40.0), rng.uniform(-10.0, 10.0),
            rng.uniform(-5.0, 5.0), 0.7, true_appear + j * rng.uniform(0.0, 2.0),
            rng.uniform(6.0, 10.0), _green(rng, (0.13, 0.38, 0.07)),
            petiole_mm=rng.uniform(2.0, 12.0), petiole_elev_deg=rng.uniform(30.0, 65.0),
            petiole_radius=0.5))
    target = rng.uniform(32.0, 78.0)
    epicotyl = rng.uniform(2.0, 15.0)
    r0 = rng.uniform(0.7, 1.3)
    axis = AxisPlan("stem", _lean(rng, 5.0), np.array([1.0, epicotyl]),
                    np.array([0.0, true_appear]), np.array([rng.uniform(3.0, 5.0), 6.0]),
                    (r0, 0.8 * r0), depth_mm=4.0, tip_mm=1.0)
    plan = Plan("seedling", f"{n_true} true", [axis], leaves, stem_colour=(0.35, 0.45, 0.20))
    # the hypocotyl sets the height: what the leaves rise above the cotyledon node first
    loose = Ground(-1e6, -1e6, 0.0, 0.0, -1e6)
    probe = build(plan, plan.mature_age(), 0.0, 0.5, loose, solids=False)
    top = max([float(p.mesh.vertices[:, 2].max()) for p in probe.parts if p.mesh is not None]
              + [float(_coarse_blade(o, pl)[..., 2].max()) for _, _, o, pl, _ in probe.leaves])
    axis.internodes[0] = float(np.clip(target - (top - 1.0), 8.0, 65.0))
    return plan


DRAW = {"dicot": draw_dicot, "rosette": draw_rosette, "branched": draw_branched,
        "grass": draw_grass, "seedling": draw_seedling}

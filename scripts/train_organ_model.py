"""Train the organ model of ``learned-organs`` from the virtual scanner (development seeds).

    python scripts/train_organ_model.py [--families dicot,grass,...] [--seeds 0-23]
        [--cache DIR] [--out plugins/plantscan_leaves/models] [--hold-out FAMILY]

For every (family, seed) — seeds below 1000 only: validation seeds (>= 1000) are never
trained on — the virtual plant is built, its exact silhouettes in the family recipe's
views (paper-72, 1296x864 unless the recipe says otherwise) are rasterised from the
truth mesh and the exact cameras (no rendering: a second per plant), and the hull and
mesh stages of the family recipe carve and mesh it.  Every sample of the hull surface
(``plantscan_leaves.features``) is labelled from the nearest truth face:

* ``LEAF`` / ``STEM`` by the organ there (petioles are stem, as in the truth traits);
  ``EDGE`` for leaf samples within ``EDGE_RINGS`` samples of another organ;
* ``DEBRIS`` where the nearest true surface is the pot, or more than
  ``DEBRIS_UNITS`` mesh units away (phantom volume no organ owns);
* phantom: the area share of the sample farther than ``PHANTOM_UNITS`` units.

Then three LightGBM boosters are trained: the organ classes (sample weights
1/sqrt(class frequency)), phantom volume (binary), and the fragment merge model
(``organs.agglomerate``): the leaf fragments of each plant are cut with an organ
model trained on the *other* half of the plants (so the merge model sees the errors
of an organ model that did not learn that plant), and the pairs scored while an
oracle merges fragments of the same truth leaf are its rows.  Everything is seeded:
the same seeds give the same model files.  Caches (hulls, samples) go under
``--cache``.  ``--hold-out FAMILY`` leaves one family out (to show the model
generalises: ``benchmarks/population.py --model DIR``).
"""

from __future__ import annotations

import argparse
import gzip
import sys
import time
from pathlib import Path

import numpy as np
from plantscan_leaves import geometry as geo
from plantscan_leaves import organs
from plantscan_leaves.features import FEATURE_NAMES, SurfaceSamples, surface_samples

EDGE_RINGS = 2  # the EDGE band: two samples (4 mesh units) on each side of an organ border
DEBRIS_UNITS = 8.0  # hull this far from any true surface belongs to no organ
ROWS_PER_PLANT = 20_000  # organ rows per plant: every rare-class sample, LEAF subsampled
ORGAN_ROUNDS, PHANTOM_ROUNDS, MERGE_ROUNDS = 150, 100, 200
ORGAN_PARAMS = dict(objective="multiclass", num_class=4, learning_rate=0.15, num_leaves=31,
                    min_data_in_leaf=50, feature_fraction=0.8, bagging_fraction=0.8,
                    bagging_freq=1, lambda_l2=1.0, num_threads=2, verbose=-1, seed=0,
                    deterministic=True, force_row_wise=True)
BINARY_PARAMS = dict(objective="binary", learning_rate=0.1, num_leaves=15, min_data_in_leaf=20,
                     feature_fraction=0.9, bagging_fraction=0.8, bagging_freq=1, num_threads=2,
                     verbose=-1, seed=0, deterministic=True, force_row_wise=True)


IMAGE_SIZES = ((1296, 864), (640, 427))  # lab-realistic and demo sizes, drawn per plant
RESOLUTIONS = (512, 256)  # hull grids, drawn per plant (the models must serve both)
BLOBS_PER_PLANT = 3.0  # mean number of debris blobs added beside the plant (Poisson)


def debris_blobs(plant_vertices: np.ndarray, unit_mm: float, rng: np.random.Generator):
    """(vertices, faces) of a few closed balls beside the plant: crumbs of phantom volume or
    mask specks, 1.5-5 mesh units in radius, 0.5-3 units off the plant's surface."""
    from plantscan_sim.geometry import TriMesh, revolve

    parts = []
    for _ in range(rng.poisson(BLOBS_PER_PLANT)):
        r = rng.uniform(1.5, 5.0) * unit_mm
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        centre = plant_vertices[rng.integers(len(plant_vertices))] + (
            r + rng.uniform(0.5, 3.0) * unit_mm) * d
        a = np.linspace(0.0, np.pi, 12)
        ball = revolve(np.stack([r * np.sin(a), -r * np.cos(a)], axis=1), 16)
        parts.append(TriMesh(ball.vertices + centre, ball.faces, ball.face_attr))
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    m = TriMesh.concat(parts)
    return m.vertices, m.faces


def exact_hull(family: str, seed: int, recipe: str | None = None,
               image_size: tuple[int, int] | None = None, resolution: int | None = None,
               blobs: bool = True):
    """(hull mesh, truth plant, debris mesh) of one virtual plant carved from exact
    silhouettes; image size and resolution drawn from ``IMAGE_SIZES``/``RESOLUTIONS`` by the
    seed when not given; the debris mesh is the pot and the blobs (``debris_blobs``)."""
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull
    from plantscan_sim.api import scan_recipe, sim_manager
    from plantscan_sim.render import silhouette_mask
    from plantscan_sim.scene import SimScene

    from plantscan_core.acquire import plan
    from plantscan_core.data import Calibration, Silhouette, Silhouettes, ViewRecord
    from plantscan_core.recipe import PROCESSING_SECTIONS, validate_recipe
    from plantscan_core.stages import StageContext

    rng = np.random.default_rng([seed, 17])
    image_size = image_size or IMAGE_SIZES[int(rng.integers(len(IMAGE_SIZES)))]
    resolution = resolution or RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    raw = scan_recipe(family, recipe=recipe, seed=seed, image_size=image_size)
    manager = sim_manager()
    scan_only = {k: v for k, v in raw.items() if k not in PROCESSING_SECTIONS and k != "export"}
    if len(raw["scan"].get("tilts_deg") or [0]) > 1 and not raw["scan"].get("tilt_arm"):
        scan_only["scan"]["tilt_arm"] = {"plugin": "sim", "params": {"axis": "tilt"}}
    rec = validate_recipe(scan_only, manager.registry, "training recipe")
    scene = SimScene(SimScene.Params.model_validate(rec.scan.scene.params),
                     StageContext(recipe=rec))
    scene.check(rec)
    pot, plant = scene.pot_mesh(), scene.plant
    pv_, pf_ = plant.mesh.vertices, plant.mesh.faces
    extent = max(float(np.ptp(pv_, axis=0).max()), 2.0 * scene.params.pot_r_top_mm)
    bv, bf = debris_blobs(pv_, extent / resolution, rng) if blobs else (np.zeros((0, 3)),
                                                                         np.zeros((0, 3), int))
    debris_v = np.concatenate([pot.vertices, bv])
    debris_f = np.concatenate([pot.faces, bf + len(pot.vertices)]).astype(np.int64)
    v = np.concatenate([debris_v, pv_])
    f = np.concatenate([debris_f, pf_ + len(debris_v)])
    models, poses, items = {}, {}, []
    for pv in plan(rec):
        if pv.role != "plant":
            continue
        cam = scene.rig.camera(pv.camera, pv.tilt_deg, pv.angle_deg)
        name = f"v{len(items)}"
        models[name], poses[(name, 0)] = cam.model, cam.pose
        view = ViewRecord(len(items), "plant", name, 0, 0.0, pv.angle_index, 0.0, None,
                          f"{name}.png", None)
        items.append(Silhouette(view, silhouette_mask(v, f, cam)))
    full = validate_recipe({k: v for k, v in raw.items() if k != "export"}, None, "recipe")
    hull = OctreeHull(OctreeHull.Params.model_validate({**full.reconstruct.params,
                                                        "resolution": resolution}),
                      StageContext())
    volume = hull.reconstruct(Silhouettes(items), Calibration(models, poses, {0: 0.0}))
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params.model_validate(full.mesh.params),
                                 StageContext())
    from plantscan_sim.geometry import TriMesh

    return mesher.mesh(volume), plant, TriMesh(debris_v, debris_f,
                                               np.zeros(len(debris_f), np.int64))


def nearest_truth(mesh, plant, debris) -> tuple[np.ndarray, np.ndarray]:
    """(F,) truth id of the nearest true surface to each hull face (leaf id, -1 stem, -2 pot
    or debris blob) and (F,) its distance, mm."""
    import open3d as o3d

    tv = np.concatenate([plant.mesh.vertices, debris.vertices])
    tf = np.concatenate([plant.mesh.faces, debris.faces + len(plant.mesh.vertices)])
    tid = np.concatenate([plant.mesh.face_attr, np.full(len(debris.faces), -2)])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(tv.astype(np.float32)),
                        o3d.core.Tensor(tf.astype(np.uint32)))
    c = geo.face_centroids(mesh.vertices, mesh.faces).astype(np.float32)
    r = scene.compute_closest_points(o3d.core.Tensor(c))
    prim = r["primitive_ids"].numpy().astype(np.int64)
    return tid[prim], np.linalg.norm(r["points"].numpy() - c, axis=1)


def sample_truth(s: SurfaceSamples, face_id: np.ndarray, face_d: np.ndarray,
                 areas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample: class (STEM/LEAF/EDGE/DEBRIS), instance (leaf id, -1 stem, -2 debris) and
    phantom share (area farther than ``organs.PHANTOM_UNITS`` from the true surface)."""
    key = np.where(face_d > DEBRIS_UNITS * s.unit_mm, -2, face_id) + 2
    nk = int(key.max()) + 1
    votes = np.bincount(s.face_sample * nk + key, areas, s.n * nk).reshape(s.n, nk)
    inst = votes.argmax(axis=1) - 2
    cls = np.where(inst == -2, organs.DEBRIS, np.where(inst == -1, organs.STEM, organs.LEAF))
    a, b = s.pairs[:, 0], s.pairs[:, 1]
    diff = (inst[a] != inst[b]) & (inst[a] != -2) & (inst[b] != -2)
    edge = np.zeros(s.n, bool)
    edge[a[diff]] = edge[b[diff]] = True
    for _ in range(EDGE_RINGS - 1):
        edge[a[edge[b]]] = edge[b[edge[a]]] = True
    cls = np.where((cls == organs.LEAF) & edge, organs.EDGE, cls)
    far = face_d > organs.PHANTOM_UNITS * s.unit_mm
    total = np.maximum(np.bincount(s.face_sample, areas, s.n), 1e-12)
    return cls, inst, np.bincount(s.face_sample, areas * far, s.n) / total


def plant_hull(family: str, seed: int, cache: Path, recipe: str | None = None) -> dict:
    """The hull mesh of one plant and the nearest truth of each face (cached as
    ``cache/hulls/<family>-<seed>.npz``: the carving is the slow part, the features are
    recomputed from it when they change)."""
    if seed >= 1000:
        raise ValueError(f"seed {seed}: validation seeds (>= 1000) are never trained on")
    path = cache / "hulls" / f"{family}-{seed}.npz"
    if path.exists():
        return dict(np.load(path))
    mesh, plant, debris = exact_hull(family, seed, recipe)
    face_id, face_d = nearest_truth(mesh, plant, debris)
    d = dict(vertices=mesh.vertices, faces=mesh.faces.astype(np.int32), face_id=face_id,
             face_d=face_d.astype(np.float32))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **d)
    return d


def plant_samples(family: str, seed: int, cache: Path, recipe: str | None = None) -> dict:
    """The labelled samples of one plant (cached as ``cache/samples/<family>-<seed>.npz``)."""
    from plantscan_core.data import Mesh

    path = cache / "samples" / f"{family}-{seed}.npz"
    if path.exists():
        return dict(np.load(path))
    h = plant_hull(family, seed, cache, recipe)
    mesh = Mesh(h["vertices"], h["faces"])
    s = surface_samples(mesh)
    cls, inst, phantom = sample_truth(s, h["face_id"], h["face_d"], mesh.face_areas())
    d = dict(x=s.features, y=cls, inst=inst, phantom=phantom, area=s.area, centroid=s.centroid,
             pairs=s.pairs, unit=s.unit_mm, moments=s.moments, thickness=s.thickness_mm,
             face_sample=s.face_sample)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **d)
    return d


def as_samples(d: dict) -> SurfaceSamples:
    return SurfaceSamples(float(d["unit"]), d["face_sample"], d["centroid"], d["area"], d["x"],
                          d["pairs"], d["thickness"], d["moments"])


def organ_rows(plants: list[dict], rng: np.random.Generator):
    """Features, classes and phantom flags of the training samples of ``plants``."""
    xs, ys, ps = [], [], []
    for d in plants:
        y = d["y"]
        idx = np.arange(len(y))
        if len(idx) > ROWS_PER_PLANT:
            rare, common = idx[y != organs.LEAF], idx[y == organs.LEAF]
            k = max(ROWS_PER_PLANT - len(rare), ROWS_PER_PLANT // 2)
            idx = np.concatenate([rare, rng.choice(common, min(k, len(common)), replace=False)])
        xs.append(d["x"][idx])
        ys.append(y[idx])
        ps.append(d["phantom"][idx] > 0.5)
    return np.vstack(xs), np.concatenate(ys), np.concatenate(ps)


def train_organ(plants: list[dict]):
    import lightgbm as lgb

    x, y, _ = organ_rows(plants, np.random.default_rng(0))
    freq = np.bincount(y, minlength=4) / len(y)
    w = 1.0 / np.sqrt(np.maximum(freq[y], 1e-6))
    data = lgb.Dataset(x, y, weight=w, feature_name=list(FEATURE_NAMES))
    return lgb.train(ORGAN_PARAMS, data, ORGAN_ROUNDS)


def fragment_truth(frags: organs.Fragments, d: dict) -> np.ndarray:
    """(G,) truth leaf of each fragment (area-weighted majority; -1: mostly not a leaf)."""
    on = frags.of_sample >= 0
    inst = d["inst"] + 2
    nk = int(inst.max()) + 1
    votes = np.bincount(frags.of_sample[on] * nk + inst[on], d["area"][on],
                        frags.n * nk).reshape(frags.n, nk)
    best = votes.argmax(axis=1) - 2
    return np.where(best >= 0, best, -1)


def merge_rows(d: dict, organ, params: organs.InstanceParams) -> tuple[np.ndarray, np.ndarray]:
    """The pairs an oracle agglomeration of one plant's fragments scores, and their labels."""
    s = as_samples(d)
    prob = np.asarray(organ.predict(s.features, num_threads=2))
    frags = organs.leaf_fragments(s, prob, params)
    truth = fragment_truth(frags, d)
    rows, labels = [], []

    def record(keys, x, root):
        lab = np.array([truth[f] == truth[g] and truth[f] >= 0 for f, g in keys], float)
        rows.append(x)
        labels.append(lab)
        oracle.last = lab

    def oracle(x):
        return oracle.last

    organs.agglomerate(frags, oracle, 0.5, record)
    if not rows:
        return np.zeros((0, len(organs.PAIR_FEATURES)), np.float32), np.zeros(0)
    return np.vstack(rows), np.concatenate(labels)


def train(plants: dict[str, dict], log=print):
    """The three boosters from ``plants`` (name -> samples)."""
    import lightgbm as lgb

    names = sorted(plants)
    folds = [names[0::2], names[1::2]]
    params = organs.InstanceParams()
    xr, yr = [], []
    for k in (0, 1):
        fold_model = train_organ([plants[n] for n in folds[k]])
        for n in folds[1 - k]:
            x, y = merge_rows(plants[n], fold_model, params)
            xr.append(x)
            yr.append(y)
            log(f"  {n}: {len(y)} merge rows, {int(y.sum())} positive")
    merge = lgb.train(BINARY_PARAMS, lgb.Dataset(np.vstack(xr), np.concatenate(yr),
                                                 feature_name=list(organs.PAIR_FEATURES)),
                      MERGE_ROUNDS)
    organ = train_organ([plants[n] for n in names])
    x, _, ph = organ_rows([plants[n] for n in names], np.random.default_rng(0))
    phantom = lgb.train(BINARY_PARAMS | dict(num_leaves=31, min_data_in_leaf=50),
                        lgb.Dataset(x, ph.astype(int), feature_name=list(FEATURE_NAMES)),
                        PHANTOM_ROUNDS)
    return {"organ": organ, "phantom": phantom, "merge": merge}


def save(boosters: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for key, name in organs.MODEL_FILES.items():
        # mtime 0: the same model gives the same bytes
        (out / name).write_bytes(gzip.compress(boosters[key].model_to_string().encode(),
                                               mtime=0))


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default="dicot,rosette,branched,grass,seedling")
    ap.add_argument("--seeds", default="0-11", help="development seeds, e.g. 0-11 or 1,3,5")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/plantscan-organ-training"))
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parents[1] / "plugins" / "plantscan_leaves"
                    / "models")
    ap.add_argument("--hold-out", default=None, help="a family left out of training")
    ap.add_argument("--hulls-only", action="store_true",
                    help="carve and cache the hulls (the slow part), train nothing")
    args = ap.parse_args(argv)
    seeds = _seeds(args.seeds)
    if any(s >= 1000 for s in seeds):
        ap.error("--seeds: validation seeds (>= 1000) are never trained on")
    families = [f for f in args.families.split(",") if f and f != args.hold_out]
    t0 = time.time()
    plants = {}
    for seed in seeds:  # seed by seed: a run cut short has every family
        for fam in families:
            if args.hulls_only:
                h = plant_hull(fam, seed, args.cache)
                print(f"{fam} {seed}: {len(h['faces'])} faces ({time.time() - t0:.0f} s)",
                      flush=True)
                continue
            plants[f"{fam}-{seed}"] = plant_samples(fam, seed, args.cache)
            print(f"{fam} {seed}: {len(plants[f'{fam}-{seed}']['y'])} samples "
                  f"({time.time() - t0:.0f} s)", flush=True)
    if args.hulls_only:
        return 0
    boosters = train(plants, log=lambda m: print(m, flush=True))
    save(boosters, args.out)
    print(f"models written to {args.out} ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

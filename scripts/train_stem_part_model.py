"""Train the stem-part judge of ``curvature-regions`` (``judge_stem_parts``) on development plants.

    python scripts/train_stem_part_model.py --runs DIR [--runs DIR ...] [--plants grass=0-9]
        [--out FILE] [--cache DIR]

The plants are ``benchmarks/population.py``'s run folders of development seeds (< 1000;
validation seeds are never trained on): ``population.py --families grass --seeds 0-9
--runs DIR`` makes them (paper-72, 1296x864, the family recipe's 512^3 hull) as
``DIR/<family>/seed-<n>``, each with its ``mesh.npz`` and the scan's truth.  For every
plant its family recipe's ``curvature-regions`` rules (``--recipe-dir``, default
``recipes/``) segment the mesh, and the stem's parts (``plantscan_leaves.stem_parts``) get
their features and a class from the truth: **blade** when at least ``ON_LEAF_SHARE`` of
the part's area lies nearest to a truth leaf's surface (the truth mesh in the evaluator's
frame, ``evaluate.gauge_frame``), else **stem**.  A LightGBM binary booster
(``BOOSTER_PARAMS``) is trained on all parts and written with its training configuration
and the hash of it; the same runs give the same file.  Without ``--out`` the model goes
into the package (``plantscan_leaves/models/stem_part_model.json.gz``, what the grass
recipe uses); ``--out`` writes another (a fold of a cross-check, a lab's own).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

from plantscan_leaves import stem_parts as sp  # noqa: E402
from train_piece_model import (  # noqa: E402
    fit_booster,
    parse_plants,
    segment_params,
    truth_dir_of,
)

ON_LEAF_SHARE = 0.5  # a part mostly on truth leaf surface is a blade
BOOSTER_PARAMS = dict(objective="binary", learning_rate=0.1, num_leaves=4, min_data_in_leaf=10,
                      feature_fraction=0.8, bagging_fraction=0.8, bagging_freq=1,
                      lambda_l2=1.0, num_threads=1, verbose=-1, seed=0, deterministic=True,
                      force_row_wise=True)
ROUNDS = 100
SHIPPED = {"grass": list(range(30))}  # the development plants the shipped model is trained on


def training_config(plants: dict[str, list[int]]) -> dict:
    """What a model trained on ``plants`` ({family: seeds}) records."""
    return {"plants": {f: list(s) for f, s in plants.items()},
            "population": "benchmarks/population.py paper-72 1296x864, "
                          "recipes/<family>.yaml 512^3",
            "labels": f"blade: >= {ON_LEAF_SHARE} of the part's area nearest to truth leaf "
                      "surface; else stem",
            "booster": BOOSTER_PARAMS, "rounds": ROUNDS, "features": list(sp.FEATURE_NAMES),
            "min_part_units2": sp.MIN_PART_UNITS2}


class _Recorder:
    """A stem-part "model" that keeps the parts it is shown (and calls every one stem)."""

    def __init__(self) -> None:
        self.parts: sp.StemParts | None = None

    def probabilities(self, parts: sp.StemParts) -> np.ndarray:
        self.parts = parts
        return np.zeros(parts.m)


def truth_leaf_of_faces(mesh, truth_dir: Path) -> np.ndarray:
    """(F,) truth leaf id nearest to every face of ``mesh`` (-1: stem or pot)."""
    from plantscan_leaves import geometry as geo
    from plantscan_leaves.evaluate import gauge_frame
    from scipy.spatial import cKDTree

    with np.load(truth_dir / "plant.npz") as z:
        tv, tf, leaf_id = z["vertices"], z["faces"], z["face_leaf_id"]
    mc = geo.face_centroids(mesh.vertices, mesh.faces)
    tc = geo.face_centroids(tv, tf)
    mc, _ = gauge_frame(mc, tc, geo.mesh_unit(mesh.vertices, mesh.faces))
    return leaf_id[cKDTree(tc).query(mc)[1]]


def plant_parts(run_dir: Path, params: dict, cache: Path) -> dict:
    """The stem parts' features and truth classes of one run (cached per mesh and params)."""
    from plantscan_leaves import geometry as geo
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    from plantscan_core.data import Mesh

    mesh_file = run_dir / "mesh.npz"
    key = hashlib.sha256(json.dumps([str(mesh_file), mesh_file.stat().st_size,
                                     mesh_file.stat().st_mtime, params,
                                     training_config({})]).encode()).hexdigest()[:16]
    path = cache / f"{run_dir.parent.name}-{run_dir.name}-{key}.npz"
    if path.exists():
        return dict(np.load(path))
    mesh = Mesh.load(mesh_file)
    rec = _Recorder()
    segment_leaves(mesh, CurvatureRegionsParams(**{**params, "judge_stem_parts": True}),
                   stem_part_model=rec)
    parts = rec.parts
    leaf_id = truth_leaf_of_faces(mesh, truth_dir_of(run_dir))
    _, areas = geo.face_normals_areas(mesh.vertices, mesh.faces)
    on = parts.part >= 0
    total = np.bincount(parts.part[on], areas[on], parts.m)
    on_leaf = np.bincount(parts.part[on], areas[on] * (leaf_id[on] >= 0), parts.m)
    classes = (on_leaf >= ON_LEAF_SHARE * np.maximum(total, 1e-30)).astype(np.int64)
    d = dict(features=parts.features, classes=classes, area=total / 2.0)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **d)
    return d


def train(plants: list[dict]):
    return fit_booster(plants, sp.FEATURE_NAMES, BOOSTER_PARAMS, ROUNDS)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", action="append", type=Path, required=True)
    ap.add_argument("--plants", action="append", default=[], metavar="FAMILY=SEEDS")
    ap.add_argument("--recipe-dir", type=Path, default=REPO / "recipes")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=Path("/work/cache/stem_parts"))
    args = ap.parse_args(argv)
    plants = parse_plants(args.plants) if args.plants else SHIPPED
    data = []
    for family, seeds in plants.items():
        params = segment_params(args.recipe_dir / f"{family}.yaml")
        for seed in seeds:
            run = next((r / family / f"seed-{seed}" for r in args.runs
                        if (r / family / f"seed-{seed}" / "mesh.npz").exists()), None)
            if run is None:
                raise SystemExit(f"{family} seed {seed}: no run folder with mesh.npz under "
                                 f"{', '.join(map(str, args.runs))}")
            d = plant_parts(run, params, args.cache)
            print(f"{family} seed-{seed}: {len(d['classes'])} parts, "
                  f"{int(d['classes'].sum())} blade", flush=True)
            data.append(d)
    booster = train(data)
    out = args.out or (REPO / "plugins" / "plantscan_leaves" / "models" / sp.MODEL_FILE)
    sp.save_model(booster, training_config(plants), out)
    print(f"model: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

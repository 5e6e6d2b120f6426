"""Train the measurer's learned lost-tip length (``measure``'s ``tip_model``) on dev plants.

    python scripts/train_tip_model.py --runs DIR [--model tip_model_grass.json.gz]
        [--plants grass=0-29] [--recipe-dir recipes/] [--out FILE] [--loo] [--cache DIR]

The plants are ``benchmarks/population.py``'s run folders of development seeds (< 1000;
validation seeds are never trained on), ``DIR/<family>/seed-<n>`` with their ``mesh.npz``
and the scan's truth.  Every plant is segmented and measured with its family recipe
(``--recipe-dir``; the tip and trust models off, the rest as the recipe says, so the
features follow its segmentation and ``tip_taper_units``), its leaves matched with the
truth (``population.evaluate_plant``, as ``plantscan evaluate``).  A blade is a training
row when the truth's base is within ``BASE_WITHIN_UNITS`` mesh units of the measured
base, the truth's tip nearer the measured tip than its base, and the measured leaf covers
at least ``MIN_COVER`` of the truth leaf: then the truth's length less the seen length
(the measured length without the rule's lost tip) is what the hull lost at the tip, as a
share of the seen length.  A LightGBM regression (``BOOSTER_PARAMS``, absolute error:
a few blades are far off for reasons the profile does not show) on ``tips.FEATURE_NAMES``
is written with its training configuration: ``--model`` retrains a shipped model
(``SHIPPED``: the file and its plants) into the package, ``--plants`` trains on other
plants (then ``--out`` says where the model goes).  Seeded and deterministic: the same
runs give the same file.  ``--loo`` also measures every plant's blades with a model
trained on the others (leave one plant out) and prints the length errors of every
matched blade, rule against model.  Per-plant rows are cached under ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
sys.path.insert(0, str(REPO / "benchmarks"))

from plantscan_leaves import tips  # noqa: E402
from train_piece_model import (  # noqa: E402
    cached_run,
    fit_booster,
    parse_plants,
    segment_measure_evaluate,
    truth_dir_of,
)

BASE_WITHIN_UNITS = 8.0
MIN_COVER = 0.9
BOOSTER_PARAMS = dict(objective="l1", learning_rate=0.05, num_leaves=7, min_data_in_leaf=10,
                      feature_fraction=0.8, bagging_fraction=0.8, bagging_freq=1,
                      num_threads=1, verbose=-1, seed=0, deterministic=True,
                      force_row_wise=True)
ROUNDS = 200
# the target is clipped to what the model may say (tips.MAX_SHARE) and a little below 0
# (a blade measured a little long at its base is not a negative tip)
TARGET_RANGE = (-0.05, tips.MAX_SHARE)
MODELS_DIR = REPO / "plugins/plantscan_leaves/models"
# the shipped models and the development plants each is trained on
SHIPPED = {"tip_model_grass.json.gz": {"grass": list(range(30))}}


def training_config(plants: dict[str, list[int]]) -> dict:
    return {"plants": {f: list(s) for f, s in plants.items()},
            "population": "benchmarks/population.py paper-72 1296x864, "
                          "recipes/<family>.yaml 512^3",
            "rows": f"base within {BASE_WITHIN_UNITS} units, oriented, cover >= {MIN_COVER}",
            "target": "(truth length - seen length) / seen length",
            "booster": BOOSTER_PARAMS, "rounds": ROUNDS, "features": list(tips.FEATURE_NAMES)}


def leaf_sections(recipe: Path) -> dict:
    """The recipe's ``segment_mesh`` and ``measure`` sections, the tip and trust models off."""
    from plantscan_core.recipe import read_recipe_file

    raw = read_recipe_file(recipe)
    measure = dict(raw["measure"])
    measure["params"] = {**(measure.get("params") or {}), "trust_model": None,
                         "tip_model": None}
    return {"segment_mesh": raw["segment_mesh"], "measure": measure}


def _rows(measurements, evaluation: dict, truth_dir: Path, unit: float) -> dict:
    """Every matched leaf's features, target, rule and seen lengths, truth length and
    whether it is a training row (the module docstring's rules)."""
    traits = evaluation["traits"]
    organs = {lf["leaf_id"]: lf for lf in
              json.loads((truth_dir / "organs.json").read_text())["leaves"]}
    by_id = {m.traits.leaf_id: m for m in measurements}
    per = {(p["measured_id"], p["truth_id"]): p for p in traits["per_leaf"]}
    out = {k: [] for k in ("features", "target", "rule", "seen", "truth", "measured", "train")}
    for pair in traits["pairs"]:
        m = by_id.get(pair["measured_id"])
        p = per.get((pair["measured_id"], pair["truth_id"]))
        f = None if m is None else m.info.get("tip_features")
        if p is None or f is None:
            continue
        base, tip = (np.asarray(organs[pair["truth_id"]][k], float) for k in ("base_mm", "tip_mm"))
        oriented = (np.linalg.norm(m.base - base) + np.linalg.norm(m.tip - tip)
                    < np.linalg.norm(m.base - tip) + np.linalg.norm(m.tip - base))
        seen = m.info["seen_mm"]
        without = m.traits.length_mm - m.info["lost_tip_mm"]
        out["features"].append(f)
        out["target"].append((p["length_truth"] - without) / seen)
        out["rule"].append(m.info["lost_tip_mm"])
        out["seen"].append(seen)
        out["truth"].append(p["length_truth"])
        out["measured"].append(without)
        out["train"].append(bool(oriented and pair["cover"] >= MIN_COVER and
                                 np.linalg.norm(m.base - base) <= BASE_WITHIN_UNITS * unit))
    n_features = len(tips.FEATURE_NAMES)
    return {"features": np.array(out.pop("features"), float).reshape(-1, n_features),
            "train": np.array(out.pop("train"), bool),
            **{k: np.array(v, float) for k, v in out.items()}}


def plant_rows(run_dir: Path, sections: dict, cache: Path) -> dict:
    """``_rows`` of one run folder, segmented and measured with ``sections`` (cached)."""
    from plantscan_leaves import geometry as geo

    path, out = cached_run(run_dir, sections, cache, training_config({}))
    if path.exists():
        return dict(np.load(path))
    mesh, _, _, measurements, evaluation = segment_measure_evaluate(run_dir, sections, out)
    d = _rows(measurements, evaluation, truth_dir_of(run_dir),
              geo.mesh_unit(mesh.vertices, mesh.faces))
    np.savez_compressed(path, **d)
    return d


def train(plants: list[dict]):
    rows = [{"features": d["features"][d["train"]],
             "classes": np.clip(d["target"][d["train"]], *TARGET_RANGE)} for d in plants]
    return fit_booster(rows, tips.FEATURE_NAMES, BOOSTER_PARAMS, ROUNDS)


def length_errors(plants: list[dict], lost_mm: list[np.ndarray]) -> str:
    """'median / p90 / off > 10 %' of |length error| over every matched blade."""
    err = np.abs(np.concatenate([(d["measured"] + lost) / d["truth"] - 1
                                 for d, lost in zip(plants, lost_mm, strict=True)]))
    return (f"{len(err)} blades: |length error| median {100 * np.median(err):.2f} %, "
            f"p90 {100 * np.quantile(err, 0.9):.2f} %, off > 10 % {int((err > 0.1).sum())}")


def leave_one_out(plants: list[dict]) -> str:
    model = []
    for i, d in enumerate(plants):
        booster = train([p for j, p in enumerate(plants) if j != i])
        share = booster.predict(d["features"].astype(np.float64), num_threads=1)
        model.append(np.clip(share, 0.0, tips.MAX_SHARE) * d["seen"])
    return "\n".join([f"rule: {length_errors(plants, [d['rule'] for d in plants])}",
                      f"model (leave one plant out): {length_errors(plants, model)}"])


def main(argv: list[str] | None = None) -> int:
    from plantscan_leaves.pieces import save_model

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--model", default="tip_model_grass.json.gz", choices=sorted(SHIPPED))
    ap.add_argument("--plants", action="append", metavar="FAMILY=SEEDS",
                    help="train on these plants instead of the model's (needs --out)")
    ap.add_argument("--recipe-dir", type=Path, default=REPO / "recipes")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--cache", type=Path, default=Path("/work/cache/tip-rows"))
    ap.add_argument("--loo", action="store_true")
    args = ap.parse_args(argv)
    if args.plants and args.out is None:
        raise SystemExit("--plants needs --out: the shipped models are trained on SHIPPED's")
    plants_spec = parse_plants(args.plants) if args.plants else SHIPPED[args.model]
    plants = []
    for family, seeds in plants_spec.items():
        sections = leaf_sections(args.recipe_dir / f"{family}.yaml")
        for s in seeds:
            run_dir = args.runs / family / f"seed-{s}"
            if not (run_dir / "mesh.npz").exists():
                raise SystemExit(f"{run_dir}: no mesh.npz (population.py --runs makes it)")
            plants.append(plant_rows(run_dir, sections, args.cache))
            print(f"{family} seed {s}: {int(plants[-1]['train'].sum())} training rows of "
                  f"{len(plants[-1]['train'])} matched", flush=True)
    if args.loo:
        print(leave_one_out(plants))
    out = args.out or MODELS_DIR / args.model
    save_model(train(plants), training_config(plants_spec), out, tips.FEATURE_NAMES,
               ("lost_tip_share",))
    print(f"model -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

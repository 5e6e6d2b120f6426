"""Train the measurer's learned trust model (``measure``'s ``trust_model``) on dev plants.

    python scripts/train_trust_model.py --runs DIR [--runs DIR ...] [--plants grass=0-9]
        [--recipe-dir recipes] [--out FILE] [--cache DIR] [--loo]

The plants are ``benchmarks/population.py``'s run folders of development seeds (< 1000;
validation seeds are never trained on), ``DIR/<family>/seed-<n>`` with its ``mesh.npz``
and the scan's truth.  Every plant's mesh goes through its family recipe's leaf stages
(``segment_mesh`` and ``measure`` as shipped, without a trust model), the run is evaluated
against the truth (``plantscan evaluate``'s instance matching), and every measured leaf
gets the features of ``plantscan_leaves.trust_model`` and a class: **good** when it is
one truth leaf measured within 10 % on length, width, area and perimeter, **bad**
otherwise (off by more, merged, a piece of a split leaf, or no truth leaf).  A LightGBM
binary booster (``BOOSTER_PARAMS``) is trained on all leaves and written with its
training configuration and the hash of it; the same runs give the same file.  Without
``--out`` the model goes into the package (``SHIPPED``'s file); ``--loo`` also prints
leave-one-plant-out figures: the share of bad leaves the rules, the model and both
together flag, and the share of flagged leaves that are accurate (within 5 %).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
sys.path.insert(0, str(REPO / "benchmarks"))

from plantscan_leaves import trust_model as tm  # noqa: E402
from train_piece_model import (  # noqa: E402
    cached_run,
    fit_booster,
    parse_plants,
    segment_measure_evaluate,
)

GOOD = ("accurate", "fair")  # leaf_population.leaf_kinds: a truth leaf within 10 %
BOOSTER_PARAMS = dict(objective="binary", learning_rate=0.05, num_leaves=4, min_data_in_leaf=8,
                      feature_fraction=0.8, bagging_fraction=0.8, bagging_freq=1,
                      lambda_l2=2.0, num_threads=1, verbose=-1, seed=0, deterministic=True,
                      force_row_wise=True)
ROUNDS = 150
# the low-confidence cut on p_bad, chosen per model on its development plants (choose_cut):
# the trust targets are >= 90 % of the off leaves flagged and <= 25 % of the flagged
# within 5 %; 15 % keeps a margin under the latter for plants the model never saw
CUTS = (0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.15, 0.1, 0.05)
CUT_FLAGGED = 0.9
CUT_ACCURATE = 0.15
# the shipped models and the development plants each is trained on: one per family whose
# recipe names it, and one on every family (the seedling's recipe: its 16 dev plants hold
# 13 bad leaves; a seedling-only model flagged 2 of 5 off validation leaves, the all-family
# one 4; a lab's new species starts there)
_DEV = {"dicot": list(range(20)), "grass": list(range(10)), "branched": list(range(14)),
        "rosette": list(range(6)), "seedling": list(range(16))}
# (session 21: the dicot model retrained on the dicot recipe's new rules, 30 dev plants;
# the all-family model keeps the 20 it was trained on)
# (session 27: the rosette model retrained on the rosette recipe's plant-only masks, 10 dev
# plants; the all-family model keeps the rosettes 0-5 of the lab-shadow recipe it saw)
# (session 28: the rosette model retrained on the same 10 dev plants measured with the
# negative outline and width offsets and the outline smoothed over 12 units)
# (session 28: the branched model retrained on the recipe's stalk and tip measurement, 28 dev
# plants; the all-family model keeps the 14 it was trained on)
# (session 29: a seedling model of its own, 40 dev plants measured with the recipe's stalk,
# 123 leaves, 26 bad: validation 1000-1029 90 % of the off leaves flagged, the all-family
# model 81 %; the all-family model keeps the seedlings 0-15 it was trained on)
# (session 32: the grass model retrained on the recipe's learned lost tip, 30 dev plants;
# the all-family model keeps the grasses 0-9 it was trained on)
SHIPPED = {"trust_model_grass.json.gz": {"grass": list(range(30))},
           "trust_model_branched.json.gz": {"branched": list(range(28))},
           "trust_model_rosette.json.gz": {"rosette": list(range(10))},
           "trust_model_dicot.json.gz": {"dicot": list(range(30))},
           "trust_model_seedling.json.gz": {"seedling": list(range(40))},
           "trust_model_all.json.gz": _DEV}
MODELS_DIR = REPO / "plugins/plantscan_leaves/models"


def training_config(plants: dict[str, list[int]]) -> dict:
    """What a model trained on ``plants`` ({family: seeds}) records."""
    return {"plants": {f: list(s) for f, s in plants.items()},
            "population": "benchmarks/population.py paper-72 1296x864, "
                          "recipes/<family>.yaml 512^3",
            "labels": "good: one truth leaf, every trait within 10 %; bad: otherwise",
            "booster": BOOSTER_PARAMS, "rounds": ROUNDS, "features": list(tm.FEATURE_NAMES)}


def leaf_sections(recipe: Path) -> dict:
    """The family recipe's ``segment_mesh`` and ``measure`` sections, the trust model off."""
    from plantscan_core.recipe import read_recipe_file

    raw = read_recipe_file(recipe)
    measure = dict(raw["measure"])
    measure["params"] = {**(measure.get("params") or {}), "trust_model": None}
    return {"segment_mesh": raw["segment_mesh"], "measure": measure}


def plant_leaves(run_dir: Path, sections: dict, cache: Path) -> dict:
    """Features, classes and evaluation figures of one run's measured leaves (cached per
    mesh and recipe sections)."""
    import leaf_population as lp
    from plantscan_leaves import geometry as geo
    from plantscan_leaves.trust import leaf_trust

    path, out = cached_run(run_dir, sections, cache, training_config({}))
    if path.exists():
        return dict(np.load(path))
    info = json.loads((run_dir / "run.json").read_text())
    views = (info.get("scan_record") or {}).get("views")
    mesh, labelled, traits, measurements, evaluation = segment_measure_evaluate(
        run_dir, sections, out, views)
    kinds = lp.leaf_kinds(evaluation)
    unit = geo.mesh_unit(mesh.vertices, mesh.faces)
    ids = np.array([m.traits.leaf_id for m in measurements], np.int64)
    kind = [kinds.get(int(i), "extra") for i in ids]
    rules_low = [leaf_trust(m.traits, labelled.evidence.get(m.traits.leaf_id)).low
                 for m in measurements]
    d = dict(features=tm.leaf_features(traits, measurements, labelled, unit),
             classes=np.array([k not in GOOD for k in kind], np.int64),
             accurate=np.array([k == "accurate" for k in kind]),
             kinds=np.array(kind), leaf_ids=ids, rules_low=np.array(rules_low, bool))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **d)
    return d


def train(plants: list[dict]):
    return fit_booster(plants, tm.FEATURE_NAMES, BOOSTER_PARAMS, ROUNDS)


def flag_figures(bad: np.ndarray, accurate: np.ndarray, low: np.ndarray) -> str:
    """'bad flagged a/b (p %); flagged accurate c/d (q %)'."""
    b, f = int(bad.sum()), int(low.sum())
    bl, fa = int((bad & low).sum()), int((accurate & low).sum())
    return (f"bad flagged {bl}/{b} ({100 * bl / max(b, 1):.0f} %), flagged that are accurate "
            f"{fa}/{f} ({100 * fa / max(f, 1):.0f} %)")


def _flags(plants: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bad, accurate, rules_low) of every leaf of ``plants``, in order."""
    return tuple(np.concatenate([d[k] for d in plants]).astype(bool)
                 for k in ("classes", "accurate", "rules_low"))


def loo_p_bad(plants: list[dict]) -> np.ndarray:
    """Every leaf's p_bad by a model trained on the other plants (all leaves, in order)."""
    p_bad = []
    for i in range(len(plants)):
        booster = train([d for j, d in enumerate(plants) if j != i])
        p_bad.append(booster.predict(plants[i]["features"].astype(np.float64), num_threads=1))
    return np.concatenate(p_bad)


def choose_cut(p_bad: np.ndarray, bad: np.ndarray, accurate: np.ndarray, rules: np.ndarray
               ) -> float:
    """The p_bad at which the shipped model calls a leaf low-confidence, from the
    development plants left out one at a time (never the validation seeds): the highest of
    ``CUTS`` at which the rules and the model together flag ``CUT_FLAGGED`` of the bad
    leaves, as long as at most ``CUT_ACCURATE`` of the flagged leaves are accurate (within
    5 %); when no cut gets there within that bound, the lowest cut within it."""
    within = []
    for cut in CUTS:
        low = rules | (p_bad >= cut)
        if (accurate & low).sum() > CUT_ACCURATE * max(low.sum(), 1):
            break
        within.append(cut)
        if (bad & low).sum() >= CUT_FLAGGED * bad.sum():
            return cut
    return within[-1] if within else CUTS[0]


def leave_one_out(plants: list[dict], names: list[str], p_bad: np.ndarray, cut: float) -> str:
    """Each plant judged by a model trained on the others (``p_bad``: ``loo_p_bad``):
    rules, model, both, at 0.5 and at the model's ``cut``."""
    bad, acc, rules = _flags(plants)
    lines = [f"leaves {len(bad)} of {len(plants)} plants ({', '.join(names)}), bad {bad.sum()}",
             f"rules: {flag_figures(bad, acc, rules)}",
             f"model at 0.5: {flag_figures(bad, acc, p_bad >= 0.5)}",
             f"both at 0.5:  {flag_figures(bad, acc, rules | (p_bad >= 0.5))}",
             f"both at the chosen cut {cut:g}: {flag_figures(bad, acc, rules | (p_bad >= cut))}"]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", action="append", type=Path, required=True)
    ap.add_argument("--model", default="trust_model_all.json.gz", choices=sorted(SHIPPED),
                    help="the shipped model to retrain (its plants: SHIPPED)")
    ap.add_argument("--plants", action="append", default=[], metavar="FAMILY=SEEDS",
                    help="train on these plants instead (repeat per family; needs --out)")
    ap.add_argument("--recipe-dir", type=Path, default=REPO / "recipes")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/plantscan-trust-training"))
    ap.add_argument("--loo", action="store_true", help="also leave one plant out")
    args = ap.parse_args(argv)
    if args.plants and args.out is None:
        ap.error("--plants: say where the model goes with --out (the shipped models are "
                 "trained on SHIPPED's plants)")
    plants_of = parse_plants(args.plants) if args.plants else SHIPPED[args.model]
    out_file = args.out or MODELS_DIR / args.model
    t0 = time.time()
    data, names = [], []
    for family, seeds in plants_of.items():
        sections = leaf_sections(args.recipe_dir / f"{family}.yaml")
        for seed in seeds:
            run = next((r / family / f"seed-{seed}" for r in args.runs
                        if (r / family / f"seed-{seed}" / "mesh.npz").exists()), None)
            if run is None:
                ap.error(f"{family} seed {seed}: no <runs>/{family}/seed-{seed}/mesh.npz "
                         f"(population.py --families {family} --seeds {seed} --runs DIR "
                         "makes it)")
            d = plant_leaves(run, sections, args.cache)
            data.append(d)
            names.append(f"{family} {seed}")
            print(f"{family} {seed}: {len(d['classes'])} leaves, {int(d['classes'].sum())} bad "
                  f"({time.time() - t0:.0f} s)", flush=True)
    booster = train(data)
    from plantscan_leaves.pieces import save_model

    p_loo = loo_p_bad(data)
    cut = choose_cut(p_loo, *_flags(data))
    config = {**training_config(plants_of), "cut": cut,
              "cut_rule": f"highest of {list(CUTS)} at which the rules and the model flag "
                          f">= {CUT_FLAGGED:.0%} of the bad development leaves left out one "
                          f"plant at a time, with <= {CUT_ACCURATE:.0%} of the flagged "
                          "accurate; else the lowest within that bound"}
    save_model(booster, config, out_file, tm.FEATURE_NAMES, tm.CLASS_NAMES)
    print(f"model written to {out_file}, cut {cut:g} ({time.time() - t0:.0f} s)")
    if args.loo:
        print(leave_one_out(data, names, p_loo, cut))
    return 0


if __name__ == "__main__":
    sys.exit(main())

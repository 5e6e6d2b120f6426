"""Train the pair judge of ``curvature-regions`` (``judge_pairs``) on development plants.

    python scripts/train_pair_model.py [--runs DIR ...] [--plants dicot=0-29] [--out FILE]
        [--loo] [--report FILE] [--cache DIR]

The plants are ``benchmarks/population.py``'s run folders of development seeds (< 1000;
validation seeds are never trained on), as for ``scripts/train_piece_model.py``.  For
every plant the family recipe's rules segment the mesh twice: without the piece judge
(the rules' pieces, many small) and with it (the leaves the pair judge is shown at run
time); every pair of leaves sharing border edges in either gets the features of
``plantscan_leaves.pairs`` and a class from the truth (``match_leaves``, how ``plantscan
evaluate`` pairs leaves): **one leaf** when both lie mostly on leaf surface (``lies_on``
leaf >= ``ON_LEAF_SHARE``) and their truth leaf is the same (the one each covers most),
else **two** (two leaves, or a leaf and phantom volume or stem: merging spoils the leaf).

A LightGBM binary booster (``BOOSTER_PARAMS``) is trained on all pairs and written with
its training configuration and its hash (``training_config``).  Everything is seeded and
deterministic: the same runs give the same file.  ``--loo`` also judges every plant's
pairs with a model trained on the other plants (leave one plant out) and tabulates the
piece judge's leaves against those with the pairs merged, measured and evaluated as
``benchmarks/leaf_population.py`` does (the piece judge there is the recipe's, trained on
these same plants: the table measures what the pair judge adds).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "scripts"))

import train_piece_model as tp  # noqa: E402
from plantscan_leaves import pairs as pr  # noqa: E402
from plantscan_leaves import pieces as pc  # noqa: E402

ON_LEAF_SHARE = 0.5  # a piece mostly on leaf surface may be part of a leaf
BOOSTER_PARAMS = dict(objective="binary", learning_rate=0.1, num_leaves=4,
                      min_data_in_leaf=20, feature_fraction=0.8, bagging_fraction=0.8,
                      bagging_freq=1, lambda_l2=1.0, num_threads=1, verbose=-1, seed=0,
                      deterministic=True, force_row_wise=True)
ROUNDS = 100
SHIPPED = {pr.MODEL_FILE: {"dicot": list(range(30))}}
# the rules again with shallower creases cutting leaves (the recipe's 0.06 /mm): split
# leaves are rare on the development plants the piece judge was trained on (2 of 32
# touching pairs), and these cuts are the rules' own, along real creases of real hulls
VARY = {"concave_curvature_per_mm": [0.04, 0.05]}
MODELS_DIR = tp.MODELS_DIR


def training_config(plants: dict[str, list[int]], vary: dict | None = None) -> dict:
    """What a model trained on ``plants`` ({family: seeds}) records."""
    return {"plants": {f: list(s) for f, s in plants.items()},
            "population": "benchmarks/population.py paper-72 1296x864, "
                          "recipes/<family>.yaml 512^3",
            "labels": "match_leaves: both on leaf (lies_on >= "
                      f"{ON_LEAF_SHARE}) with the same truth leaf: one leaf; else two",
            "pairs_from": "the rules' pieces (judge_pieces off) and the piece judge's leaves",
            "varied": VARY if vary is None else vary, "booster": BOOSTER_PARAMS, "rounds": ROUNDS,
            "features": list(pr.FEATURE_NAMES)}


def pair_classes(labelled, pairs: pr.Pairs, truth_dir: Path) -> np.ndarray:
    """(k,) 1 when both leaves of a pair are on one truth leaf, else 0."""
    from plantscan_leaves.evaluate import match_leaves

    with np.load(truth_dir / "plant.npz") as z:
        m = match_leaves(labelled, z["vertices"], z["faces"], z["face_leaf_id"])
    col = {lab: j for j, lab in enumerate(m["measured_labels"])}
    cover = np.asarray(m["cover"]) if m.get("cover") else np.zeros((0, len(col)))

    def truth_of(lab: int):
        j = col.get(lab)
        if (j is None or not len(cover) or cover[:, j].max() <= 0
                or m["lies_on"].get(lab, {}).get("leaf", 0.0) < ON_LEAF_SHARE):
            return None
        return m["truth_ids"][int(np.argmax(cover[:, j]))]

    out = np.zeros(len(pairs.pairs), np.int64)
    for i, (a, b) in enumerate(pairs.pairs):
        ta = truth_of(int(a))
        out[i] = int(ta is not None and ta == truth_of(int(b)))
    return out


def plant_pairs(run_dir: Path, params: dict, cache: Path) -> dict:
    """The pairs of the rules' pieces and of the judged leaves of one run, with their
    classes and the judged labels (cached per mesh and params)."""
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    from plantscan_core.data import Mesh

    mesh_file = run_dir / "mesh.npz"
    key = hashlib.sha256(json.dumps([str(mesh_file), mesh_file.stat().st_size,
                                     mesh_file.stat().st_mtime, params,
                                     list(pr.FEATURE_NAMES), ON_LEAF_SHARE]
                                    ).encode()).hexdigest()[:16]
    path = cache / f"{run_dir.parent.name}-{run_dir.name}-{key}.npz"
    if path.exists():
        return dict(np.load(path))
    mesh = Mesh.load(mesh_file)
    truth = tp.truth_dir_of(run_dir)
    out = {}
    for name, judge in (("rules", False), ("judged", True)):
        rec = _Recorder()  # sees the pairs the pair judge is shown, merges none
        p = CurvatureRegionsParams(**{**params, "judge_pieces": judge, "judge_pairs": True})
        labelled, _ = segment_leaves(mesh, p, pair_model=rec)
        pairs = rec.pairs
        out[f"{name}_pairs"] = pairs.pairs
        out[f"{name}_features"] = pairs.features
        out[f"{name}_classes"] = pair_classes(labelled, pairs, truth)
        if judge:
            out["judged_labels"] = labelled.face_labels
            out["judged_n"] = np.int64(len(labelled.leaf_labels))
            out["judged_debris"] = np.bool_("debris" in labelled.kinds.values())
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    return out


class _Recorder:
    """A pair "model" that keeps the pairs it is shown (and merges none)."""

    def __init__(self) -> None:
        self.pairs = pr.Pairs(np.zeros((0, 2), np.int64),
                              np.zeros((0, len(pr.FEATURE_NAMES)), np.float32))

    def probabilities(self, pairs: pr.Pairs) -> np.ndarray:
        self.pairs = pairs
        return np.zeros(len(pairs.pairs))


def train(plants: list[dict]):
    import lightgbm as lgb

    x = np.vstack([d[f"{s}_features"] for d in plants for s in ("rules", "judged", "varied")])
    y = np.concatenate([d[f"{s}_classes"] for d in plants for s in ("rules", "judged",
                                                                      "varied")])
    return lgb.train(BOOSTER_PARAMS, lgb.Dataset(x.astype(np.float64), y,
                                                 feature_name=list(pr.FEATURE_NAMES)), ROUNDS)


def held_out(runs: list[Path], plants: list[dict], recipe_dir: Path, work: Path) -> str:
    """Markdown: per family, the piece judge's leaves and those with the pairs merged by a
    model trained without the plant, measured and evaluated."""
    import population as pop
    from plantscan_leaves.measure import LeafGeometryParams

    from plantscan_core.recipe import read_recipe_file

    rows: dict[str, dict[str, tuple[list, list]]] = {}
    lines = []
    for i, (run_dir, d) in enumerate(zip(runs, plants)):
        family = run_dir.parent.name
        mp = LeafGeometryParams(**(read_recipe_file(recipe_dir / f"{family}.yaml")["measure"]
                                   .get("params") or {}))
        booster = train([p for j, p in enumerate(plants) if j != i])
        labels, n = d["judged_labels"], int(d["judged_n"])
        pairs = pr.Pairs(d["judged_pairs"], d["judged_features"])
        prob = (np.asarray(booster.predict(pairs.features.astype(np.float64), num_threads=1))
                if len(pairs.pairs) else np.zeros(0))
        merged, n2, joined, _ = pr.merge_pairs(labels, n, pairs, prob)
        debris = bool(d["judged_debris"])
        fam = rows.setdefault(family, {"judged": ([], []), "pairs merged": ([], [])})
        for name, (lab, k, jn) in (("judged", (labels, n, {})),
                                   ("pairs merged", (merged, n2, joined))):
            verdict = pc.Verdict(lab, k, debris, np.zeros(0, np.int64), jn)
            prow, lrows = tp.evaluate_labels(run_dir, verdict, work / name / family /
                                             run_dir.name, mp)
            fam[name][0].append(prow)
            fam[name][1].extend(lrows)
        truth = d["judged_classes"]
        hit = prob >= pr.MERGE_PROBABILITY
        right = int((hit & (truth == 1)).sum())
        lines.append(f"{family} {run_dir.name}: {len(truth)} touching pairs ({int(truth.sum())} "
                     f"one leaf), merged {int(hit.sum())} (right {right})")
        print(lines[-1], flush=True)
    out = []
    for family, fam in rows.items():
        for name, (prows, lrows) in fam.items():
            out += [f"### {family}: {name}", "", pop.tabulate(prows, lrows), ""]
    return "\n".join(out + ["", *lines])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, action="append", default=[],
                    help="a folder of <family>/seed-<n> run folders (repeat: first match wins)")
    ap.add_argument("--plants", action="append", default=[], metavar="FAMILY=SEEDS",
                    help="train on these plants (default: the shipped model's, SHIPPED)")
    ap.add_argument("--recipe-dir", type=Path, default=REPO / "recipes")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/plantscan-pair-training"))
    ap.add_argument("--out", type=Path, default=None,
                    help="where the model goes (default: the shipped file in the package)")
    ap.add_argument("--vary", action="append", default=[], metavar="PARAM=V1,V2",
                    help="also train on the pairs the rules give with a segment_mesh "
                         "parameter at these values (more crease cuts: more split leaves to "
                         "learn from); default: VARY")
    ap.add_argument("--loo", action="store_true", help="also leave one plant out")
    ap.add_argument("--report", type=Path, default=None, help="write the --loo tables here")
    args = ap.parse_args(argv)
    plants_of = tp.parse_plants(args.plants) if args.plants else SHIPPED[pr.MODEL_FILE]
    if args.plants and args.out is None:
        ap.error("--plants: say where the model goes with --out")
    out_file = args.out or MODELS_DIR / pr.MODEL_FILE
    if not args.runs:
        ap.error("--runs: the development run folders (population.py --runs DIR)")
    vary = VARY if not args.vary else {
        name: [float(v) for v in values.split(",")]
        for name, _, values in (spec.partition("=") for spec in args.vary)}
    t0 = time.time()
    runs, plants = [], []
    for family, seeds in plants_of.items():
        params = tp.segment_params(args.recipe_dir / f"{family}.yaml")
        for seed in seeds:
            found = [r / family / f"seed-{seed}" for r in args.runs
                     if (r / family / f"seed-{seed}" / "mesh.npz").exists()]
            if not found:
                ap.error(f"{family} seed {seed}: no <runs>/{family}/seed-{seed}/mesh.npz")
            d = plant_pairs(found[0], params, args.cache)
            varied = [plant_pairs(found[0], {**params, name: value}, args.cache)
                      for name, values in vary.items() for value in values]
            d = {**d, **{f"varied_{k}": np.concatenate(
                [v[f"{s}_{k}"] for v in varied for s in ("rules", "judged")]
                or [d[f"rules_{k}"][:0]]) for k in ("features", "classes")}}
            runs.append(found[0])
            plants.append(d)
            print(f"{family} {seed}: pairs rules {len(d['rules_classes'])} "
                  f"({int(d['rules_classes'].sum())} one leaf), judged "
                  f"{len(d['judged_classes'])} ({int(d['judged_classes'].sum())}) "
                  f"({time.time() - t0:.0f} s)", flush=True)
    booster = train(plants)
    pc.save_model(booster, training_config(plants_of, vary), out_file, pr.FEATURE_NAMES,
                  ("two", "one"))
    print(f"model written to {out_file} ({time.time() - t0:.0f} s)")
    if args.loo:
        text = "## Leave one plant out\n\n" + held_out(runs, plants, args.recipe_dir,
                                                       args.cache / "loo")
        print(text)
        if args.report:
            args.report.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

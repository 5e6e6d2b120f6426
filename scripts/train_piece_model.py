"""Train the piece judge of ``curvature-regions`` (``judge_pieces``) on development plants.

    python scripts/train_piece_model.py [--model piece_model.json.gz] [--runs DIR ...]
        [--plants dicot=0-7 --plants branched=0-2 ...] [--out FILE] [--loo] [--validate]
        [--report FILE]

``--model`` names one of the models shipped in ``plantscan_leaves/models`` (``SHIPPED``:
the file and the plants it is trained on; default the dicot model, ``pc.MODEL_FILE``) and
retrains it into the package; ``--plants`` (repeated, one family each) trains on other
plants (then ``--out`` says where the model goes).

The plants are ``benchmarks/population.py``'s run folders of development seeds (< 1000;
validation seeds are never trained on): ``population.py --families dicot --seeds 0-7
--runs DIR`` makes them (paper-72, 1296x864, the family recipe's 512^3 hull) as
``DIR/<family>/seed-<n>``, each with its ``mesh.npz`` and the scan's truth; ``--runs``
(repeated) lists the folders to look in, first match wins.  For every plant its family
recipe's ``curvature-regions`` rules (``--recipe-dir``, default ``recipes/``) segment the
mesh (judge off) and every numbered leaf (a piece) gets its features
(``plantscan_leaves.pieces``) and a class from the truth, by
``plantscan_leaves.evaluate.match_leaves`` (how ``plantscan evaluate`` pairs leaves):

* ``leaf``: the piece is paired with a truth leaf (its main match);
* ``join``: unpaired, lying mostly on leaf surface (``lies_on`` leaf >= ``ON_LEAF_SHARE``),
  and its partner (the piece the judge would join it to) belongs to the same truth leaf
  (paired with it, or its own unpaired fragment): a split piece, or a crumb of a leaf,
  that joining puts back where it belongs;
* ``debris``: every other unpaired piece (phantom volume, stem, a fragment whose
  partner is another leaf: joining it there would spoil that leaf).

A LightGBM multiclass booster (``BOOSTER_PARAMS``, small trees: eight plants give about
160 pieces) is trained on all pieces and written with its training configuration and the
hash of it (``training_config``): the test checks that every shipped model records this
script's configuration for it.  Everything is seeded and deterministic: the same runs give
the same file.  ``--loo`` also judges every plant with a model trained on the others
(leave one plant out), ``--validate`` every family with a model trained on the other
families (leave one family out); both tabulate the rules against the judged labels per
family, measured and evaluated as ``benchmarks/leaf_population.py`` does.  Per-plant
pieces are cached under ``--cache``.
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

from plantscan_leaves import pieces as pc  # noqa: E402

ON_LEAF_SHARE = 0.5  # an unpaired piece mostly on leaf surface may be a leaf's fragment
BOOSTER_PARAMS = dict(objective="multiclass", num_class=3, learning_rate=0.1, num_leaves=4,
                      min_data_in_leaf=20, feature_fraction=0.8, bagging_fraction=0.8,
                      bagging_freq=1, lambda_l2=1.0, num_threads=1, verbose=-1, seed=0,
                      deterministic=True, force_row_wise=True)
ROUNDS = 100
TRAINING = {  # what every model is trained with (the plants and recipes: training_config)
    "family": "dicot",
    "seeds": list(range(30)),
    "population": "benchmarks/population.py paper-72 1296x864, recipes/dicot.yaml 512^3",
    "labels": "match_leaves: paired leaf; unpaired on leaf with partner of the same truth "
              f"leaf join (lies_on leaf >= {ON_LEAF_SHARE}); else debris",
    "booster": BOOSTER_PARAMS,
    "rounds": ROUNDS,
    "features": list(pc.FEATURE_NAMES),
    "join_reach_units": pc.JOIN_REACH_UNITS,
}
ALL_MODEL_FILE = "piece_model_all.json.gz"
GRASS_MODEL_FILE = "piece_model_grass.json.gz"  # the pieces of the grass rules + stem judge
# every model shipped in plantscan_leaves/models and the development plants it is trained
# on (the recipes name them with segment_mesh.params.piece_model; the test checks each)
SHIPPED = {
    pc.MODEL_FILE: {"dicot": list(range(30))},
    ALL_MODEL_FILE: {"dicot": list(range(8)), "branched": list(range(3)),
                     "grass": list(range(3))},
    GRASS_MODEL_FILE: {"grass": list(range(30))},
}
MODELS_DIR = REPO / "plugins" / "plantscan_leaves" / "models"


def training_config(plants: dict[str, list[int]]) -> dict:
    """The configuration a model trained on ``plants`` ({family: seeds}) records.  One
    family: ``TRAINING`` with its family and seeds (the shipped dicot model's form);
    several: ``plants`` in their place."""
    if len(plants) == 1:
        ((family, seeds),) = plants.items()
        return {**TRAINING, "family": family, "seeds": list(seeds),
                "population": TRAINING["population"].replace("recipes/dicot.yaml",
                                                             f"recipes/{family}.yaml")}
    config = {k: v for k, v in TRAINING.items() if k not in ("family", "seeds")}
    return {**config, "plants": {f: list(s) for f, s in plants.items()},
            "population": TRAINING["population"].replace("recipes/dicot.yaml",
                                                         "recipes/<family>.yaml")}


def trained_seeds(config: dict) -> dict[str, list[int]]:
    """{family: seeds} a model's recorded configuration was trained on."""
    return config.get("plants") or {config["family"]: config["seeds"]}


class _Recorder:
    """A piece "model" that keeps the pieces it is shown (and calls every one a leaf)."""

    def __init__(self) -> None:
        self.pieces: pc.Pieces | None = None

    def probabilities(self, pieces: pc.Pieces) -> np.ndarray:
        self.pieces = pieces
        prob = np.zeros((len(pieces.area), 3))
        prob[:, pc.LEAF] = 1.0
        return prob


def segment_params(recipe: Path) -> dict:
    from plantscan_core.recipe import read_recipe_file

    sm = read_recipe_file(recipe)["segment_mesh"]
    if sm["plugin"] != "curvature-regions":
        raise SystemExit(f"{recipe}: segment_mesh is {sm['plugin']}, not curvature-regions")
    return dict(sm.get("params") or {})


def truth_dir_of(run_dir: Path) -> Path:
    info = json.loads((run_dir / "run.json").read_text())
    record = info.get("scan_record") or {}
    return Path(info.get("scan") or record.get("path", "")) / "ground_truth"


def piece_classes(labelled, partner: np.ndarray, truth_dir: Path) -> np.ndarray:
    """(n,) class of every piece from the truth (the module docstring's rules)."""
    from plantscan_leaves.evaluate import match_leaves

    with np.load(truth_dir / "plant.npz") as z:
        m = match_leaves(labelled, z["vertices"], z["faces"], z["face_leaf_id"])
    labels = m["measured_labels"]
    col = {lab: j for j, lab in enumerate(labels)}
    cover = np.asarray(m["cover"]) if m.get("cover") else np.zeros((0, len(labels)))
    paired = {mm: t for t, mm, _ in m["pairs"]}

    def truth_of(lab: int):
        if lab in paired:
            return paired[lab]
        j = col.get(lab)
        if j is None or not len(cover) or cover[:, j].max() <= 0:
            return None
        return m["truth_ids"][int(np.argmax(cover[:, j]))]

    out = np.full(len(labels), pc.DEBRIS, np.int64)
    for lab in labels:
        i = lab - 1
        if lab in paired:
            out[i] = pc.LEAF
        elif (m["lies_on"].get(lab, {}).get("leaf", 0.0) >= ON_LEAF_SHARE and partner[i] > 0
              and truth_of(lab) is not None and truth_of(int(partner[i])) == truth_of(lab)):
            out[i] = pc.JOIN
    return out


def plant_pieces(run_dir: Path, params: dict, cache: Path) -> dict:
    """The rules' labels, pieces and truth classes of one run (cached per mesh and params)."""
    from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves

    from plantscan_core.data import Mesh

    mesh_file = run_dir / "mesh.npz"
    key = hashlib.sha256(json.dumps([str(mesh_file), mesh_file.stat().st_size,
                                     mesh_file.stat().st_mtime, params,
                                     list(pc.FEATURE_NAMES), pc.JOIN_REACH_UNITS,
                                     ON_LEAF_SHARE]).encode()).hexdigest()[:16]
    path = cache / f"{run_dir.parent.name}-{run_dir.name}-{key}.npz"
    if path.exists():
        return dict(np.load(path))
    mesh = Mesh.load(mesh_file)
    labelled, _ = segment_leaves(mesh, CurvatureRegionsParams(**{**params,
                                                                 "judge_pieces": False}))
    rec = _Recorder()  # the same rules again, to see the pieces the judge is shown
    segment_leaves(mesh, CurvatureRegionsParams(**{**params, "judge_pieces": True}),
                   piece_model=rec)
    pieces = rec.pieces
    classes = piece_classes(labelled, pieces.partner, truth_dir_of(run_dir))
    d = dict(labels=labelled.face_labels, features=pieces.features, partner=pieces.partner,
             area=pieces.area, classes=classes)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **d)
    return d


def cached_run(run_dir: Path, sections: dict, cache: Path, config: dict) -> tuple[Path, Path]:
    """Where a training script caches one run's rows, and the folder its labels, traits
    and evaluation go to: keyed by the mesh file, the recipe sections and the script's
    training configuration (``config``)."""
    mesh_file = run_dir / "mesh.npz"
    key = hashlib.sha256(json.dumps([str(mesh_file), mesh_file.stat().st_size,
                                     mesh_file.stat().st_mtime, sections,
                                     config]).encode()).hexdigest()[:16]
    path = cache / f"{run_dir.parent.name}-{run_dir.name}-{key}.npz"
    return path, cache / path.stem


def segment_measure_evaluate(run_dir: Path, sections: dict, out: Path, views: int | None = None):
    """The recipe ``sections``' ``segment_mesh`` and ``measure`` on a run's ``mesh.npz``,
    the labels and traits saved in ``out`` and evaluated against the scan's truth:
    (mesh, labelled, traits, measurements, evaluation)."""
    import population as pop
    from plantscan_leaves.measure import measure_plant

    from plantscan_core.api import build_stage
    from plantscan_core.data import Mesh

    mesh = Mesh.load(run_dir / "mesh.npz")
    seg = build_stage("mesh_segmenter", sections["segment_mesh"]["plugin"],
                      sections["segment_mesh"].get("params") or {})
    mea = build_stage("measurer", sections["measure"]["plugin"],
                      sections["measure"].get("params") or {})
    labelled = seg.segment(mesh)
    traits, measurements, _ = measure_plant(labelled, mea.params, views)
    out.mkdir(parents=True, exist_ok=True)
    labelled.save(out / "labelled.npz")
    traits.save(out / "traits.csv", out / "plant_traits.json")
    evaluation = pop.evaluate_plant(out, truth_dir_of(run_dir))
    (out / "evaluation.json").write_text(json.dumps(evaluation, indent=1, default=str))
    return mesh, labelled, traits, measurements, evaluation


def fit_booster(plants: list[dict], feature_names, params: dict, rounds: int):
    """LightGBM on the plants' ``features`` rows and ``classes`` (every training script's
    fit: the same data in the same order, so a model is reproducible to the byte)."""
    import lightgbm as lgb

    x = np.vstack([d["features"] for d in plants]).astype(np.float64)
    y = np.concatenate([d["classes"] for d in plants])
    return lgb.train(params, lgb.Dataset(x, y, feature_name=list(feature_names)), rounds)


def train(plants: list[dict]):
    # unweighted: balancing the classes (weights 1/frequency, or its square root) made the
    # rare ones take real leaves (leave one plant out, dev seeds 0-7: 5-9 leaves lost, not 2)
    return fit_booster(plants, pc.FEATURE_NAMES, BOOSTER_PARAMS, ROUNDS)


def evaluate_labels(run_dir: Path, labels_verdict: pc.Verdict, out: Path, measure_params):
    """Measure + evaluate one plant with the given labels (leaf_population's way)."""
    import population as pop
    from plantscan_leaves.measure import measure_plant

    from plantscan_core.data import Mesh

    mesh = Mesh.load(run_dir / "mesh.npz")
    labelled = pc.verdict_labelled(mesh, labels_verdict)
    info = json.loads((run_dir / "run.json").read_text())
    traits, _, _ = measure_plant(labelled, measure_params,
                                 (info.get("scan_record") or {}).get("views"))
    out.mkdir(parents=True, exist_ok=True)
    labelled.save(out / "labelled.npz")
    traits.save(out / "traits.csv", out / "plant_traits.json")
    truth = truth_dir_of(run_dir)
    evaluation = pop.evaluate_plant(out, truth)
    seed = int(run_dir.name.split("-")[1])
    key = pop.PlantKey(run_dir.parent.name, seed)
    return pop.plant_row(key, evaluation, truth, None), pop.leaf_rows(key, evaluation)


def held_out(runs: list[Path], plants: list[dict], groups: list, recipe_dir: Path,
             work: Path) -> str:
    """Markdown: per family, the rules and the judge trained without each plant's group
    (``groups``: one key per plant; a plant's own index leaves one plant out, its family
    one family out), measured and evaluated."""
    import population as pop
    from plantscan_leaves.measure import LeafGeometryParams

    from plantscan_core.recipe import read_recipe_file

    rows: dict[str, dict[str, tuple[list, list]]] = {}
    per_plant = []
    boosters = {g: train([p for p, h in zip(plants, groups) if h != g])
                for g in dict.fromkeys(groups)}
    for run_dir, d, g in zip(runs, plants, groups):
        family = run_dir.parent.name
        mp = LeafGeometryParams(**(read_recipe_file(recipe_dir / f"{family}.yaml")["measure"]
                                   .get("params") or {}))
        pieces = pc.Pieces(d["features"], d["partner"], d["area"])
        prob = np.asarray(boosters[g].predict(d["features"].astype(np.float64),
                                              num_threads=1))
        judged = pc.apply_verdict(d["labels"], pieces, prob.reshape(len(d["area"]), -1))
        n = len(d["area"])  # the rules alone (apply_verdict would apply its thickness rule)
        rules = pc.Verdict(d["labels"], n, False, np.full(n, pc.LEAF), {})
        fam_rows = rows.setdefault(family, {"rules": ([], []), "judged": ([], [])})
        for name, verdict in (("rules", rules), ("judged", judged)):
            prow, lrows = evaluate_labels(run_dir, verdict,
                                          work / name / family / run_dir.name, mp)
            fam_rows[name][0].append(prow)
            fam_rows[name][1].extend(lrows)
        truth = d["classes"]
        per_plant.append(f"{family} {run_dir.name}: {len(truth)} pieces (truth leaf/join/"
                         f"debris {np.bincount(truth, minlength=3).tolist()}), judged "
                         f"{np.bincount(judged.verdict, minlength=3).tolist()}, "
                         f"right {int((judged.verdict == truth).sum())}")
        print(per_plant[-1], flush=True)
    out = []
    for family, fam_rows in rows.items():
        for name, (prows, lrows) in fam_rows.items():
            out += [f"### {family}: {name}", "", pop.tabulate(prows, lrows), ""]
    return "\n".join(out + ["", *per_plant])


def parse_plants(specs: list[str]) -> dict[str, list[int]]:
    """``["dicot=0-7", "grass=0-2"]`` -> {family: seeds}."""
    import population as pop

    out = {}
    for spec in specs:
        family, sep, seeds = spec.partition("=")
        if not sep or family not in pop.FAMILIES:
            raise SystemExit(f"--plants {spec!r}: FAMILY=SEEDS with FAMILY one of "
                             f"{', '.join(pop.FAMILIES)}")
        out[family] = pop.parse_seeds(seeds)
        if any(s >= 1000 for s in out[family]):
            raise SystemExit(f"--plants {spec!r}: seeds >= 1000 are validation seeds, never "
                             "trained on")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, action="append", default=[],
                    help="a folder of <family>/seed-<n> run folders (repeat: first match "
                         "wins; default /work/cache/leavesd/dev-runs)")
    ap.add_argument("--model", default=pc.MODEL_FILE, choices=sorted(SHIPPED),
                    help="the shipped model to retrain (its plants: SHIPPED)")
    ap.add_argument("--plants", action="append", default=[], metavar="FAMILY=SEEDS",
                    help="train on these plants instead (repeat per family; needs --out)")
    ap.add_argument("--recipe-dir", type=Path, default=REPO / "recipes",
                    help="the family recipes whose rules make the pieces (<family>.yaml)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/plantscan-piece-training"))
    ap.add_argument("--out", type=Path, default=None,
                    help="where the model goes (default: --model's file in the package)")
    ap.add_argument("--loo", action="store_true", help="also leave one plant out")
    ap.add_argument("--validate", action="store_true",
                    help="also leave one family out (train on the others, judge it)")
    ap.add_argument("--report", type=Path, default=None,
                    help="write the --loo / --validate tables here")
    args = ap.parse_args(argv)
    if args.plants and args.out is None:
        ap.error("--plants: say where the model goes with --out (the shipped models are "
                 "trained on SHIPPED's plants)")
    plants_of = parse_plants(args.plants) if args.plants else SHIPPED[args.model]
    out_file = args.out or MODELS_DIR / args.model
    if any(s >= 1000 for seeds in plants_of.values() for s in seeds):
        ap.error("validation seeds (>= 1000) are never trained on")
    roots = args.runs or [Path("/work/cache/leavesd/dev-runs")]
    t0 = time.time()
    runs, plants = [], []
    for family, seeds in plants_of.items():
        params = segment_params(args.recipe_dir / f"{family}.yaml")
        for seed in seeds:
            found = [r / family / f"seed-{seed}" for r in roots
                     if (r / family / f"seed-{seed}" / "mesh.npz").exists()]
            if not found:
                ap.error(f"{family} seed {seed}: no <runs>/{family}/seed-{seed}/mesh.npz "
                         f"(population.py --families {family} --seeds {seed} --runs DIR "
                         "makes it)")
            d = plant_pieces(found[0], params, args.cache)
            runs.append(found[0])
            plants.append(d)
            print(f"{family} {seed}: {len(d['classes'])} pieces, leaf/join/debris "
                  f"{np.bincount(d['classes'], minlength=3).tolist()} "
                  f"({time.time() - t0:.0f} s)", flush=True)
    booster = train(plants)
    pc.save_model(booster, training_config(plants_of), out_file)
    print(f"model written to {out_file} ({time.time() - t0:.0f} s)")
    texts = []
    if args.loo:
        texts += ["## Leave one plant out", "",
                  held_out(runs, plants, list(range(len(runs))), args.recipe_dir,
                           args.cache / "loo")]
    if args.validate:
        texts += ["## Leave one family out", "",
                  held_out(runs, plants, [r.parent.name for r in runs], args.recipe_dir,
                           args.cache / "lofo")]
    if texts:
        print("\n".join(texts))
        if args.report:
            args.report.write_text("\n".join(texts) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Population benchmark: accuracy over many virtual plants per family, the figure that counts.

For each family, N plants from **validation seeds** (>= 1000; seeds below 1000
are for development and tuning) are scanned with a protocol at a lab image
size, processed with the family's shipped recipe (one recipe per family, no
per-plant setting) and evaluated against the virtual scanner's truth::

    python benchmarks/population.py                    # 5 families x 10 plants, paper-72,
                                                       # 1296x864, recipes' 512^3 hull
    python benchmarks/population.py --families dicot,grass --n 5 --protocol paper-360
    python benchmarks/population.py --seeds 1000-1004 --size 5184x3456 --out /tmp/p.md
    python benchmarks/population.py --recipe-dir my-recipes/ --seeds 0-9   # tuning (dev)

It writes a table per family (``--out``, default ``docs/benchmarks/population.md``)
with one line per plant in a CSV beside it, and one line per matched leaf in
``<runs>/leaves.csv``.  Renders are cached under ``--cache`` (default
``/work/cache/population``, outside the repository, shared by everyone who
benchmarks): one scan per (family, seed, protocol, size, rig, age), written to a
temporary folder and renamed when complete, so a reader never sees half a scan.

**Calibration once per session.** A lab calibrates its rig once per session, not
per plant: the board is rendered once per (rig, protocol, image size), the
recipe's calibrator calibrates it, and every plant is processed with that
calibration (``plantscan process --calibration``); plant scans hold background
and plant views only.  ``--calibrate-each`` renders the board with every plant
and calibrates per plant instead.

Another script can call the pieces: ``scan_plant`` (make or reuse a cached scan),
``session_calibration``, ``process_plant`` (a scan + a recipe -> a run dir),
``evaluate_plant`` (run dir -> the evaluation and one flat row),
``run_population`` and ``tabulate``.
"""

from __future__ import annotations

import argparse
import copy
import csv
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FAMILIES = ("dicot", "rosette", "branched", "grass", "seedling")
DEFAULT_CACHE = Path(os.environ.get("PLANTSCAN_POPULATION_CACHE", "/work/cache/population"))
DEFAULT_SIZE = (1296, 864)
VALIDATION_SEED0 = 1000
# scan-section changes that make a protocol from the recipes' paper-72 (docs/virtual-scanner.md)
PROTOCOLS: dict[str, dict[str, Any]] = {
    "paper-72": {"protocol": "paper-72", "tilts_deg": [0.0]},
    "paper-360": {"protocol": "paper-360", "tilts_deg": [-10.0, 0.0, 10.0, 20.0, 30.0]},
}
TRAITS = ("length", "width", "area", "perimeter")
PLANT_TRAITS = ("height_mm", "leaf_count", "total_leaf_area_mm2")
# issue #22 judges the rosette, branched and seedling families over the truth leaves at
# least this long: the counts are given over them too (a 5 mm rosette leaf just appearing
# is below what a lab measures)
COUNTED_LEAF_MM = 15.0


@dataclass(frozen=True)
class PlantKey:
    """One cached scan: a seeded plant of a family, scanned with a protocol at an image size."""

    family: str
    seed: int
    protocol: str = "paper-72"
    size: tuple[int, int] = DEFAULT_SIZE
    age: float | None = None

    def label(self) -> str:
        age = "" if self.age is None else f"-age{self.age:g}"
        return f"seed-{self.seed}{age}"


# --------------------------------------------------------------------------- recipes
def recipe_path(family: str, recipe_dir: Path | None = None) -> Path:
    """The recipe of ``family``: ``<recipe_dir>/<family>.yaml`` or the shipped one."""
    path = Path(recipe_dir or REPO / "recipes") / f"{family}.yaml"
    if not path.exists():
        raise SystemExit(f"{path}: no recipe for family {family!r}")
    return path


def scan_raw(key: PlantKey, recipe: Path, roles: Sequence[str]) -> dict[str, Any]:
    """The raw recipe the scan of ``key`` is made with (the family recipe's scan section)."""
    from plantscan_sim.api import scan_recipe

    if key.protocol not in PROTOCOLS:
        raise SystemExit(f"--protocol {key.protocol!r}: valid: {', '.join(PROTOCOLS)}")
    proto = PROTOCOLS[key.protocol]
    raw = scan_recipe(key.family, recipe=recipe, image_size=key.size, seed=key.seed,
                      tilts_deg=proto["tilts_deg"], roles=roles,
                      scene={"age": key.age} if key.age is not None else None)
    raw["scan"]["protocol"] = proto["protocol"]
    if len(proto["tilts_deg"]) > 1 and not raw["scan"].get("tilt_arm"):
        raw["scan"]["tilt_arm"] = {"plugin": "sim", "params": {"axis": "tilt"}}
    return raw


def rig_hash(raw: dict[str, Any]) -> str:
    """A short hash of what the images depend on apart from the seed (rig, board, pot,
    lights, protocol, size, and the generators' ``GENERATOR_VERSION``): scans with equal
    hashes share a session calibration."""
    scan = copy.deepcopy(raw["scan"])
    params = dict(scan.get("scene", {}).get("params") or {})
    for k in ("preset", "seed", "age"):
        params.pop(k, None)
    scan["scene"]["params"] = params
    scan.pop("roles", None)
    from plantscan_sim.families import GENERATOR_VERSION

    if GENERATOR_VERSION != 1:  # version 1 renders were cached before the version existed
        scan["generator_version"] = GENERATOR_VERSION
    text = json.dumps(scan, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def _atomic_dir(final: Path, build) -> Path:
    """Run ``build(tmp)`` into a temporary sibling of ``final``, then rename it into place."""
    if final.exists():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        build(tmp)
        os.rename(tmp, final)
    except OSError:
        if final.exists():  # another process finished the same scan first: keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
            return final
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _scan_into(raw: dict[str, Any], folder: Path) -> None:
    from plantscan_sim.api import sim_manager

    from plantscan_core.acquire import acquire
    from plantscan_core.recipe import PROCESSING_SECTIONS, validate_recipe

    manager = sim_manager()
    scan_only = {k: v for k, v in raw.items() if k not in PROCESSING_SECTIONS and k != "export"}
    recipe = validate_recipe(scan_only, manager.registry, "population scan recipe")
    t0, c0 = time.perf_counter(), time.process_time()
    acquire(recipe, folder / "scan", manager, raw_recipe=raw)
    (folder / "done.json").write_text(json.dumps({
        "render_wall_s": time.perf_counter() - t0, "render_cpu_s": time.process_time() - c0,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}))


def scan_plant(key: PlantKey, recipe_dir: Path | None = None, cache: Path = DEFAULT_CACHE,
               with_board: bool = False) -> Path:
    """The scan folder of ``key`` (rendered once, then reused from ``cache``).

    Without ``with_board`` the scan holds background and plant views (the session
    calibration comes from ``session_calibration``); with it, board views too.
    """
    roles = ["calibration", "background", "plant"] if with_board else ["background", "plant"]
    raw = scan_raw(key, recipe_path(key.family, recipe_dir), roles)
    w, h = key.size
    where = (cache / key.family / f"{key.protocol}-{w}x{h}-{rig_hash(raw)}"
             / (key.label() + ("-board" if with_board else "")))
    return _atomic_dir(where, lambda tmp: _scan_into(raw, tmp)) / "scan"


def session_calibration(family: str, protocol: str = "paper-72",
                        size: tuple[int, int] = DEFAULT_SIZE, recipe_dir: Path | None = None,
                        cache: Path = DEFAULT_CACHE) -> Path:
    """``calibration.yaml`` of the family rig's session: its board rendered once, calibrated
    with the recipe's calibrator (cached per rig and calibrator settings)."""
    from plantscan_core.plugins import get_manager
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.scanfolder import ScanFolder
    from plantscan_core.stages import StageContext

    path = recipe_path(family, recipe_dir)
    key = PlantKey(family, 0, protocol, size)
    raw = scan_raw(key, path, ["calibration"])
    w, h = size
    rig = cache / "sessions" / f"{protocol}-{w}x{h}-{rig_hash(raw)}"
    board = _atomic_dir(rig / "board", lambda tmp: _scan_into(raw, tmp)) / "scan"
    cal_key = hashlib.sha256(json.dumps(raw.get("calibrate"), sort_keys=True).encode()
                             ).hexdigest()[:8]

    def calibrate(tmp: Path) -> None:
        manager = get_manager()
        recipe = validate_recipe(copy.deepcopy(raw), manager.registry, str(path))
        scan = ScanFolder.open(board)
        calibrator = manager.build("calibrator", recipe.calibrate.plugin,
                                   recipe.calibrate.params, StageContext(recipe=recipe, scan=scan))
        tmp.mkdir(parents=True)
        calibrator.calibrate(scan).save(tmp / "calibration.yaml")

    return _atomic_dir(rig / f"calibration-{cal_key}", calibrate) / "calibration.yaml"


# --------------------------------------------------------------------------- process
def process_plant(scan: Path, recipe: Path, run_dir: Path, calibration: Path | None = None,
                  overrides: Sequence[str] = (), fresh: bool = True) -> dict[str, Any]:
    """Process ``scan`` with ``recipe`` (+ ``overrides``) into a fresh ``run_dir`` (or, without
    ``fresh``, into the run folder as it is: the stages whose inputs, code and parameters did
    not change are taken from its cache, e.g. the hull when only leaf parameters changed).

    Returns ``{"wall_s", "cpu_s", "stages_s"}`` of ``process()`` itself (in this
    process: the compiled kernels are warm after the first plant).
    """
    from plantscan_core.pipeline import process
    from plantscan_core.plugins import get_manager
    from plantscan_core.recipe import apply_overrides, read_recipe_file, validate_recipe

    manager = get_manager()
    raw = apply_overrides(read_recipe_file(recipe), list(overrides))
    rec = validate_recipe(raw, manager.registry, str(recipe))
    if fresh and run_dir.exists():
        shutil.rmtree(run_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    result = process(scan, rec, run_dir, manager, raw_recipe=raw, overrides=list(overrides),
                     calibration_path=calibration)
    info = result.info
    return {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
            "stages_s": {k: v for k, v in info.get("timings_s", {}).items() if k != "total"}}


def evaluate_plant(run_dir: Path, truth_dir: Path) -> dict[str, Any]:
    """``plantscan evaluate`` of one run (every plugin's section)."""
    from plantscan_core.plugins import get_manager

    return get_manager().evaluate(run_dir, truth_dir)


def plant_row(key: PlantKey, evaluation: dict[str, Any], truth_dir: Path,
              timing: dict[str, Any] | None, error: str | None = None,
              run_dir: Path | None = None) -> dict[str, Any]:
    """One flat CSV row: counts, ε per trait over the plant's pairs, plant-level errors
    (and the run's plant quality flag when ``run_dir`` is given)."""
    truth = json.loads((truth_dir / "plant_traits.json").read_text())
    organs = json.loads((truth_dir / "organs.json").read_text()) \
        if (truth_dir / "organs.json").exists() else {}
    scene = (truth_dir / "scene.yaml")
    import yaml

    plant_info = (yaml.safe_load(scene.read_text()) or {}).get("plant", {}) if scene.exists() \
        else {}
    row: dict[str, Any] = {
        "family": key.family, "seed": key.seed, "protocol": key.protocol,
        "size": f"{key.size[0]}x{key.size[1]}", "age_days": plant_info.get("age_days"),
        "variant": plant_info.get("variant"), "truth_leaves": truth.get("leaf_count"),
        "height_truth_mm": truth.get("height_mm"),
        "crossings_truth": plant_info.get("crossings"), "error": error or "",
        "kinds": ",".join(sorted({lf["kind"] for lf in organs.get("leaves", [])})),
    }
    lengths = _truth_lengths(truth_dir)
    row["truth_leaves_15mm"] = sum(1 for x in lengths.values() if x >= COUNTED_LEAF_MM)
    t = evaluation.get("traits")
    if t is None:
        row.update(found=0, measured=0, missed=truth.get("leaf_count"), merged=0, split=0,
                   split_pieces=0, extra=0, debris_area_mm2=0.0, debris_share=0.0,
                   found_15mm=0, measured_15mm=0)
        return row
    inst = t["instances"]
    row.update({k: inst[k] for k in ("found", "measured", "missed", "merged", "split",
                                      "split_pieces", "extra", "recall", "precision",
                                      "debris_area_mm2", "debris_share")})
    row.update(_counts_over_long_leaves(t, lengths))
    measured_plant = run_dir / "plant_traits.json" if run_dir is not None else None
    if measured_plant is not None and measured_plant.exists():
        m = json.loads(measured_plant.read_text())
        row["quality_flag"] = m.get("quality_flag") or ""
        row["quality_reasons"] = "; ".join(m.get("quality_reasons") or [])
    for name in TRAITS:
        row[f"eps_{name}"] = t["mean_relative_error"].get(name)
    for name in PLANT_TRAITS:
        p = (t.get("plant") or {}).get(name)
        row[f"{name}_measured"] = None if p is None else p["measured"]
        row[f"{name}_rel_error"] = None if p is None else p["relative_error"]
    row["leaves_warned"] = t.get("leaves_warned")
    # what the earlier stages left: silhouettes, phantom volume of the hull, calibration
    sil, hull = evaluation.get("silhouettes") or {}, evaluation.get("hull") or {}
    row["silhouette_iou_mean"] = (sil.get("iou") or {}).get("mean")
    row["hull_phantom_voxels"] = hull.get("hull_to_truth_mean_voxels")
    row["hull_leaves_lost"] = hull.get("leaves_lost")
    cal = (evaluation.get("calibration") or {}).get("camera_centre_error_mm") or {}
    row["camera_centre_error_mm"] = cal.get("mean")
    if timing:
        row["process_wall_s"] = round(timing["wall_s"], 2)
        row["process_cpu_s"] = round(timing["cpu_s"], 2)
    return row


def _truth_lengths(truth_dir: Path) -> dict[int, float]:
    from plantscan_core.data import Traits

    path = truth_dir / "traits.csv"
    return {lf.leaf_id: lf.length_mm for lf in Traits.load(path).leaves} if path.exists() \
        else {}


def _counts_over_long_leaves(traits: dict[str, Any], lengths: dict[int, float]
                             ) -> dict[str, int]:
    """Found and measured leaves counting only truth leaves >= ``COUNTED_LEAF_MM`` long.

    A measured leaf paired with a shorter truth leaf, or a split piece of one (and
    paired with no long leaf), is left out of the measured count; extra pieces stay in.
    """
    short = {tid for tid, x in lengths.items() if x < COUNTED_LEAF_MM}
    pairs = [(p["truth_id"], p["measured_id"]) for p in traits.get("pairs", [])]
    paired_long = {m for tid, m in pairs if tid not in short}
    of_short = {m for tid, m in pairs if tid in short}
    for tid, labels in (traits["instances"].get("split_ids") or {}).items():
        if int(tid) in short:
            of_short.update(labels)
    return {"found_15mm": len(paired_long),
            "measured_15mm": traits["instances"]["measured"] - len(of_short - paired_long)}


def leaf_rows(key: PlantKey, evaluation: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per matched leaf: truth and measured traits, signed relative errors."""
    t = evaluation.get("traits") or {}
    out = []
    for r in t.get("per_leaf", []):
        row = {"family": key.family, "seed": key.seed, "truth_id": r["truth_id"],
               "measured_id": r["measured_id"], "thick_share": r.get("thick_share")}
        for name in TRAITS:
            tv, mv = r[f"{name}_truth"], r[f"{name}_measured"]
            row[f"{name}_truth"], row[f"{name}_measured"] = tv, mv
            row[f"{name}_rel_error"] = (mv - tv) / tv if tv else None
        out.append(row)
    return out


# --------------------------------------------------------------------------- population
def parse_seeds(text: str) -> list[int]:
    """``"1000-1009"`` or ``"1000,1003,1007"`` (or a mix) -> seeds."""
    seeds: list[int] = []
    for part in text.split(","):
        if "-" in part.strip()[1:]:
            a, b = part.split("-", 1)
            seeds += list(range(int(a), int(b) + 1))
        elif part.strip():
            seeds.append(int(part))
    return seeds


def run_population(families: Sequence[str], seeds: Sequence[int] | dict[str, Sequence[int]],
                   protocol: str = "paper-72",
                   size: tuple[int, int] = DEFAULT_SIZE, *, resolution: int | None = None,
                   recipe_dir: Path | None = None, runs: Path, cache: Path = DEFAULT_CACHE,
                   calibrate_each: bool = False, overrides: Sequence[str] = (),
                   reuse_runs: bool = False, reuse_hulls: bool = False,
                   log=print) -> tuple[list[dict], list[dict]]:
    """Scan (cached), process and evaluate every (family, seed); (plant rows, leaf rows).

    A plant whose processing fails is a row with ``error`` set and every truth
    leaf missed (it counts against recall); the run goes on.  ``reuse_runs``
    takes a plant's finished run folder as it is (its evaluation.json and
    run.json timings) instead of processing it again: to re-tabulate; ``reuse_hulls``
    processes it again in place, recomputing only the stages that changed (new leaf
    parameters: the mesh segmentation and what follows, not the hull).  ``seeds``
    may be a dict family -> seeds (fewer plants for a family whose renders cost more).
    """
    plants, leaves = [], []
    extra = list(overrides)
    if resolution is not None:
        extra.append(f"reconstruct.params.resolution={int(resolution)}")
    for family in families:
        recipe = recipe_path(family, recipe_dir)
        calibration = None
        if not calibrate_each:
            t0 = time.perf_counter()
            calibration = session_calibration(family, protocol, size, recipe_dir, cache)
            log(f"{family}: session calibration {calibration} ({time.perf_counter() - t0:.0f} s)")
        for seed in (seeds.get(family, ()) if isinstance(seeds, dict) else seeds):
            key = PlantKey(family, int(seed), protocol, tuple(size))
            t0 = time.perf_counter()
            scan = scan_plant(key, recipe_dir, cache, with_board=calibrate_each)
            t_scan = time.perf_counter() - t0
            run_dir = runs / family / key.label()
            truth_dir = scan / "ground_truth"
            timing, error, evaluation = None, None, {}
            done = run_dir / "evaluation.json"
            if reuse_runs and done.exists():
                evaluation = json.loads(done.read_text())
                info = json.loads((run_dir / "run.json").read_text())
                timing = {"wall_s": info["timings_s"]["total"], "cpu_s": info["cpu_s"]["total"]}
                row = plant_row(key, evaluation, truth_dir, timing, run_dir=run_dir)
                plants.append(row)
                leaves += leaf_rows(key, evaluation)
                continue
            try:
                timing = process_plant(scan, recipe, run_dir, calibration, extra,
                                       fresh=not reuse_hulls)
                evaluation = evaluate_plant(run_dir, truth_dir)
                (run_dir / "evaluation.json").write_text(json.dumps(evaluation, indent=1,
                                                                    sort_keys=True))
            except Exception as exc:  # a failed plant is a result, not the end of the run
                error = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
                log(traceback.format_exc())
            row = plant_row(key, evaluation, truth_dir, timing, error, run_dir)
            plants.append(row)
            leaves += leaf_rows(key, evaluation)
            log(f"{family} {key.label()}: scan {t_scan:.0f} s, "
                f"process {timing['wall_s'] if timing else float('nan'):.0f} s; found "
                f"{row.get('found')}/{row.get('truth_leaves')}, measured {row.get('measured')}, "
                f"merged {row.get('merged')}, split {row.get('split')}, extra {row.get('extra')}"
                f"; ε L {_pct(row.get('eps_length'))} A {_pct(row.get('eps_area'))}"
                + (f"; FAILED {error}" if error else ""))
    return plants, leaves


# --------------------------------------------------------------------------- tables
def _pct(x, nd: int = 1) -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) \
        else f"{100 * x:.{nd}f}"


def _stats(values: Sequence[float]) -> tuple[float, float, float]:
    v = np.abs(np.asarray([x for x in values if x is not None and math.isfinite(x)], float))
    if not len(v):
        return (math.nan,) * 3
    return float(v.mean()), float(np.median(v)), float(np.percentile(v, 90))


def family_summary(plants: list[dict], leaves: list[dict]) -> dict[str, Any]:
    """Population figures of one family's rows (see ``tabulate``)."""
    truth = sum(p["truth_leaves"] or 0 for p in plants)
    measured = sum(p.get("measured") or 0 for p in plants)
    found = sum(p.get("found") or 0 for p in plants)
    s: dict[str, Any] = {
        "plants": len(plants), "failed": sum(1 for p in plants if p["error"]),
        "truth": truth, "measured": measured, "found": found,
        "recall": found / truth if truth else math.nan,
        "precision": found / measured if measured else math.nan,
        **{k: sum(p.get(k) or 0 for p in plants)
           for k in ("missed", "merged", "split", "split_pieces", "extra")},
        "debris_share": (sum(p.get("debris_area_mm2") or 0 for p in plants)
                         / max(1e-9, sum((p.get("total_leaf_area_mm2_measured") or 0)
                                         for p in plants))),
        "leaves_matched": len(leaves),
    }
    truth15 = sum(p.get("truth_leaves_15mm") or 0 for p in plants)
    found15 = sum(p.get("found_15mm") or 0 for p in plants)
    measured15 = sum(p.get("measured_15mm") or 0 for p in plants)
    s.update(truth_15mm=truth15, recall_15mm=found15 / truth15 if truth15 else math.nan,
             precision_15mm=found15 / measured15 if measured15 else math.nan,
             flags={f: sum(p.get("quality_flag") == f for p in plants)
                    for f in ("ok", "check", "fail")})
    for name in TRAITS:
        errs = [lf[f"{name}_rel_error"] for lf in leaves]
        s[f"eps_{name}"] = _stats(errs)
        vals = np.abs([e for e in errs if e is not None])
        s[f"over10_{name}"] = float(np.mean(vals > 0.10)) if len(vals) else math.nan
    for name in PLANT_TRAITS:
        s[f"plant_{name}"] = _stats([p.get(f"{name}_rel_error") for p in plants])
    counts = [(p.get("leaf_count_measured"), p["truth_leaves"]) for p in plants
              if p.get("leaf_count_measured") is not None]
    s["leaf_count_exact"] = (sum(1 for m, t in counts if m == t) / len(counts)) if counts \
        else math.nan
    s["leaf_count_mean_abs"] = float(np.mean([abs(m - t) for m, t in counts])) if counts \
        else math.nan
    walls = [p["process_wall_s"] for p in plants if p.get("process_wall_s") is not None]
    cpus = [p["process_cpu_s"] for p in plants if p.get("process_cpu_s") is not None]
    for k in ("silhouette_iou_mean", "hull_phantom_voxels", "camera_centre_error_mm"):
        v = [p[k] for p in plants if p.get(k) is not None]
        s[k] = float(np.median(v)) if v else math.nan
    s["hull_leaves_lost"] = sum(p.get("hull_leaves_lost") or 0 for p in plants)
    s["wall_s"] = float(np.median(walls)) if walls else math.nan
    s["cpu_s"] = float(np.median(cpus)) if cpus else math.nan
    return s


def tabulate(plants: list[dict], leaves: list[dict]) -> str:
    """Markdown tables: instance counts, ε per trait (mean / median / p90 over all matched
    leaves of all plants), share of leaves off by more than 10 %, plant-level errors, time."""
    fams = list(dict.fromkeys(p["family"] for p in plants))
    sums = {f: family_summary([p for p in plants if p["family"] == f],
                              [lf for lf in leaves if lf["family"] == f]) for f in fams}
    out = ["| family | plants (failed) | truth leaves | measured | found (recall %) "
           "| precision % | missed | merged | split (pieces) | extra | debris % of leaf area "
           f"| leaves ≥ {COUNTED_LEAF_MM:g} mm: truth, recall %, precision % "
           "| plants ok / check / fail |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for f, s in sums.items():
        flags = s["flags"]
        out.append(f"| {f} | {s['plants']} ({s['failed']}) | {s['truth']} | {s['measured']} "
                   f"| {s['found']} ({_pct(s['recall'])}) | {_pct(s['precision'])} "
                   f"| {s['missed']} | {s['merged']} | {s['split']} ({s['split_pieces']}) "
                   f"| {s['extra']} | {_pct(s['debris_share'])} "
                   f"| {s['truth_15mm']}, {_pct(s['recall_15mm'])}, {_pct(s['precision_15mm'])} "
                   f"| {flags['ok']} / {flags['check']} / {flags['fail']} |")
    out += ["", "ε = |measured − truth| / truth over the matched leaves of all plants, %: "
            "mean / median / 90th percentile (the share of matched leaves off by more than "
            "10 % in brackets).", "",
            "| family | matched leaves | length | width | area | perimeter |",
            "|---|---|---|---|---|---|"]
    for f, s in sums.items():
        cells = [" / ".join(_pct(x) for x in s[f"eps_{n}"]) + f" ({_pct(s[f'over10_{n}'], 0)})"
                 for n in TRAITS]
        out.append(f"| {f} | {s['leaves_matched']} | " + " | ".join(cells) + " |")
    out += ["", "Plant-level errors, |relative error| %, mean / median / 90th percentile "
            "(height: the top above the pot's rim, measured and truth, where the mesher removed "
            "a pot; else the vertical extent against the truth's height from the soil); "
            "leaf count: share of plants exactly right, mean |error| in leaves; seconds per "
            "plant: processing (median wall, CPU; session calibration, renders excluded).", "",
            "| family | height | total leaf area | leaf count (exact %, mean abs) "
            "| s per plant wall (CPU) |", "|---|---|---|---|---|"]
    for f, s in sums.items():
        out.append(
            f"| {f} | " + " / ".join(_pct(x) for x in s["plant_height_mm"])
            + " | " + " / ".join(_pct(x) for x in s["plant_total_leaf_area_mm2"])
            + f" | {_pct(s['leaf_count_exact'], 0)}, {s['leaf_count_mean_abs']:.1f} "
            f"| {s['wall_s']:.1f} ({s['cpu_s']:.1f}) |")
    out += ["", "What the stages before the leaves left (medians over plants): silhouette IoU "
            "against the truth masks, the hull's mean distance to the truth surface in voxels "
            "(phantom volume: large when views cannot carve the space between leaves), truth "
            "leaves with no hull surface, camera-centre error of the session calibration.", "",
            "| family | silhouette IoU | hull → truth, voxels | leaves lost by the hull "
            "| camera centre error mm |", "|---|---|---|---|---|"]
    for f, s in sums.items():
        out.append(f"| {f} | {s['silhouette_iou_mean']:.4f} | {s['hull_phantom_voxels']:.1f} "
                   f"| {s['hull_leaves_lost']} | {s['camera_centre_error_mm']:.2f} |")
    return "\n".join(out)


def write_csv(rows: list[dict], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, cols)
        w.writeheader()
        w.writerows(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--families", default=",".join(FAMILIES),
                    help=f"comma-separated (default all: {','.join(FAMILIES)})")
    ap.add_argument("--seeds", help="e.g. 1000-1009 or 1000,1004 (default: the first --n "
                    "validation seeds from 1000)")
    ap.add_argument("--family-seeds", action="append", default=[], metavar="FAMILY=SEEDS",
                    help="seeds of one family instead of --seeds, e.g. branched=1000-1002")
    ap.add_argument("--n", type=int, default=10, help="plants per family (default 10)")
    ap.add_argument("--protocol", default="paper-72", choices=sorted(PROTOCOLS))
    ap.add_argument("--size", default="1296x864", help="image size WxH (default 1296x864)")
    ap.add_argument("--resolution", type=int, help="hull resolution (default: the recipe's)")
    ap.add_argument("--recipe-dir", type=Path, help="folder of <family>.yaml (default recipes/)")
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    metavar="PATH=VALUE", help="processing override for every plant")
    ap.add_argument("--out", type=Path, default=REPO / "docs/benchmarks/population.md",
                    help="markdown page (a CSV of one line per plant is written beside it)")
    ap.add_argument("--runs", type=Path, help="run folders and leaves.csv (default "
                    "<cache>/runs/<protocol>-<size>)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--calibrate-each", action="store_true",
                    help="render the board with every plant and calibrate per plant")
    ap.add_argument("--reuse-runs", action="store_true",
                    help="take finished run folders as they are (re-tabulate)")
    ap.add_argument("--reuse-hulls", action="store_true",
                    help="process into the existing run folders, recomputing only the stages "
                         "that changed (leaf parameters: not the hull); times then count only "
                         "those stages")
    ap.add_argument("--title", default="", help="heading of this run's section")
    args = ap.parse_args(argv)

    families = [f.strip() for f in args.families.split(",") if f.strip()]
    seeds = parse_seeds(args.seeds) if args.seeds else list(
        range(VALIDATION_SEED0, VALIDATION_SEED0 + args.n))
    w, h = (int(x) for x in args.size.lower().split("x"))
    runs = args.runs or args.cache / "runs" / f"{args.protocol}-{w}x{h}"
    per_family = {f: list(seeds) for f in families}
    for item in args.family_seeds:
        fam, _, text = item.partition("=")
        if fam.strip() not in per_family:
            ap.error(f"--family-seeds {item}: {fam.strip()!r} is not one of --families "
                     f"({', '.join(families)})")
        per_family[fam.strip()] = parse_seeds(text)
    dev = [s for v in per_family.values() for s in v if s < VALIDATION_SEED0]
    t0 = time.perf_counter()
    plants, leaves = run_population(families, per_family, args.protocol, (w, h),
                                    resolution=args.resolution, recipe_dir=args.recipe_dir,
                                    runs=runs, cache=args.cache,
                                    calibrate_each=args.calibrate_each,
                                    overrides=args.overrides, reuse_runs=args.reuse_runs,
                                    reuse_hulls=args.reuse_hulls,
                                    log=lambda m: print(m, flush=True))
    table = tabulate(plants, leaves)
    csv_path = args.out.with_suffix(".csv")
    write_csv(plants, csv_path)
    write_csv(leaves, runs / "leaves.csv")
    kind = ("DEVELOPMENT seeds (tuning, not a validation figure)" if dev else
            "validation seeds")
    head = (f"## {args.title or 'Population'}: {', '.join(families)}; seeds "
            f"{_seed_text(per_family)} ({kind}); {args.protocol}, "
            f"{w}×{h}, hull {args.resolution or 'of the recipe'}; "
            f"{'calibration per plant' if args.calibrate_each else 'one calibration per rig'}"
            f"; recipes {_rel(args.recipe_dir) if args.recipe_dir else 'recipes/'} "
            f"(segment_mesh: {_segmenters(families, args.recipe_dir)}); commit {_commit()}"
            f" ({time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.1f}, "
            f"{(time.perf_counter() - t0) / 60:.0f} min)")
    section = f"{head}\n\n{table}\n\nOne line per plant: `{_rel(csv_path)}`.\n"
    print("\n" + section)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(section if not args.out.exists() else _merge(args.out.read_text(),
                                                                      section))
    return 0


def _seed_text(per_family: dict[str, list[int]]) -> str:
    def one(v: list[int]) -> str:
        return f"{v[0]}–{v[-1]} ({len(v)} per family)" if v else "none"
    texts = {f: one(v) for f, v in per_family.items()}
    if len(set(texts.values())) == 1:
        return next(iter(texts.values()))
    return ", ".join(f"{f} {t}" for f, t in texts.items()).replace(" per family", "")


def _segmenters(families: Sequence[str], recipe_dir: Path | None) -> str:
    """Which mesh segmenter each family's recipe ships (the table measures it)."""
    import yaml
    names = {}
    for f in families:
        try:
            raw = yaml.safe_load(recipe_path(f, recipe_dir).read_text())
            names[f] = (raw.get("segment_mesh") or {}).get("plugin", "?")
        except (OSError, yaml.YAMLError, AttributeError):
            names[f] = "?"
    if len(set(names.values())) == 1:
        return next(iter(names.values()))
    return ", ".join(f"{f} {n}" for f, n in names.items())


def _commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(REPO))
    except ValueError:
        return str(path)


def _merge(page: str, section: str) -> str:
    """Put ``section`` under the page's intro (before earlier runs' sections)."""
    marker = "\n## "
    if marker not in page:
        return page.rstrip() + "\n\n" + section
    intro, rest = page.split(marker, 1)
    return intro.rstrip() + "\n\n" + section + "\n## " + rest


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())

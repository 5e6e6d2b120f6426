"""View planning benchmark: paper-72, paper-360, adaptive and random extra views, side by side.

Two parts::

    python benchmarks/planning.py tilts                       # cameras at tilts never calibrated
    python benchmarks/planning.py population --families dicot,rosette,branched,grass \\
        --seeds 1000-1002                                     # the comparison table

**population.**  Every plant (validation seeds >= 1000) is rendered once, with the
reference system's paper-360 protocol (5 tilts -10..30 deg x 36 stops x 2 cameras;
``population.scan_plant``, cached), and the four protocols are acquired from those
renders by the real orchestrator with a *replay* camera that serves the rendered image
of each (camera, tilt, turntable angle) it is asked for:

* **paper-72**: the tilt-0 ring (72 images);
* **paper-360**: the render itself (360 images);
* **adaptive**: ``plantscan scan --adaptive`` (``adaptive.scan_adaptive``) from a base
  ring (``--base-stops`` at tilt 0), the planner choosing among the 180 paper-360 stops
  (pan every 10 deg, tilts -10..30), within 100 plant images and 6 minutes of capture by
  the reference rig's timing model;
* **random**: the same base and as many extra stops as the adaptive scan took, drawn at
  random from the same candidates: the planner's value, measured.

All four are processed with the family's shipped recipe and one session calibration (the
paper-360 board views: every tilt used is calibrated), and evaluated against the truth
(``population.evaluate_plant``).  Capture time is the reference rig's (recipes/default.yaml:
turntable 12 deg/s, tilt arm 4 deg/s, settle 0.3 s, cameras 1 s capture + 1 s download,
downloads during moves) for each scan's plant stops in the order they were taken.

**tilts.**  A synthetic rig (``plantscan_calib.synthetic``, 1296 x 864, 0.2 px corner
noise) calibrated at some tilts, its cameras at every other tilt from the fitted tilt
axis, compared with the truth (camera centre, rotation, reprojection of plant-volume
points).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import population as pop  # noqa: E402

from plantscan_core.errors import HardwareError  # noqa: E402
from plantscan_core.hookspecs import hookimpl  # noqa: E402
from plantscan_core.stages import CameraBackend, CaptureRequest, MotionAxis, StageParams  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CACHE = Path(os.environ.get("PLANTSCAN_PLANNING_CACHE", "/work/cache/plan27/population"))
PROTOCOLS = ("paper-72", "paper-360", "adaptive", "random")
CANDIDATE_TILTS = [-10.0, 0.0, 10.0, 20.0, 30.0]  # the paper-360 renders' tilts
# The reference system's rig (recipes/default.yaml): Phidget steppers and gphoto2 defaults.
REFERENCE_AXES = {"turntable": {"velocity_deg_s": 12.0, "acceleration_deg_s2": 24.0,
                                "settle_s": 0.3},
                  "tilt": {"velocity_deg_s": 4.0, "acceleration_deg_s2": 8.0, "settle_s": 0.3}}
REFERENCE_CAMERA = {"capture_s": 1.0, "download_s": 1.0}


# --------------------------------------------------------------------------- replay rig
class ReplayCamera(CameraBackend):
    """Serves the image another scan folder holds for the same (camera, tilt, angle, role)."""

    name = "replay"

    class Params(StageParams):
        source: str
        capture_s: float | None = None   # timing model only
        download_s: float | None = None

    _index: dict[str, dict[tuple, Path]] = {}

    def _lookup(self) -> dict[tuple, Path]:
        src = self.params.source
        if src not in self._index:
            from plantscan_core.scanfolder import ScanFolder

            scan = ScanFolder.open(Path(src))
            self._index[src] = {_key(v.role, v.camera, v.tilt_deg, v.commanded_angle_deg):
                                scan.root / v.file for v in scan.views}
        return self._index[src]

    def capture(self, request: CaptureRequest) -> Path:
        # background plates: one per (camera, tilt), whatever the angle
        angle = 0.0 if request.role == "background" else request.commanded_angle_deg
        path = self._lookup().get(_key(request.role, request.camera, request.tilt_deg, angle))
        if path is None:
            raise HardwareError(f"replay: {self.params.source} has no {request.role} image of "
                                f"{request.camera} at tilt {request.tilt_deg:g}, angle "
                                f"{request.commanded_angle_deg:g}")
        try:
            os.link(path, request.out_path)
        except OSError:
            shutil.copyfile(path, request.out_path)
        return Path(request.out_path)

    def close(self) -> None:
        # the source's truth under this scan's view indices, after every acquisition (the
        # adaptive loop's quick runs read it with the exact calibrator and masks)
        scan = self.context.scan if self.context is not None else None
        if scan is not None and (scan.root / "scan.yaml").exists():
            copy_truth(Path(self.params.source), scan.root)


class ReplayAxis(MotionAxis):
    """Goes where it is told at once; its timing parameters are the reference rig's."""

    name = "replay"

    class Params(StageParams):
        velocity_deg_s: float | None = None
        acceleration_deg_s2: float | None = None
        settle_s: float = 0.0

    def move_to(self, deg: float) -> float | None:
        return None

    def position(self) -> float | None:
        return None

    def home(self) -> None:
        pass


def _key(role: str, camera: str, tilt: float, angle: float) -> tuple:
    return (role, camera, round(float(tilt), 4), round(float(angle) % 360.0, 4) % 360.0)


class _ReplayPlugin:
    @staticmethod
    @hookimpl
    def plantscan_register_stages(registry) -> None:
        registry.add(ReplayCamera)
        registry.add(ReplayAxis)


def manager():
    """The installed plugins plus the replay rig (the adaptive loop finds it by name)."""
    from plantscan_core.plugins import get_manager

    m = get_manager()
    if not any(r.name == "replay" for r in m.registry):
        m.register(_ReplayPlugin(), name="replay-benchmark")
    return m


INPUTS_LABEL = {"exact": "EXACT cameras and masks (only the view set differs)",
                "pipeline": "session calibration and the recipe's segmenter"}
EXACT_INPUTS = {"calibrate": {"plugin": "truth"}, "segment": {"plugin": "truth-masks"}}


def family_raw(family: str, exact: bool) -> dict[str, Any]:
    """The family's shipped recipe; with ``exact`` the virtual scanner's exact cameras and
    masks (calibrator ``truth``, segmenter ``truth-masks``): only the view set differs."""
    from plantscan_core.recipe import read_recipe_file

    raw = copy.deepcopy(read_recipe_file(pop.recipe_path(family)))
    if exact:
        raw.update(copy.deepcopy(EXACT_INPUTS))
    return raw


def replay_recipe(family: str, source: Path, base_stops: int, adaptive: dict[str, Any],
                  image_size: tuple[int, int], exact: bool = False) -> dict[str, Any]:
    """The family recipe with the replay rig, a base ring of ``base_stops`` at tilt 0, and
    background plates at every candidate tilt."""
    raw = family_raw(family, exact)
    cams = raw["scan"]["cameras"]
    raw["scan"] = {
        "protocol": "adaptive", "image_size": list(image_size), "image_format": "png",
        "cameras": [{"name": c["name"], "plugin": "replay",
                     "params": {"source": str(source), **REFERENCE_CAMERA}} for c in cams],
        "turntable": {"plugin": "replay", "params": REFERENCE_AXES["turntable"]},
        "tilt_arm": {"plugin": "replay", "params": REFERENCE_AXES["tilt"]},
        "tilts_deg": [0.0], "images_per_revolution": base_stops,
        "roles": {"calibration": {"enabled": False},
                  "background": {"images_per_revolution": 1, "tilts_deg": CANDIDATE_TILTS},
                  "plant": {}},
        "adaptive": {"tilts_deg": CANDIDATE_TILTS, "pan_step_deg": 10.0, **adaptive},
    }
    raw.pop("store", None)
    return raw


def copy_truth(source: Path, scan_dir: Path) -> None:
    """The source's plant truth, and its per-view truth under this scan's view indices."""
    from plantscan_core.scanfolder import ScanFolder

    src, dst = Path(source) / "ground_truth", Path(scan_dir) / "ground_truth"
    dst.mkdir(exist_ok=True)
    for p in src.iterdir():
        if p.is_file() and p.name != "cameras.jsonl":
            shutil.copyfile(p, dst / p.name)
    source_scan, scan = ScanFolder.open(Path(source)), ScanFolder.open(Path(scan_dir))
    by_key = {_key(v.role, v.camera, v.tilt_deg, v.commanded_angle_deg): v
              for v in source_scan.views}
    cams = {}
    for line in (src / "cameras.jsonl").read_text().splitlines():
        d = json.loads(line)
        cams[d["index"]] = d
    (dst / "masks").mkdir(exist_ok=True)
    lines = []
    for v in scan.views_by_role("plant"):
        s = by_key[_key(v.role, v.camera, v.tilt_deg, v.commanded_angle_deg)]
        shutil.copyfile(src / "masks" / f"{s.index:05d}.png", dst / "masks" / f"{v.index:05d}.png")
        if s.index in cams:
            lines.append(json.dumps({**cams[s.index], "index": v.index, "file": v.file},
                                    sort_keys=True))
    (dst / "cameras.jsonl").write_text("".join(line + "\n" for line in lines))


# --------------------------------------------------------------------------- one plant
def reference_motion():
    from plantscan_core.timing import AxisTiming
    from plantscan_core.trajectory import MotionModel

    t, a = REFERENCE_AXES["turntable"], REFERENCE_AXES["tilt"]
    return MotionModel(AxisTiming(t["velocity_deg_s"], t["acceleration_deg_s2"], t["settle_s"]),
                       AxisTiming(a["velocity_deg_s"], a["acceleration_deg_s2"], a["settle_s"]),
                       REFERENCE_CAMERA["capture_s"], REFERENCE_CAMERA["download_s"])


def capture_s(scan_dir: Path) -> float:
    """Plant-role capture time of a scan by the reference rig, stops in capture order."""
    from plantscan_core.adaptive import captured_stops
    from plantscan_core.scanfolder import ScanFolder

    return reference_motion().tour_s(captured_stops(ScanFolder.open(scan_dir)))


def acquire_replay(raw: dict[str, Any], out: Path, *, adaptive: bool,
                   calibration: Path | None, extra_random: int = 0, seed: int = 0) -> Path:
    """Acquire ``raw`` with the replay rig into ``out`` (reused when finished)."""
    from plantscan_core.acquire import acquire
    from plantscan_core.adaptive import candidate_stops, captured_stops, record_round
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.trajectory import PlannedStop, ViewPlan

    done = out / "done.json"
    if done.exists():
        return out / "scan"
    m = manager()
    recipe = validate_recipe(copy.deepcopy(raw), m.registry, f"replay recipe {out}")
    scan_dir = out / "scan"
    resume = (scan_dir / "scan.yaml").exists()
    if adaptive:
        from plantscan_core.adaptive import scan_adaptive

        scan_adaptive(recipe, scan_dir, m, raw_recipe=raw, resume=resume,
                      calibration_path=calibration, log=lambda s: print("   ", s, flush=True))
    else:
        scan = acquire(recipe, scan_dir, m, raw_recipe=raw, resume=resume)
        if extra_random and not scan.planned_rounds():
            rng = np.random.default_rng(seed)
            cands = candidate_stops(recipe, captured_stops(scan))
            pick = rng.choice(len(cands), size=min(extra_random, len(cands)), replace=False)
            stops = [PlannedStop(cands[i].pan_deg, cands[i].tilt_deg, 0.0, "drawn at random")
                     for i in sorted(pick)]
            record_round(scan, recipe, ViewPlan(stops=stops), "random")
        acquire(recipe, scan_dir, m, raw_recipe=raw, resume=True)
    copy_truth(Path(raw["scan"]["cameras"][0]["params"]["source"]), scan_dir)
    done.write_text(json.dumps({"finished": time.strftime("%Y-%m-%dT%H:%M:%S")}))
    return scan_dir


def run_plant(family: str, seed: int, runs: Path, args) -> list[dict[str, Any]]:
    """The four protocols of one plant: (plant row + extras) per protocol."""
    from plantscan_core.scanfolder import ScanFolder

    size = tuple(args.size)
    key = pop.PlantKey(family, seed, "paper-360", size)
    source = pop.scan_plant(key, cache=args.cache)
    exact = args.inputs == "exact"
    calibration = (None if exact else
                   pop.session_calibration(family, "paper-360", size, cache=args.cache))
    overrides = [f"{k}={json.dumps(v)}" for k, v in EXACT_INPUTS.items()] if exact else []
    adaptive_spec = {"max_plant_images": args.max_images, "max_capture_s": args.max_capture_s,
                     "stops_per_round": args.stops_per_round, "max_rounds": args.max_rounds,
                     "resolution": args.quick_resolution,
                     "min_gain_fraction": args.min_gain_fraction}
    where = runs / family / f"seed-{seed}"
    scans: dict[str, Path] = {"paper-360": source}
    scans["paper-72"] = acquire_replay(replay_recipe(family, source, 36, adaptive_spec, size,
                                                     exact),
                                       where / "paper-72", adaptive=False, calibration=None)
    raw = replay_recipe(family, source, args.base_stops, adaptive_spec, size, exact)
    scans["adaptive"] = acquire_replay(raw, where / "adaptive", adaptive=True,
                                       calibration=calibration)
    planned = ScanFolder.open(scans["adaptive"]).planned_rounds()
    n_extra = sum(len(r.stops) for r in planned)
    scans["random"] = acquire_replay(raw, where / "random", adaptive=False, calibration=None,
                                     extra_random=n_extra, seed=seed)
    rows = []
    for proto in PROTOCOLS:
        scan_dir = scans[proto]
        run_dir = where / proto / "run"
        truth_dir = scan_dir / "ground_truth"
        timing, error, evaluation = None, None, {}
        done = run_dir / "evaluation.json"
        if done.exists():
            evaluation = json.loads(done.read_text())
            info = json.loads((run_dir / "run.json").read_text())
            timing = {"wall_s": info["timings_s"]["total"], "cpu_s": info["cpu_s"]["total"]}
        else:
            try:
                timing = pop.process_plant(scan_dir, pop.recipe_path(family), run_dir,
                                           calibration, overrides)
                evaluation = pop.evaluate_plant(run_dir, truth_dir)
                done.write_text(json.dumps(evaluation, indent=1, sort_keys=True))
            except Exception as exc:  # a failed plant is a result
                error = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
        key = pop.PlantKey(family, seed, proto, size)
        row = pop.plant_row(key, evaluation, truth_dir, timing, error)
        scan = ScanFolder.open(scan_dir)
        rounds = scan.planned_rounds()
        row.update(protocol=proto, plant_images=len(scan.views_by_role("plant")),
                   capture_s=capture_s(scan_dir),
                   planner_s=[r.figures.get("planner_s") for r in rounds if r.stops or
                              r.figures.get("planner_s") is not None],
                   planner_cpu_s=[(r.figures.get("figures") or {}).get("cpu_s")
                                  for r in rounds if r.figures.get("figures")],
                   rounds=sum(1 for r in rounds if r.stops),
                   hull_mm3=hull_volume_mm3(run_dir),
                   stop_reason=rounds[-1].stop_reason if rounds else None)
        leaves = pop.leaf_rows(key, evaluation)
        for lf in leaves:
            lf["protocol"] = proto
        row["_leaves"] = leaves
        row["_truth_lengths"] = pop._truth_lengths(truth_dir)
        rows.append(row)
        print(f"{family} {seed} {proto}: {row['plant_images']} images, capture "
              f"{row['capture_s']:.0f} s, found {row.get('found')}/{row.get('truth_leaves')}, "
              f"ε L {pop._pct(row.get('eps_length'))}" + (f" FAILED {error}" if error else ""),
              flush=True)
    return rows


def hull_volume_mm3(run_dir: Path) -> float | None:
    """Volume of the run's carved hull (occupied voxels; phantom volume is what a better
    view set removes from it)."""
    from plantscan_core.data import BlockField, Volume

    path = run_dir / "volume.npz"
    if not path.exists():
        return None
    vol = Volume.load(path)
    blocks = vol.blocks
    if blocks is None:
        n = int(np.count_nonzero(vol.field > 0))
    else:  # without the dense grid: mixed blocks' positive voxels + whole inside blocks
        inside = np.argwhere(blocks.index == BlockField.INSIDE)
        extent = np.minimum(blocks.block, np.asarray(blocks.shape) - inside * blocks.block)
        n = int(np.count_nonzero(blocks.values > 0) + np.prod(extent, axis=1).sum())
    return float(n * vol.voxel_size ** 3)


# --------------------------------------------------------------------------- tables
def _p(values: Sequence[float], q: float) -> float:
    v = [abs(x) for x in values if x is not None and math.isfinite(x)]
    return float(np.percentile(v, q)) if v else math.nan


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    leaves = [lf for r in rows for lf in r["_leaves"]]
    s: dict[str, Any] = {"plants": len(rows), "failed": sum(1 for r in rows if r["error"]),
                         "truth": sum(r["truth_leaves"] or 0 for r in rows),
                         "found": sum(r.get("found") or 0 for r in rows),
                         **{k: sum(r.get(k) or 0 for r in rows)
                            for k in ("merged", "split", "extra")},
                         "leaves": len(leaves)}
    for name in pop.TRAITS:
        errs = [lf[f"{name}_rel_error"] for lf in leaves]
        s[f"{name}_med"], s[f"{name}_p90"] = _p(errs, 50), _p(errs, 90)
    area = np.array([lf["area_measured"] or 0.0 for lf in leaves])
    share = np.array([lf["thick_share"] if lf["thick_share"] is not None and
                      math.isfinite(lf["thick_share"]) else 0.0 for lf in leaves])
    s["phantom_share"] = float((area * share).sum() / area.sum()) if area.sum() else math.nan
    s["images"] = float(np.median([r["plant_images"] for r in rows]))
    hull = [r["hull_mm3"] for r in rows if r.get("hull_mm3") is not None]
    s["hull_cm3"] = float(np.median(hull)) / 1000.0 if hull else math.nan
    s["capture_s"] = float(np.median([r["capture_s"] for r in rows]))
    s["capture_max_s"] = float(np.max([r["capture_s"] for r in rows]))
    planner = [x for r in rows for x in r["planner_s"] if x is not None]
    cpu = [x for r in rows for x in r["planner_cpu_s"] if x is not None]
    s["planner_s"] = (float(np.median(planner)), float(np.max(planner))) if planner else None
    s["planner_cpu_s"] = (float(np.median(cpu)), float(np.max(cpu))) if cpu else None
    return s


TARGET_VS_360 = 0.15   # adaptive p90 at most 15 % (relative) above paper-360's
TARGET_VS_72 = 0.40    # ... and at least 40 % below paper-72's
TARGET_CAPTURE_S = 360.0
TARGET_PLANNER_S = 10.0


def _counts(s: dict[str, Any]) -> str:
    return f"{s['found']} / {s['truth']} ({s['merged']}, {s['split']}, {s['extra']})"


def trait_verdict(p72: float, p360: float, adaptive: float) -> tuple[bool, str]:
    """Issue #27's two p90 targets for one trait: met, and by how much each is met or missed."""
    vs360, vs72 = adaptive / p360 - 1.0, 1.0 - adaptive / p72
    ok360, ok72 = vs360 <= TARGET_VS_360, vs72 >= TARGET_VS_72
    parts = [f"vs 360 {'met' if ok360 else 'missed'} by "
             f"{100 * abs(TARGET_VS_360 - vs360):.0f} pt",
             f"vs 72 {'met' if ok72 else 'missed'} by {100 * abs(vs72 - TARGET_VS_72):.0f} pt"]
    return ok360 and ok72, ("yes" if ok360 and ok72 else "no") + " (" + "; ".join(parts) + ")"


def _relative(vs360: float, vs72: float) -> tuple[str, str]:
    return (f"{100 * vs360:+.0f} %",
            f"{100 * abs(vs72):.0f} % {'below' if vs72 >= 0 else 'above'}")


def tabulate(rows: list[dict[str, Any]]) -> str:
    """The comparison table (leaves pooled over a family's plants: ε median and p90 per trait
    over every matched leaf, counts summed) and the targets, each met or missed by how much."""
    fams = list(dict.fromkeys(r["family"] for r in rows))
    out = ["| family | protocol | plants (failed) | plant images (median) "
           "| capture, reference rig (median; max) "
           "| found / truth (merged, split, extra) | matched leaves | ε length med / p90 % "
           "| width | area | perimeter | leaf area in phantom volume "
           "| hull volume, cm³ (median) | planner s per round wall (CPU), median / max |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    targets = ["", "Targets (issue #27): adaptive's p90 within 15 % (relative) of paper-360's, "
               "and at least 40 % below paper-72's; capture <= 6 min; planning <= 10 s per "
               "round. The p90s over every leaf each view set matched (its count is in the "
               "table above), and over the leaves that all four matched; 'pt' = percentage "
               "points of the relative change.", "",
               "| family | target | paper-72 | paper-360 | adaptive | random "
               "| adaptive vs 360 | adaptive vs 72 | met |",
               "|---|---|---|---|---|---|---|---|---|"]
    for f in fams:
        sums = {p: summary([r for r in rows if r["family"] == f and r["protocol"] == p])
                for p in PROTOCOLS if any(r["family"] == f and r["protocol"] == p for r in rows)}
        for p, s in sums.items():
            cells = [f"{100 * s[f'{n}_med']:.1f} / {100 * s[f'{n}_p90']:.1f}" for n in pop.TRAITS]
            plan = ("–" if s["planner_s"] is None else
                    f"{s['planner_s'][0]:.1f} / {s['planner_s'][1]:.1f}" + (
                        "" if s["planner_cpu_s"] is None else
                        f" ({s['planner_cpu_s'][0]:.1f} / {s['planner_cpu_s'][1]:.1f})"))
            out.append(f"| {f} | {p} | {s['plants']} ({s['failed']}) | {s['images']:.0f} "
                       f"| {s['capture_s'] / 60:.1f} min; {s['capture_max_s'] / 60:.1f} "
                       f"| {_counts(s)} | {s['leaves']} | " + " | ".join(cells)
                       + f" | {100 * s['phantom_share']:.1f} % | {s['hull_cm3']:.1f} "
                       f"| {plan} |")
        if not {"paper-72", "paper-360", "adaptive"} <= set(sums):
            continue
        # each view set's p90 is over the leaves it matched, and a view set that matches more
        # leaves adds hard ones; so the targets also over the leaves every view set matched
        common = common_leaves([r for r in rows if r["family"] == f])
        same = {p: summary([{**r, "_leaves": [lf for lf in r["_leaves"]
                                              if (r["seed"], lf["truth_id"]) in common]}
                            for r in rows if r["family"] == f and r["protocol"] == p])
                for p in sums}
        for label, by in (("all matched", sums), (f"{len(common)} common", same)):
            for n in pop.TRAITS:
                a, b, c = (by[p][f"{n}_p90"] for p in ("paper-72", "paper-360", "adaptive"))
                r = by.get("random", {}).get(f"{n}_p90", math.nan)
                vs360, vs72 = _relative(c / b - 1.0, 1.0 - c / a)
                targets.append(f"| {f} | ε {n} p90 %, {label} leaves | {100 * a:.1f} "
                               f"| {100 * b:.1f} | {100 * c:.1f} | {100 * r:.1f} | {vs360} "
                               f"| {vs72} | {trait_verdict(a, b, c)[1]} |")
        cap = {p: sums[p]["capture_max_s"] / 60.0 for p in sums}
        worst = cap["adaptive"]
        targets.append(f"| {f} | capture, min (max over plants) | {cap['paper-72']:.1f} "
                       f"| {cap['paper-360']:.1f} | {worst:.1f} "
                       f"| {cap.get('random', math.nan):.1f} | – | – "
                       f"| {'yes' if worst <= TARGET_CAPTURE_S / 60 else 'no'} "
                       f"({abs(TARGET_CAPTURE_S / 60 - worst):.1f} min "
                       f"{'under' if worst <= TARGET_CAPTURE_S / 60 else 'over'} 6 min) |")
        ps, pc = sums["adaptive"]["planner_s"], sums["adaptive"]["planner_cpu_s"]
        if ps is not None:
            cpu_max = pc[1] if pc is not None else math.nan
            verdict = ("yes" if cpu_max <= TARGET_PLANNER_S else "no") + \
                f" in CPU ({abs(TARGET_PLANNER_S - cpu_max):.1f} s " \
                f"{'under' if cpu_max <= TARGET_PLANNER_S else 'over'} 10 s at the worst " \
                f"round); wall {'met' if ps[1] <= TARGET_PLANNER_S else 'missed'} on this " \
                "machine's load"
            targets.append(f"| {f} | planner s per round, wall (CPU), max | – | – "
                           f"| {ps[1]:.1f} ({cpu_max:.1f}) | – | – | – | {verdict} |")
    return "\n".join(out + targets)


def common_leaves(rows: list[dict[str, Any]]) -> set[tuple[int, int]]:
    """(seed, truth id) of the leaves matched by every protocol run on their plant."""
    out: set[tuple[int, int]] = set()
    for seed in {r["seed"] for r in rows}:
        sets = [{lf["truth_id"] for lf in r["_leaves"]} for r in rows if r["seed"] == seed]
        out |= {(seed, t) for t in set.intersection(*sets)} if sets else set()
    return out


def youngest_table(rows: list[dict[str, Any]], n: int) -> str:
    """Per plant, the ``n`` youngest truth leaves (shortest; the plastic dicot's top leaves
    among the equal-length ones: the highest ids): signed length error per protocol, with
    the leaf's thick share (phantom volume) in brackets."""
    out = ["| family | seed | truth leaf (length, mm) | " + " | ".join(PROTOCOLS) + " |",
           "|---|---|---|" + "---|" * len(PROTOCOLS)]
    plants = list(dict.fromkeys((r["family"], r["seed"]) for r in rows))
    for fam, seed in plants:
        leaves = {(lf["protocol"], lf["truth_id"]): lf for r in rows
                  if (r["family"], r["seed"]) == (fam, seed) for lf in r["_leaves"]}
        truth = {}
        for r in rows:
            if (r["family"], r["seed"]) == (fam, seed) and r.get("_truth_lengths"):
                truth = r["_truth_lengths"]
        pick = sorted(truth, key=lambda t: (truth[t], -t))[:n]
        for tid in sorted(pick):
            cells = []
            for p in PROTOCOLS:
                lf = leaves.get((p, tid))
                if lf is None:
                    cells.append("not matched" if any(r["protocol"] == p for r in rows) else "–")
                    continue
                share = lf["thick_share"]
                cells.append(f"{100 * lf['length_rel_error']:+.1f} %" + (
                    "" if share is None else f" ({100 * share:.0f} %)"))
            out.append(f"| {fam} | {seed} | {tid} ({truth[tid]:.1f}) | " + " | ".join(cells) + " |")
    return "\n".join(out)


def cmd_population(args) -> int:
    rows: list[dict[str, Any]] = []
    runs = args.runs or args.cache / "planning-runs"
    t0 = time.perf_counter()
    # plant by plant across families (seed-major), the table rewritten after each plant:
    # a run stopped early still leaves every family's first plants tabulated
    for seed in pop.parse_seeds(args.seeds):
        for family in args.families.split(","):
            rows += run_plant(family, seed, runs, args)
            write_population(rows, runs, args, t0)
    return 0


def write_population(rows: list[dict[str, Any]], runs: Path, args, t0: float) -> None:
    table = tabulate(rows)
    dev = any(r["seed"] < pop.VALIDATION_SEED0 for r in rows)
    head = (f"## Adaptive scanning (issue #27): {args.families}; seeds {args.seeds} "
            f"({'DEVELOPMENT seeds' if dev else 'validation seeds'}); "
            f"{args.size[0]}x{args.size[1]}, hull of the recipes (512^3); "
            f"{INPUTS_LABEL[args.inputs]}; base "
            f"{args.base_stops} stops at tilt 0, <= {args.max_images} plant images, <= "
            f"{args.max_capture_s:.0f} s capture; ({time.strftime('%Y-%m-%d %H:%M')}, load "
            f"{os.getloadavg()[0]:.1f}, {(time.perf_counter() - t0) / 60:.0f} min)")
    section = head + "\n\n" + table + "\n"
    if args.youngest:
        section += (f"\nThe {args.youngest} youngest (shortest) truth leaves of each plant: "
                    "signed length error (thick share of the leaf's area, i.e. in phantom "
                    "volume):\n\n" + youngest_table(rows, args.youngest) + "\n")
    print("\n" + section)
    pop.write_csv([{k: v for k, v in r.items() if not k.startswith("_")} for r in rows],
                  runs / "plants.csv")
    pop.write_csv([lf for r in rows for lf in r["_leaves"]], runs / "leaves.csv")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(section if not args.out.exists() else
                            pop._merge(args.out.read_text(), section))


# --------------------------------------------------------------------------- tilts
def tilt_errors(calibrated: Sequence[float], tilts: Sequence[float], seed: int = 0,
                size=(1296, 864)) -> list[dict[str, Any]]:
    """Per tilt: centre and rotation error and volume reprojection of the calibration made
    at ``calibrated`` tilts only (the others from its tilt axis), against the truth."""
    from plantscan_calib.evaluate import aligned
    from plantscan_calib.solver import SolveOptions, calibrate_turntable
    from plantscan_calib.synthetic import make_rig, synthetic_detections, volume_points

    from plantscan_core.data import rotation_angle_deg

    rig = make_rig(image_size=size, tilts_deg=tuple(tilts))
    idx = {i for i, t in enumerate(tilts) if t in calibrated}
    dets = synthetic_detections(rig, np.arange(0.0, 360.0, 10.0), noise_px=0.2, seed=seed,
                                tilt_indices=idx)
    sizes = {c: (m.width, m.height) for c, m in rig.truth.models.items()}
    cal = calibrate_turntable(dets, rig.boards, sizes, {i: rig.truth.tilts_deg[i] for i in idx},
                              SolveOptions(cross_validate=False, covariance=False))
    est, _, _ = aligned(cal, rig.truth)
    pts = volume_points()
    out = []
    for ti, tilt in enumerate(tilts):
        ce, re, px = [], [], []
        for cam in sorted(rig.truth.models):
            e = est.camera_at_stop(cam, tilt, 0.0)
            t = rig.truth.camera_at(cam, ti, 0.0)
            ce.append(float(np.linalg.norm(e.pose.centre - t.pose.centre)))
            re.append(rotation_angle_deg(e.pose.R.T @ t.pose.R))
            for a in range(0, 360, 30):
                ea, ta = est.camera_at_stop(cam, tilt, float(a)), rig.truth.camera_at(cam, ti, a)
                ue, ut = ea.project(pts), ta.project(pts)
                m = ta.model
                ok = (np.isfinite(ut).all(axis=1) & np.isfinite(ue).all(axis=1)
                      & (ut[:, 0] >= 0) & (ut[:, 0] < m.width) & (ut[:, 1] >= 0)
                      & (ut[:, 1] < m.height))
                px.append(np.linalg.norm(ue[ok] - ut[ok], axis=1))
        d = np.concatenate(px)
        out.append({"tilt": tilt, "calibrated": ti in idx, "centre_mm": max(ce),
                    "rotation_deg": max(re), "reprojection_px_rms": float(np.sqrt(np.mean(d**2)))})
    return out


def cmd_tilts(args) -> int:
    tilts = [-10.0, 0.0, 10.0, 20.0, 30.0, 40.0]
    lines = ["| calibrated at | seed | " + " | ".join(f"{t:g}°" for t in tilts) + " |",
             "|---|---|" + "---|" * len(tilts)]
    for calibrated in ([0.0, 30.0], [-10.0, 0.0, 10.0, 20.0, 30.0]):
        for seed in range(args.seeds):
            errs = tilt_errors(calibrated, tilts, seed)
            cells = [f"{'**' if e['calibrated'] else ''}{e['centre_mm']:.3f} mm, "
                     f"{e['rotation_deg']:.4f}°, {e['reprojection_px_rms']:.3f} px"
                     f"{'**' if e['calibrated'] else ''}" for e in errs]
            lines.append(f"| {', '.join(f'{t:g}' for t in calibrated)} | {seed} | "
                         + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="part", required=True)
    p = sub.add_parser("population", help="paper-72 / paper-360 / adaptive / random table")
    p.add_argument("--families", default="dicot,rosette,branched,grass")
    p.add_argument("--seeds", default="1000-1002")
    p.add_argument("--size", type=lambda s: tuple(int(x) for x in s.lower().split("x")),
                   default=(1296, 864))
    p.add_argument("--base-stops", type=int, default=18,
                   help="base ring at tilt 0 (stops; 18 = every 20 deg, 36 images)")
    p.add_argument("--max-images", type=int, default=100)
    p.add_argument("--max-capture-s", type=float, default=360.0)
    p.add_argument("--stops-per-round", type=int, default=8)
    p.add_argument("--max-rounds", type=int, default=6)
    p.add_argument("--min-gain-fraction", type=float, default=0.0)
    p.add_argument("--quick-resolution", type=int, default=128)
    p.add_argument("--inputs", choices=("exact", "pipeline"), default="pipeline",
                   help="exact: the virtual scanner's cameras and masks (the view set's effect "
                   "alone); pipeline: session calibration and the recipe's segmenter")
    p.add_argument("--cache", type=Path, default=CACHE)
    p.add_argument("--runs", type=Path)
    p.add_argument("--out", type=Path, help="markdown page to add the section to")
    p.add_argument("--youngest", type=int, default=0,
                   help="add a table of each plant's N youngest (shortest) leaves' length "
                   "error per protocol (the plastic dicot's top leaves: --families "
                   "plastic-dicot --seeds 0 --youngest 4)")
    p.set_defaults(func=cmd_population)
    p = sub.add_parser("tilts", help="cameras at tilts never calibrated, against the truth")
    p.add_argument("--seeds", type=int, default=2)
    p.set_defaults(func=cmd_tilts)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())

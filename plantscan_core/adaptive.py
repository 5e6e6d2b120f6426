"""Adaptive scanning: capture, carve a quick hull, plan the next views, capture them, repeat.

``plantscan scan --adaptive`` (``scan_adaptive``) captures the recipe's
protocol (the base views), then in rounds:

1. processes the scan quickly into ``SCAN/planning/`` (the recipe's
   calibration and segmentation, a coarse hull at ``scan.adaptive.resolution``),
2. runs the recipe's ``plan`` stage (default ``next-best-view``) on it: the
   stops among the candidates (``scan.adaptive.tilts_deg`` x every
   ``pan_step_deg``, within ``scan.limits``, not yet taken) predicted to carve
   the most unsure hull volume, within what is left of the image and
   capture-time budgets,
3. records the round in ``planned_views.jsonl`` (stops, predicted gains, why),
   *then* captures its stops through the ordinary orchestrator,

until a budget is spent, the predicted gain is small or ``max_rounds`` is
reached; the last line of ``planned_views.jsonl`` then says why it stopped.
Everything the loop needs is in the scan folder, so ``--adaptive --resume``
continues an interrupted adaptive scan where it stopped: the recorded stops
are captured (never planned again), then planning goes on.  Reprocessing with
every view is the ordinary ``plantscan process``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from plantscan_core.errors import PlantScanError
from plantscan_core.recipe import AdaptiveSpec, Recipe, StageSpec
from plantscan_core.scanfolder import ScanFolder, now_iso
from plantscan_core.trajectory import (
    PlannedRound,
    PlanRequest,
    Stop,
    ViewPlan,
    order_stops,
)

if TYPE_CHECKING:
    from plantscan_core.progress import Display

PLANNING_DIR = "planning"
"""The quick runs of an adaptive scan: a run folder inside the scan folder."""

DEFAULT_PLANNER = "next-best-view"

# Processing sections the quick runs leave out: the planner needs the hull, not the leaves.
_AFTER_PLAN = ("mesh", "segment_mesh", "measure", "store")


def adaptive_spec(recipe: Recipe) -> AdaptiveSpec:
    return recipe.scan.adaptive if recipe.scan.adaptive is not None else AdaptiveSpec()


def _position(pan_deg: float, tilt_deg: float) -> tuple[float, float]:
    return (round(float(pan_deg) % 360.0, 6) % 360.0, round(float(tilt_deg), 6))


def captured_stops(scan: ScanFolder) -> list[Stop]:
    """The plant stops already taken, in capture order (one per rig position)."""
    seen: dict[tuple[float, float], Stop] = {}
    for v in scan.views_by_role("plant"):
        pos = _position(v.commanded_angle_deg, v.tilt_deg)
        seen.setdefault(pos, Stop(pos[0], pos[1], v.angle_index))
    return list(seen.values())


def candidate_stops(recipe: Recipe, taken: list[Stop]) -> list[Stop]:
    """Every stop the planner may choose: candidate tilts x pans, within limits, not taken."""
    spec = adaptive_spec(recipe)
    done = {s.position for s in taken}
    n = max(1, round(360.0 / spec.pan_step_deg))
    out = []
    for tilt in recipe.scan.adaptive_tilts():
        if not recipe.scan.limits.tilt_ok(tilt):
            continue
        for i in range(n):
            pos = _position(i * 360.0 / n, tilt)
            if pos not in done:
                out.append(Stop(pos[0], pos[1], -1))
    return out


def plan_request(recipe: Recipe, scan: ScanFolder, registry=None) -> PlanRequest:
    """The request the core hands the planner for the next round of ``scan``.

    The budgets are what is left of ``scan.adaptive``'s: plant images, and capture
    time of the plant role by the timing model (the stops taken so far, in the
    order they were taken, plus the new ones ordered from where the rig stands).
    """
    from plantscan_core.timing import rig_motion

    spec = adaptive_spec(recipe)
    cams = [c.name for c in recipe.scan.cameras]
    taken = captured_stops(scan)
    n_plant = len(scan.views_by_role("plant"))
    images_left = max(0, spec.max_plant_images - n_plant)
    max_stops = min(spec.stops_per_round, images_left // max(1, len(cams)))
    motion = rig_motion(recipe, registry)
    used_s = motion.tour_s(taken)
    at = taken[-1].position if taken else (0.0, 0.0)

    def seconds_of(stops: list[Stop]) -> float:
        return motion.tour_s(order_stops(stops, motion, at)[0], at)

    max_seconds = None if spec.max_capture_s is None else max(0.0, spec.max_capture_s - used_s)
    return PlanRequest(candidate_stops(recipe, taken), cams, max_stops, max_seconds, seconds_of,
                       final_views=n_plant + max_stops * len(cams))


def next_index(scan: ScanFolder, recipe: Recipe) -> int:
    """The first ``angle_index`` no plant stop of the scan or the recipe uses."""
    used = [s.index for s in recipe.scan.role_stops("plant")]
    used += [v.angle_index for v in scan.views_by_role("plant")]
    used += [s.index for r in scan.planned_rounds() for s in r.stops]
    return max(used, default=-1) + 1


def record_round(scan: ScanFolder, recipe: Recipe, view_plan: ViewPlan, planner: str,
                 figures: dict[str, Any] | None = None,
                 stop_reason: str | None = None) -> PlannedRound:
    """Give the plan's stops their ``angle_index`` and append the round to the scan folder."""
    first = next_index(scan, recipe)
    stops = [dataclasses.replace(s, index=first + i) for i, s in enumerate(view_plan.stops)]
    summary = {k: v for k, v in view_plan.to_dict().items() if k != "stops"}
    rnd = PlannedRound(len(scan.planned_rounds()) + 1, stops, planner, stop_reason,
                       {**summary, **(figures or {})}, now_iso())
    scan.append_planned_round(rnd)
    return rnd


def quick_recipe(recipe: Recipe) -> Recipe:
    """The recipe of the quick runs: its calibration and segmentation, a coarse hull, the
    planner, nothing after (``scan.adaptive.resolution``, ``plan`` default next-best-view)."""
    if recipe.reconstruct is None or recipe.segment is None:
        raise PlantScanError("scan --adaptive / plan: the recipe needs segment and reconstruct "
                             "sections (the planner works on the hull)")
    spec = adaptive_spec(recipe)
    params = {**recipe.reconstruct.params, "resolution": spec.resolution}
    update: dict[str, Any] = {name: None for name in _AFTER_PLAN}
    update["export"] = []
    update["reconstruct"] = recipe.reconstruct.model_copy(update={"params": params})
    update["plan"] = recipe.plan or StageSpec(plugin=DEFAULT_PLANNER)
    return recipe.model_copy(update=update)


@dataclasses.dataclass
class RoundResult:
    """One planning pass: the plan and the seconds it took."""

    view_plan: ViewPlan
    planner: str
    processing_s: float
    planner_s: float
    run_dir: Path


def plan_next(scan_dir: Path, recipe: Recipe, manager, *, run_dir: Path | None = None,
              calibration_path: Path | None = None,
              progress: bool | Display = False) -> RoundResult:
    """Process ``scan_dir`` quickly and plan its next stops (nothing is recorded)."""
    from plantscan_core.pipeline import process

    quick = quick_recipe(recipe)
    run_dir = Path(run_dir) if run_dir is not None else Path(scan_dir) / PLANNING_DIR
    t0 = time.perf_counter()
    result = process(Path(scan_dir), quick, run_dir, manager, progress=progress,
                     calibration_path=calibration_path)
    total = time.perf_counter() - t0
    view_plan = result.results.get("view_plan")
    if view_plan is None:
        skipped = ", ".join(result.info.get("skipped") or [])
        raise PlantScanError(f"{run_dir}: the planner did not run (not run: {skipped})")
    planner_s = float(result.info.get("timings_s", {}).get("plan", view_plan.seconds))
    return RoundResult(view_plan, quick.plan.plugin, total - planner_s, planner_s, run_dir)


def _stop_reason(recipe: Recipe, scan: ScanFolder, request: PlanRequest | None,
                 view_plan: ViewPlan | None) -> str | None:
    spec = adaptive_spec(recipe)
    n_plant = len(scan.views_by_role("plant"))
    done_rounds = sum(1 for r in scan.planned_rounds() if r.stops)
    if done_rounds >= spec.max_rounds:
        return f"max_rounds reached ({spec.max_rounds})"
    if spec.max_plant_images - n_plant < len(recipe.scan.cameras):
        return (f"image budget spent ({n_plant} of {spec.max_plant_images} plant images; one "
                f"more stop takes {len(recipe.scan.cameras)})")
    if request is not None and not request.candidates:
        return "no candidate stop left (every candidate position is taken)"
    if view_plan is None:
        return None
    if not view_plan.stops:
        return "no stop fits the budgets or is predicted to carve anything"
    floor = spec.min_gain_fraction * view_plan.hull_volume_mm3
    if view_plan.predicted_carve_mm3 < floor:
        return (f"predicted gain small: {view_plan.predicted_carve_mm3:.0f} mm3 < "
                f"{spec.min_gain_fraction:g} of the hull's {view_plan.hull_volume_mm3:.0f} mm3")
    return None


def scan_adaptive(recipe: Recipe, out: Path, manager, *, raw_recipe: dict | None = None,
                  resume: bool = False, progress: bool | Display = False,
                  on_role_start: Callable[[str], None] | None = None,
                  calibration_path: Path | None = None,
                  log: Callable[[str], None] | None = None) -> ScanFolder:
    """``plantscan scan --adaptive``: the base protocol, then planned rounds (module docstring).

    ``calibration_path`` gives the quick runs a saved calibration instead of the
    recipe's calibrator (a session calibration).  ``log`` receives one line per round.
    """
    from plantscan_core.acquire import acquire

    say = log or (lambda line: print(line, file=sys.stderr))
    scan = acquire(recipe, out, manager, raw_recipe=raw_recipe, resume=resume,
                   on_role_start=on_role_start, progress=progress)
    while True:
        rounds = scan.planned_rounds()
        if rounds and rounds[-1].stop_reason is not None:
            say(f"adaptive: {rounds[-1].stop_reason} ({len(scan.views_by_role('plant'))} "
                "plant images)")
            return scan
        reason = _stop_reason(recipe, scan, None, None)
        if reason is None:
            rr = plan_next(scan.root, recipe, manager, calibration_path=calibration_path,
                           progress=progress)
            request = plan_request(recipe, scan, manager.registry)
            reason = _stop_reason(recipe, scan, request, rr.view_plan)
            figures = {"processing_s": round(rr.processing_s, 3),
                       "planner_s": round(rr.planner_s, 3),
                       "plant_images_before": len(scan.views_by_role("plant"))}
            if reason is None:
                rnd = record_round(scan, recipe, rr.view_plan, rr.planner, figures)
                say(f"adaptive: round {rnd.round}: {len(rnd.stops)} stops predicted to carve "
                    f"{rr.view_plan.predicted_carve_mm3:.0f} mm3 of "
                    f"{rr.view_plan.unsure_volume_mm3:.0f} mm3 unsure (planning "
                    f"{rr.planner_s:.1f} s, quick processing {rr.processing_s:.1f} s)")
                scan = acquire(recipe, out, manager, raw_recipe=raw_recipe, resume=True,
                               progress=progress)
                continue
            record_round(scan, recipe, ViewPlan(stops=[], **_totals(rr.view_plan)),
                         rr.planner, figures, reason)
        else:
            record_round(scan, recipe, ViewPlan(), "", {}, reason)


def _totals(view_plan: ViewPlan) -> dict[str, Any]:
    return {"unsure_volume_mm3": view_plan.unsure_volume_mm3,
            "hull_volume_mm3": view_plan.hull_volume_mm3,
            "predicted_carve_mm3": view_plan.predicted_carve_mm3,
            "seconds": view_plan.seconds, "figures": view_plan.figures}


def describe_plan(view_plan: ViewPlan, cameras: int) -> str:
    """The plan as text for the terminal: one line per stop, then the totals."""
    lines = [f"{'#':>3}{'pan deg':>9}{'tilt deg':>10}{'gain mm3':>10}  why"]
    for i, s in enumerate(view_plan.stops, 1):
        lines.append(f"{i:>3}{s.pan_deg:>9.1f}{s.tilt_deg:>10.1f}{s.gain_mm3:>10.0f}  {s.reason}")
    frac = (view_plan.predicted_carve_mm3 / view_plan.unsure_volume_mm3
            if view_plan.unsure_volume_mm3 > 0 else math.nan)
    lines.append(f"{len(view_plan.stops)} stops ({len(view_plan.stops) * cameras} images, "
                 f"{view_plan.capture_s:.0f} s capture by the timing model): predicted to carve "
                 f"{view_plan.predicted_carve_mm3:.0f} of {view_plan.unsure_volume_mm3:.0f} mm3 "
                 f"unsure ({frac:.0%}) in a hull of {view_plan.hull_volume_mm3:.0f} mm3; "
                 f"planned in {view_plan.seconds:.1f} s")
    return "\n".join(lines)


def describe_budget(recipe: Recipe, registry=None) -> str:
    """``scan --adaptive --dry-run``: the base views' capture time and what the budgets allow."""
    from plantscan_core.timing import rig_motion

    spec = adaptive_spec(recipe)
    cams = len(recipe.scan.cameras)
    motion = rig_motion(recipe, registry)
    base = order_stops(recipe.scan.role_stops("plant"), motion)[0]
    base_s = motion.tour_s(base)
    more = max(0, spec.max_plant_images - len(base) * cams) // cams
    budget = ("no time budget" if spec.max_capture_s is None
              else f"capture time of the plant views <= {spec.max_capture_s:.0f} s")
    cand = len(candidate_stops(recipe, base))
    return (f"adaptive: base plant views {len(base)} stops ({len(base) * cams} images, "
            f"{base_s:.0f} s by the timing model); then up to {more} planned stops "
            f"({more * cams} images; at most {spec.stops_per_round} per round, "
            f"{spec.max_rounds} rounds) among {cand} candidates (tilts "
            f"{', '.join(f'{t:g}' for t in recipe.scan.adaptive_tilts())} deg, every "
            f"{spec.pan_step_deg:g} deg); {budget}. Each round adds a quick processing "
            f"(hull at {spec.resolution}) and the planner's time.")

"""The ``plantscan`` command.

Every error prints as ``path: message`` on stderr, never as a traceback: exit
status 2 for an error in the user's input, 1 for an internal error (a bug).  The
traceback goes to ``run.log`` in the command's run or scan folder (the
temporary folder otherwise), and to the screen with ``--debug`` or
``PLANTSCAN_DEBUG=1``.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import os
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any

from plantscan_core import __version__
from plantscan_core.errors import PlantScanError, RecipeError
from plantscan_core.plugins import PluginManager, get_manager
from plantscan_core.preflight import FORCE_ENV, check_recipe, recipe_estimates, recipe_plan
from plantscan_core.recipe import (
    apply_overrides,
    read_recipe_file,
    recipe_json_schema,
    resolve_recipe_path,
    validate_recipe,
)

EXIT_USER_ERROR = 2
EXIT_INTERNAL_ERROR = 1


def _add_recipe_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--recipe", required=required,
                   help="recipe YAML file, or the name of a shipped recipe (e.g. plastic-dicot)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a recipe value (YAML), repeatable: "
                   "--set scan.image_size=[600,400]")


def _add_output_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="say more: every warning, also of cached stages, and INFO messages")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress display; warnings and errors only")


def _display(args):
    """The command's progress display: rich in a terminal, plain lines otherwise (-q: none)."""
    from plantscan_core.progress import Display

    return Display("quiet" if getattr(args, "quiet", False) else "auto",
                   verbose=getattr(args, "verbose", 0))


def _load(args, manager: PluginManager):
    path = resolve_recipe_path(args.recipe)
    raw = apply_overrides(read_recipe_file(path), list(args.overrides))
    recipe = validate_recipe(raw, manager.registry, str(path))
    return recipe, raw


def _add_sample_sheet_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sample-sheet", metavar="CSV",
                   help="plant metadata per scan folder or plant id (genotype, treatment, "
                   "replicate, sowing_date...; docs/experiments.md): overrides the recipe's "
                   "plant: and experiment:")


# --------------------------------------------------------------------------- commands
def cmd_plugins(args) -> int:
    manager = get_manager()
    if args.json:
        print(json.dumps({
            "stages": [{"stage": r.stage, "name": r.name, "plugin": r.plugin,
                        "distribution": r.distribution, "version": r.version}
                       for r in manager.registry],
            "failed": [f.__dict__ for f in manager.failed],
        }, indent=2))
        return 1 if manager.failed else 0
    from rich.console import Console
    from rich.table import Table

    console = Console()
    table = Table(title="plantscan stages")
    for col in ("stage", "name", "plugin", "distribution", "version"):
        table.add_column(col, overflow="fold")  # a narrow terminal wraps, never cuts, names
    for r in manager.registry:  # in pipeline order
        table.add_row(r.stage, r.name, r.plugin, r.distribution, r.version)
    console.print(table)
    if manager.failed:
        ft = Table(title="plugins that failed to load", style="red")
        for col in ("plugin", "entry point", "distribution", "error"):
            ft.add_column(col, overflow="fold")
        for f in manager.failed:
            ft.add_row(f.name, f.value, f.distribution, f.error)
        console.print(ft)
        return 1
    return 0


def cmd_recipe_check(args) -> int:
    manager = get_manager()
    recipe, _ = _load(args, manager)
    scan = recipe.scan
    stops = scan.role_stops("plant")
    print(f"{args.recipe}: OK ({recipe.name}: {len(scan.cameras)} camera(s), "
          f"{len(scan.role_tilts('plant'))} plant tilt(s), {len(stops)} plant stop(s) = "
          f"{len(stops) * len(scan.cameras)} plant images)")
    return 0


def cmd_recipe_list(args) -> int:
    from plantscan_core.recipe import RECIPES_DIR, shipped_recipes

    for name in shipped_recipes():
        print(name)
    print(f"({RECIPES_DIR}; a name works from any folder: plantscan recipe check NAME)",
          file=sys.stderr)
    return 0


def cmd_schema(args) -> int:
    print(json.dumps(recipe_json_schema(), indent=2))
    return 0


def _positional_recipe(args) -> None:
    """``plantscan scan RECIPE`` and ``plantscan scan --recipe RECIPE`` are the same."""
    given = [r for r in (args.recipe_arg, args.recipe) if r]
    if not given:
        raise RecipeError([("RECIPE", "required: a recipe file or the name of a shipped recipe "
                                      "(plantscan recipe list)")], "plantscan scan")
    if len(set(given)) > 1:
        raise RecipeError([("RECIPE", f"given twice ({given[0]!r} and --recipe {given[1]!r})")],
                          "plantscan scan")
    args.recipe = given[0]


def cmd_scan(args) -> int:
    from plantscan_core.acquire import acquire, plan

    _positional_recipe(args)
    manager = get_manager()
    recipe, raw = _load(args, manager)
    if args.sample_sheet:
        from plantscan_core.metadata import (
            SampleSheetError,
            apply_to_raw_recipe,
            load_sample_sheet,
        )

        sheet = load_sample_sheet(args.sample_sheet, require_scans=False)
        row = sheet.row_for(Path(args.out) if args.out else None, recipe.plant.id)
        if row is None:
            raise SampleSheetError([(args.sample_sheet, f"no row for scan folder {args.out} "
                                     f"nor for plant_id {recipe.plant.id!r} (set it with --set "
                                     "plant.id=...)")], args.sample_sheet)
        raw = apply_to_raw_recipe(raw, row)
        recipe = validate_recipe(raw, manager.registry, f"{args.recipe} + {args.sample_sheet}")
    _set_force(args)
    if args.dry_run:
        _print_estimates(recipe, manager)
        try:
            from plantscan_core.timing import estimate_scan_time
        except ImportError:
            print(f"{len(plan(recipe))} images planned")
            return 0
        print(estimate_scan_time(recipe, manager.registry))
        if args.adaptive:
            from plantscan_core.adaptive import describe_budget

            print(describe_budget(recipe, manager.registry))
        return 0
    if args.out is None:
        raise PlantScanError("--out: required (the scan folder to write)")
    check_recipe(recipe, manager.registry)  # before any motor moves
    interactive = recipe.scan.scene is None and sys.stdin.isatty()

    def on_role_start(role: str) -> None:
        if interactive:
            what = {"calibration": "mount the calibration target on the turntable",
                    "background": "remove the plant (background plates)",
                    "plant": "place the plant on the turntable"}[role]
            input(f"{role}: {what}, then press Enter ")

    if args.adaptive:
        from plantscan_core.adaptive import scan_adaptive

        scan = scan_adaptive(recipe, Path(args.out), manager, raw_recipe=raw,
                             resume=args.resume, on_role_start=on_role_start,
                             progress=_display(args),
                             calibration_path=Path(args.calibration) if args.calibration
                             else None)
    else:
        scan = acquire(recipe, Path(args.out), manager, raw_recipe=raw, resume=args.resume,
                       on_role_start=on_role_start, progress=_display(args))
    print(f"{scan.root}: {len(scan.views)} images")
    return 0


def cmd_plan(args) -> int:
    from plantscan_core.adaptive import describe_plan, plan_next, record_round
    from plantscan_core.scanfolder import ScanFolder

    manager = get_manager()
    recipe, _ = _recipe_from_scan_or_args(args, manager)
    scan = ScanFolder.open(Path(args.scan))
    rr = plan_next(scan.root, recipe, manager, run_dir=Path(args.out) if args.out else None,
                   calibration_path=Path(args.calibration) if args.calibration else None,
                   progress=_display(args))
    print(describe_plan(rr.view_plan, len(recipe.scan.cameras)))
    print(f"{rr.run_dir / 'plan.json'}: the plan (quick processing {rr.processing_s:.1f} s, "
          f"planner {rr.planner_s:.1f} s)")
    if args.record:
        if not rr.view_plan.stops:
            raise PlantScanError(f"{scan.root}: nothing to record, the plan has no stop")
        rnd = record_round(scan, recipe, rr.view_plan, rr.planner,
                           {"processing_s": rr.processing_s, "planner_s": rr.planner_s})
        print(f"{scan.root}: round {rnd.round} recorded in planned_views.jsonl; capture it "
              f"with: plantscan scan --recipe ... --out {scan.root} --resume")
    return 0


def _recipe_from_scan_or_args(args, manager):
    from plantscan_core.scanfolder import ScanFolder

    if args.recipe:
        return _load(args, manager)
    scan = ScanFolder.open(Path(args.scan))
    raw = apply_overrides(dict(scan.recipe_dict), list(args.overrides))
    return validate_recipe(raw, manager.registry, f"{args.scan}/scan.yaml recipe"), raw


def cmd_calibrate(args) -> int:
    from plantscan_core.scanfolder import ScanFolder

    manager = get_manager()
    recipe, _ = _recipe_from_scan_or_args(args, manager)
    if recipe.calibrate is None:
        raise RecipeError([("calibrate", "the recipe names no calibrator")])
    scan = ScanFolder.open(Path(args.scan))
    from plantscan_core.stages import StageContext

    calibrator = manager.build("calibrator", recipe.calibrate.plugin, recipe.calibrate.params,
                               StageContext(recipe=recipe, scan=scan))
    display = _display(args)
    with display.step("calibrate"):
        calibration = calibrator.calibrate(scan)
    display.close()
    out = Path(args.output) if args.output else scan.root / "calibration.yaml"
    calibration.save(out)
    print(f"{out}: calibration of {', '.join(calibration.camera_names)}")
    q = calibration.quality
    if q.get("rms_px") is not None:
        print(f"  RMS reprojection {q['rms_px']:.4f} px")
    return 0


def cmd_process(args) -> int:
    from plantscan_core.pipeline import process

    manager = get_manager()
    recipe, raw = _recipe_from_scan_or_args(args, manager)
    metadata = None
    if args.sample_sheet:
        from plantscan_core.metadata import load_sample_sheet
        from plantscan_core.scanfolder import ScanFolder

        sheet = load_sample_sheet(args.sample_sheet)
        metadata = sheet.metadata_for(recipe.plant, recipe.experiment, Path(args.scan),
                                      ScanFolder.open(Path(args.scan)).info)
    _set_force(args)
    check_recipe(recipe, manager.registry, _captured_size(Path(args.scan)))
    out = Path(args.out) if args.out else Path(args.scan).with_name(Path(args.scan).name + "-run")
    result = process(Path(args.scan), recipe, out, manager, raw_recipe=raw,
                     overrides=args.overrides, progress=_display(args),
                     calibration_path=Path(args.calibration) if args.calibration else None,
                     metadata=metadata)
    if args.profile:
        print(profile_table(result.info))
    skipped = result.info.get("skipped")
    if skipped:
        print(f"{out}: not run: {', '.join(skipped)} (not in the recipe, or an input missing)")
    if result.traits is not None:
        print(f"{out}: {len(result.traits.leaves)} leaves measured -> {out / 'traits.csv'}")
    else:
        print(f"{out}: run written")
    return 0


def _set_force(args) -> None:
    if getattr(args, "force", False):
        os.environ[FORCE_ENV] = "1"  # the stages' own checks (and Dask workers) see it too


def _print_estimates(recipe, manager) -> None:
    for est in recipe_estimates(recipe, manager.registry, recipe_plan(recipe)):
        print(f"estimate: {est.describe()}")


def _captured_size(scan_dir: Path) -> tuple[int, int] | None:
    """Width and height of a scan's first plant image (header only), or None."""
    from PIL import Image, UnidentifiedImageError

    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(scan_dir)
    for view in scan.views_by_role("plant")[:1]:
        try:
            with Image.open(scan.root / view.file) as im:
                return im.size
        except (OSError, UnidentifiedImageError):
            return None  # the segment stage names the file
    return None


def profile_table(info: dict[str, Any]) -> str:
    """Seconds (wall and CPU), peak memory and warnings per stage of a run (run.json), as text.

    CPU above wall time means the stage used both cores; peak memory is the
    process's high-water mark when the stage ended (it never goes down);
    warnings counts the warnings of the stage's report.  Exporters are named by
    their plugin (``export ply``).
    """
    cpu, rss = info.get("cpu_s", {}), info.get("peak_rss_mb", {})
    lines = [f"{'stage':<20}{'wall s':>9}{'cpu s':>9}{'peak MB':>9}{'warnings':>9}  cached"]
    for stage, sec in info.get("timings_s", {}).items():
        if stage == "total":
            continue
        record = info.get("stages", {}).get(stage, {})
        warned = len((record.get("info") or {}).get("warnings") or [])
        label = stage
        if stage.startswith("export.") and record.get("plugin"):
            label = f"export {record['plugin']}"  # export.1 -> export ply
        lines.append(f"{label:<20}{sec:>9.2f}{cpu.get(stage, float('nan')):>9.2f}"
                     f"{rss.get(stage, float('nan')):>9.0f}{warned or '':>9}"
                     f"  {'yes' if record.get('cached') else ''}")
    lines.append(f"{'total':<20}{info.get('timings_s', {}).get('total', 0.0):>9.2f}"
                 f"{cpu.get('total', float('nan')):>9.2f}{rss.get('total', float('nan')):>9.0f}")
    return "\n".join(lines)


def cmd_evaluate(args) -> int:
    run_dir = Path(args.run)
    if not (run_dir / "run.json").exists():
        raise PlantScanError(f"{run_dir}: not a run folder (no run.json)")
    truth = Path(args.truth) if args.truth else None
    if truth is None:
        info = json.loads((run_dir / "run.json").read_text())
        truth = Path(info["scan"]) / "ground_truth"
    if (truth / "ground_truth").is_dir():
        truth = truth / "ground_truth"
    if not truth.is_dir():
        raise PlantScanError(f"{truth}: truth folder not found (pass --truth SCAN/ground_truth)")
    metrics = evaluate(run_dir, truth)
    print(json.dumps(metrics, indent=2, sort_keys=True))
    return 0


def evaluate(run_dir: Path, truth_dir: Path) -> dict[str, Any]:
    """Merged metrics of every plugin's ``plantscan_evaluate`` hook."""
    return get_manager().evaluate(Path(run_dir), Path(truth_dir))


def cmd_demo(args) -> int:
    from plantscan_core.demo import run_demo

    return run_demo(Path(args.out), list(args.overrides), recipe_name=args.recipe,
                    display=_display(args))


def cmd_warm_up(args) -> int:
    """Run every plugin's one-time work now (numba kernels compiled into their cache)."""
    import time

    t0 = time.perf_counter()
    display = _display(args)
    done = get_manager().warm_up(display)
    display.close()
    for plugin, said in done:
        print(f"warm-up: {plugin}: {said}")
    print(f"warm-up: {len(done)} plugin(s) in {time.perf_counter() - t0:.1f} s")
    return 1 if any(said.startswith("failed:") for _, said in done) else 0


def cmd_batch(args) -> int:
    _set_force(args)
    try:
        from plantscan_core.batch import run_batch
    except ImportError as exc:
        raise PlantScanError(f"batch: not available ({exc})") from exc
    summary = run_batch([Path(s) for s in args.scans], resolve_recipe_path(args.recipe),
                        Path(args.out), overrides=args.overrides, scheduler=args.scheduler,
                        workers=args.workers, progress=_display(args),
                        calibration=Path(args.calibration) if args.calibration else None,
                        sample_sheet=Path(args.sample_sheet) if args.sample_sheet else None)
    print(summary)
    return summary.exit_status  # the number of failed plants (capped at 125)


# --------------------------------------------------------------------------- parser
def _print_help(parser: argparse.ArgumentParser, args) -> int:
    """A command that needs an action and got none: its own help, and a usage error."""
    parser.print_help()
    return EXIT_USER_ERROR


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="go on when the memory estimate says the machine cannot hold a stage")


def build_parser(manager: PluginManager | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="plantscan",
        description="Turntable 3D scanning and leaf measurement for plant phenotyping.")
    parser.add_argument("--version", action="version", version=f"plantscan {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (always written to run.log)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("plugins", help="list loaded and failed plugins by stage")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_plugins)

    recipe = sub.add_parser("recipe", help="recipe tools")
    rsub = recipe.add_subparsers(dest="recipe_command", metavar="ACTION")
    pc = rsub.add_parser("check", help="validate a recipe in full (every error at once)")
    pc.add_argument("recipe", help="recipe YAML file or shipped recipe name")
    pc.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE")
    pc.set_defaults(func=cmd_recipe_check)
    pl = rsub.add_parser("list", help="the shipped recipes, by name")
    pl.set_defaults(func=cmd_recipe_list)
    ps = rsub.add_parser("schema", help="print the JSON Schema of recipes (= plantscan schema)")
    ps.set_defaults(func=cmd_schema)
    recipe.set_defaults(func=functools.partial(_print_help, recipe))

    p = sub.add_parser("schema", help="print the JSON Schema of recipes")
    p.set_defaults(func=cmd_schema)

    p = sub.add_parser("scan", help="acquire a scan with the recipe's rig (real or virtual)")
    p.add_argument("recipe_arg", nargs="?", metavar="RECIPE",
                   help="recipe YAML file or shipped recipe name (or --recipe)")
    _add_recipe_args(p, required=False)
    p.add_argument("--out", help="scan folder to write")
    p.add_argument("--resume", action="store_true", help="continue an interrupted scan in --out")
    p.add_argument("--dry-run", action="store_true",
                   help="check the recipe and print the timing model; move nothing")
    p.add_argument("--adaptive", action="store_true",
                   help="after the protocol's views, plan and capture more where the hull is "
                   "unsure, in rounds, within scan.adaptive's budgets (docs/trajectories.md)")
    p.add_argument("--calibration", help="--adaptive: a calibration YAML for the quick runs "
                   "instead of the recipe's calibrator (a session calibration)")
    _add_sample_sheet_arg(p)
    _add_force(p)
    _add_output_args(p)
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("plan", help="where more views would carve a scan's hull: the next "
                       "stops (pan, tilt), with their predicted gain and why")
    p.add_argument("scan", help="scan folder")
    _add_recipe_args(p, required=False)
    p.add_argument("--calibration", help="use this calibration YAML instead of calibrating")
    p.add_argument("--out", help="run folder of the quick processing (default SCAN/planning)")
    p.add_argument("--record", action="store_true",
                   help="record the stops as the scan's next round (planned_views.jsonl): "
                   "scan --resume then captures them")
    _add_output_args(p)
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("calibrate", help="calibrate the rig from a scan's calibration views")
    p.add_argument("scan", help="scan folder")
    _add_recipe_args(p, required=False)
    p.add_argument("-o", "--output", help="calibration YAML (default SCAN/calibration.yaml)")
    _add_output_args(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("process", help="images -> calibration, masks, hull, mesh, leaves, traits")
    p.add_argument("scan", help="scan folder")
    _add_recipe_args(p, required=False)
    p.add_argument("--calibration", help="use this calibration YAML instead of calibrating")
    p.add_argument("--out", help="run folder (default SCAN-run beside the scan)")
    p.add_argument("--profile", action="store_true", help="print seconds per stage")
    _add_sample_sheet_arg(p)
    _add_force(p)
    _add_output_args(p)
    p.set_defaults(func=cmd_process)

    p = sub.add_parser("evaluate", help="compare a run with the virtual scanner's truth (JSON)")
    p.add_argument("run", help="run folder")
    p.add_argument("--truth", help="ground_truth folder (default: the run's scan/ground_truth)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("demo", help="virtual scan of a plant, full pipeline, report")
    p.add_argument("--out", default="plantscan-demo", help="output folder")
    p.add_argument("--recipe", default="plastic-dicot", help="shipped recipe name or file")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE")
    _add_output_args(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("warm-up", help="compile the plugins' kernels now, so that the first "
                       "scan and run do not wait for it (make setup runs it)")
    _add_output_args(p)
    p.set_defaults(func=cmd_warm_up)

    p = sub.add_parser("batch", help="process many scans in parallel on Dask")
    p.add_argument("scans", nargs="+", help="scan folders")
    _add_recipe_args(p)
    p.add_argument("--out", default="plantscan-batch", help="output folder for runs + summary")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: local)")
    p.add_argument("--workers", type=positive_int, default=2, help="local workers (default 2)")
    _add_force(p)
    p.add_argument("--calibration", help="use this calibration YAML for every plant instead of "
                   "calibrating each scan (one calibration per session)")
    _add_sample_sheet_arg(p)
    _add_output_args(p)
    p.set_defaults(func=cmd_batch)

    (manager or get_manager()).add_commands(sub)
    return parser


RUN_LOG = "run.log"


def _log_folder(args: argparse.Namespace | None) -> Path:
    """Where ``run.log`` goes: the run or scan folder of the command when it exists."""
    for name in ("out", "run", "scan"):
        value = getattr(args, name, None) if args is not None else None
        if isinstance(value, str) and Path(value).is_dir():
            return Path(value)
    return Path(tempfile.gettempdir())


def write_run_log(folder: Path, argv: list[str], exc: BaseException) -> Path | None:
    """Append the traceback of ``exc`` to ``folder/run.log``; None when it cannot be written.

    Never raises: a full disk or a read-only folder must not hide the error itself.
    """
    path = Path(folder) / RUN_LOG
    text = (f"--- {datetime.datetime.now().isoformat(timespec='seconds')} plantscan "
            f"{__version__}: plantscan {' '.join(argv)}\n"
            + "".join(traceback.format_exception(exc)))
    try:
        with open(path, "a", encoding="utf-8") as f:
            f.write(text)
        return path
    except Exception:  # noqa: BLE001 - the log is a courtesy; the message on stderr is the error
        return None


def _report(exc: BaseException, argv: list[str], args, debug: bool) -> None:
    """Print ``exc`` for a user, its traceback to run.log (and to the screen with --debug)."""
    log = write_run_log(_log_folder(args), argv, exc)
    where = f" (traceback in {log})" if log is not None else ""
    if isinstance(exc, RecipeError):
        for path, msg in exc.errors:
            print(f"{path}: {msg}" if path else f"{exc.source}: {msg}", file=sys.stderr)
        print(f"{exc.source}: {len(exc.errors)} error(s)", file=sys.stderr)
    elif isinstance(exc, PlantScanError):
        print(f"plantscan: error: {exc}", file=sys.stderr)
        cause = exc.__cause__
        if cause is not None and not isinstance(cause, PlantScanError):
            print(f"  caused by {type(cause).__name__}: {cause}", file=sys.stderr)
    else:
        print(f"plantscan: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
        print("  hint: this is a bug in plantscan or one of its plugins, not in your input; "
              f"please report it with run.log{where} (--debug prints it)", file=sys.stderr)
    if debug:
        traceback.print_exception(exc, file=sys.stderr)


# Commands that go on to work for minutes: loading the plugins is their first step on screen.
_LONG_COMMANDS = frozenset({"scan", "calibrate", "process", "demo", "batch", "warm-up"})


def _show_plugin_loading(argv: list[str]) -> None:
    """Load the plugins under a progress step when a long command follows.

    The parser needs the plugins (they add commands), and importing them (numba,
    Open3D, SciPy, OpenCV) takes 2 s on an idle machine and up to 8 s on a busy
    one: without this the command would start in silence.
    """
    words = [a for a in argv if not a.startswith("-")]
    if not words or words[0] not in _LONG_COMMANDS or {"-q", "--quiet", "-h", "--help"} & set(argv):
        return
    from plantscan_core.progress import Display

    display = Display("auto")
    with display.step("load plugins"):
        get_manager()
    display.close()


def main(argv: list[str] | None = None) -> int:
    """Run the command; every error is a message on stderr, never a traceback (--debug).

    Exit status: 0 done, 2 an error in the user's input or setup (the message names the
    file, line, view or parameter), 1 an internal error (a bug: traceback in run.log),
    130 interrupted.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = bool(os.environ.get("PLANTSCAN_DEBUG")) or "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    args = None
    try:
        _show_plugin_loading(argv)
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return EXIT_USER_ERROR
        return int(args.func(args) or 0)
    except PlantScanError as exc:
        _report(exc, argv, args, debug)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("plantscan: interrupted; everything finished so far is kept", file=sys.stderr)
        return 130
    except SystemExit:
        raise  # argparse's own exit (status 2 for a bad argument, 0 for --help)
    except BaseException as exc:  # noqa: BLE001 - the top level: no traceback reaches a user
        _report(exc, argv, args, debug)
        return EXIT_INTERNAL_ERROR


if __name__ == "__main__":
    sys.exit(main())

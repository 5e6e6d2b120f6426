"""Processing orchestrator: runs the stage table over a scan folder into a run folder.

The steps and their order are the table in ``plantscan_core.steps``.  Each
step's result is cached in the run folder, keyed by the step's plugin,
version, parameters and the keys of what it needs: changing segmentation
parameters recomputes segmentation and what follows, never calibration.  Input
files are fingerprinted by (path, size, modification time) — cheap on hundreds
of 18 MP images — and the scan's ``views.jsonl`` by content.  Each step's
``StageReport`` is stored with its cache entry and reported again on a cache hit.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from plantscan_core import __version__
from plantscan_core.data import plain
from plantscan_core.errors import PlantScanError, StageError
from plantscan_core.lock import one_writer
from plantscan_core.metadata import Metadata, resolve_metadata, scan_summary
from plantscan_core.parallel import image_pool
from plantscan_core.photos import Photos
from plantscan_core.plugins import PluginManager
from plantscan_core.progress import Display, RunLog, display_for, run_logging
from plantscan_core.recipe import Recipe, StageSpec, stage_spec
from plantscan_core.runfolder import CACHE_DIR
from plantscan_core.scanfolder import ScanFolder, atomic_write_text, now_iso
from plantscan_core.stages import RunResult, StageContext, StageReport
from plantscan_core.steps import Step, StepRun, sha

# segment.reduce "auto" keeps the long side of the images the segmenter sees at least this
# long: on the 18 MP virtual paper-72 scan 1296 px masks (1/4) merged two leaf pairs at 512^3
# where 2592 px ones (1/2) found all 12 (docs/decisions.md).
AUTO_REDUCE_MIN_LONG_SIDE_PX = 2400


def resolve_reduce(reduce: int | str, image_paths: Sequence[Path]) -> int:
    """``segment.reduce`` as a number; "auto" from the size in the first readable header.

    A file whose header cannot be read is skipped here: decoding it in the
    segment stage names it (and the stage) properly.  No readable header: 1.
    """
    if reduce != "auto":
        return int(reduce)
    from PIL import Image, UnidentifiedImageError

    for path in image_paths:
        try:
            with Image.open(path) as im:  # reads the header only
                long_side = max(im.size)
        except (OSError, UnidentifiedImageError):
            continue
        for r in (8, 4, 2):
            if long_side / r >= AUTO_REDUCE_MIN_LONG_SIDE_PX:
                return r
        return 1
    return 1


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux reports kB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


# --------------------------------------------------------------------------- the run
class Run:
    """One processing run (internal): the steps' execution, caching and run.json."""

    def __init__(self, scan: ScanFolder, recipe: Recipe, run_dir: Path, manager: PluginManager,
                 raw_recipe: dict | None, overrides: list[str], progress: bool | Display,
                 workers: int | None, metadata: Metadata | None = None) -> None:
        self.scan = scan
        self.recipe = recipe
        self.run_dir = Path(run_dir)
        self.manager = manager
        self.display = display_for(progress)
        self.log: RunLog | None = None  # set by process() for the run's duration
        # the step running in this thread (its items counted by _map): two steps may run at
        # once (``process``), each in its own thread
        self._local = threading.local()
        self._lock = threading.RLock()  # run.json's record and the results, between steps
        self.workers = workers or min(4, os.cpu_count() or 1)
        self.context = StageContext(recipe=recipe, scan=scan, run_dir=self.run_dir)
        self.result = RunResult(run_dir=self.run_dir, recipe=recipe, scan=scan)
        self.keys: dict[str, str] = {}  # result name -> cache key of the step that made it
        self._photos: dict[int, Photos] = {}
        if metadata is None:
            metadata = resolve_metadata(recipe.plant, recipe.experiment, scan.info)
        self.info: dict[str, Any] = {
            "format": "plantscan-run/1",
            "plantscan_version": __version__,
            "created": now_iso(),
            "scan": str(scan.root.resolve()),
            "plant_id": metadata.plant.id,
            # who the plant is and when it was scanned: what the results store keeps
            "metadata": metadata.to_dict(),
            "scan_record": scan_summary(scan),
            "recipe": raw_recipe if raw_recipe is not None else recipe.model_dump(mode="json"),
            "overrides": list(overrides),
            "stages": {},
            "timings_s": {},
            "input_hashes": {},
        }
        self.result.info = self.info
        self.step_run = StepRun(scan, self.run_dir, self.context, self.result, self._map,
                                self.photos_at)

    # ------------------------------------------------------------------ photos
    def prepare_photos(self, keep: bool) -> None:
        """Resolve the decode reduction and give the context the plant photos at it."""
        views = self.scan.views_by_role("plant")
        if self.recipe.segment is not None and views:
            self.context.reduce = resolve_reduce(self.recipe.segment.reduce,
                                                 [self.scan.path_of(v) for v in views[:8]])
            self.info["segment_reduce"] = self.context.reduce
        self.context.photos = Photos(self.scan, views, self.context.reduce, keep=keep)
        self._photos[self.context.reduce] = self.context.photos

    def photos_at(self, reduce: int) -> Photos:
        if reduce not in self._photos:
            self._photos[reduce] = Photos(self.scan, self.scan.views_by_role("plant"), reduce)
        return self._photos[reduce]

    # ------------------------------------------------------------------ cache
    def _cache_path(self, section: str) -> Path:
        return self.run_dir / CACHE_DIR / f"{section}.json"

    def _cached(self, section: str, key: str, files: list[Path]) -> dict | None:
        """The step's cache entry when its last result is for ``key`` and on disk, else None."""
        p = self._cache_path(section)
        if not p.exists() or not all(f.exists() for f in files):
            return None
        try:
            entry = json.loads(p.read_text())
        except (OSError, ValueError):
            return None
        return entry if isinstance(entry, dict) and entry.get("key") == key else None

    def _store(self, section: str, key: str, report: StageReport) -> None:
        entry = {"key": key, "at": now_iso(), "report": report.to_dict()}
        atomic_write_text(self._cache_path(section), json.dumps(entry))

    # ------------------------------------------------------------------ steps
    def inputs_key(self, step: Step) -> str:
        """The key of what ``step`` reads: its needs' keys and the scan files it reads."""
        parts: list[Any] = [self.keys[n] for n in step.needs]
        if step.scan_inputs is not None:
            scan_inputs = step.scan_inputs(self.step_run)
            with self._lock:
                self.info["input_hashes"][step.section] = sha(scan_inputs)
            parts.append(scan_inputs)
        return sha(parts)

    def use_file(self, step: Step, path: Path) -> None:
        """``step``'s result read from a file the user gave (``--calibration``)."""
        key = sha({"file": Path(path).read_bytes().hex()})
        value = step.from_file(path, self.step_run)
        report = StageReport(figures={"file": str(path)})
        self.info["stages"][step.section] = {"plugin": step.file_option, "file": str(path),
                                             "key": key, "info": report.to_dict()}
        self._keep(step, step.section, value, key, report)

    def run_step(self, step: Step, section: str, spec: StageSpec, inputs_key: str) -> Any:
        """Run (or load from the cache) one stage of ``step``; returns its result."""
        context, step_run = self.context, self.step_run
        if isinstance(step.photos, int) and step.photos != context.reduce:
            context = dataclasses.replace(context, photos=self.photos_at(step.photos))
            step_run = dataclasses.replace(step_run, context=context)
        plugin = self.manager.build(step.stage, spec.plugin, spec.params, context)
        params = plugin.params.model_dump(mode="json")
        identity = {"stage": step.stage, "plugin": spec.plugin, "version": plugin.version(),
                    "params": params, "inputs": inputs_key}
        input_files = getattr(plugin, "input_files", None)
        if input_files is not None:  # files a stage reads besides the scan's images: by content
            identity["files"] = [file_content_hash(p) for p in input_files(self.scan)]
        input_roles = getattr(plugin, "input_roles", None)
        if input_roles is not None:  # views a stage reads besides its step's own inputs
            from plantscan_core.steps import views_fingerprint

            identity["roles"] = {role: views_fingerprint(self.scan, self.scan.views_by_role(role))
                                 for role in input_roles(self.scan)}
        key = sha(identity)
        record = {"plugin": spec.plugin, "version": plugin.version(), "params": params,
                  "key": key}
        with self._lock:
            self.info["stages"][section] = record
        entry = self._cached(section, key, step.files(step_run)) if step.cached else None
        self.manager.before_stage(step.stage, plugin, context)
        title = f"{step.section} {spec.plugin}" if step.many else section  # export ply
        t0, c0 = time.perf_counter(), time.process_time()
        with self.display.step(title) as progress:
            self._local.step = progress
            try:
                with self._log_stage():
                    if entry is not None:
                        value = step.load(step_run)
                        plugin.report = StageReport.from_dict(entry.get("report"))
                    else:
                        self._cache_path(section).unlink(missing_ok=True)
                        value = step.run(plugin, step_run)
                        if step.cached:
                            self._store(section, key, plugin.report)
            except BaseException as exc:
                # The handler never raises: a full disk or a broken observer must not replace
                # the stage's own error (which names what went wrong) with its own.
                try:
                    self.manager.on_stage_error(step.stage, plugin, context, exc)
                    self._write_info()
                except Exception as handler_exc:  # noqa: BLE001
                    print(f"plantscan: warning: could not record the failure of {section} in "
                          f"{self.run_dir / 'run.json'} ({handler_exc})", file=sys.stderr)
                if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                    raise
                raise StageError(section, spec.plugin, str(exc) or type(exc).__name__) from exc
            if self.log is not None:
                progress.note = self.log.summarise(section, title, plugin.report.warnings,
                                                   cached=entry is not None)
            elif entry is not None:
                progress.note = "cached"
        self._local.step = None
        seconds = time.perf_counter() - t0
        with self._lock:
            record["cached"] = entry is not None
            record["info"] = plugin.report.to_dict()
            self.info["timings_s"][section] = round(seconds, 4)
            # the process's CPU: a step running beside another (``process``) counts both
            self.info.setdefault("cpu_s", {})[section] = round(time.process_time() - c0, 4)
            self.info.setdefault("peak_rss_mb", {})[section] = round(peak_rss_mb(), 1)
            self.result.timings[section] = seconds
            self._keep(step, section, value, key, plugin.report)
        self.manager.after_stage(step.stage, plugin, context, seconds, entry is not None)
        self._write_info()
        return value

    def _keep(self, step: Step, section: str, value: Any, key: str, report: StageReport) -> None:
        self.result.reports[section] = report
        if step.many:
            return
        self.keys[step.result] = key
        self.result.results[step.result] = value
        if step.result in RunResult.STEP_RESULTS:
            setattr(self.result, step.result, value)

    def run_many(self, step: Step, specs: list[StageSpec]) -> None:
        """A list section (exporters): each stage in turn, never cached."""
        values: list[Any] = []
        for i, spec in enumerate(specs):
            values += self.run_step(step, f"{step.section}.{i}", spec, now_iso()) or []
        self.result.results[step.result] = values
        self.info[step.result] = values

    def _log_stage(self):
        return self.log.stage() if self.log is not None else contextlib.nullcontext()

    def _map(self, fn: Callable[[int], Any], n: int, unit: str) -> list[Any]:
        """Run ``fn(i)`` for i < n on a thread pool (OpenCV releases the GIL), in order; the
        running step's progress counts them."""
        results: list[Any] = [None] * n
        step = getattr(self._local, "step", None)
        if step is not None:
            step.count(n, unit)
        with image_pool(self.workers) as pool:
            futures = {pool.submit(fn, i): i for i in range(n)}
            for fut in futures:
                results[futures[fut]] = fut.result()
                if step is not None:
                    step.advance()
        return results

    def _write_info(self) -> None:
        with self._lock:
            atomic_write_text(self.run_dir / "run.json", json.dumps(plain(self.info), indent=2))


def file_content_hash(path: Path) -> str:
    """SHA-256 of a file's content ("missing" when absent: the stage then names the file)."""
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except FileNotFoundError:
        return "missing"


def _run_steps(run: Run, steps: list[Step], named: list[Step], given: dict[str, Path]) -> None:
    """Run ``steps`` in table order; a step needing nothing runs beside the next one.

    A step with no needs reads only the scan (calibrate).  When the next step the
    recipe names does not need its result either (segment), the first runs in a worker
    thread while the next runs here, and a later step needing it (reconstruct), or a
    list step (the exports), or the end of the run waits for it.  The wall time saved
    is the idle core of either: the calibration's solve is one thread (paper-360 at
    18 MP: 2.7 of its 8 s), segmentation leaves ~10 % of two cores idle
    (docs/benchmarks/end_to_end.md).  One step at a time beside; none with one worker.

    A failure of either is raised after both have ended: the other's result is kept
    (its cache entry written), so a re-run after fixing the cause redoes only what
    failed.
    """
    beside: dict[str, Future] = {}  # result name -> the step computing it in the worker

    def wait_for(names: Sequence[str]) -> None:
        for name in names:
            if name in beside:
                beside.pop(name).result()  # the step's StageError, if it failed

    with ThreadPoolExecutor(1, thread_name_prefix="plantscan-step") as worker:
        for i, step in enumerate(steps):
            spec = stage_spec(run.recipe, step.section)
            wait_for(list(beside) if step.many else step.needs)
            if step.many:
                run.run_many(step, list(spec or []))
            elif step not in named or any(n not in run.keys for n in step.needs):
                with run._lock:
                    run.info.setdefault("skipped", []).append(step.section)
            elif step.section in given:
                run.use_file(step, given[step.section])
            else:
                key = run.inputs_key(step)
                following = next((s for s in steps[i + 1:] if s in named), None)
                if (not step.needs and not beside and run.workers > 1
                        and following is not None and not following.many
                        and step.result not in following.needs):
                    beside[step.result] = worker.submit(run.run_step, step, step.section,
                                                        spec, key)
                    with run._lock:  # their timings overlap (the CPU column counts both)
                        run.info.setdefault("side_by_side", []).append(
                            [step.section, following.section])
                else:
                    run.run_step(step, step.section, spec, key)
        wait_for(list(beside))


@one_writer("run_dir", "run folder")
def process(
    scan_dir: Path,
    recipe: Recipe,
    run_dir: Path,
    manager: PluginManager,
    *,
    raw_recipe: dict | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    calibration_path: Path | None = None,
    progress: bool | Display = False,
    workers: int | None = None,
    metadata: Metadata | None = None,
) -> RunResult:
    """Run the recipe's processing stages over ``scan_dir`` into ``run_dir``.

    ``progress``: a ``Display`` (the CLI's: rich in a terminal, plain lines
    otherwise), True for one chosen by stderr, False for warnings only.  The
    run's log goes to ``run_dir/run.log`` (``plantscan_core.progress``).

    The steps of the stage table run in order (``manager.registry.steps``:
    calibrate, segment, reconstruct, mesh, segment_mesh, measure, export, and
    any a plugin added); a step runs when the recipe names it and the results
    it needs exist (``run.json: skipped`` lists the others).  A step that reads
    only the scan runs beside the next one when that one does not need it
    (calibrate beside segment: ``_run_steps``).
    ``calibration_path`` replaces the calibrate stage with a saved calibration.
    ``metadata`` is the plant's and the experiment's (a sample sheet's row,
    resolved by the caller); by default the recipe's and the scan's own record.

    Returns
    -------
    RunResult : everything produced (fields of stages that did not run are None).
    """
    scan = ScanFolder.open(scan_dir)
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PlantScanError(f"{run_dir}: cannot create the run folder ({exc.strerror})") from exc
    run = Run(scan, recipe, run_dir, manager, raw_recipe, list(overrides), progress, workers,
              metadata)
    if scan.torn_line is not None:
        torn = (f"{scan.root / 'views.jsonl'}:{scan.torn_line}: torn last line (a crash while it "
                "was appended) left out: that view is not processed (scan --resume captures it)")
        run.info.setdefault("warnings", []).append(torn)
        print(f"plantscan: warning: {torn}", file=sys.stderr)
    given = {"calibrate": calibration_path} if calibration_path is not None else {}
    steps = list(manager.registry.steps)
    named = [s for s in steps if stage_spec(recipe, s.section) or s.section in given]
    run.prepare_photos(keep=any(s.photos == "segment" for s in named))
    t0, c0 = time.perf_counter(), time.process_time()
    with run_logging(run_dir, run.display) as run.log:
        logging.getLogger("plantscan.run").info(
            "process %s -> %s (recipe %s%s)", scan.root, run_dir, recipe.name,
            f", --set {' '.join(overrides)}" if overrides else "")
        _run_steps(run, steps, named, given)
        logging.getLogger("plantscan.run").info(
            "done in %.1f s%s", time.perf_counter() - t0,
            f"; not run: {', '.join(run.info['skipped'])}" if run.info.get("skipped") else "")
    run.log = None
    run.context.photos.release()
    if run.result.traits is not None:
        run.info["traits"] = {"leaf_count": len(run.result.traits.leaves),
                              "plant": plain(run.result.traits.plant)}
    run.info["timings_s"]["total"] = round(time.perf_counter() - t0, 4)
    run.info.setdefault("cpu_s", {})["total"] = round(time.process_time() - c0, 4)
    run.info.setdefault("peak_rss_mb", {})["total"] = round(peak_rss_mb(), 1)
    run._write_info()
    return run.result

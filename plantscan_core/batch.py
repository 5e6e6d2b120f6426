"""``plantscan batch``: many plants through the same per-plant pipeline, as Dask tasks.

One task per scan folder runs ``plantscan_core.pipeline.process`` in a Dask
worker process: an embedded ``distributed.LocalCluster`` (processes, one
thread each) by default, or the workers of a running scheduler when given its
address (``tcp://host:8786``; the workers must see the scan and output folders
at the same paths and have plantscan installed).

A plant that fails (corrupt scan, a stage error, even a crashed worker) is
reported with its error; the others finish.  Results::

    OUT/
      <scan name>/            one run folder per plant (docs/formats.md)
      batch_summary.csv       one row per plant: scan, plant_id, status, error, seconds,
                              cpu_seconds, leaf_count, total_leaf_area_mm2, height_mm,
                              run_dir, worker
      traits_all.csv          every leaf of every plant that succeeded, with scan, plant_id,
                              scan_time, the plant's metadata (study, genotype, treatment,
                              replicate...; factor.NAME columns) and the leaf traits
      <scan name>/batch_error.txt   the traceback of a failed plant
"""

from __future__ import annotations

import csv
import io
import logging
import os
import sys
import time
import traceback
import uuid
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from plantscan_core.data import LEAF_TRAIT_COLUMNS, leaf_value_text
from plantscan_core.errors import PlantScanError
from plantscan_core.progress import Display, display_for
from plantscan_core.scanfolder import atomic_write_text

SUMMARY_CSV = "batch_summary.csv"
TRAITS_CSV = "traits_all.csv"
ERROR_TXT = "batch_error.txt"
SUMMARY_COLUMNS = ("scan", "plant_id", "status", "quality_flag", "quality_reasons", "error",
                   "seconds", "cpu_seconds", "leaf_count", "total_leaf_area_mm2", "height_mm",
                   "run_dir", "worker")
# who the plant is, from its metadata (the recipe, the scan, the sample sheet)
METADATA_COLUMNS = ("investigation_id", "study_id", "species", "genotype", "accession",
                    "treatment", "replicate", "sowing_date")
TRAITS_COLUMNS = ("scan", "plant_id", "scan_time", *METADATA_COLUMNS, *LEAF_TRAIT_COLUMNS)


@dataclass
class PlantOutcome:
    """What happened to one plant of a batch (one row of ``batch_summary.csv``)."""

    scan: str
    plant_id: str = ""
    status: str = "failed"  # "ok" | "failed": whether it ran, not whether to trust it
    quality_flag: str = ""  # the plant's flag, "ok" | "check" | "fail" (docs/leaves.md, Trust)
    quality_reasons: str = ""  # "; "-separated
    error: str = ""
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # CPU time of the worker process while it ran this plant
    leaf_count: int | None = None
    total_leaf_area_mm2: float | None = None
    height_mm: float | None = None
    run_dir: str = ""
    worker: str = ""
    scan_time: str = ""
    warnings: int = 0  # of every stage's report (in the plant's run.log and report)
    leaves: list[dict[str, Any]] = field(default_factory=list, repr=False)
    metadata: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass
class BatchSummary:
    """All plants of a batch, in the order the scans were given.

    Attributes
    ----------
    plants : list of PlantOutcome
    out_dir : Path
    summary_csv, traits_csv : Path
    seconds : float
        Wall time of the whole batch (cluster start included).
    scheduler : str
        ``"local (N workers)"`` or the scheduler address.
    """

    plants: list[PlantOutcome]
    out_dir: Path
    summary_csv: Path
    traits_csv: Path
    seconds: float
    scheduler: str

    @property
    def failed(self) -> int:
        """Number of plants that failed (the CLI exits non-zero when > 0)."""
        return sum(not p.ok for p in self.plants)

    @property
    def succeeded(self) -> int:
        return sum(p.ok for p in self.plants)

    @property
    def exit_status(self) -> int:
        """Shell exit status saying how many plants failed (capped at 125, 0 = all fine)."""
        return min(self.failed, 125)

    def __str__(self) -> str:
        lines = [f"{'scan':<28} {'status':<7} {'seconds':>8} {'leaves':>6}  error"]
        for p in self.plants:
            leaves = "" if p.leaf_count is None else str(p.leaf_count)
            error = p.error.splitlines()[0] if p.error else ""
            lines.append(f"{p.scan[-28:]:<28} {p.status:<7} {p.seconds:>8.1f} {leaves:>6}  "
                         f"{error[:160]}")
        lines.append(f"{self.succeeded} succeeded, {self.failed} failed in {self.seconds:.1f} s "
                     f"on {self.scheduler}")
        lines.append(f"summary: {self.summary_csv}")
        lines.append(f"traits:  {self.traits_csv}")
        return "\n".join(lines)


# --------------------------------------------------------------------------- the task
_MANAGER = None


def _worker_manager():
    """Plugins loaded once per worker process (entry points, like ``plantscan process``)."""
    global _MANAGER
    if _MANAGER is None:
        from plantscan_core.plugins import load_plugins

        _MANAGER = load_plugins()
    return _MANAGER


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def process_plant(scan_dir: str, recipe_path: str, overrides: Sequence[str], run_dir: str,
                  threads: int = 1, calibration_path: str | None = None,
                  metadata: dict[str, Any] | None = None) -> PlantOutcome:
    """Process one scan; never raises for a plant's own failure (it is returned as such).

    Parameters
    ----------
    scan_dir, recipe_path, run_dir : str
        Paths as the worker sees them.
    overrides : sequence of str
        ``--set PATH=VALUE`` overrides of the recipe.
    threads : int
        Threads a plant may use inside its stages (1 when plants already fill the cores).
    calibration_path : str, optional
        A calibration YAML used instead of calibrating (one per session).
    metadata : dict, optional
        The plant's resolved metadata (``Metadata.to_dict``, from a sample sheet).
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    outcome = PlantOutcome(scan=str(scan_dir), run_dir=str(run_dir), worker=_worker_name())
    try:
        (Path(run_dir) / ERROR_TXT).unlink(missing_ok=True)  # from an earlier failed attempt
        from plantscan_core.pipeline import process
        from plantscan_core.recipe import apply_overrides, load_recipe, read_recipe_file
        from plantscan_core.scanfolder import ScanFolder

        manager = _worker_manager()
        _limit_threads(threads)  # after the plugins imported their numerical libraries
        recipe = load_recipe(recipe_path, list(overrides), manager.registry)
        raw = apply_overrides(read_recipe_file(Path(recipe_path)), list(overrides))
        from plantscan_core.metadata import Metadata, resolve_metadata

        scan_info = ScanFolder.open(Path(scan_dir)).info
        md = Metadata.from_dict(metadata) if metadata else resolve_metadata(
            recipe.plant, recipe.experiment, scan_info)
        outcome.plant_id = md.plant.id
        outcome.metadata = md.to_dict()
        outcome.scan_time = str(scan_info.get("created", ""))
        # the worker says nothing itself: the plant's run.log has its log, the batch's
        # display one line per plant
        result = process(Path(scan_dir), recipe, Path(run_dir), manager, raw_recipe=raw,
                         overrides=list(overrides), workers=threads,
                         calibration_path=Path(calibration_path) if calibration_path else None,
                         metadata=md, progress=Display("off"))
        outcome.warnings = len(result.warnings())
        if result.traits is not None:
            outcome.leaf_count = len(result.traits.leaves)
            plant = result.traits.plant
            outcome.total_leaf_area_mm2 = _float_or_none(plant.get("total_leaf_area_mm2"))
            outcome.height_mm = _float_or_none(plant.get("height_mm"))
            outcome.quality_flag = str(plant.get("quality_flag") or "")
            outcome.quality_reasons = "; ".join(plant.get("quality_reasons") or [])
            outcome.leaves = [{c: getattr(leaf, c) for c in LEAF_TRAIT_COLUMNS}
                              for leaf in result.traits.leaves]
        outcome.status = "ok"
    except Exception as exc:  # noqa: BLE001 - one plant's failure must not stop the batch
        outcome.status = "failed"
        outcome.error = _describe(exc)
        try:
            Path(run_dir).mkdir(parents=True, exist_ok=True)
            atomic_write_text(Path(run_dir) / ERROR_TXT, "".join(traceback.format_exception(exc)))
        except OSError:
            pass  # the error is still in the summary
    outcome.seconds = round(time.perf_counter() - t0, 3)
    outcome.cpu_seconds = round(time.process_time() - cpu0, 3)
    return outcome


def _limit_threads(threads: int) -> None:
    """At most ``threads`` threads inside OpenCV and numba for this plant (one plant per core)."""
    import cv2

    cv2.setNumThreads(threads)
    if "numba" in sys.modules:  # only when a plugin uses it; importing it costs ~0.5 s
        import numba

        # Thread-local in numba: set in the thread that runs the stages (this one).
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def _float_or_none(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _describe(exc: BaseException) -> str:
    """One-line error for the summary; user errors (PlantScanError) as their own message."""
    if isinstance(exc, PlantScanError):
        text = str(exc)
        cause = exc.__cause__
        if cause is not None and not isinstance(cause, PlantScanError):
            text += f" ({type(cause).__name__}: {cause})"
        return text
    return f"{type(exc).__name__}: {exc}"


# --------------------------------------------------------------------------- the batch
def _run_dirs(scans: list[Path], out_dir: Path) -> list[Path]:
    """One run folder per scan, named after the scan folder (suffixed when names repeat)."""
    used: set[str] = set()
    out = []
    for scan in scans:
        base = scan.resolve().name or "scan"
        name, n = base, 1
        while name in used:
            n += 1
            name = f"{base}-{n}"
        used.add(name)
        out.append(out_dir / name)
    return out


def write_summary(plants: list[PlantOutcome], path: Path) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SUMMARY_COLUMNS)
    for p in plants:
        row = asdict(p)
        w.writerow(["" if row[c] is None else row[c] for c in SUMMARY_COLUMNS])
    atomic_write_text(path, buf.getvalue())


def write_traits(plants: list[PlantOutcome], path: Path) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    factors = sorted({k for p in plants if p.ok
                      for k in (p.metadata.get("plant") or {}).get("factors", {})})
    w.writerow([*TRAITS_COLUMNS[:3 + len(METADATA_COLUMNS)], *(f"factor.{k}" for k in factors),
                *LEAF_TRAIT_COLUMNS])
    for p in plants:
        if not p.ok:
            continue
        plant = p.metadata.get("plant") or {}
        experiment = p.metadata.get("experiment") or {}
        who = [("" if (v := {**plant, **experiment}.get(c)) is None else v)
               for c in METADATA_COLUMNS]
        who += [plant.get("factors", {}).get(k, "") for k in factors]
        for leaf in p.leaves:
            w.writerow([p.scan, p.plant_id, p.scan_time, *who, leaf["leaf_id"],
                        *(leaf_value_text(leaf[c]) for c in LEAF_TRAIT_COLUMNS[1:])])
    atomic_write_text(path, buf.getvalue())


def run_batch(
    scans: list[Path],
    recipe_path: Path,
    out_dir: Path,
    *,
    overrides: Sequence[str] = (),
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool | Display = True,
    connect_timeout_s: float = 30.0,
    task: Callable[..., PlantOutcome] = process_plant,
    calibration: Path | None = None,
    sample_sheet: Path | None = None,
) -> BatchSummary:
    """Process every scan in ``scans`` with the recipe, one Dask task per plant.

    Parameters
    ----------
    scans : list of Path
        Scan folders.  A folder that is not a readable scan fails alone.
    recipe_path : Path
        Recipe file, read (with ``overrides``) inside each worker.
    out_dir : Path
        Receives one run folder per plant, ``batch_summary.csv`` and ``traits_all.csv``.
    overrides : sequence of str
        ``--set PATH=VALUE`` recipe overrides.
    scheduler : str, optional
        Address of a running Dask scheduler; None starts a local cluster of ``workers``
        processes (one thread each) for this batch.
    workers : int
        Local worker processes (ignored with ``scheduler``).
    progress : Display or bool
        Where the batch shows its progress (the plants done, the time left from the
        rate so far) and one line per finished plant; True: one chosen by stderr.
    connect_timeout_s : float
        How long to wait for ``scheduler`` to answer.
    task : callable
        The per-plant function, ``process_plant`` or one with its signature (an
        importable module-level function: it is pickled to the workers).
    calibration : Path, optional
        A calibration YAML (e.g. the session's, from ``plantscan calibrate``)
        used by every plant instead of calibrating each scan; read once here,
        so a bad file fails before any work.
    sample_sheet : Path, optional
        CSV of plant metadata per scan or plant id (``plantscan_core.metadata``),
        checked in full against the scans before any work: a row naming a
        missing scan, an unknown column, a bad date, a plant id given two
        genotypes raise ``SampleSheetError`` listing every problem.

    Returns
    -------
    BatchSummary : ``summary.failed`` plants failed; ``exit_status`` for the shell.
    """
    from distributed import Client, LocalCluster, as_completed

    from plantscan_core.recipe import load_recipe

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    scans = [Path(s).resolve() for s in scans]
    out_dir = Path(out_dir).resolve()
    recipe_path = Path(recipe_path).resolve()
    if not scans:
        raise PlantScanError("batch: no scan folder given")
    # A broken recipe would fail every plant the same way: say it once, before any work.
    from plantscan_core.plugins import get_manager

    recipe = load_recipe(recipe_path, list(overrides), get_manager().registry)
    per_plant: list[dict[str, Any]] = [{} for _ in scans]
    if sample_sheet is not None:
        for kwargs, md in zip(per_plant, sheet_metadata(Path(sample_sheet), scans, recipe)):
            if md is not None:
                kwargs["metadata"] = md.to_dict()
    extra = {}
    if calibration is not None:
        from plantscan_core.data import Calibration

        calibration = Path(calibration).resolve()
        Calibration.load(calibration)  # names the file when missing or malformed
        extra["calibration_path"] = str(calibration)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_dirs = _run_dirs(scans, out_dir)
    t0 = time.perf_counter()
    batch_id = uuid.uuid4().hex[:8]  # task keys unique even when batches share a scheduler
    cluster = None
    if scheduler:
        client = Client(scheduler, timeout=connect_timeout_s)
        where = f"scheduler {scheduler}"
    else:
        # One plant per single-threaded worker process: numba's parallel loops (hull) would
        # otherwise start one thread per core in every worker and oversubscribe the cores
        # (Dask already pins OMP/MKL/OpenBLAS to 1 thread in its workers).  With several
        # workers no core is idle for the leaf stages' ray-casting helper (plantscan_leaves
        # .rays): its start would be CPU taken from the other plants.
        env = {"NUMBA_NUM_THREADS": "1"}
        if workers > 1:
            env["PLANTSCAN_RAY_HELPER"] = "0"
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, env=env)
        client = Client(cluster)
        where = f"local cluster ({workers} worker{'s' if workers > 1 else ''})"
    outcomes: dict[int, PlantOutcome] = {}
    try:
        futures = {
            client.submit(task, str(scan), str(recipe_path), list(overrides), str(rd),
                          1, key=f"plantscan-{batch_id}-{i}-{scan.name}", pure=False,
                          **extra, **per_plant[i]): i
            for i, (scan, rd) in enumerate(zip(scans, run_dirs, strict=True))
        }
        display = display_for(progress)
        with display.step(f"plants on {where}", len(futures), "plants") as step:
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    outcome = fut.result()
                except Exception as exc:  # noqa: BLE001 - a killed worker, lost connection...
                    outcome = PlantOutcome(scan=str(scans[i]), run_dir=str(run_dirs[i]),
                                           error=f"task failed on the cluster: {_describe(exc)}")
                outcomes[i] = outcome
                display.message(_plant_line(outcome),
                                logging.INFO if outcome.ok else logging.WARNING)
                step.advance()
    finally:
        # Workers still busy with a cancelled plant are killed by the nanny on close, which
        # says so in a warning per worker: nothing a user can act on at the end of a batch.
        nanny = logging.getLogger("distributed.nanny")
        level = nanny.level
        nanny.setLevel(logging.ERROR)
        try:
            client.close()
            if cluster is not None:
                cluster.close()
        finally:
            nanny.setLevel(level)
    plants = [outcomes[i] for i in range(len(scans))]
    summary = BatchSummary(plants, out_dir, out_dir / SUMMARY_CSV, out_dir / TRAITS_CSV,
                           round(time.perf_counter() - t0, 3), where)
    write_summary(plants, summary.summary_csv)
    write_traits(plants, summary.traits_csv)
    return summary


def sheet_metadata(sheet_path: Path, scans: list[Path], recipe) -> list:
    """Every scan's metadata with the sample sheet's row; all problems at once, before work.

    ``SampleSheetError`` for a bad sheet (``load_sample_sheet``) and for two
    scans that make one plant id two genotypes.  A scan folder that cannot be
    read gets None (its plant fails alone, as without a sheet).
    """
    from plantscan_core.errors import ScanFolderError
    from plantscan_core.metadata import (
        SampleSheetError,
        check_plant_consistency,
        load_sample_sheet,
    )
    from plantscan_core.scanfolder import ScanFolder

    sheet = load_sample_sheet(sheet_path)
    out = []
    for scan in scans:
        try:
            info = ScanFolder.open(scan).info
        except ScanFolderError:
            out.append(None)
            continue
        out.append(sheet.metadata_for(recipe.plant, recipe.experiment, scan, info))
    errors = check_plant_consistency([(str(s), md) for s, md in zip(scans, out)
                                      if md is not None])
    if errors:
        raise SampleSheetError(errors, str(sheet_path))
    return out


def _plant_line(p: PlantOutcome) -> str:
    """One line per finished plant: status, scan, seconds, leaves and warnings or the error."""
    if p.ok:
        detail = f"{p.leaf_count} leaves" if p.leaf_count is not None else "done"
        if p.warnings:
            detail += f", {p.warnings} warning{'s' if p.warnings > 1 else ''} (its run.log)"
        return f"ok {Path(p.scan).name} ({p.seconds:.1f} s) {detail}"
    return f"FAILED {Path(p.scan).name} ({p.seconds:.1f} s) {p.error[:160]}"

"""The processing pipeline as one table of steps.

Each ``Step`` declares its recipe section, its stage base, the results it needs
from earlier steps, how it runs the plugin, which files hold its result and how
they are read back.  ``pipeline.process`` is one loop over the table: a step
runs when the recipe names its section and every result it needs exists; its
cache key is its plugin, version and parameters with the keys of what it needs
(and the fingerprints of the scan files it reads).  The recipe's processing
sections, their order and the stage kinds a plugin may implement are derived
from this table.

Adding an optional stage is one base class (a subclass of ``Stage``), one
``Step`` and one recipe field; a plugin can add a step to its registry's table
for itself (``registry.add_step(step, after="reconstruct")``; see
docs/plugin-guide.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from plantscan_core.data import (
    Calibration,
    CarvingViews,
    LabelledMesh,
    Mesh,
    Silhouette,
    Silhouettes,
    Traits,
    ViewRecord,
    Volume,
    plain,
)
from plantscan_core.errors import DataError, PlantScanError
from plantscan_core.runfolder import MASKS_DIR, read_mask, write_mask, write_ply
from plantscan_core.scanfolder import atomic_write_text
from plantscan_core.stages import (
    Calibrator,
    Exporter,
    Measurer,
    Mesher,
    MeshSegmenter,
    Reconstructor,
    ResultsStore,
    RunResult,
    Segmenter,
    Stage,
    StageContext,
    ViewPlanner,
)
from plantscan_core.trajectory import ViewPlan

if TYPE_CHECKING:
    from plantscan_core.photos import Photos
    from plantscan_core.scanfolder import ScanFolder


# --------------------------------------------------------------------------- fingerprints
def sha(obj: Any) -> str:
    """SHA-256 of the canonical JSON of ``obj`` (cache keys)."""
    return hashlib.sha256(json.dumps(plain(obj), sort_keys=True, default=str).encode()).hexdigest()


def file_fingerprint(path: Path) -> str:
    """Cheap identity of an input file: name, size and modification time (ns)."""
    st = Path(path).stat()
    return f"{Path(path).name}:{st.st_size}:{st.st_mtime_ns}"


def views_fingerprint(scan: ScanFolder, views: list[ViewRecord]) -> str:
    return sha([[v.to_dict(), file_fingerprint(scan.path_of(v))] for v in views])


# --------------------------------------------------------------------------- the table
@dataclass
class StepRun:
    """What a step's functions see of the run.

    Attributes
    ----------
    scan : ScanFolder
    run_dir : Path
    context : StageContext
        The context every stage of the run is built with (``reduce``, ``photos``).
    result : RunResult
        What the run produced so far; ``result.results`` by result name.
    map : callable ``(fn, n, unit) -> list``
        ``[fn(i) for i in range(n)]`` on the run's thread pool; the step's progress
        counts the ``n`` items (``unit``: what they are, e.g. ``"views"``).
    photos_at : callable ``(reduce) -> Photos``
        The plant photos at a reduction (the context's are shared with segmentation).
    """

    scan: ScanFolder
    run_dir: Path
    context: StageContext
    result: RunResult
    map: Callable[[Callable[[int], Any], int, str], list[Any]]
    photos_at: Callable[[int], Photos]

    @property
    def results(self) -> dict[str, Any]:
        """What the steps before produced, by result name (``calibration``, ``silhouettes``...)."""
        return self.result.results

    def path(self, name: str) -> Path:
        return self.run_dir / name


def _no_files(run: StepRun) -> list[Path]:
    return []


@dataclass(frozen=True)
class Step:
    """One processing step of the table.

    Attributes
    ----------
    section : str
        Its recipe section, and its name in ``run.json`` and ``cache/``.
    base : type of Stage
        The stage base its plugins subclass (the plugin kind is ``base.stage``).
    result : str
        The name of its result; a ``RunResult`` attribute when one has the name.
        A step may produce the result of an earlier one (a refinement of the
        volume produces ``volume``), and the steps after it get the new one.
    run : callable ``(plugin, StepRun) -> result``
        Computes the result with the plugin and writes its files.
    load : callable ``(StepRun) -> result``
        Reads the result back from its files (a cache hit).
    needs : tuple of str
        Results of earlier steps it needs; without one of them it is skipped.
    files : callable ``(StepRun) -> list of Path``
        Files that must exist for a cache hit.
    scan_inputs : callable ``(StepRun) -> JSON value``, optional
        Fingerprint of the scan files it reads (part of its cache key).
    photos : "segment", int or None
        The step needs the plant photos: at segmentation's reduction
        ("segment": decoded once, segmentation's photos are kept for it) or at
        1/n; ``StepRun.context.photos`` holds them when it runs.
    from_file : callable ``(Path, StepRun) -> result``, optional
        The step can be replaced by a file the user gives, with the command-line
        option ``file_option`` (``--calibration``).
    many : bool
        The section is a list of stages, each run in turn (exporters).
    cached : bool
        False for steps run every time (exporters: cheap, their input is the whole run).
    """

    section: str
    base: type[Stage]
    result: str
    run: Callable[[Stage, StepRun], Any]
    load: Callable[[StepRun], Any]
    needs: tuple[str, ...] = ()
    files: Callable[[StepRun], list[Path]] = _no_files
    scan_inputs: Callable[[StepRun], Any] | None = None
    photos: Literal["segment"] | int | None = None
    from_file: Callable[[Path, StepRun], Any] | None = None
    file_option: str = ""
    many: bool = False
    cached: bool = True

    @property
    def stage(self) -> str:
        """The plugin kind of the step (``"reconstructor"``)."""
        return self.base.stage


class StageTable:
    """The ordered steps of processing (a copy per plugin registry: plugins may add steps)."""

    def __init__(self, steps: Sequence[Step]) -> None:
        self._steps: list[Step] = []
        for step in steps:
            self.add(step)

    def add(self, step: Step, after: str | None = None) -> None:
        """Insert ``step`` after the section ``after`` (default: before the exporters).

        ``ValueError`` when its section is taken or ``after`` is not in the table.
        """
        if step.section in self.sections:
            raise ValueError(f"the stage table already has a step {step.section!r}")
        taken = {s.stage: s.base for s in self._steps}
        if taken.get(step.stage, step.base) is not step.base:
            raise ValueError(f"step {step.section!r}: stage kind {step.stage!r} is "
                             f"{taken[step.stage].__name__}'s")
        if after is None:
            at = next((i for i, s in enumerate(self._steps) if s.many), len(self._steps))
        elif after in self.sections:
            at = self.sections.index(after) + 1
        else:
            raise ValueError(f"no step {after!r} to add {step.section!r} after; steps: "
                             f"{', '.join(self.sections)}")
        self._steps.insert(at, step)

    def remove(self, section: str) -> None:
        self._steps = [s for s in self._steps if s.section != section]

    @property
    def sections(self) -> list[str]:
        return [s.section for s in self._steps]

    @property
    def bases(self) -> dict[str, type[Stage]]:
        """Stage kind -> base of every step, in table order."""
        return {s.stage: s.base for s in self._steps}

    def __iter__(self) -> Iterator[Step]:
        return iter(list(self._steps))

    def __getitem__(self, section: str) -> Step:
        for s in self._steps:
            if s.section == section:
                return s
        raise KeyError(section)

    def copy(self) -> StageTable:
        return StageTable(self._steps)


# --------------------------------------------------------------------------- calibrate
def _calibration_views(run: StepRun) -> str:
    return views_fingerprint(run.scan, run.scan.views_by_role("calibration"))


def _calibrate(plugin: Calibrator, run: StepRun) -> Calibration:
    calibration = plugin.calibrate(run.scan)
    calibration.save(run.path("calibration.yaml"))
    return calibration


def _calibration_from_file(path: Path, run: StepRun) -> Calibration:
    calibration = Calibration.load(path)
    calibration.save(run.path("calibration.yaml"))
    return calibration


# --------------------------------------------------------------------------- segment
def plant_views(scan: ScanFolder) -> list[ViewRecord]:
    """The scan's plant views; ``DataError`` when it has none."""
    views = scan.views_by_role("plant")
    if not views:
        raise DataError(f"{scan.root}: the scan has no plant views")
    return views


def _mask_paths(run: StepRun) -> list[Path]:
    return [run.path(MASKS_DIR) / f"{v.index:05d}.png" for v in plant_views(run.scan)]


def _skip_marks(run: StepRun) -> list[Path]:
    """Where a view skipped as a bad image (``segment.bad_images: skip``) says why."""
    return [run.path(MASKS_DIR) / f"{v.index:05d}.skipped" for v in plant_views(run.scan)]


def _skips_bad_images(run: StepRun) -> bool:
    recipe = run.context.recipe
    return bool(recipe is not None and recipe.segment is not None
                and recipe.segment.bad_images == "skip")


def _skipped(run: StepRun) -> list[bool]:
    if not _skips_bad_images(run):
        return [False] * len(plant_views(run.scan))
    return [m.exists() and not p.exists() for p, m in zip(_mask_paths(run), _skip_marks(run))]


def _segment_outputs(run: StepRun) -> list[Path]:
    """The files of a segmentation: each view's mask, or the mark of a skipped view."""
    return [m if gone else p
            for p, m, gone in zip(_mask_paths(run), _skip_marks(run), _skipped(run))]


def _segment_inputs(run: StepRun) -> Any:
    photos = run.context.photos
    used = sorted({(v.camera, v.tilt_index) for v in photos.views} & set(photos.plates))
    return [views_fingerprint(run.scan, photos.views),
            views_fingerprint(run.scan, [photos.plates[k] for k in used]),
            {"reduce": photos.reduce}] + ([{"bad_images": "skip"}] if _skips_bad_images(run)
                                          else [])


def _segment(plugin: Segmenter, run: StepRun) -> Silhouettes:
    photos = run.context.photos
    paths, marks = _mask_paths(run), _skip_marks(run)
    skip_bad = _skips_bad_images(run)
    plugin.report.figure("reduce", photos.reduce)
    sizes: dict[str, tuple[tuple[int, ...], ViewRecord]] = {}
    size_lock = threading.Lock()

    def decoded(i: int) -> np.ndarray:
        """Photo ``i``, refused when another size than its camera's first photo."""
        v = photos.views[i]
        image = photos.image(i)
        with size_lock:
            first_shape, first = sizes.setdefault(v.camera, (image.shape, v))
        if image.shape != first_shape:
            raise DataError(
                f"{run.scan.path_of(v)}: view {v.index} is {image.shape[1]}x{image.shape[0]} "
                f"px but view {first.index} of the same camera {v.camera!r} is "
                f"{first_shape[1]}x{first_shape[0]} px (a replaced or cropped image?)")
        return image

    def one(i: int) -> Silhouette | None:
        v = photos.views[i]
        try:
            image = decoded(i)
        except DataError as exc:
            if not skip_bad:
                raise
            paths[i].unlink(missing_ok=True)
            atomic_write_text(marks[i], f"{exc}\n")
            _warn_skipped(plugin.report, v, str(exc))
            return None
        marks[i].unlink(missing_ok=True)
        plate = photos.background(v)
        photos.check_plate(v, image, plate)
        try:
            mask = np.asarray(plugin.segment(image, plate, v), dtype=bool)
        except PlantScanError:
            raise
        except Exception as exc:
            raise DataError(f"view {v.index} ({v.file}): {exc}") from exc
        if mask.shape != image.shape[:2]:
            raise DataError(f"view {v.index} ({v.file}): segmenter returned a mask of "
                            f"shape {mask.shape}, image is {image.shape[:2]}")
        write_mask(paths[i], mask)
        silhouette = Silhouette(v, mask)
        if silhouette.area == 0:
            plugin.report.warn("empty-mask", f"view {v.index}: the mask is empty (no plant "
                               "pixel); the hull is carved away wherever this view looks",
                               view=v.index, file=v.file)
        return silhouette

    run.path(MASKS_DIR).mkdir(parents=True, exist_ok=True)
    made = run.map(one, len(photos.views), "views")
    silhouettes = Silhouettes([s for s in made if s is not None])
    plugin.report.count("views", len(silhouettes))
    if len(made) > len(silhouettes):
        plugin.report.count("views_skipped", len(made) - len(silhouettes))
    return silhouettes


def _warn_skipped(report, view: ViewRecord, reason: str) -> None:
    report.warn("bad-image", f"view {view.index} ({view.file}) skipped: {reason}",
                view=view.index, file=view.file)
    print(f"plantscan: warning: view {view.index} ({view.file}) skipped: {reason}",
          file=sys.stderr)


def _load_silhouettes(run: StepRun) -> Silhouettes:
    return Silhouettes([Silhouette(v, read_mask(p)) for v, p, gone in
                        zip(plant_views(run.scan), _mask_paths(run), _skipped(run)) if not gone])


# --------------------------------------------------------------------------- reconstruct
def calibration_for_masks(calibration: Calibration, silhouettes: Silhouettes,
                          reduce: int) -> Calibration:
    """The calibration whose camera models match masks taken at 1/``reduce`` size.

    Masks decoded at a reduced size (``segment.reduce``) keep the lens but not
    its pixel units: each camera model is scaled by ``1/reduce`` (pixel centres
    kept, ``CameraModel.scaled``) and its image size set to the masks' own,
    which decoders round up (5184 -> 2592, 427 -> 214 at 1/2).
    """
    if reduce == 1:
        return calibration
    sizes = {s.view.camera: s.shape for s in silhouettes}
    models = dict(calibration.models)
    for name, (h, w) in sizes.items():
        if name not in models:
            continue  # the reconstructor names the view whose camera is missing
        m = models[name]
        if m.width and m.height and (-(-m.width // reduce), -(-m.height // reduce)) != (w, h):
            raise DataError(
                f"camera {name!r}: masks are {w}x{h} px, but 1/{reduce} of the calibrated "
                f"{m.width}x{m.height} px images would be "
                f"{-(-m.width // reduce)}x{-(-m.height // reduce)}")
        models[name] = dataclasses.replace(m.scaled(1.0 / reduce), width=w, height=h)
    return dataclasses.replace(calibration, models=models)


def _reconstruct(plugin: Reconstructor, run: StepRun) -> Volume:
    silhouettes = run.results["silhouettes"]
    calibration = calibration_for_masks(run.results["calibration"], silhouettes,
                                        run.context.reduce)
    volume = plugin.reconstruct(silhouettes, calibration)
    volume.save(run.path("volume.npz"))
    return volume


# --------------------------------------------------------------------------- plan
PLAN_JSON = "plan.json"


def _plan_inputs(run: StepRun) -> Any:
    """What the plan depends on besides the hull: the budgets, the rig and the planned rounds."""
    recipe = run.context.recipe
    scan = recipe.scan if recipe is not None else None
    return None if scan is None else [
        scan.adaptive.model_dump(mode="json") if scan.adaptive is not None else None,
        scan.limits.model_dump(mode="json"), [c.name for c in scan.cameras],
        [r.to_dict() for r in run.scan.planned_rounds()]]


def _plan(plugin: ViewPlanner, run: StepRun) -> ViewPlan:
    from plantscan_core.adaptive import plan_request

    silhouettes = run.results["silhouettes"]
    calibration = calibration_for_masks(run.results["calibration"], silhouettes,
                                        run.context.reduce)
    request = plan_request(run.context.recipe, run.scan)
    view_plan = plugin.plan(run.results["volume"], silhouettes, calibration, request)
    atomic_write_text(run.path(PLAN_JSON), json.dumps(view_plan.to_dict(), indent=1))
    return view_plan


def _load_plan(run: StepRun) -> ViewPlan:
    return ViewPlan.from_dict(json.loads(run.path(PLAN_JSON).read_text()))


# --------------------------------------------------------------------------- mesh, leaves
def call_mesher(plugin: Mesher, volume: Volume, views: CarvingViews) -> Mesh:
    """``plugin.mesh(volume, views)``; a mesher written before the views were passed
    (``mesh(self, volume)``, docs/plugin-guide.md) is called with the volume alone."""
    if "views" in inspect.signature(plugin.mesh).parameters:
        return plugin.mesh(volume, views)
    return plugin.mesh(volume)


def _mesh(plugin: Mesher, run: StepRun) -> Mesh:
    hull = run.result.reports.get("reconstruct")
    views = CarvingViews.of(run.results["silhouettes"], run.results["calibration"],
                            hull.counts.get("k", 0) if hull is not None else 0)
    mesh = call_mesher(plugin, run.results["volume"], views)
    mesh.save(run.path("mesh.npz"))
    write_ply(run.path("mesh.ply"), mesh)
    return mesh


def _segment_mesh(plugin: MeshSegmenter, run: StepRun) -> LabelledMesh:
    labelled = plugin.segment(run.results["mesh"])
    labelled.save(run.path("labelled.npz"))  # its PLY (colours + labels): the ply exporter's
    return labelled


def _measure(plugin: Measurer, run: StepRun) -> Traits:
    traits = plugin.measure(run.results["labelled"])
    traits.save(run.path("traits.csv"), run.path("plant_traits.json"))
    return traits


def _export(plugin: Exporter, run: StepRun) -> list[str]:
    return [str(p) for p in plugin.export(run.result) or []]


def _store(plugin: ResultsStore, run: StepRun) -> dict[str, Any]:
    summary = plugin.store(run.result)
    run.result.info["stored"] = summary
    return summary


def _files(*names: str) -> Callable[[StepRun], list[Path]]:
    return lambda run: [run.path(n) for n in names]


CORE_STEPS: tuple[Step, ...] = (
    Step("calibrate", Calibrator, "calibration", _calibrate,
         lambda run: Calibration.load(run.path("calibration.yaml")),
         files=_files("calibration.yaml"), scan_inputs=_calibration_views,
         from_file=_calibration_from_file, file_option="--calibration"),
    Step("segment", Segmenter, "silhouettes", _segment, _load_silhouettes,
         files=_segment_outputs, scan_inputs=_segment_inputs),
    Step("reconstruct", Reconstructor, "volume", _reconstruct,
         lambda run: Volume.load(run.path("volume.npz")),
         needs=("calibration", "silhouettes"), files=_files("volume.npz")),
    # where more views would carve the hull (plantscan plan, scan --adaptive)
    Step("plan", ViewPlanner, "view_plan", _plan, _load_plan,
         needs=("calibration", "silhouettes", "volume"), files=_files(PLAN_JSON),
         scan_inputs=_plan_inputs),
    Step("mesh", Mesher, "mesh", _mesh, lambda run: Mesh.load(run.path("mesh.npz")),
         needs=("calibration", "silhouettes", "volume"), files=_files("mesh.npz")),
    Step("segment_mesh", MeshSegmenter, "labelled", _segment_mesh,
         lambda run: LabelledMesh.load(run.path("labelled.npz")),
         needs=("mesh",), files=_files("labelled.npz")),
    Step("measure", Measurer, "traits", _measure,
         lambda run: Traits.load(run.path("traits.csv"), run.path("plant_traits.json")),
         needs=("labelled",), files=_files("traits.csv")),
    Step("export", Exporter, "exports", _export, lambda run: [], many=True, cached=False),
    # last: the run folder is complete (traits, exports, run.json) when it is stored
    Step("store", ResultsStore, "stored", _store, lambda run: None, needs=("traits",),
         cached=False),
)
"""The core's steps, in pipeline order."""

CORE_TABLE = StageTable(CORE_STEPS)

"""One abstract base per pipeline stage.

A plugin implements a stage with a class that has

* ``name`` — the name a recipe uses (``plugin: lab-shadow``),
* a nested pydantic ``Params`` model with ``extra="forbid"`` (its recipe
  parameters, with defaults), and
* the stage's one method.

The class is registered with ``registry.add(cls)`` from the hook
``plantscan_register_stages``.  It is built as ``cls(params, context)`` where
``params`` is an instance of ``cls.Params`` and ``context`` a ``StageContext``.

What a stage says of its work goes into ``self.report``, a ``StageReport``
(counts, figures, warnings naming the leaf, view or file they concern); the run
stores it with the stage's cache entry and writes it to ``run.json``.  The order
of the processing stages is the table in ``plantscan_core.steps``.
"""

from __future__ import annotations

import abc
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from plantscan_core.bounds import CheckedModel
from plantscan_core.data import (
    Calibration,
    CarvingViews,
    LabelledMesh,
    Mesh,
    Silhouettes,
    Traits,
    ViewRecord,
    Volume,
)

if TYPE_CHECKING:
    from plantscan_core.photos import Photos
    from plantscan_core.recipe import Recipe
    from plantscan_core.scanfolder import ScanFolder
    from plantscan_core.trajectory import PlanRequest, ViewPlan


class StageParams(CheckedModel):
    """Base of every plugin's ``Params``: unknown keys are errors, every float is finite."""


@dataclass
class StageContext:
    """What a stage may know about the run it is part of.

    Attributes
    ----------
    recipe : Recipe or None
    scan : ScanFolder or None
        The scan being acquired or processed.
    run_dir : Path or None
        The run folder being written (processing only).
    reduce : int
        The plant photos are decoded at 1/``reduce`` of their size (the
        recipe's ``segment.reduce`` resolved to a number): masks and the
        cameras handed to the reconstructor are at that size.
    photos : Photos or None
        The plant photos at 1/``reduce`` (processing only), decoded on
        demand; a step that declares ``photos`` in the stage table gets the
        ones segmentation decoded, not a second decode.
    shared : dict
        Objects shared by the stages of one acquisition or run (e.g. the
        virtual scanner's scene, shared by its cameras and axes).
    """

    recipe: Recipe | None = None
    scan: ScanFolder | None = None
    run_dir: Path | None = None
    reduce: int = 1
    photos: Photos | None = None
    shared: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- reports
_REPORT_LOCK = threading.Lock()  # segmenters report from several threads at once


@dataclass(frozen=True)
class StageWarning:
    """Something a user should know about a stage's result, and what it concerns.

    Attributes
    ----------
    code : str
        Stable kebab-case identifier of the kind of warning (``thick-leaf``,
        ``empty-mask``), for programs that filter or count warnings.
    message : str
        One sentence for a person: what was seen and what it means.
    leaf, view : int or None
        The leaf id (traits table) or view index (``views.jsonl``) it names.
    file : str or None
        The file it names (path as the user gave it, or relative to the scan).
    """

    code: str
    message: str
    leaf: int | None = None
    view: int | None = None
    file: str | None = None

    def __str__(self) -> str:
        return self.message

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "message": self.message}
        for name in ("leaf", "view", "file"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StageWarning:
        return cls(str(d["code"]), str(d["message"]), d.get("leaf"), d.get("view"), d.get("file"))


@dataclass
class StageReport:
    """What one stage says of its work: the one channel from a stage to the user.

    Stored with the stage's cache entry, so a stage loaded from the cache reports
    the same again; ``run.json`` holds it under ``stages.<section>.info``.

    Attributes
    ----------
    counts : dict str -> int
        Work counts (``views``, ``regions``, ``pot_voxels_removed``).
    figures : dict str -> JSON value
        Other figures, with the unit in the name (``voxel_size_mm``, ``rms_px``).
    warnings : list of StageWarning
    """

    counts: dict[str, int] = field(default_factory=dict)
    figures: dict[str, Any] = field(default_factory=dict)
    warnings: list[StageWarning] = field(default_factory=list)

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to the count ``name`` (thread-safe)."""
        with _REPORT_LOCK:
            self.counts[name] = self.counts.get(name, 0) + int(n)

    def figure(self, name: str, value: Any) -> None:
        """Set the figure ``name`` (a JSON value: number, string, list, mapping)."""
        from plantscan_core.data import plain

        with _REPORT_LOCK:
            self.figures[name] = plain(value)

    def note(self, values: dict[str, Any]) -> None:
        """Record a mapping of results: integers as counts, anything else as figures."""
        for name, value in values.items():
            if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
                self.count(name, int(value))
            else:
                self.figure(name, value)

    def warn(self, code: str, message: str, *, leaf: int | None = None,
             view: int | None = None, file: str | None = None) -> StageWarning:
        """Add a warning (thread-safe); returns it."""
        w = StageWarning(code, message, None if leaf is None else int(leaf),
                         None if view is None else int(view), None if file is None else str(file))
        with _REPORT_LOCK:
            self.warnings.append(w)
        return w

    def warnings_about(self, *, leaf: int | None = None, view: int | None = None,
                       code: str | None = None) -> list[StageWarning]:
        """The warnings that name ``leaf`` / ``view`` / have ``code`` (all given must match)."""
        return [w for w in self.warnings
                if (leaf is None or w.leaf == leaf) and (view is None or w.view == view)
                and (code is None or w.code == code)]

    def to_dict(self) -> dict[str, Any]:
        from plantscan_core.data import plain

        return {"counts": dict(self.counts), "figures": plain(self.figures),
                "warnings": [w.to_dict() for w in self.warnings]}

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> StageReport:
        d = d or {}
        return cls({str(k): int(v) for k, v in (d.get("counts") or {}).items()},
                   dict(d.get("figures") or {}),
                   [StageWarning.from_dict(w) for w in d.get("warnings") or []])


class Stage(abc.ABC):
    """Common base: a named, parametrised implementation of one stage.

    ``report`` (a fresh ``StageReport`` per instance; the run builds one
    instance per stage run) is where the stage says what it did.
    """

    stage: ClassVar[str] = ""
    name: ClassVar[str] = ""
    Params: ClassVar[type[StageParams]] = StageParams

    def __init__(self, params: StageParams | None = None, context: StageContext | None = None):
        self.params = params if params is not None else self.Params()
        self.context = context if context is not None else StageContext()
        self.report = StageReport()

    @classmethod
    def version(cls) -> str:
        """Version recorded in ``run.json`` and in cache keys (defaults to the distribution's)."""
        return getattr(cls, "__version__", "") or _distribution_version(cls)


def _distribution_version(cls: type) -> str:
    from plantscan_core.plugins import distribution_of_module

    dist = distribution_of_module(cls.__module__)
    return dist[1] if dist else "0"


# --------------------------------------------------------------------------- acquisition
@dataclass(frozen=True)
class CaptureRequest:
    """What the acquisition orchestrator asks a camera for.

    The camera writes the image to ``out_path`` (a temporary name inside the
    scan folder); the orchestrator fsyncs and renames it into place.
    """

    out_path: Path
    role: str
    camera: str
    tilt_index: int
    tilt_deg: float
    angle_index: int
    commanded_angle_deg: float
    measured_angle_deg: float | None
    image_size: tuple[int, int]
    image_format: str = "png"


class CameraBackend(Stage):
    """A camera: ``capture(request) -> path`` of the image written."""

    stage = "camera"

    def open(self) -> None:
        """Connect to the device (called once before the first capture)."""

    def close(self) -> None:
        """Release the device (always called, also after errors)."""

    @abc.abstractmethod
    def capture(self, request: CaptureRequest) -> Path:
        """Take one image and write it to ``request.out_path``; return that path."""

    def trigger(self, request: CaptureRequest) -> Callable[[], Path]:
        """Release the shutter now; return a function that finishes (downloads) the image.

        The orchestrator triggers every camera of a stop together and runs the
        returned functions while the next move happens.  The default captures
        completely here; a camera with a slow download overrides it.
        """
        self.capture(request)
        return lambda: request.out_path


class MotionAxis(Stage):
    """A motion axis (turntable or tilt arm), in degrees."""

    stage = "axis"

    def open(self) -> None:
        """Connect and engage (called once before the first move)."""

    def close(self) -> None:
        """Disengage and release (always called)."""

    @abc.abstractmethod
    def move_to(self, deg: float) -> float | None:
        """Move to ``deg`` and block until stopped; return the measured position or None."""

    @abc.abstractmethod
    def position(self) -> float | None:
        """Measured position in degrees, or None when the axis cannot tell."""

    @abc.abstractmethod
    def home(self) -> None:
        """Find the reference position and call it 0."""

    def stop(self) -> None:
        """Stop moving now (Ctrl-C).  Must not block.  Default: nothing to stop."""


class Scene(Stage):
    """A virtual world for virtual cameras and axes (the virtual scanner).

    ``setup`` is called once by the acquisition orchestrator before any move;
    it may write ``ground_truth/`` into the scan folder and put itself into
    ``context.shared`` for the virtual cameras and axes.
    """

    stage = "scene"

    def check(self, recipe: Recipe) -> None:
        """Refuse an impossible rig (named errors) before the scan folder exists.  Optional."""

    @abc.abstractmethod
    def setup(self, scan: ScanFolder) -> None:
        """Prepare the scene for a scan written to ``scan``."""

    def now(self) -> str | None:
        """The world's clock: ISO 8601 UTC time stamp for the scan and its views, or None.

        None (the default) time-stamps with the real clock.  A virtual world may
        keep its own time, so that virtual scans of a growing plant fall on the
        days of a virtual experiment.
        """
        return None


# --------------------------------------------------------------------------- processing
class Calibrator(Stage):
    """``calibrate(scan) -> Calibration`` from the scan's calibration views."""

    stage = "calibrator"

    @abc.abstractmethod
    def calibrate(self, scan: ScanFolder) -> Calibration:
        """Calibrate the rig from ``scan`` (its ``calibration`` role views)."""


class Segmenter(Stage):
    """``segment(image, background) -> mask``."""

    stage = "segmenter"

    @abc.abstractmethod
    def segment(
        self, image: np.ndarray, background: np.ndarray | None, view: ViewRecord | None = None
    ) -> np.ndarray:
        """Plant mask of one image.

        Parameters
        ----------
        image : (H, W, 3) uint8 array, BGR
        background : (H, W, 3) uint8 array, BGR, or None
            The background plate of the same camera and tilt (None when the
            scan has none; a segmenter that needs one raises ``DataError``).
        view : ViewRecord, optional

        Returns
        -------
        mask : (H, W) bool array, True = plant or pot
        """


class Reconstructor(Stage):
    """``reconstruct(silhouettes, calibration) -> Volume``."""

    stage = "reconstructor"

    @abc.abstractmethod
    def reconstruct(self, silhouettes: Silhouettes, calibration: Calibration) -> Volume:
        """Carve a volume from the silhouettes seen by the calibrated cameras."""


class ViewPlanner(Stage):
    """``plan(volume, silhouettes, calibration, request) -> ViewPlan``: where to look next.

    Given the hull carved from the views taken so far, choose the stops (pan,
    tilt) among ``request.candidates`` whose views are predicted to carve the
    most of the hull's unsure (possibly phantom) volume, within the request's
    budgets (``plantscan plan``, ``plantscan scan --adaptive``).
    """

    stage = "view_planner"

    @abc.abstractmethod
    def plan(self, volume: Volume, silhouettes: Silhouettes, calibration: Calibration,
             request: PlanRequest) -> ViewPlan:
        """Choose the next stops.

        Parameters
        ----------
        volume : Volume
            The hull of ``silhouettes`` (any resolution; the quick runs of an
            adaptive scan carve a coarse one).
        silhouettes : Silhouettes
            The plant views taken so far, at the masks' size.
        calibration : Calibration
            Cameras at the masks' size; ``Calibration.camera_at_stop`` gives the
            camera of any candidate (tilts never calibrated from the tilt axis).
        request : trajectory.PlanRequest
            Candidates, cameras, budgets and the capture-time model.

        Returns
        -------
        trajectory.ViewPlan
            The chosen stops, each with its predicted gain and a reason.
        """


class Mesher(Stage):
    """``mesh(volume) -> Mesh``: pot removal and surface extraction."""

    stage = "mesher"

    @abc.abstractmethod
    def mesh(self, volume: Volume, views: CarvingViews | None = None) -> Mesh:
        """Watertight surface of the plant (pot removed) from ``volume``.

        ``views`` (the run passes them) are the cameras that carved ``volume``:
        what no view could carve (the cone over the pot's opening) follows from them.
        """


class MeshSegmenter(Stage):
    """``segment(mesh) -> LabelledMesh``: leaves and stem."""

    stage = "mesh_segmenter"

    @abc.abstractmethod
    def segment(self, mesh: Mesh) -> LabelledMesh:
        """Label every face of ``mesh``."""


class Measurer(Stage):
    """``measure(labelled) -> Traits``."""

    stage = "measurer"

    @abc.abstractmethod
    def measure(self, labelled: LabelledMesh) -> Traits:
        """Per-leaf and plant-level traits."""


@dataclass
class RunResult:
    """Everything a processing run produced, handed to exporters.

    Attributes are None for stages that did not run.

    Attributes
    ----------
    reports : dict section -> StageReport
        What every stage that ran (or came from the cache) said of its work.
    results : dict result name -> object
        The result of every step by the name it declares in the stage table
        (``calibration``, ``silhouettes``...; also those of added steps).
    info : dict
        The run's ``run.json`` record.
    """

    run_dir: Path
    recipe: Recipe
    scan: ScanFolder
    calibration: Calibration | None = None
    silhouettes: Silhouettes | None = None
    volume: Volume | None = None
    mesh: Mesh | None = None
    labelled: LabelledMesh | None = None
    traits: Traits | None = None
    timings: dict[str, float] = field(default_factory=dict)
    reports: dict[str, StageReport] = field(default_factory=dict)
    results: dict[str, Any] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    STEP_RESULTS: ClassVar[tuple[str, ...]] = ("calibration", "silhouettes", "volume", "mesh",
                                               "labelled", "traits")
    """The results that have an attribute of their own (the core steps')."""

    def warnings(self) -> list[tuple[str, StageWarning]]:
        """(section, warning) of every stage's report, in stage order."""
        return [(section, w) for section, r in self.reports.items() for w in r.warnings]


class Exporter(Stage):
    """``export(run) -> files`` written into the run folder."""

    stage = "exporter"

    @abc.abstractmethod
    def export(self, run: RunResult) -> list[Path]:
        """Write this exporter's files for ``run``; return their paths."""


class ResultsStore(Stage):
    """``store(run) -> summary``: keep a run's traits and metadata in a database.

    The last step of a run when the recipe has a ``store:`` section.  The run
    folder is complete (``run.json`` with ``metadata`` and ``scan_record``,
    ``traits.csv``); storing a run again must replace it, never duplicate it,
    and several processes may store at once.
    """

    stage = "results_store"

    @abc.abstractmethod
    def store(self, run: RunResult) -> dict[str, Any]:
        """Store ``run``; return what was stored (``{"store": name, "leaves": n, ...}``)."""


ACQUISITION_BASES: tuple[type[Stage], ...] = (CameraBackend, MotionAxis, Scene)
"""The stage bases of acquisition; those of processing are the stage table's."""

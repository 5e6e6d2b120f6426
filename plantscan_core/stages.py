"""One abstract base per pipeline stage.

A plugin implements a stage with a class that has

* ``name`` — the name a recipe uses (``plugin: lab-shadow``),
* a nested pydantic ``Params`` model with ``extra="forbid"`` (its recipe
  parameters, with defaults), and
* the stage's one method.

The class is registered with ``registry.add(cls)`` from the hook
``plantscan_register_stages``.  It is built as ``cls(params, context)`` where
``params`` is an instance of ``cls.Params`` and ``context`` a ``StageContext``.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from plantscan_core.data import (
    Calibration,
    LabelledMesh,
    Mesh,
    Silhouettes,
    Traits,
    ViewRecord,
    Volume,
)

if TYPE_CHECKING:
    from plantscan_core.recipe import Recipe
    from plantscan_core.scanfolder import ScanFolder


class StageParams(BaseModel):
    """Base of every plugin's ``Params``: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


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
    shared : dict
        Objects shared by the stages of one acquisition or run (e.g. the
        virtual scanner's scene, shared by its cameras and axes).
    """

    recipe: Recipe | None = None
    scan: ScanFolder | None = None
    run_dir: Path | None = None
    shared: dict[str, Any] = field(default_factory=dict)


class Stage(abc.ABC):
    """Common base: a named, parametrised implementation of one stage.

    A processing stage may leave what it has to say of its last call (work
    counts, ``"warnings"``: a list of messages) in a plain dict attribute
    ``info``; the run writes it to ``run.json`` under ``stages.<section>.info``,
    also when the stage's result comes from the cache.
    """

    stage: ClassVar[str] = ""
    name: ClassVar[str] = ""
    Params: ClassVar[type[StageParams]] = StageParams

    def __init__(self, params: StageParams | None = None, context: StageContext | None = None):
        self.params = params if params is not None else self.Params()
        self.context = context if context is not None else StageContext()

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


class Mesher(Stage):
    """``mesh(volume) -> Mesh``: pot removal and surface extraction."""

    stage = "mesher"

    @abc.abstractmethod
    def mesh(self, volume: Volume) -> Mesh:
        """Watertight surface of the plant (pot removed) from ``volume``."""


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
    info: dict[str, Any] = field(default_factory=dict)


class Exporter(Stage):
    """``export(run) -> files`` written into the run folder."""

    stage = "exporter"

    @abc.abstractmethod
    def export(self, run: RunResult) -> list[Path]:
        """Write this exporter's files for ``run``; return their paths."""


STAGE_BASES: dict[str, type[Stage]] = {
    cls.stage: cls
    for cls in (
        CameraBackend,
        MotionAxis,
        Scene,
        Calibrator,
        Segmenter,
        Reconstructor,
        Mesher,
        MeshSegmenter,
        Measurer,
        Exporter,
    )
}
"""Stage kind -> abstract base, in pipeline order."""

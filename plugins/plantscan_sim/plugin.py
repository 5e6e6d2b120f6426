"""Stages of the virtual scanner: scene, camera and axes ``sim``; calibrator ``truth``;
segmenter ``truth-masks``.

The camera and axes implement the same contracts as real hardware and are
driven by the same acquisition orchestrator; they talk to the scene through
``context.shared["sim_scene"]``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from plantscan_core.data import Calibration, ViewRecord
from plantscan_core.errors import DataError, HardwareError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.runfolder import read_mask
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.stages import (
    Calibrator,
    CameraBackend,
    CaptureRequest,
    MotionAxis,
    Segmenter,
    StageParams,
)
from plantscan_sim.rig import SimCameraParams
from plantscan_sim.scene import SimScene, finalize_truth, scene_of

# Render time of one image on one core (fast renderer, 2026-12 on the shared 2-core machine,
# CPU seconds per image at 640x427 and 1296x864, scene set-up included): plant and background
# views ~0.20 s + 0.62 s/MP (3x3 anti-aliasing at edges), board views ~0.37 s + 1.09 s/MP (6x6).
_RENDER_S = {"plant": (0.20, 0.62), "background": (0.20, 0.62), "calibration": (0.37, 1.09)}


class SimCamera(CameraBackend):
    """A virtual camera on the rig's arm: renders the scene for each request."""

    name = "sim"
    Params = SimCameraParams
    camera_name: str | None = None

    @classmethod
    def capture_time_s(cls, params: SimCameraParams, image_size: tuple[int, int],
                       role: str) -> float:
        """Seconds to render one ``role`` image of ``image_size`` px (the timing model of
        ``plantscan scan --dry-run``); the cameras of a stop render in parallel threads."""
        base, per_mp = _RENDER_S.get(role, _RENDER_S["plant"])
        return base + per_mp * image_size[0] * image_size[1] / 1e6

    def trigger(self, request: CaptureRequest):
        """Render now (the rig is still); return the callable that writes the file."""
        scene = scene_of(self.context)
        camera = self.camera_name or request.camera
        image, coverage, truth = scene.render_request(request, camera)

        def finish() -> Path:
            import cv2

            fmt = request.image_format.lower()
            if fmt in ("jpg", "jpeg"):
                ok, data = cv2.imencode(".jpg", image,
                                        [cv2.IMWRITE_JPEG_QUALITY, int(scene.jpeg_quality)])
            elif fmt == "png":
                ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            else:
                raise HardwareError(f"sim camera {camera!r}: unknown image format {fmt!r} "
                                    "(png, jpg)")
            if not ok:
                raise HardwareError(f"sim camera {camera!r}: cannot encode {fmt}")
            Path(request.out_path).write_bytes(data.tobytes())
            scan = self.context.scan
            if scan is not None:
                rel = _final_relpath(scan, request)
                scene.stage_view_truth(scan, rel, truth, coverage)
            return Path(request.out_path)

        return finish

    def capture(self, request: CaptureRequest) -> Path:
        return self.trigger(request)()

    def close(self) -> None:
        scan = self.context.scan
        if scan is not None and scan.ground_truth_dir.is_dir():
            finalize_truth(scan)


def _final_relpath(scan: ScanFolder, request: CaptureRequest) -> str:
    """The image's final path relative to the scan (the request names a temporary)."""
    from plantscan_core.acquire import PlannedView, image_relpath

    v = PlannedView(request.role, request.camera, request.tilt_index, request.tilt_deg,
                    request.angle_index, request.commanded_angle_deg)
    return image_relpath(v, request.image_format)


class SimAxisParams(StageParams):
    axis: Literal["turntable", "tilt"] = Field(
        "turntable", description="which rig axis this is (the tilt arm needs 'tilt')")
    backlash_deg: float = Field(0.0, ge=0.0, le=10.0,
                                description="dead band: the true position lags the command by "
                                "half of it against the direction of the last move")
    error_sigma_deg: float = Field(0.0, ge=0.0, le=5.0,
                                   description="random positioning error per stop (seeded)")
    report_position: bool = Field(False, description="return the true angle like an encoder "
                                  "(default: None, like an open-loop stepper)")
    seed: int = 0
    # The virtual axis is where it is told at once; these say how long a lab's axis would
    # take (plantscan_core.timing), for scan --dry-run and the adaptive planner's budget.
    velocity_deg_s: float | None = Field(None, gt=0.0, le=1e6,
                                         description="timing model only: cruise speed")
    acceleration_deg_s2: float | None = Field(None, gt=0.0, le=1e9,
                                              description="timing model only")
    settle_s: float = Field(0.0, ge=0.0, le=60.0, description="timing model only")


class SimAxis(MotionAxis):
    """A virtual turntable or tilt arm; tells the scene its TRUE position after each move."""

    name = "sim"
    Params = SimAxisParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self._commanded = 0.0
        self._true = 0.0
        self._direction = 1.0

    def _error(self, deg: float) -> float:
        p = self.params
        err = -self._direction * 0.5 * p.backlash_deg
        if p.error_sigma_deg > 0:
            # Seeded by the commanded position: the same stop errs the same way on a resume.
            rng = np.random.default_rng([p.seed, 0 if p.axis == "turntable" else 1,
                                         int(round(deg * 1000.0)) % (2**32)])
            err += float(rng.normal(0.0, p.error_sigma_deg))
        return err

    def move_to(self, deg: float) -> float | None:
        deg = float(deg)
        if deg != self._commanded:
            self._direction = 1.0 if deg > self._commanded else -1.0
        self._commanded = deg
        self._true = deg + self._error(deg)
        scene_of(self.context).axis_moved(self.params.axis, self._true)
        return self.position()

    def position(self) -> float | None:
        return self._true if self.params.report_position else None

    def home(self) -> None:
        # Homing approaches the switch from below: the dead band is taken up forwards.
        self._commanded, self._direction = 0.0, 1.0
        self._true = 0.0
        scene_of(self.context).axis_moved(self.params.axis, 0.0)


class TruthCalibrator(Calibrator):
    """The exact calibration of a virtual scan (to test later stages on truth)."""

    name = "truth"

    def calibrate(self, scan: ScanFolder) -> Calibration:
        path = scan.ground_truth_dir / "calibration.yaml"
        if not path.exists():
            raise DataError(f"{path}: not found; calibrator 'truth' needs a virtual scan")
        cal = Calibration.load(path)
        cal.quality = {**cal.quality, "calibrator": "truth"}
        return cal


class TruthMaskSegmenter(Segmenter):
    """The exact silhouette of a virtual scan's plant view (to test later stages on truth)."""

    name = "truth-masks"

    def segment(self, image: np.ndarray, background: np.ndarray | None,
                view: ViewRecord | None = None) -> np.ndarray:
        scan = self.context.scan
        if view is None or scan is None:
            raise DataError("segmenter 'truth-masks' needs the view and the scan in its context")
        path = scan.ground_truth_dir / "masks" / f"{view.index:05d}.png"
        if not path.exists():
            raise DataError(f"{path}: no truth mask for view {view.index} ({view.file})")
        mask = read_mask(path)
        if image is not None and mask.shape != image.shape[:2]:
            raise DataError(f"{path}: mask is {mask.shape[::-1]} px but view {view.index}'s "
                            f"image is {image.shape[1::-1]} px")
        return mask


@hookimpl
def plantscan_register_stages(registry) -> None:
    for cls in (SimScene, SimCamera, SimAxis, TruthCalibrator, TruthMaskSegmenter):
        registry.add(cls)


@hookimpl
def plantscan_warm_up() -> str:
    from plantscan_sim.warmup import warm_up

    return warm_up()

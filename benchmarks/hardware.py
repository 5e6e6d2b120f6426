"""Acquisition wall time: this orchestrator beside a sequential loop, and the timing model.

    python benchmarks/hardware.py [--scale 0.05] [--angles 36]

A rig of 2 cameras and a turntable whose devices *sleep* for the seed-like times
of the plugins' defaults, scaled by ``--scale`` (capture 1.0 s, download 1.0 s,
a 10 deg turntable step 1.63 s with 12 deg/s, 24 deg/s^2 and 0.3 s settle), so
the benchmark measures the orchestration, not a device.  The same protocol runs

* ``sequential``: move, then for each camera capture + download, then commit
  (the simplest correct orchestrator, what tethering scripts do);
* ``acquire``: ``plantscan_core.acquire.acquire`` (both cameras triggered at
  once, downloads overlapping the next move);

and each wall time is printed beside ``estimate_scan_time``'s prediction.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field

from plantscan_core.acquire import acquire, image_relpath, plan, stops
from plantscan_core.data import ViewRecord
from plantscan_core.hookspecs import hookimpl
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.stages import CameraBackend, CaptureRequest, MotionAxis, StageParams
from plantscan_core.timing import estimate_scan_time, move_time_s


class BenchCamera(CameraBackend):
    name = "bench"

    class Params(StageParams):
        capture_s: float = Field(default=1.0)
        download_s: float = Field(default=1.0)

    def trigger(self, request: CaptureRequest):
        time.sleep(self.params.capture_s)

        def download():
            time.sleep(self.params.download_s)
            img = np.full((request.image_size[1], request.image_size[0], 3), 128, np.uint8)
            cv2.imwrite(str(request.out_path), img)
            return request.out_path

        return download

    def capture(self, request: CaptureRequest) -> Path:
        return self.trigger(request)()


class BenchAxis(MotionAxis):
    name = "bench"

    class Params(StageParams):
        velocity_deg_s: float = 12.0
        acceleration_deg_s2: float = 24.0
        settle_s: float = 0.3

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.pos = 0.0

    def move_to(self, deg: float) -> float:
        p = self.params
        if deg != self.pos:
            time.sleep(move_time_s(deg - self.pos, p.velocity_deg_s, p.acceleration_deg_s2)
                       + p.settle_s)
        self.pos = deg
        return deg

    def position(self) -> float:
        return self.pos

    def home(self) -> None:
        self.pos = 0.0


@hookimpl
def plantscan_register_stages(registry):
    registry.add(BenchCamera)
    registry.add(BenchAxis)


def sequential(recipe, out: Path, manager) -> None:
    """The simplest correct orchestrator: one thing after another."""
    scan = ScanFolder.create(out, {"recipe": {}})
    cams = {c.name: manager.build("camera", c.plugin, c.params) for c in recipe.scan.cameras}
    axis = manager.build("axis", recipe.scan.turntable.plugin, recipe.scan.turntable.params)
    axis.home()
    for group in stops(plan(recipe)):
        measured = axis.move_to(group[0].angle_deg)
        for v in group:
            view = ViewRecord(len(scan.views), v.role, v.camera, v.tilt_index, v.tilt_deg,
                              v.angle_index, v.angle_deg, measured, image_relpath(v, "png"))

            def write(tmp, v=v, measured=measured):
                cams[v.camera].capture(CaptureRequest(
                    tmp, v.role, v.camera, v.tilt_index, v.tilt_deg, v.angle_index, v.angle_deg,
                    measured, tuple(recipe.scan.image_size), "png"))

            scan.append_view(view, write)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.05, help="device time scale (1 = real)")
    ap.add_argument("--angles", type=int, default=36)
    args = ap.parse_args()
    s = args.scale
    cam = {"capture_s": 1.0 * s, "download_s": 1.0 * s}
    # Time scaled by s: velocity / s, acceleration / s^2 keep the profile's shape.
    axis = {"velocity_deg_s": 12.0 / s, "acceleration_deg_s2": 24.0 / s ** 2, "settle_s": 0.3 * s}
    raw = {"name": "bench", "scan": {
        "cameras": [{"name": f"cam{i}", "plugin": "bench", "params": cam} for i in range(2)],
        "turntable": {"plugin": "bench", "params": axis},
        "images_per_revolution": args.angles, "image_size": [64, 48],
        "roles": {"calibration": {"enabled": False}, "background": {"enabled": False},
                  "plant": {}}}}
    manager = new_manager()
    import sys

    manager.register(sys.modules[__name__], name="bench")
    recipe = validate_recipe(raw, manager.registry)
    est = estimate_scan_time(recipe, manager.registry)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        sequential(recipe, Path(tmp) / "seq", manager)
        rows.append(("sequential", time.perf_counter() - t, est.sequential_s))
        t = time.perf_counter()
        scan = acquire(recipe, Path(tmp) / "acq", manager, raw_recipe=raw)
        rows.append(("acquire", time.perf_counter() - t, est.total_s))
        assert len(scan.views) == 2 * args.angles
    print(f"{args.angles} stops x 2 cameras, device times x {s:g}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print("| orchestrator | wall time (s) | model (s) | wall / model | at real speed (min) |")
    print("|---|---|---|---|---|")
    for name, wall, model in rows:
        print(f"| {name} | {wall:.2f} | {model:.2f} | {wall / model:.2f} | "
              f"{wall / s / 60:.1f} |")
    print(f"speed-up: {rows[0][1] / rows[1][1]:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

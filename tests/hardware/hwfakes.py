"""A tiny in-test rig (camera ``fake`` and axis ``fake``) to test the acquisition orchestrator.

Registered in-process with ``new_manager()`` + ``manager.register(hwfakes)``.
Behaviour is driven by ``RIG`` (a module-level, thread-safe event log and
fault switches) so a test can inject faults and check what happened in
which order; a subprocess gets its switches from the environment variable
``HWFAKES`` (JSON).
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from plantscan_core.errors import HardwareError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import CameraBackend, CaptureRequest, MotionAxis, StageParams


class RigState:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        self.events: list[tuple] = []
        self.fail_camera_at: dict[str, int] = {}  # camera -> n-th trigger that fails for good
        self.interrupt_on_move: int | None = None  # n-th turntable move raises KeyboardInterrupt
        self.barrier: threading.Barrier | None = None  # triggers of one stop must meet here
        self.move_started = threading.Event()
        self.require_overlap = False
        self.delay_s = 0.0
        self.triggers: dict[str, int] = {}
        self.moves = 0
        self.stops = 0
        self.events_file: str | None = None
        cfg = os.environ.get("HWFAKES")
        if cfg:
            c = json.loads(cfg)
            self.delay_s = float(c.get("delay_s", 0.0))
            self.events_file = c.get("events_file")

    def log(self, *event) -> None:
        with self.lock:
            self.events.append(event)
            if self.events_file:  # seen by a parent process (tests of signals)
                with open(self.events_file, "a") as f:
                    f.write(" ".join(map(str, event)) + "\n")


RIG = RigState()


def view_image(request: CaptureRequest) -> np.ndarray:
    """The image a fake camera takes: its view key written into the pixels (checkable)."""
    w, h = request.image_size
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 0] = request.angle_index % 256
    img[:, :, 1] = request.tilt_index
    img[:, :, 2] = sum(map(ord, request.camera + request.role)) % 256
    return img


class FakeCamera(CameraBackend):
    """Two-phase camera: ``trigger`` exposes, the returned callable 'downloads' (writes) it."""

    name = "fake"

    class Params(StageParams):
        pass

    def trigger(self, request: CaptureRequest):
        cam = request.camera
        with RIG.lock:
            RIG.triggers[cam] = n = RIG.triggers.get(cam, 0) + 1
        RIG.log("trigger", cam, request.role, request.tilt_index, request.angle_index)
        if RIG.barrier is not None:
            RIG.barrier.wait(timeout=5)  # both cameras must be exposing at the same time
        if RIG.fail_camera_at.get(cam) is not None and n >= RIG.fail_camera_at[cam]:
            raise HardwareError(f"fake camera {cam}: USB device disappeared")
        image = view_image(request)
        if RIG.delay_s:
            time.sleep(RIG.delay_s)
        RIG.move_started.clear()

        def download() -> Path:
            overlapped = RIG.move_started.wait(timeout=1) if RIG.require_overlap else None
            RIG.log("download", cam, request.angle_index, overlapped)
            if not cv2.imwrite(str(request.out_path), image):
                raise HardwareError(f"cannot write {request.out_path}")
            if RIG.delay_s:
                time.sleep(RIG.delay_s)
            return request.out_path

        return download

    def capture(self, request: CaptureRequest) -> Path:
        return self.trigger(request)()


class FakeAxis(MotionAxis):
    name = "fake"

    class Params(StageParams):
        pass

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.pos = 0.0

    def move_to(self, deg: float) -> float:
        with RIG.lock:
            RIG.moves += 1
            n = RIG.moves
        RIG.move_started.set()
        RIG.log("move", deg)
        if RIG.interrupt_on_move is not None and n == RIG.interrupt_on_move:
            raise KeyboardInterrupt
        if RIG.delay_s:
            time.sleep(RIG.delay_s)
        self.pos = deg
        return deg + 0.001  # a measured position that differs from the command

    def position(self) -> float:
        return self.pos

    def home(self) -> None:
        self.pos = 0.0

    def stop(self) -> None:
        with RIG.lock:
            RIG.stops += 1
        RIG.log("stop")


@hookimpl
def plantscan_register_stages(registry):
    registry.add(FakeCamera)
    registry.add(FakeAxis)


def fake_recipe(tilts=(0.0,), n_angles=6, cameras=("cam0", "cam1"), size=(32, 24)) -> dict:
    """A raw recipe of the fake rig (background role off to keep counts simple)."""
    raw = {
        "name": "fake-rig",
        "plant": {"id": "p1"},
        "scan": {
            "cameras": [{"name": c, "plugin": "fake"} for c in cameras],
            "turntable": {"plugin": "fake"},
            "tilts_deg": list(tilts),
            "images_per_revolution": n_angles,
            "image_size": list(size),
            "roles": {"calibration": {"images_per_revolution": 2}, "background": {"enabled": False},
                      "plant": {}},
        },
    }
    if len(tilts) > 1:
        raw["scan"]["tilt_arm"] = {"plugin": "fake"}
    return raw


def check_scan(root: Path, recipe) -> dict[str, tuple[int, int]]:
    """Assert the scan holds exactly the protocol's views, each a complete, decodable image.

    Returns ``file -> (inode, mtime_ns)`` so a caller can check nothing was rewritten.
    """
    from plantscan_core.acquire import plan
    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(root)
    keys = [v.key for v in scan.views]
    assert len(keys) == len(set(keys)), "a view was listed twice"
    assert set(keys) == {v.key for v in plan(recipe)}, "views differ from the protocol"
    assert [v.index for v in scan.views] == list(range(len(keys)))
    stamps = {}
    for v in scan.views:
        img = scan.read_image(v)  # DataError if missing or corrupt
        assert img.shape[:2] == tuple(reversed(recipe.scan.image_size))
        assert int(img[0, 0, 0]) == v.angle_index % 256, f"{v.file} holds another view's image"
        st = scan.path_of(v).stat()
        stamps[v.file] = (st.st_ino, st.st_mtime_ns)
    leftovers = [p for p in (root / "images").rglob(".*") if p.is_file()]
    assert not leftovers, f"temporary files left: {leftovers}"
    return stamps

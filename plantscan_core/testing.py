"""Fixtures for plugin authors (a pytest plugin, loaded through the ``pytest11`` entry point).

* ``plantscan_manager`` — a fresh plugin manager with autoload off (no
  entry point loaded): register your plugin into it and test it in isolation.
* ``tiny_rig_manager`` — the same with the tiny synthetic rig below registered.
* ``tiny_scan`` — a tiny synthetic scan folder (calibration, background and
  plant views of a dark sphere) acquired by the real orchestrator with the
  tiny rig.
* ``tiny_processing_plugin`` — the tiny rig's exact calibrator (``tiny-exact``)
  and a dark-pixel segmenter (``tiny-dark``), so that a reconstructor or an
  added step can be tested with the real ``process()`` on ``tiny_scan``
  (``TINY_CALLS`` counts their calls).
* ``--hardware`` — run tests marked ``hardware`` (skipped otherwise).

The tiny rig is deliberately simple (no lens, no shadows): it exercises the
framework, not the algorithms; the virtual scanner (``plantscan_sim``) is the
yardstick for those.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import sys
import threading
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from plantscan_core.data import Calibration, Camera, CameraModel, Pose, rotation_z
from plantscan_core.hookspecs import hookimpl
from plantscan_core.plugins import PluginManager, new_manager
from plantscan_core.stages import (
    Calibrator,
    CameraBackend,
    CaptureRequest,
    MotionAxis,
    Segmenter,
    Stage,
    StageParams,
)

TINY_SPHERE_RADIUS_MM = 40.0
TINY_SPHERE_CENTRE_MM = (15.0, 0.0, 80.0)


def tiny_camera(name: str, tilt_deg: float, angle_deg: float, size: tuple[int, int]) -> Camera:
    """The tiny rig's exact camera ``name`` (``cam0``/``cam1``) at a tilt and turntable angle."""
    w, h = size
    model = CameraModel(f=1.2 * w, cu=(w - 1) / 2, cv=(h - 1) / 2, width=w, height=h)
    azimuth = 0.0 if name == "cam0" else 40.0
    el = math.radians(tilt_deg + 10.0)
    dist = 600.0
    centre = (dist * math.cos(el) * math.cos(math.radians(azimuth)),
              dist * math.cos(el) * math.sin(math.radians(azimuth)),
              80.0 + dist * math.sin(el))
    pose = Pose.look_at(centre, (0.0, 0.0, 80.0))
    return Camera(model, pose.compose_world(rotation_z(angle_deg)))


class TinyCamera(CameraBackend):
    """Renders a dark sphere (off the axis, so it moves with the turntable) on a light plate."""

    name = "tiny"

    class Params(StageParams):
        noise: float = 0.0

    camera_name = "cam0"

    def capture(self, request: CaptureRequest) -> Path:
        import cv2

        cam = tiny_camera(request.camera, request.tilt_deg, request.commanded_angle_deg,
                          request.image_size)
        w, h = request.image_size
        img = np.full((h, w, 3), 200, np.uint8)
        if request.role == "plant":
            uv = cam.project(np.array([TINY_SPHERE_CENTRE_MM]))[0]
            depth = cam.depth(np.array([TINY_SPHERE_CENTRE_MM]))[0]
            r = cam.model.f * TINY_SPHERE_RADIUS_MM / depth
            cv2.circle(img, (round(uv[0]), round(uv[1])), round(r), (30, 90, 40), -1)
        elif request.role == "calibration":
            img[::8, :] = 0
        cv2.imwrite(str(request.out_path.with_suffix(".png")), img)
        if request.out_path.suffix != ".png":
            request.out_path.with_suffix(".png").rename(request.out_path)
        return request.out_path


class TinyAxis(MotionAxis):
    """An ideal axis: goes where it is told, reads back nothing (like an open-loop stepper)."""

    name = "tiny"

    class Params(StageParams):
        pass

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self._pos = 0.0
        self.moves = 0

    def move_to(self, deg: float) -> float | None:
        self._pos = deg
        self.moves += 1
        return None

    def position(self) -> float | None:
        return self._pos

    def home(self) -> None:
        self._pos = 0.0


def stages_plugin(*classes: type[Stage]) -> object:
    """A plugin object whose ``plantscan_register_stages`` adds ``classes``, for
    ``manager.register(...)`` in a test."""

    class _Plugin:
        @staticmethod
        @hookimpl
        def plantscan_register_stages(registry) -> None:
            for cls in classes:
                registry.add(cls)

    return _Plugin()


@contextlib.contextmanager
def plugin_file(manager: PluginManager, path: Path, name: str) -> Iterator[ModuleType]:
    """Import the one-file plugin ``path`` as module ``name`` (as an installed plugin
    would be) and register it in ``manager`` for the ``with`` block."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        manager.register(module, name=name)
        try:
            yield module
        finally:
            manager.unregister(module)
    finally:
        sys.modules.pop(name, None)


tiny_rig_plugin = stages_plugin(TinyCamera, TinyAxis)

TINY_CALLS: Counter[str] = Counter()
"""Calls of the tiny processing stages: ``calibrate`` per scan, ``segment`` per view."""
_CALLS_LOCK = threading.Lock()  # segmenters run on a thread pool


def _count_call(what: str) -> None:
    with _CALLS_LOCK:
        TINY_CALLS[what] += 1


class TinyExactCalibrator(Calibrator):
    """The tiny rig's exact cameras (what a perfect calibrator would return)."""

    name = "tiny-exact"

    def calibrate(self, scan) -> Calibration:
        _count_call("calibrate")
        size = tuple(scan.info["rig"]["image_size"])
        models, poses = {}, {}
        for name in scan.info["rig"]["cameras"]:
            cam = tiny_camera(name, 0.0, 0.0, size)
            models[name], poses[(name, 0)] = cam.model, cam.pose
        return Calibration(models, poses, {0: 0.0})


class TinyDarkSegmenter(Segmenter):
    """Plant = pixels whose red channel is under ``threshold`` (the tiny sphere is dark)."""

    name = "tiny-dark"

    class Params(StageParams):
        threshold: int = 100

    def segment(self, image, background, view=None):
        _count_call("segment")
        assert background is not None and background.shape == image.shape
        return image[..., 2] < self.params.threshold


tiny_processing_plugin = stages_plugin(TinyExactCalibrator, TinyDarkSegmenter)


def tiny_recipe(image_size=(96, 64), images_per_revolution: int = 6) -> dict:
    """A raw recipe for the tiny rig (scan part only)."""
    return {
        "name": "tiny",
        "plant": {"id": "tiny-001", "species": "sphere"},
        "scan": {
            "protocol": "tiny",
            "cameras": [{"name": "cam0", "plugin": "tiny"}, {"name": "cam1", "plugin": "tiny"}],
            "turntable": {"plugin": "tiny"},
            "images_per_revolution": images_per_revolution,
            "image_size": list(image_size),
            "roles": {"calibration": {"images_per_revolution": 2},
                      "background": {"images_per_revolution": 1}, "plant": {}},
        },
    }


def make_tiny_scan(root: Path, manager: PluginManager, **kwargs):
    """Acquire a tiny synthetic scan at ``root`` with the real orchestrator."""
    from plantscan_core.acquire import acquire
    from plantscan_core.recipe import validate_recipe

    raw = tiny_recipe(**kwargs)
    recipe = validate_recipe(raw, manager.registry)
    return acquire(recipe, root, manager, raw_recipe=raw)


# --------------------------------------------------------------------------- fixtures
@pytest.fixture
def plantscan_manager() -> PluginManager:
    """A fresh plugin manager with no entry point loaded."""
    return new_manager()


@pytest.fixture
def tiny_rig_manager(plantscan_manager: PluginManager) -> PluginManager:
    plantscan_manager.register(tiny_rig_plugin, name="tiny-rig")
    return plantscan_manager


@pytest.fixture
def tiny_scan(tmp_path: Path, tiny_rig_manager: PluginManager):
    return make_tiny_scan(tmp_path / "scan", tiny_rig_manager)


def pytest_addoption(parser) -> None:
    parser.addoption("--hardware", action="store_true", default=False,
                     help="run tests marked 'hardware' (need a real device attached)")


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "hardware: needs a real device; run with --hardware")
    config.addinivalue_line("markers", "slow: end-to-end test (seconds to minutes)")


def pytest_collection_modifyitems(config, items) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs a real device: run with --hardware")
    for item in items:
        if item.get_closest_marker("hardware") is not None:
            item.add_marker(skip)


__all__ = ["make_tiny_scan", "tiny_camera", "tiny_recipe", "TinyCamera", "TinyAxis",
           "tiny_rig_plugin", "TinyExactCalibrator", "TinyDarkSegmenter",
           "tiny_processing_plugin", "TINY_CALLS", "stages_plugin", "plugin_file"]

"""The ``opencv`` camera on a real ``cv2.VideoCapture`` fed by an image sequence."""

from __future__ import annotations

import os

import cv2
import hwfakes
import numpy as np
import pytest
from hwfakes import RIG, fake_recipe
from plantscan_opencvcam import plugin as opencv_plugin

from plantscan_core.acquire import acquire
from plantscan_core.errors import HardwareError
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import ScanFolder

SIZE = (40, 30)


def _frames(folder, n=200):
    """A 'stream' whose frame k has every pixel's blue value = k (checkable)."""
    folder.mkdir()
    for k in range(n):
        img = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
        img[:, :, 0] = k
        img[:, :, 2] = 255 - k
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    return str(folder / "%03d.png")


@pytest.fixture
def manager():
    m = new_manager()
    m.register(hwfakes)
    m.register(opencv_plugin, name="opencvcam")
    RIG.reset()
    try:
        yield m
    finally:
        m.unregister(hwfakes)


def test_scan_keeps_a_fresh_frame_per_view(manager, tmp_path):
    device = _frames(tmp_path / "frames")
    raw = fake_recipe(cameras=("cam0",), n_angles=4, size=SIZE)
    raw["scan"]["cameras"][0].update(plugin="opencv", params={
        "device": device, "backend": "images", "warmup_frames": 5, "flush_frames": 2})
    recipe = validate_recipe(raw, manager.registry)
    scan = acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    got = [int(scan.read_image(v)[0, 0, 0]) for v in scan.views]
    # Frames 0-4 are warm-up; then each capture drops 2 buffered frames and keeps the 3rd.
    assert got == [5 + 3 * i + 2 for i in range(len(scan.views))]
    assert len(scan.views) == 2 + 4


def test_size_mismatch_names_both_sizes(manager, tmp_path):
    device = _frames(tmp_path / "frames", n=30)
    raw = fake_recipe(cameras=("cam0",), n_angles=2, size=(64, 48))
    raw["scan"]["cameras"][0].update(plugin="opencv", params={"device": device,
                                                              "backend": "images"})
    recipe = validate_recipe(raw, manager.registry)
    with pytest.raises(HardwareError, match=r"40x30 px .*scan.image_size = \[64, 48\]"):
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    assert ScanFolder.open(tmp_path / "s").views == []


def test_missing_device_is_a_clear_error(manager, tmp_path):
    raw = fake_recipe(cameras=("cam0",), n_angles=2, size=SIZE)
    raw["scan"]["cameras"][0].update(plugin="opencv", params={"device": "/dev/video97",
                                                              "backend": "v4l2"})
    recipe = validate_recipe(raw, manager.registry)
    with pytest.raises(HardwareError, match="cannot open the video device.*'video' group"):
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)


def test_stream_that_ends_is_reported(manager, tmp_path):
    device = _frames(tmp_path / "frames", n=5)
    raw = fake_recipe(cameras=("cam0",), n_angles=6, size=SIZE)
    raw["scan"]["cameras"][0].update(plugin="opencv", params={
        "device": device, "backend": "images", "warmup_frames": 0, "flush_frames": 0,
        "retries": 0})
    recipe = validate_recipe(raw, manager.registry)
    from plantscan_core.acquire import AcquisitionError

    with pytest.raises(AcquisitionError, match="no frame after 1 tries") as err:
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    assert err.value.captured == 5  # every frame the 'device' gave is in the scan


@pytest.mark.hardware
def test_real_webcam(request, tmp_path):
    """With a webcam at $PLANTSCAN_WEBCAM (index or path): one frame is written."""
    dev = os.environ.get("PLANTSCAN_WEBCAM")
    if not request.config.getoption("--hardware", default=False) or dev is None:
        pytest.skip("set PLANTSCAN_WEBCAM and run with --hardware")
    from plantscan_opencvcam.camera import OpenCVCamera

    from plantscan_core.stages import CaptureRequest

    cam = OpenCVCamera(OpenCVCamera.Params(device=int(dev) if dev.isdigit() else dev,
                                           set_size=False))
    cam.open()
    try:
        ok, frame = cam.cap.read()
        assert ok
        h, w = frame.shape[:2]
        out = tmp_path / "one.png"
        cam.capture(CaptureRequest(out, "plant", "cam0", 0, 0.0, 0, 0.0, None, (w, h), "png"))
        assert cv2.imread(str(out)).shape == frame.shape
    finally:
        cam.close()

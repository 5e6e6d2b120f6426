"""The ``gphoto2`` camera against libgphoto2's virtual camera (real capture/download code).

libgphoto2's ``vcamera`` driver emulates a PTP camera on a virtual USB bus and
serves the images of the folder ``VCAMERADIR`` as its captures; python-gphoto2
selects it when that variable is set before import, so each scan runs in a
subprocess (``gphoto_runner.py``).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hwfakes import fake_recipe
from plantscan_gphoto.camera import jpeg_size

HERE = Path(__file__).resolve().parent
SIZE = (64, 48)


@pytest.fixture
def vcamdir(tmp_path):
    """Synthetic 'photos' the virtual camera hands out (distinct checkerboards)."""
    d = tmp_path / "vcam"
    d.mkdir()
    for i in range(3):
        yy, xx = np.mgrid[: SIZE[1], : SIZE[0]]
        img = (((xx // (4 + 2 * i)) + (yy // (4 + 2 * i))) % 2 * 200 + 20).astype(np.uint8)
        cv2.imwrite(str(d / f"photo{i}.jpg"), cv2.merge([img, img // 2, 255 - img]))
    return d


def _recipe(plugin="gphoto2", params=None, size=SIZE, fmt="jpg", n_angles=3):
    raw = fake_recipe(cameras=("cam0",), n_angles=n_angles, size=size)
    raw["scan"]["cameras"][0].update(plugin=plugin, params={"retry_backoff_s": 0.01,
                                                             **(params or {})})
    raw["scan"]["image_format"] = fmt
    return raw


def _run(raw, out, vcamdir, faults=None, resume=False):
    rfile = out.parent / f"{out.name}.recipe.json"
    rfile.write_text(json.dumps(raw))
    env = {**os.environ, "VCAMERADIR": str(vcamdir), "GPHOTO_FAULTS": json.dumps(faults or {})}
    args = [sys.executable, str(HERE / "gphoto_runner.py"), str(rfile), str(out)]
    res = subprocess.run(args + (["resume"] if resume else []), env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def _sources(vcamdir):
    return {p.read_bytes() for p in vcamdir.iterdir()}


def test_scan_with_the_virtual_camera_writes_its_jpegs_untouched(tmp_path, vcamdir):
    out = tmp_path / "scan"
    summary = _run(_recipe(), out, vcamdir)
    assert summary["error"] is None
    assert len(summary["views"]) == 2 + 3  # calibration 2 stops + plant 3 stops, one camera
    sources = _sources(vcamdir)
    for v in summary["views"]:
        data = (out / v["file"]).read_bytes()
        assert data in sources, f"{v['file']} is not the camera's file byte for byte"
        assert v["measured_angle_deg"] is not None


def test_png_scan_decodes_to_the_camera_pixels(tmp_path, vcamdir):
    out = tmp_path / "scan"
    summary = _run(_recipe(fmt="png"), out, vcamdir)
    assert summary["error"] is None
    decoded = [cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR)
               for b in _sources(vcamdir)]
    for v in summary["views"]:
        img = cv2.imread(str(out / v["file"]))
        assert v["file"].endswith(".png")
        assert any(np.array_equal(img, d) for d in decoded)  # PNG is lossless: exact pixels


def test_transient_errors_are_retried_and_the_scan_completes(tmp_path, vcamdir):
    out = tmp_path / "scan"
    faults = {"init": [-53, -53], "capture": [-110, 0, -10, -60, 0, -110],
              "file_get": [-10, 0, -53]}
    summary = _run(_recipe("gphoto2-faulty"), out, vcamdir, faults)
    assert summary["error"] is None
    assert len(summary["views"]) == 5
    assert summary["retries"] == 2 + 4 + 2  # every injected fault was retried once


def test_usb_reset_mid_scan_reconnects(tmp_path, vcamdir):
    """-7 / -52 on the shutter release: the camera is re-opened and the scan goes on."""
    out = tmp_path / "scan"
    faults = {"capture": [0, 0, -7, 0, -52], "init": [0, 0, -53]}
    summary = _run(_recipe("gphoto2-faulty"), out, vcamdir, faults)
    assert summary["error"] is None and len(summary["views"]) == 5
    # 2 reconnects + one -53 while re-opening, retried with back-off
    assert summary["retries"] == 3


def test_camera_held_by_another_program_gives_an_actionable_error(tmp_path, vcamdir):
    out = tmp_path / "scan"
    summary = _run(_recipe("gphoto2-faulty", {"retries": 3}), out, vcamdir,
                   {"init": [-53] * 50})
    err = summary["error"]
    assert err is not None and err["type"] == "GPhotoError"
    assert "after 4 tries" in err["message"] and "gvfs" in err["message"]
    assert "-53" in err["message"] and "cam0" in err["message"]
    assert summary["views"] == []


def test_camera_busy_for_good_mid_scan_keeps_images_and_resume_completes(tmp_path, vcamdir):
    out = tmp_path / "scan"
    faults = {"capture": [0, 0, 0] + [-110] * 20}
    summary = _run(_recipe("gphoto2-faulty", {"retries": 2}), out, vcamdir, faults)
    err = summary["error"]
    assert err["type"] == "AcquisitionError"
    assert "camera 'cam0'" in err["message"] and "--resume" in err["message"]
    assert len(summary["views"]) == 3
    kept = {v["file"]: os.stat(out / v["file"]).st_ino for v in summary["views"]}
    summary = _run(_recipe("gphoto2-faulty"), out, vcamdir, resume=True)
    assert summary["error"] is None and len(summary["views"]) == 5
    assert all(os.stat(out / f).st_ino == ino for f, ino in kept.items()), "image rewritten"


def test_jpeg_size_reads_the_header():
    ok, buf = cv2.imencode(".jpg", np.zeros((37, 53, 3), np.uint8))
    assert jpeg_size(buf.tobytes()) == (53, 37)
    assert jpeg_size(b"\x89PNG....") is None


@pytest.mark.hardware
def test_real_camera_captures_one_image(tmp_path, request):
    """With a real camera attached: one capture lands as a decodable JPEG."""
    if not request.config.getoption("--hardware", default=False):
        pytest.skip("needs a camera: run with --hardware")
    import gphoto2 as gp

    if os.environ.get("VCAMERADIR"):
        pytest.skip("VCAMERADIR is set: that is the virtual camera, not a real one")
    cams = list(gp.Camera.autodetect())
    if not cams:
        pytest.fail("--hardware given but no camera detected by libgphoto2")
    from plantscan_gphoto.camera import GPhotoCamera

    from plantscan_core.stages import CaptureRequest

    cam = GPhotoCamera(GPhotoCamera.Params(check_image_size=False))
    cam.open()
    try:
        out = tmp_path / "one.jpg"
        cam.capture(CaptureRequest(out, "plant", "cam0", 0, 0.0, 0, 0.0, None, (1, 1), "jpg"))
        assert cv2.imread(str(out)) is not None
    finally:
        cam.close()


PROBES = {
    "model": ({"model": "nikon dsc"}, None),
    "port": ({"port": "usb:001,001"}, None),
    "serial": ({"serial": "0.1"}, None),  # the virtual camera's serial number
    "other model": ({"model": "EOS 600D"}, ["model='EOS 600D'", "Nikon DSC D750 on usb:001,001"]),
    "other serial": ({"serial": "123456"}, ["'123456'", "Nikon DSC D750 on usb:001,001"]),
    "unknown setting": ({"settings": {"whitebalance": "Daylight"}},
                        ["'whitebalance'", "params.settings.whitebalance", "offers:"]),
    "size mismatch": ({"check_image_size": True}, ["64x48", "scan.image_size = [640, 480]"]),
    "settings": ({"aperture": "f/8", "shutter_speed": "0.0050s", "capture_target": "card",
                  "settings": {"exposurecompensation": "-1"}}, None),
    "invalid value": ({"aperture": "8"}, ["params.aperture = '8'", "valid: f/2.8, f/3.5"]),
}
READ_BACK = {"f-number": "f/8", "shutterspeed": "0.0050s", "capturetarget": "Memory card",
             "exposurecompensation": "-1"}


@pytest.fixture(scope="module")
def probe_results(tmp_path_factory):
    """Open the virtual camera once per case (one subprocess for all cases)."""
    root = tmp_path_factory.mktemp("probe")
    d = root / "vcam"
    d.mkdir()
    cv2.imwrite(str(d / "photo.jpg"), np.full((SIZE[1], SIZE[0], 3), 90, np.uint8))
    cases = [{"params": {"retry_backoff_s": 0.01, **params},
              "size": [640, 480] if name == "size mismatch" else list(SIZE),
              "read": list(READ_BACK) if name == "settings" else []}
             for name, (params, _) in PROBES.items()]
    (root / "cases.json").write_text(json.dumps(cases))
    env = {**os.environ, "VCAMERADIR": str(d)}
    res = subprocess.run([sys.executable, str(HERE / "gphoto_runner.py"), "--probe",
                          str(root / "cases.json")], env=env, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    return dict(zip(PROBES, json.loads(res.stdout.strip().splitlines()[-1]), strict=True))


@pytest.mark.parametrize("case", list(PROBES))
def test_camera_selection_settings_and_size(probe_results, case):
    expected = PROBES[case][1]
    error = probe_results[case]["error"]
    if expected is None:
        assert error is None
        if case == "settings":  # what the virtual camera reports after open()
            assert probe_results[case]["values"] == READ_BACK
    else:
        assert error is not None and all(part in error for part in expected), error


def test_list_cameras_command_shows_what_a_recipe_needs(tmp_path, vcamdir):
    env = {**os.environ, "VCAMERADIR": str(vcamdir)}
    res = subprocess.run([sys.executable, str(HERE / "gphoto_runner.py"), "--command",
                          "gphoto2-cameras", "--config"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    assert "Nikon DSC D750 on usb:001,001: serial 0.1" in out
    assert "f-number = f/2.8  [f/2.8, f/3.5," in out  # the exact spelling for params.aperture
    assert re.search(r"capturetarget = .+  \[Internal RAM, Memory card\]", out)
    assert "serialnumber = 0.1  (read-only)" in out


def test_two_identical_cameras_need_a_serial():
    """Picking 'the first' of two matching cameras could swap cam0 and cam1 between scans."""
    from plantscan_gphoto.camera import GPhotoCamera, GPhotoError

    class TwoCanons(GPhotoCamera):
        def _detect(self):
            return [("Canon EOS 600D", "usb:001,004"), ("Canon EOS 600D", "usb:001,005")]

    cam = TwoCanons(GPhotoCamera.Params(model="600D"))
    cam.camera_name = "cam1"
    with pytest.raises(GPhotoError, match=r"camera 'cam1': 2 connected cameras match .*"
                                          r"params.serial"):
        cam.open()


def test_virtual_camera_with_a_grbl_turntable(tmp_path, vcamdir):
    """The real-rig stack without hardware: libgphoto2 capture + G-code over a socket."""
    from grbl_emulator import TcpGrbl

    emu = TcpGrbl()
    try:
        raw = _recipe(n_angles=4)  # one camera: libgphoto2 has one virtual camera
        raw["scan"]["cameras"][0]["params"]["port"] = "usb:001,001"
        raw["scan"]["turntable"] = {"plugin": "grbl", "params": {
            "port": emu.url, "poll_interval_s": 0.01, "feed_rate": 6000}}
        summary = _run(raw, tmp_path / "scan", vcamdir)
    finally:
        emu.close()
    assert summary["error"] is None and len(summary["views"]) == 2 + 4
    for v in summary["views"]:  # angles read back from the controller's status reports
        assert v["measured_angle_deg"] == pytest.approx(v["commanded_angle_deg"], abs=0.002)
    assert emu.machine.moves == 2 + 4  # one G1 per stop: calibration 0, 180; plant 0..270

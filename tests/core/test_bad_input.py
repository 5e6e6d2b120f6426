"""Bad input found by a hostile pass over plantscan (issue #23), one test per case.

Each test is named after what it feeds.  The property is the same everywhere:
plantscan refuses with exit status 2 and a message naming the file, line or
parameter, never a traceback and never a NaN carried into a result.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from plantscan_core.cli import main
from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord, mean_relative_error
from plantscan_core.errors import DataError, ScanFolderError
from plantscan_core.scanfolder import ScanFolder, read_image
from plantscan_core.testing import tiny_recipe


def _check(capsys, *argv: str) -> str:
    """Run ``plantscan ARGV``; assert it refused cleanly (status 2); return stderr."""
    status = main(list(argv))
    err = capsys.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err
    return err


# --------------------------------------------------------------------------- recipe numbers
@pytest.mark.parametrize("override, path", [
    ("reconstruct.params.floor_z_mm=.nan", "reconstruct.params.floor_z_mm"),
    ("reconstruct.params.bbox=[-100,-100,0,100,100,.inf]", "reconstruct.params.bbox.5"),
    ("mesh.params.pot_margin_mm=.nan", "mesh.params.pot_margin_mm"),
    ("segment.params.threshold=.inf", "segment.params.threshold"),
    ("calibrate.params.square_mm=.nan", "calibrate.params.square_mm"),
    ("calibrate.params.lowest_corner_height_mm=-.inf", "calibrate.params.lowest_corner_height_mm"),
    ("scan.roles.plant.tilts_deg=[.nan]", "scan.roles.plant.tilts_deg.0"),
    ("scan.roles.plant.tilts_deg=[1000]", "scan.roles.plant.tilts_deg.0"),
    ("scan.roles.background.tilts_deg=[-720]", "scan.roles.background.tilts_deg.0"),
    ("scan.image_size=[100000,100000]", "scan.image_size.0"),
])
def test_set_override_with_nan_inf_or_out_of_range_number(capsys, override, path):
    err = _check(capsys, "recipe", "check", "plastic-dicot", "--set", override)
    assert f"{path}: " in err


def test_set_override_with_acceleration_1e308(capsys):
    err = _check(capsys, "recipe", "check", "plastic-dicot", "--set", "scan.turntable.plugin=grbl",
                 "--set", "scan.turntable.params={port: 'loop://', acceleration_deg_s2: 1e308}")
    assert "scan.turntable.params.acceleration_deg_s2: " in err and "out of range" in err


def test_scan_with_images_too_large_for_the_machine(capsys, tmp_path):
    """60000x40000 px passes the format's limit; the memory estimate refuses it before any motor
    moves or the scan folder exists."""
    out = tmp_path / "scan"
    err = _check(capsys, "scan", "--recipe", "plastic-dicot", "--set",
                 "scan.image_size=[60000,40000]", "--out", str(out))
    assert "scan.scene (sim): rendering one 60000x40000 px image needs about 57.6 GB" in err
    assert "lower scan.image_size" in err and "--force" in err
    assert not out.exists()


def test_scan_dry_run_prints_the_estimates_of_resolution_1024(capsys):
    assert main(["scan", "--recipe", "plastic-dicot", "--dry-run",
                 "--set", "reconstruct.params.resolution=1024"]) == 0
    out = capsys.readouterr().out
    assert "estimate: reconstruct (octree-hull): a 1024x1024x1024 grid and 72 views needs about" \
        in out


# --------------------------------------------------------------------------- text files
def _recipe_file(tmp_path, data: bytes):
    f = tmp_path / "r.yaml"
    f.write_bytes(data)
    return str(f)


def test_recipe_file_in_utf16(tmp_path, capsys):
    f = _recipe_file(tmp_path, yaml.safe_dump(tiny_recipe()).encode("utf-16"))
    assert f"{f}:1: is UTF-16 text; save it as UTF-8" in _check(capsys, "recipe", "check", f)


def test_recipe_file_in_latin1(tmp_path, capsys):
    text = yaml.safe_dump(tiny_recipe()) + "description: Blätter\n"
    f = _recipe_file(tmp_path, text.encode("latin-1"))
    line = text.count("\n")
    assert f"{f}:{line}: not UTF-8 text (byte 0xe4" in _check(capsys, "recipe", "check", f)


def test_recipe_nested_1000_deep(tmp_path, capsys):
    f = _recipe_file(tmp_path, b"scan: " + b"[" * 1000 + b"]" * 1000 + b"\n")
    assert "nested deeper than" in _check(capsys, "recipe", "check", f)


def test_recipe_alias_bomb(tmp_path, capsys):
    lines = ["a0: [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    lines[0] = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]"
    f = _recipe_file(tmp_path, ("\n".join(lines) + "\n").encode())
    assert "expands to more than" in _check(capsys, "recipe", "check", f)


def test_recipe_with_a_yaml_syntax_error_names_the_line(tmp_path, capsys):
    f = _recipe_file(tmp_path, b"name: x\nscan: {cameras: [\n  bad: : :\n")
    err = _check(capsys, "recipe", "check", f)
    assert f"{f}:3: not valid YAML" in err


def test_scan_yaml_in_utf16(tmp_scan_folder):
    (tmp_scan_folder / "scan.yaml").write_bytes("plant_id: p\n".encode("utf-16"))
    with pytest.raises(ScanFolderError, match=r"scan.yaml:1: is UTF-16"):
        ScanFolder.open(tmp_scan_folder)


@pytest.fixture
def tmp_scan_folder(tmp_path):
    scan = ScanFolder.create(tmp_path / "s", {"plant_id": "p"})
    return scan.root


# --------------------------------------------------------------------------- calibration files
def _calibration() -> Calibration:
    model = CameraModel(f=800.0, cu=319.5, cv=213.0, width=640, height=427)
    return Calibration({"cam0": model}, {("cam0", 0): Pose(np.eye(3), [0.0, 0.0, 900.0])},
                       {0: 0.0})


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(models=5), "models: Input should be a valid dictionary"),
    (lambda d: d["models"]["cam0"].update(f=float("nan")), "models.cam0.f: Input should be a "
                                                            "finite number"),
    (lambda d: d["models"]["cam0"].update(f=-800.0), "models.cam0.f: Input should be greater"),
    (lambda d: d["poses"][0].update(t=[0, 0, float("inf")]), "poses.0.t.2: Input should be a "
                                                               "finite number"),
    (lambda d: d["poses"][0].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "R is not a rotation"),
    (lambda d: d["poses"][0].update(camera="cam9"), "poses name camera(s) ['cam9']"),
    (lambda d: d.update(angle_scale=float("nan")), "angle_scale: Input should be a finite"),
])
def test_calibration_file_with_bad_values(tmp_path, edit, message):
    d = _calibration().to_dict()
    edit(d)
    f = tmp_path / "calibration.yaml"
    f.write_text(yaml.safe_dump(d))
    with pytest.raises(DataError) as info:
        Calibration.load(f)
    assert f"{f}: " in str(info.value) and message in str(info.value)


def test_calibration_file_round_trips():
    """The checks accept what plantscan writes (no false alarm)."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        _calibration().save(Path(d) / "c.yaml")
        assert Calibration.load(Path(d) / "c.yaml").models["cam0"].f == 800.0


# --------------------------------------------------------------------------- manifests
def _view(i: int, **kw) -> ViewRecord:
    base = dict(index=i, role="plant", camera="cam0", tilt_index=0, tilt_deg=0.0, angle_index=i,
                commanded_angle_deg=10.0 * i, measured_angle_deg=None,
                file=f"images/plant/{i:05d}.png")
    base.update(kw)
    return ViewRecord(**base)


def _write_views(root, views) -> None:
    (root / "views.jsonl").write_text(
        "".join(json.dumps(v.to_dict() if isinstance(v, ViewRecord) else v) + "\n"
                for v in views))


@pytest.mark.parametrize("second, what", [
    (_view(0), "index"),                                   # a repeated line
    (_view(0, angle_index=1, file="images/plant/x.png"), "index"),   # a shared index
    (_view(1, angle_index=0, file="images/plant/x.png"), "view"),    # a shared view key
    (_view(1, file="images/plant/00000.png"), "file"),                # a shared file
])
def test_views_jsonl_with_duplicate_views(tmp_scan_folder, second, what):
    _write_views(tmp_scan_folder, [_view(0), second])
    with pytest.raises(ScanFolderError, match=rf"views.jsonl:2: repeats the {what} .* of line 1"):
        ScanFolder.open(tmp_scan_folder)


@pytest.mark.parametrize("field, value", [("commanded_angle_deg", float("nan")),
                                          ("measured_angle_deg", float("inf")),
                                          ("tilt_deg", 1000.0), ("index", -1)])
def test_views_jsonl_with_nan_or_out_of_range_numbers(tmp_scan_folder, field, value):
    line = _view(0).to_dict()
    line[field] = value
    _write_views(tmp_scan_folder, [line])
    with pytest.raises(ScanFolderError, match=rf"views.jsonl:1: malformed view line \({field}"):
        ScanFolder.open(tmp_scan_folder)


def test_views_jsonl_torn_last_line_is_reported(tmp_scan_folder):
    _write_views(tmp_scan_folder, [_view(0)])
    with open(tmp_scan_folder / "views.jsonl", "a") as f:
        f.write('{"index": 1, "ro')
    scan = ScanFolder.open(tmp_scan_folder)
    assert len(scan.views) == 1 and scan.torn_line == 2


# --------------------------------------------------------------------------- images
@pytest.fixture(scope="module")
def jpeg_bytes() -> bytes:
    rng = np.random.default_rng(0)
    img = cv2.resize((rng.random((30, 45, 3)) * 255).astype(np.uint8), (451, 301))
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()


@pytest.mark.parametrize("reduce", [1, 2, 4])
@pytest.mark.parametrize("grayscale", [False, True])
def test_jpeg_decode_is_the_same_as_opencv(tmp_path, jpeg_bytes, reduce, grayscale):
    """The strict decoder changes nothing on a good file (odd sizes round as OpenCV's)."""
    f = tmp_path / "ok.jpg"
    f.write_bytes(jpeg_bytes)
    flag = {(1, False): cv2.IMREAD_COLOR, (2, False): cv2.IMREAD_REDUCED_COLOR_2,
            (4, False): cv2.IMREAD_REDUCED_COLOR_4, (1, True): cv2.IMREAD_GRAYSCALE,
            (2, True): cv2.IMREAD_REDUCED_GRAYSCALE_2, (4, True): cv2.IMREAD_REDUCED_GRAYSCALE_4}
    expected = cv2.imread(str(f), flag[(reduce, grayscale)])
    np.testing.assert_array_equal(read_image(f, reduce, grayscale), expected)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_jpeg_with_exif_orientation_is_the_same_as_opencv(tmp_path, jpeg_bytes, orientation):
    import io

    from PIL import Image

    im = Image.open(io.BytesIO(jpeg_bytes))
    exif = im.getexif()
    exif[0x0112] = orientation
    f = tmp_path / "o.jpg"
    im.save(f, "JPEG", quality=92, exif=exif)
    np.testing.assert_array_equal(read_image(f, 2), cv2.imread(str(f), cv2.IMREAD_REDUCED_COLOR_2))


def test_truncated_jpeg(tmp_path, jpeg_bytes):
    f = tmp_path / "t.jpg"
    f.write_bytes(jpeg_bytes[: len(jpeg_bytes) // 2])
    with pytest.raises(DataError, match=r"t.jpg: corrupt or truncated JPEG"):
        read_image(f)


@pytest.mark.parametrize("with_marker_bytes", [True, False])
def test_jpeg_with_random_bytes_mid_file(tmp_path, jpeg_bytes, with_marker_bytes):
    rng = np.random.default_rng(3)
    noise = rng.integers(0, 256, 200, dtype=np.uint8).tobytes()
    if not with_marker_bytes:
        noise = noise.replace(b"\xff", b"\x00")
    data = bytearray(jpeg_bytes)
    mid = len(data) // 2
    data[mid:mid + 200] = noise
    f = tmp_path / "c.jpg"
    f.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"c.jpg: corrupt or truncated JPEG"):
        read_image(f)


def test_truncated_png(tmp_path):
    f = tmp_path / "t.png"
    f.write_bytes(cv2.imencode(".png", np.full((40, 60, 3), 99, np.uint8))[1].tobytes()[:-30])
    with pytest.raises(DataError, match=r"t.png: cannot decode image"):
        read_image(f)


# --------------------------------------------------------------------------- commands
def test_batch_with_workers_0(capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        main(["batch", str(tmp_path), "--recipe", "plastic-dicot", "--workers", "0"])
    assert info.value.code == 2
    assert "--workers: must be at least 1, got 0" in capsys.readouterr().err


def test_internal_error_is_a_message_and_run_log_holds_the_traceback(tmp_path, capsys,
                                                                    monkeypatch):
    from plantscan_core import cli

    def broken(args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(cli, "cmd_evaluate", broken)  # build_parser looks it up by name
    status = main(["evaluate", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 1
    assert "internal error: ZeroDivisionError: a bug" in err and "Traceback" not in err
    log = (tmp_path / "run.log").read_text()
    assert "Traceback" in log and "ZeroDivisionError: a bug" in log


def test_relative_error_of_a_trait_whose_truth_is_zero():
    """A closed external mesh has perimeter 0: no relative error, not inf."""
    with np.errstate(all="raise"):
        assert mean_relative_error([0.0, 10.0], [5.0, 11.0]) == pytest.approx(0.1)
        assert np.isnan(mean_relative_error([0.0], [5.0]))


# --------------------------------------------------------------------------- processing
def test_process_of_a_scan_with_a_torn_last_view_line(tiny_rig_manager, tmp_path, capsys):
    from plantscan_core.pipeline import process
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.testing import make_tiny_scan

    scan = make_tiny_scan(tmp_path / "scan", tiny_rig_manager)
    with open(scan.root / "views.jsonl", "a") as f:
        f.write('{"index": 99, "role": "pla')
    raw = tiny_recipe()
    result = process(scan.root, validate_recipe(raw, tiny_rig_manager.registry), tmp_path / "run",
                     tiny_rig_manager)
    n = len(scan.views) + 1
    assert f"views.jsonl:{n}: torn last line" in capsys.readouterr().err
    assert any(f"views.jsonl:{n}: torn" in w for w in result.info["warnings"])
    assert json.loads((tmp_path / "run" / "run.json").read_text())["warnings"]


def test_stage_error_on_a_full_disk_keeps_the_stage_message(tiny_rig_manager, tmp_path,
                                                            monkeypatch, capsys):
    """ENOSPC while the error handler writes run.json: the stage's own error still comes out."""
    import errno

    from plantscan_core import pipeline
    from plantscan_core.errors import StageError
    from plantscan_core.hookspecs import hookimpl
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.stages import Calibrator
    from plantscan_core.testing import make_tiny_scan

    class BrokenCalibrator(Calibrator):
        name = "tiny-broken"

        def calibrate(self, scan):
            raise DataError("no board found in view 3")

    class Plugin:
        @hookimpl
        def plantscan_register_stages(self, registry):
            registry.add(BrokenCalibrator)

    tiny_rig_manager.register(Plugin(), name="broken")
    scan = make_tiny_scan(tmp_path / "scan", tiny_rig_manager)
    raw = {**tiny_recipe(), "calibrate": {"plugin": "tiny-broken"}}
    recipe = validate_recipe(raw, tiny_rig_manager.registry)

    def disk_full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline.Run, "_write_info", disk_full)
    with pytest.raises(StageError, match="no board found in view 3"):
        pipeline.process(scan.root, recipe, tmp_path / "run", tiny_rig_manager)
    assert "No space left on device" in capsys.readouterr().err


def test_fixed_calibration_file_replaced_between_runs(tiny_rig_manager, tmp_path):
    """Re-importing a scan with another calibration.yaml, same --out: the calibration is new."""
    import os

    import plantscan_calib.plugin as calib_plugin

    from plantscan_core.pipeline import process
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.testing import make_tiny_scan, tiny_camera

    tiny_rig_manager.register(calib_plugin, name="calib")
    scan = make_tiny_scan(tmp_path / "scan", tiny_rig_manager)
    recipe = validate_recipe({**tiny_recipe(), "calibrate": {"plugin": "fixed"}},
                             tiny_rig_manager.registry)
    cal_file = scan.root / "calibration.yaml"
    runs = []
    for distance_mm in (0.0, 5.0):
        cams = {n: tiny_camera(n, 0.0, 0.0, (96, 64)) for n in ("cam0", "cam1")}
        Calibration({n: c.model for n, c in cams.items()},
                    {(n, 0): Pose(c.pose.R, c.pose.t + [0, 0, distance_mm])
                     for n, c in cams.items()}, {0: 0.0}).save(cal_file)
        os.utime(cal_file, ns=(0, 0))  # same size and time stamp: only the content differs
        runs.append(process(scan.root, recipe, tmp_path / "run", tiny_rig_manager))
    assert not runs[1].info["stages"]["calibrate"]["cached"]
    assert runs[1].calibration.poses[("cam0", 0)].t[2] == pytest.approx(
        runs[0].calibration.poses[("cam0", 0)].t[2] + 5.0)

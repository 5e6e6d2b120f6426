"""COLMAP models that a hostile pass found imported without a word (issue #23), one per case.

Every case must be refused by ``plantscan import colmap`` with exit status 2 and
a message naming ``file:line``, before anything is written.
"""

from __future__ import annotations

import shutil

import pytest
from test_colmap import colmap_dir  # noqa: F401 - the fixture: a sphere seen by a known rig

from plantscan_core.cli import main

CAMERAS = "1 RADIAL 640 427 800.0 320.0 213.5 0.0 0.0\n"
POSE = "0.5 0.5 0.5 0.5 0.0 0.0 900.0"


def _import(capsys, model_dir, images_dir, out, *extra: str) -> str:
    status = main(["import", "colmap", str(model_dir), "--images", str(images_dir),
                   "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err
    assert not (out / "views.jsonl").exists()  # nothing written
    return err


def _model(tmp_path, cameras: str, images: str):
    d = tmp_path / "sparse"
    d.mkdir()
    (d / "cameras.txt").write_text(cameras)
    (d / "images.txt").write_text(images)
    return d


@pytest.mark.parametrize("line, message", [
    ("1 RADIAL 640 427 nan 320.0 213.5 0.0 0.0", "parameters must be finite numbers"),
    ("1 RADIAL 640 427 800.0 inf 213.5 0.0 0.0", "parameters must be finite numbers"),
    ("1 RADIAL 640 427 -800.0 320.0 213.5 0.0 0.0", "focal length f=-800 must be > 0"),
    ("1 PINHOLE 640 427 800.0 -800.0 320.0 213.5", "focal length fy=-800 must be > 0"),
    ("1 RADIAL 640 427 800.0 320.0", "2 parameters, the model has 5"),
    ("1 OPENCV 640 427 800.0 800.0 320.0", "3 parameters, the model has 8"),
    ("1 RADIAL", "malformed camera line"),
    ("1 RADIAL 0 427 800.0 320.0 213.5 0.0 0.0", "image size 0x427 px out of range"),
])
def test_cameras_txt_with_bad_parameters(tmp_path, capsys, line, message):
    model = _model(tmp_path, line + "\n", f"1 {POSE} 1 a.png\n\n")
    err = _import(capsys, model, tmp_path, tmp_path / "scan")
    assert "cameras.txt:1" in err and message in err


@pytest.mark.parametrize("pose, message", [
    ("nan 0.5 0.5 0.5 0.0 0.0 900.0", "quaternion QW QX QY QZ must be finite"),
    ("0 0 0 0 0.0 0.0 900.0", "is zero (no rotation)"),
    ("0.5 0.5 0.5 0.5 0.0 inf 900.0", "translation TX TY TZ must be finite"),
])
def test_images_txt_with_bad_pose(tmp_path, capsys, pose, message):
    model = _model(tmp_path, CAMERAS, f"1 {pose} 1 a.png\n\n")
    err = _import(capsys, model, tmp_path, tmp_path / "scan")
    assert "images.txt:1 (image 1)" in err and message in err


def test_images_txt_with_duplicate_image_names(tmp_path, capsys):
    model = _model(tmp_path, CAMERAS, f"1 {POSE} 1 a.png\n\n2 {POSE} 1 a.png\n\n")
    err = _import(capsys, model, tmp_path, tmp_path / "scan")
    assert "images.txt:3 (image 2): image name 'a.png' is listed again (first at line 1)" in err


def test_images_txt_with_duplicate_image_ids(tmp_path, capsys):
    model = _model(tmp_path, CAMERAS, f"1 {POSE} 1 a.png\n\n1 {POSE} 1 b.png\n\n")
    assert "image id 1 is used again" in _import(capsys, model, tmp_path, tmp_path / "scan")


def test_images_txt_missing_the_second_line_of_an_image(tmp_path, capsys):
    images = f"1 {POSE} 1 a.png\n2 {POSE} 1 b.png\n\n3 {POSE} 1 c.png\n\n"
    err = _import(capsys, _model(tmp_path, CAMERAS, images), tmp_path, tmp_path / "scan")
    assert "images.txt:2: an image line where the 2D points line of image 1" in err


def test_cameras_txt_in_utf16(tmp_path, capsys):
    model = _model(tmp_path, "", f"1 {POSE} 1 a.png\n\n")
    (model / "cameras.txt").write_bytes(CAMERAS.encode("utf-16"))
    assert "cameras.txt:1: is UTF-16 text" in _import(capsys, model, tmp_path, tmp_path / "scan")


def test_images_txt_not_utf8(tmp_path, capsys):
    model = _model(tmp_path, CAMERAS, "")
    (model / "images.txt").write_bytes(f"1 {POSE} 1 Blätter.png\n\n".encode("latin-1"))
    err = _import(capsys, model, tmp_path, tmp_path / "scan")
    assert "images.txt:1: not UTF-8 text" in err


@pytest.mark.parametrize("scale", ["nan", "inf", "0", "-1"])
def test_import_with_scale(colmap_dir, tmp_path, capsys, scale):  # noqa: F811
    root, *_ = colmap_dir
    err = _import(capsys, root / "sparse", root / "images", tmp_path / "scan", "--scale", scale)
    assert "--scale: must be a finite number > 0" in err


def test_a_good_model_still_imports(colmap_dir, tmp_path, capsys):  # noqa: F811
    root, *_ = colmap_dir
    shutil.copytree(root / "sparse", tmp_path / "sparse")
    assert main(["import", "colmap", str(tmp_path / "sparse"), "--images", str(root / "images"),
                 "--out", str(tmp_path / "scan")]) == 0

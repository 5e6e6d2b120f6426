"""``plantscan import colmap``: parsing, conventions, round trip, errors."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest
from hull_phantoms import Sphere, render, ring_calibration, views
from plantscan_hull.colmap import (
    add_import_command,
    export_colmap_text,
    import_colmap,
    matrix_to_quaternion,
    quaternion_to_matrix,
    read_cameras,
)

from plantscan_core.data import Calibration
from plantscan_core.errors import DataError
from plantscan_core.scanfolder import ScanFolder


@pytest.fixture(scope="module")
def colmap_dir(tmp_path_factory):
    """A COLMAP text model + images + masks of an analytic sphere seen by a known rig."""
    root = tmp_path_factory.mktemp("colmap")
    cal = ring_calibration(elevations=(0.0, 30.0))
    vl = views(6, (0.0, 30.0))
    sils = render(cal, vl, [Sphere((0.0, 0.0, 0.0), 30.0)])
    (root / "images").mkdir()
    (root / "masks").mkdir()
    for s in sils:
        name = s.view.file.split("/")[-1]
        img = np.where(s.mask[..., None], 40, 200).astype(np.uint8).repeat(3, axis=2)
        cv2.imwrite(str(root / "images" / name), img)
        cv2.imwrite(str(root / "masks" / f"{name}.png"), s.mask.astype(np.uint8) * 255)
    export_colmap_text(cal, vl, root / "sparse")
    return root, cal, vl, sils


def test_quaternion_roundtrip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        r = quaternion_to_matrix(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.allclose(matrix_to_quaternion(r), q, atol=1e-9)


def test_import_roundtrips_the_cameras(colmap_dir, tmp_path):
    root, cal, vl, sils = colmap_dir
    scan = import_colmap(root / "sparse", root / "images", tmp_path / "scan", root / "masks")
    imported = Calibration.load(tmp_path / "scan" / "calibration.yaml")
    pts = np.random.default_rng(0).uniform(-40, 40, size=(200, 3))
    views_in = scan.views
    assert len(views_in) == len(vl)
    for v_orig, v_new in zip(vl, views_in):
        a = cal.camera_for_view(v_orig).project(pts)
        b = imported.camera_for_view(v_new).project(pts)
        # Text round trip with repr() floats: exact to rounding (1e-6 px is far below a pixel).
        assert np.abs(a - b).max() < 1e-6
    # Masks where the given-masks segmenter reads them, identical to the input ones.
    for s, v_new in zip(sils, views_in):
        stem = v_new.file.split("/")[-1].rsplit(".", 1)[0]
        m = cv2.imread(str(tmp_path / "scan" / "masks" / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
        assert np.array_equal(m > 127, s.mask)
    # The scan carries a recipe that processes it with the fixed calibration and given masks.
    recipe = ScanFolder.open(tmp_path / "scan").recipe_dict
    assert recipe["calibrate"]["plugin"] == "fixed"
    assert recipe["segment"]["plugin"] == "given-masks"


def test_colmap_pixel_convention(tmp_path):
    # COLMAP's top-left pixel centre is (0.5, 0.5); plantscan's is (0, 0).
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 500 320 240 -0.1\n")
    m = read_cameras(tmp_path / "cameras.txt")[1]
    assert (m.cu, m.cv, m.d1, m.d2) == (319.5, 239.5, -0.1, 0.0)


def test_pinhole_with_fx_ne_fy_keeps_the_aspect_ratio(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 500 500.3 320 240\n")
    m = read_cameras(tmp_path / "cameras.txt")[1]
    assert (m.f, m.fy) == (500.0, pytest.approx(500.3, abs=1e-12))


@pytest.mark.parametrize("line, message", [
    ("1 OPENCV 640 480 500 500 320 240 0.1 0.0 0.001 0 ", "tangential"),
    ("1 PINHOLE 640 480 500 520 320 240", "fx=500 and fy=520 differ"),
    ("1 FISHEYE 640 480 500 320 240 0.1", "not supported"),
])
def test_unsupported_cameras_are_named(tmp_path, line, message):
    (tmp_path / "cameras.txt").write_text(line + "\n")
    with pytest.raises(DataError, match=message):
        read_cameras(tmp_path / "cameras.txt")


def test_mask_of_wrong_size_is_named(colmap_dir, tmp_path):
    root, *_ = colmap_dir
    masks = tmp_path / "masks"
    masks.mkdir()
    for p in (root / "masks").iterdir():
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(masks / p.name), m[:, :-2])
    with pytest.raises(DataError, match="masks do not match the images"):
        import_colmap(root / "sparse", root / "images", tmp_path / "scan", masks)
    assert not (tmp_path / "scan" / "scan.yaml").exists()  # nothing written on bad input


def test_missing_model_file_is_named(tmp_path):
    with pytest.raises(DataError, match="cameras.txt: not found"):
        import_colmap(tmp_path, tmp_path, tmp_path / "scan")


def test_cli_command(colmap_dir, tmp_path):
    root, *_ = colmap_dir
    parser = argparse.ArgumentParser(prog="plantscan")
    sub = parser.add_subparsers(dest="command")
    add_import_command(sub)
    args = parser.parse_args(["import", "colmap", str(root / "sparse"), "--images",
                              str(root / "images"), "--masks", str(root / "masks"),
                              "--out", str(tmp_path / "scan")])
    assert args.func(args) == 0
    assert len(ScanFolder.open(tmp_path / "scan").views) == 12

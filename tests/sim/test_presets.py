"""Other plants and boards: wheat, sorghum, external meshes, ChArUco."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
from plantscan_sim import make_scan, read_truth_cameras
from plantscan_sim.geometry import LeafPlacement, leaf_outline, leaf_surface, mesh_area

from plantscan_core.data import Traits
from plantscan_core.errors import DataError

TINY = dict(image_size=(320, 214), images_per_revolution=2)


@pytest.mark.parametrize("preset", ["wheat", "sorghum"])
def test_grass_presets_scan_with_their_recipes(preset, tmp_path):
    scan = make_scan(tmp_path / preset, preset=preset, **TINY, roles=["plant"])
    gt = scan.ground_truth_dir
    traits = Traits.load(gt / "traits.csv", gt / "plant_traits.json")
    assert traits.plant["leaf_count"] == len(traits.leaves) >= 6
    # Grass blades: long and narrow.
    assert all(t.length_mm > 4 * t.width_mm for t in traits.leaves)
    for view in scan.views:
        mask = cv2.imread(str(gt / "masks" / f"{view.index:05d}.png"), cv2.IMREAD_GRAYSCALE)
        assert 0.01 < (mask > 0).mean() < 0.5


def _two_leaf_obj(tmp_path):
    import open3d as o3d

    parts, labels = [], []
    off = 0
    faces_all = []
    for k, az in enumerate((0.0, 180.0)):
        o = leaf_outline(120.0, 40.0, 0.72 * 120 * 40)
        v, f = leaf_surface(o, LeafPlacement.with_total_bend([0, 0, 20.0], az, 30.0, 120.0, 40.0))
        parts.append(v)
        faces_all.append(f + off)
        labels.append(np.full(len(f), k))
        off += len(v)
    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.concatenate(parts) / 1000.0)  # metres
    m.triangles = o3d.utility.Vector3iVector(np.concatenate(faces_all))
    path = tmp_path / "plant.obj"
    o3d.io.write_triangle_mesh(str(path), m)
    np.save(tmp_path / "labels.npy", np.concatenate(labels))
    return path, tmp_path / "labels.npy", 120.0 * 40 * 0.72


def test_external_mesh_preset(tmp_path):
    path, labels, area = _two_leaf_obj(tmp_path)
    scan = make_scan(tmp_path / "scan", preset="mesh", **TINY, roles=["plant"], scene={
        "mesh_path": str(path), "mesh_labels_path": str(labels), "mesh_scale": 1000.0})
    gt = scan.ground_truth_dir
    traits = Traits.load(gt / "traits.csv")
    # Surface measurements of each labelled leaf (area exact up to OBJ's float precision).
    assert [t.leaf_id for t in traits.leaves] == [0, 1]
    for t in traits.leaves:
        assert t.area_mm2 == pytest.approx(area, rel=1e-3)
    with np.load(gt / "plant.npz") as z:
        assert sorted(set(z["face_leaf_id"].tolist())) == [0, 1]
        assert mesh_area(z["vertices"], z["faces"]) == pytest.approx(2 * area, rel=1e-3)
    mask = cv2.imread(str(gt / "masks" / f"{scan.views[0].index:05d}.png"), 0)
    assert (mask > 0).mean() > 0.01


def test_external_mesh_errors_name_the_file(tmp_path):
    path, _, _ = _two_leaf_obj(tmp_path)
    bad = tmp_path / "labels.txt"
    bad.write_text("0\n1\n")
    with pytest.raises(DataError, match="labels.txt"):
        make_scan(tmp_path / "a", preset="mesh", **TINY, scene={
            "mesh_path": str(path), "mesh_labels_path": str(bad)})
    with pytest.raises(DataError, match="nothing.ply"):
        make_scan(tmp_path / "b", preset="mesh", **TINY,
                  scene={"mesh_path": str(tmp_path / "nothing.ply")})


@pytest.mark.slow
def test_charuco_corners_with_ids_where_the_truth_projects_them(tmp_path):
    # ChArUco corner ids index scene.yaml's corners_world_mm; noise-free detections show no
    # systematic offset (< 0.03 px: renderer and camera model agree) and an RMS scatter
    # < 0.25 px: OpenCV's ChArUco refinement scatters more than the chessboard's cornerSubPix
    # on 15-25 px squares (0.15-0.2 px measured here), so the bound is looser than there.
    scan = make_scan(tmp_path / "ch", image_size=(800, 534), images_per_revolution=6,
                     noise_sigma=0.0, roles=["calibration"], scene={"board": "charuco"})
    gt = scan.ground_truth_dir
    spec = yaml.safe_load((gt / "scene.yaml").read_text())["board"]
    corners = np.array(spec["corners_world_mm"])
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec["charuco"]["dictionary"]))
    board = cv2.aruco.CharucoBoard(tuple(spec["squares"]), spec["square_mm"],
                                   spec["charuco"]["marker_mm"], d)
    detector = cv2.aruco.CharucoDetector(board)
    cams = read_truth_cameras(gt)
    errs = []
    for view in scan.views:
        cc, ids, _, _ = detector.detectBoard(scan.read_image(view))
        if ids is None or len(ids) < 10:
            continue
        errs.append(cc.reshape(-1, 2) - cams[view.index].project(corners)[ids.ravel()])
    assert len(errs) >= 3
    e = np.concatenate(errs)
    assert np.abs(e.mean(axis=0)).max() < 0.03
    assert np.sqrt(np.mean(np.sum(e**2, axis=1))) < 0.25

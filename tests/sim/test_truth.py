"""The images and the ground truth of a virtual scan agree with each other."""

from __future__ import annotations

import functools
import json

import cv2
import numpy as np
import pytest
import yaml
from plantscan_sim import read_truth_cameras
from plantscan_sim.geometry import TriMesh, frustum
from plantscan_sim.render import silhouette_mask

from plantscan_core.data import Calibration, Camera


def _truth_foreground_mesh(gt) -> TriMesh:
    with np.load(gt / "plant.npz") as z:
        plant = TriMesh(z["vertices"], z["faces"], z["face_leaf_id"])
    pot = yaml.safe_load((gt / "pot.yaml").read_text())["pot"]
    pot_mesh = frustum(pot["z_bottom_mm"], pot["z_top_mm"], pot["r_bottom_mm"], pot["r_top_mm"],
                       n=720)
    return TriMesh.concat([plant, pot_mesh])


def test_masks_are_the_projection_of_the_truth_mesh(small_scan):
    # Projecting plant.npz + the pot of pot.yaml with each view's exact camera
    # (silhouette_mask, the rasteriser the organ model's training carves with) reproduces the
    # truth mask: IoU >= 0.99 away from edges (pixels within 1 px of the mask boundary
    # are partial-coverage pixels where rasteriser and 50 %-coverage rule may differ).
    gt = small_scan.ground_truth_dir
    cams = read_truth_cameras(gt)
    mesh = _truth_foreground_mesh(gt)
    plant_views = small_scan.views_by_role("plant")
    assert plant_views
    kernel = np.ones((3, 3), np.uint8)
    for view in plant_views:
        mask = cv2.imread(str(gt / "masks" / f"{view.index:05d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        proj = silhouette_mask(mesh.vertices, mesh.faces, cams[view.index])
        m8 = mask.astype(np.uint8)
        edge = cv2.dilate(m8, kernel).astype(bool) & ~cv2.erode(m8, kernel).astype(bool)
        keep = ~edge
        inter = np.sum(mask & proj & keep)
        union = np.sum((mask | proj) & keep)
        assert inter / union >= 0.99, f"view {view.index}: IoU {inter / union:.4f}"
        # The whole plant and pot are in the image (needed by the visual hull).
        assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def test_cameras_jsonl_matches_the_views_and_calibration(small_scan):
    gt = small_scan.ground_truth_dir
    lines = [json.loads(x) for x in (gt / "cameras.jsonl").read_text().splitlines()]
    assert [d["index"] for d in lines] == [v.index for v in small_scan.views]
    assert [d["file"] for d in lines] == [v.file for v in small_scan.views]
    cal = Calibration.load(gt / "calibration.yaml")
    pts = np.random.default_rng(0).uniform([-200, -200, 0], [200, 200, 400], (50, 3))
    for view, d in zip(small_scan.views, lines, strict=True):
        exact = Camera.from_dict(d["camera"])
        # No backlash in this recipe: the nominal calibration is the exact camera.
        assert np.abs(cal.camera_for_view(view).project(pts) - exact.project(pts)).max() < 1e-6


def test_truth_files_follow_the_format(small_scan):
    from plantscan_core.data import Traits

    gt = small_scan.ground_truth_dir
    with np.load(gt / "plant.npz") as z:
        assert z["faces"].shape[0] == z["face_leaf_id"].shape[0]
        assert set(np.unique(z["face_leaf_id"])) == set(range(-1, 12))
    traits = Traits.load(gt / "traits.csv", gt / "plant_traits.json")
    assert len(traits.leaves) == 12 and traits.plant["leaf_count"] == 12
    assert traits.plant["total_leaf_area_mm2"] == pytest.approx(
        sum(t.area_mm2 for t in traits.leaves))
    masks = sorted(p.name for p in (gt / "masks").iterdir())
    assert masks == [f"{v.index:05d}.png" for v in small_scan.views_by_role("plant")]
    scene = yaml.safe_load((gt / "scene.yaml").read_text())
    assert scene["seed"] == 0 and scene["preset"] == "plastic-dicot"
    for name in ("plant.ply", "pot.yaml"):
        assert (gt / name).stat().st_size > 0


def test_truth_stages_give_the_truth(small_scan):
    from plantscan_sim.plugin import TruthCalibrator, TruthMaskSegmenter

    from plantscan_core.stages import StageContext

    ctx = StageContext(scan=small_scan)
    cal = TruthCalibrator(None, ctx).calibrate(small_scan)
    assert set(cal.camera_names) == {"cam0", "cam1"}
    seg = TruthMaskSegmenter(None, ctx)
    view = small_scan.views_by_role("plant")[3]
    mask = seg.segment(small_scan.read_image(view), None, view)
    assert mask.dtype == bool and mask.shape == (240, 360) and 0.02 < mask.mean() < 0.6


def test_plant_sway_is_rendered_and_recorded(tmp_path):
    # With sway, each stop's plant is the rest mesh turned by cameras.jsonl's plant_sway;
    # the masks match that displaced mesh (IoU >= 0.99 edges aside) and not the rest pose.
    from plantscan_sim import make_scan

    scan = make_scan(tmp_path / "sway", image_size=(360, 240), images_per_revolution=3,
                     roles=["plant"], scene={"sway_deg": 3.0})
    gt = scan.ground_truth_dir
    lines = {json.loads(x)["index"]: json.loads(x)
             for x in (gt / "cameras.jsonl").read_text().splitlines()}
    with np.load(gt / "plant.npz") as z:
        plant = TriMesh(z["vertices"], z["faces"], z["face_leaf_id"])
    pot = _truth_foreground_mesh(gt)
    pot = TriMesh(pot.vertices, pot.faces[len(plant.faces):], pot.face_attr[len(plant.faces):])
    kernel = np.ones((3, 3), np.uint8)
    worse = 0
    for view in scan.views:
        d = lines[view.index]
        r, pivot = np.array(d["plant_sway"]["R"]), np.array(d["plant_sway"]["pivot_mm"])
        swayed = TriMesh(pivot + (plant.vertices - pivot) @ r.T, plant.faces, plant.face_attr)
        cam = Camera.from_dict(d["camera"])
        mask = cv2.imread(str(gt / "masks" / f"{view.index:05d}.png"), 0) > 127
        m8 = mask.astype(np.uint8)
        keep = ~(cv2.dilate(m8, kernel).astype(bool) & ~cv2.erode(m8, kernel).astype(bool))

        def iou(mesh, mask=mask, keep=keep, cam=cam):
            both = TriMesh.concat([mesh, pot])
            proj = silhouette_mask(both.vertices, both.faces, cam)
            return np.sum(mask & proj & keep) / np.sum((mask | proj) & keep)

        assert iou(swayed) >= 0.99
        worse += iou(plant) < iou(swayed) - 0.005
    assert worse >= len(scan.views) // 2


def test_background_plate_fits_every_angle(small_scan):
    # The plate and carrier are round and plain, so the one background plate per camera
    # and tilt equals every plant view outside the foreground, except where the plant or
    # pot casts a shadow: at least 85 % of the non-foreground pixels within 4 sigma of
    # the sensor noise (2 DN per image, so sigma of a difference ~2.8 DN).
    gt = small_scan.ground_truth_dir
    bg = {(v.camera, v.tilt_index): small_scan.read_image(v)
          for v in small_scan.views_by_role("background")}
    for view in small_scan.views_by_role("plant"):
        img = small_scan.read_image(view).astype(np.int16)
        mask = cv2.imread(str(gt / "masks" / f"{view.index:05d}.png"), 0) > 127
        ring = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        diff = np.abs(img - bg[(view.camera, view.tilt_index)].astype(np.int16)).max(axis=2)
        same = diff[~ring] <= 4 * 2.0 * np.sqrt(2)
        assert same.mean() >= 0.85, f"view {view.index}: {same.mean():.3f}"
        # and the shadows are real: some background pixels are clearly darker
        assert np.mean(diff[~ring] > 20) > 0.01


@functools.lru_cache(maxsize=2)
def _sim_scene(image_size, sway_deg=0.0):
    """A set-up SimScene of the plastic-dicot recipe (world, rig, renderer), no scan folder."""
    from plantscan_sim.api import scan_recipe, sim_manager
    from plantscan_sim.scene import SimScene

    from plantscan_core.recipe import PROCESSING_SECTIONS, validate_recipe
    from plantscan_core.stages import StageContext

    raw = scan_recipe("plastic-dicot", image_size=image_size, scene={"sway_deg": sway_deg})
    scan_only = {k: v for k, v in raw.items() if k not in PROCESSING_SECTIONS and k != "export"}
    recipe = validate_recipe(scan_only, sim_manager().registry)
    scene = SimScene(SimScene.Params(**raw["scan"]["scene"]["params"]), StageContext(recipe))
    scene.check(recipe)
    return scene


@pytest.mark.parametrize("role,sway", [("plant", 0.0), ("plant", 3.0), ("calibration", 0.0),
                                       ("background", 0.0)])
def test_fast_renderer_gives_the_open3d_images(role, sway):
    # The fast path (analytic backdrop, rays culled by box footprints and a shadow map)
    # must reproduce the plain Open3D path: the same hits, so only float32 rounding of the
    # backdrop's distance differs (a sub-1e-3 DN change of shading that can flip a rounding).
    # Hence mean |difference| < 0.01 DN, < 0.1 % of pixels off by more than 1 DN (a flipped
    # adaptive-AA decision moves an edge pixel by a few DN), truth masks identical but for
    # < 0.1 % of pixels (a 50 %-coverage tie), and far fewer rays cast into Open3D.
    scene = _sim_scene((360, 240), sway_deg=sway)
    r = scene.renderer
    ss = 6 if role == "calibration" else 3
    for cam_name, angle in (("cam0", 0.0), ("cam1", 130.0)):
        cam = scene.rig.camera(cam_name, 0.0, angle)
        sway_rt = scene.plant_sway(0, 1) if sway and role == "plant" else None
        out, rays = {}, {}
        for fast in (True, False):
            r.rays_cast = 0
            out[fast] = r.render(role, cam, angle, ss, 0.0, None, True, sway=sway_rt, fast=fast)
            rays[fast] = r.rays_cast
        diff = np.abs(out[True][0].astype(np.int16) - out[False][0].astype(np.int16)).max(2)
        assert diff.mean() < 0.01 and np.mean(diff > 1) < 1e-3, (cam_name, diff.mean())
        masks = [o[1] >= 0.5 for o in out.values()]
        assert np.mean(masks[0] != masks[1]) < 1e-3
        if role == "plant":
            assert 0.02 < masks[0].mean() < 0.6  # the plant is in the picture
        # The board of the shipped recipe (13x10 x 40 mm) fills a third of a calibration
        # view, where the fast path must cast as Open3D does: 0.6x measured there.
        assert rays[True] < (0.5 if role != "calibration" else 0.7) * rays[False], rays

"""The ``hull`` section of ``plantscan evaluate``: the run's mesh against the truth.

A visual hull can only be right where a silhouette constrains it: on the
*rims*, the points of the surface whose projection lies on a silhouette's
boundary in some view.  Concave parts and faces hidden from every outline are
not "visible" to any silhouette method, so the accuracy figure is taken on
rim points only:

``mean_surface_distance_voxels``
    mean distance from truth rim points (truth vertices within 1 px of the
    boundary of the truth mask of at least one view, in front of that
    camera) to the run's mesh, in voxels of the run's volume.
``hull_to_truth_mean_voxels``
    mean distance from the run's mesh vertices to the truth plant (how fat
    the hull is; inherent to the number of views, reported, not a bound).
``leaves_lost``
    truth leaves of which fewer than half the vertices are inside the mesh
    or within 1.5 voxels of it.
pot metrics
    ``pot_vertices_left``: mesh vertices within a voxel of the truth pot,
    below its rim less a voxel; ``leaf_vertices_removed``: truth leaf vertices inside the removed
    cylinders (``pot_fit.json``), ``pot_fit``: fitted vs true rim height and
    radius.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from plantscan_core.data import Calibration, Camera, Mesh, Silhouettes, mask_box
from plantscan_core.parallel import thread_map
from plantscan_core.runfolder import read_mask as _read_mask
from plantscan_hull.views import signed_distance

RIM_PX = 1.0
LOST_RADIUS_VOXELS = 1.5




def truth_views(truth_dir: Path) -> list[tuple[int, Camera, Path]]:
    """(view index, exact camera, truth mask path) of every view with a truth mask."""
    out = []
    path = truth_dir / "cameras.jsonl"
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        d = json.loads(line)
        mask = truth_dir / "masks" / f"{int(d['index']):05d}.png"
        if mask.exists():
            out.append((int(d["index"]), Camera.from_dict(d["camera"]), mask))
    return out


def rim_points(points: np.ndarray, views: list[tuple[int, Camera, Path]]) -> np.ndarray:
    """(N,) bool: points within ``RIM_PX`` of a silhouette boundary in some view.

    Views run on a small thread pool: reading the mask PNG and its distance
    transform (most of the time, ~0.2 s per 18 MP view) release the GIL.
    """
    margin = int(np.ceil(RIM_PX)) + 3

    def near_in(cam: Camera, mask_path: Path) -> np.ndarray:
        mask = _read_mask(mask_path)
        box = mask_box(mask)
        if box is None:
            return np.zeros(0, dtype=np.int64)  # no boundary in this view
        # Only the mask's box (+ a background margin) can be within RIM_PX of its boundary:
        # the chamfer distances there equal the full image's (8x less work at 18 MP).
        r0, c0 = max(box[0].start - margin, 0), max(box[1].start - margin, 0)
        r1 = min(box[0].stop + margin, mask.shape[0])
        c1 = min(box[1].stop + margin, mask.shape[1])
        sd = signed_distance(mask[r0:r1, c0:c1])
        uv = cam.project(points)
        h, w = sd.shape
        u = np.rint(np.nan_to_num(uv[:, 0], nan=-1)).astype(int) - c0
        v = np.rint(np.nan_to_num(uv[:, 1], nan=-1)).astype(int) - r0
        ok = np.flatnonzero((u >= 0) & (u < w) & (v >= 0) & (v < h))
        return ok[np.abs(sd[v[ok], u[ok]]) <= RIM_PX]

    rim = np.zeros(len(points), dtype=bool)
    for near in thread_map(near_in, [v[1] for v in views], [v[2] for v in views]):
        rim[near] = True
    return rim


def _scene(mesh: Mesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh.to_open3d()))
    return scene


def _distance(scene, pts: np.ndarray, signed_outside: bool = False) -> np.ndarray:
    import open3d as o3d

    q = o3d.core.Tensor(np.ascontiguousarray(pts, dtype=np.float32))
    d = scene.compute_distance(q).numpy().astype(float)
    if signed_outside:
        d = np.where(scene.compute_occupancy(q).numpy() > 0, 0.0, d)
    return d


def _inside_cylinder(points: np.ndarray, c: dict, grow: float) -> np.ndarray:
    z0, z1 = c["z_bottom_mm"] - grow, c["z_top_mm"] + grow
    t = (points[:, 2] - c["z_bottom_mm"]) / max(c["z_top_mm"] - c["z_bottom_mm"], 1e-9)
    r = c["r_bottom_mm"] + np.clip(t, 0, 1) * (c["r_top_mm"] - c["r_bottom_mm"]) + grow
    cx, cy = c.get("centre_xy_mm", (0.0, 0.0))
    rho = np.hypot(points[:, 0] - cx, points[:, 1] - cy)
    return (points[:, 2] >= z0) & (points[:, 2] <= z1) & (rho <= r)


def evaluate_hull(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    """The ``hull`` section, or None when the run has no mesh or the truth no plant."""
    mesh_path, vol_path = run_dir / "mesh.npz", run_dir / "volume.npz"
    plant_path = truth_dir / "plant.npz"
    if not (mesh_path.exists() and vol_path.exists() and plant_path.exists()):
        return None
    mesh = Mesh.load(mesh_path)
    with np.load(vol_path) as z:
        voxel = float(z["voxel_size"])
    with np.load(plant_path) as z:
        tv, tf, leaf_id = z["vertices"], z["faces"], z["face_leaf_id"]
    out: dict[str, Any] = {"voxel_size_mm": voxel, "mesh_faces": int(len(mesh.faces))}
    if mesh.is_empty:
        out.update({"leaves_lost": int(leaf_id.max() + 1), "mean_surface_distance_voxels": None})
        return out
    scene = _scene(mesh)
    views = truth_views(truth_dir)
    rim = rim_points(tv, views) if views else np.ones(len(tv), dtype=bool)
    d_truth = _distance(scene, tv) / voxel
    out["rim_points"] = int(rim.sum())
    out["mean_surface_distance_voxels"] = float(d_truth[rim].mean()) if rim.any() else None
    out["p90_surface_distance_voxels"] = (float(np.percentile(d_truth[rim], 90))
                                          if rim.any() else None)
    truth_scene = _scene(Mesh(tv, tf))
    out["hull_to_truth_mean_voxels"] = float((_distance(truth_scene, mesh.vertices) / voxel)
                                             .mean())
    # Leaves: coverage of each truth leaf's vertices by the mesh.
    covered = _distance(scene, tv, signed_outside=True) / voxel <= LOST_RADIUS_VOXELS
    lost, coverage = [], {}
    for leaf in sorted(int(x) for x in np.unique(leaf_id) if x >= 0):
        verts = np.unique(tf[leaf_id == leaf])
        frac = float(covered[verts].mean())
        coverage[str(leaf)] = round(frac, 4)
        if frac < 0.5:
            lost.append(leaf)
    out.update({"leaves_total": len(coverage), "leaves_lost": len(lost), "lost_leaf_ids": lost,
                "leaf_coverage_min": min(coverage.values()) if coverage else None})
    # Pot.
    pot_yaml = truth_dir / "pot.yaml"
    if pot_yaml.exists():
        pot = (yaml.safe_load(pot_yaml.read_text()) or {}).get("pot")
        if pot:
            # Below the rim (less a voxel) and within a voxel of the pot wall only the pot
            # can be: leaves hanging over the side are farther out.
            below_rim = dict(pot, z_top_mm=pot["z_top_mm"] - voxel)
            out["pot_vertices_left"] = int(_inside_cylinder(mesh.vertices, below_rim, voxel).sum())
            fit_path = run_dir / "pot_fit.json"
            if fit_path.exists():
                fit = json.loads(fit_path.read_text())
                margin = float(fit.get("pot_margin_mm", 0.0))
                leaf_verts = np.unique(tf[leaf_id >= 0])
                removed = np.zeros(len(leaf_verts), dtype=bool)
                for c in fit.get("pot", []):
                    removed |= _inside_cylinder(tv[leaf_verts], c, margin)
                out["leaf_vertices_removed"] = int(removed.sum())
                if fit.get("pot"):
                    top = max(fit["pot"], key=lambda c: c["z_top_mm"])
                    out["pot_fit"] = {
                        "z_top_error_mm": top["z_top_mm"] - pot["z_top_mm"],
                        "r_top_error_mm": top["r_top_mm"] - pot["r_top_mm"],
                        "mode": fit.get("pot_mode")}
    return out


def truth_silhouettes(scan) -> tuple[Silhouettes, Calibration]:
    """The truth masks of a virtual scan with each view's exact camera.

    The exact per-view cameras of ``cameras.jsonl`` (backlash and sway
    included) become a calibration with one camera name per view
    (``v<index>``, tilt index 0, angle 0), so any reconstructor can use them
    through the ordinary ``Calibration.camera_for_view``.
    """
    from plantscan_core.data import Silhouette, ViewRecord

    by_index = {v.index: v for v in scan.views}
    models, poses, items = {}, {}, []
    for index, cam, mask_path in truth_views(scan.ground_truth_dir):
        name = f"v{index}"
        models[name], poses[(name, 0)] = cam.model, cam.pose
        view = by_index[index]
        record = ViewRecord(index, view.role, name, 0, 0.0, view.angle_index, 0.0, None,
                            view.file, view.captured_at)
        items.append(Silhouette(record, _read_mask(mask_path)))
    return Silhouettes(items), Calibration(models, poses, {0: 0.0})

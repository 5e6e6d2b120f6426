"""Synthetic runs for the exporter tests: an analytic plant, an exact calibration, a tiny scan.

The plant is two flat elliptical leaves and a cylindrical stem, so its traits
are known in closed form; the scan's images and masks are the plant's exact
projection through the calibration, so silhouettes, images and poses agree.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

PLUGINS = Path(__file__).resolve().parents[2] / "plugins"
if str(PLUGINS) not in sys.path:  # until the editable install maps every plugin package
    sys.path.insert(0, str(PLUGINS))

from plantscan_core.data import (  # noqa: E402
    Calibration,
    CameraModel,
    LabelledMesh,
    LeafTraits,
    Mesh,
    Pose,
    Silhouette,
    Silhouettes,
    Traits,
    ViewRecord,
)
from plantscan_core.recipe import Recipe  # noqa: E402
from plantscan_core.scanfolder import ScanFolder  # noqa: E402
from plantscan_core.stages import RunResult, StageReport, StageWarning  # noqa: E402

HOSTILE_ID = '<script>alert("x")</script> & plant-7'
HOSTILE_RECIPE = "recipe <img src=x onerror=alert(1)>"

# (centre x, centre y, z, semi-axis a along x, semi-axis b along y) mm
LEAVES = {0: (45.0, 0.0, 150.0, 40.0, 15.0), 1: (-35.0, 10.0, 190.0, 30.0, 12.0)}
STEM = (4.0, 200.0)  # radius, height mm
N_RIM = 96


def ellipse_mesh(cx, cy, z, a, b, n=N_RIM) -> Mesh:
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    rim = np.column_stack([cx + a * np.cos(t), cy + b * np.sin(t), np.full(n, z)])
    vertices = np.vstack([[cx, cy, z], rim])
    faces = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    return Mesh(vertices, faces)


def cylinder_mesh(r, h, n=24) -> Mesh:
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    ring = np.column_stack([r * np.cos(t), r * np.sin(t)])
    vertices = np.vstack([np.column_stack([ring, np.zeros(n)]), np.column_stack([ring,
                                                                                   np.full(n, h)])])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
    return Mesh(vertices, np.array(faces))


def analytic_plant() -> LabelledMesh:
    parts = [(label, ellipse_mesh(*p)) for label, p in LEAVES.items()] + [(2, cylinder_mesh(*STEM))]
    vertices, faces, labels, offset = [], [], [], 0
    for label, m in parts:
        vertices.append(m.vertices)
        faces.append(m.faces + offset)
        labels.append(np.full(len(m.faces), label))
        offset += len(m.vertices)
    return LabelledMesh(Mesh(np.vstack(vertices), np.vstack(faces)), np.concatenate(labels),
                        {0: "leaf", 1: "leaf", 2: "stem"})


def ellipse_perimeter(a: float, b: float) -> float:
    h = ((a - b) / (a + b)) ** 2  # Ramanujan's second approximation (error < 1e-9 here)
    return math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))


def analytic_traits(leaf_ids: dict[int, int] | None = None) -> Traits:
    """Exact flat-leaf traits; ``leaf_ids`` renames leaves (truth ids differ from ours)."""
    leaf_ids = leaf_ids or {k: k for k in LEAVES}
    leaves = [LeafTraits(leaf_ids[k], 2 * a, 2 * b, math.pi * a * b, ellipse_perimeter(a, b))
              for k, (_, _, _, a, b) in LEAVES.items()]
    return Traits(leaves, {"height_mm": STEM[1], "leaf_count": len(LEAVES),
                           "total_leaf_area_mm2": sum(x.area_mm2 for x in leaves)})


def make_calibration() -> Calibration:
    model = CameraModel(f=420.0, cu=159.5, cv=119.5, d1=-0.04, d2=0.01, width=320, height=240)
    pose = Pose.look_at((0.0, -650.0, 260.0), (0.0, 0.0, 120.0))
    rng = np.random.default_rng(3)
    u, v = rng.uniform(0, 320, 60), rng.uniform(0, 240, 60)
    quality = {
        "rms_px": 0.21,
        "per_view": [{"camera": "cam0", "tilt_index": 0, "angle_index": i, "rms_px": 0.2 + 0.01 * i}
                     for i in range(6)],
        "residual_field": {"camera": "cam0", "u": u.tolist(), "v": v.tolist(),
                           "du": rng.normal(0, 0.2, 60).tolist(),
                           "dv": rng.normal(0, 0.2, 60).tolist()},
        "note": "<b>not bold</b>",
    }
    return Calibration({"cam0": model}, {("cam0", 0): pose}, {0: 0.0}, 1.0, None, quality)


def make_recipe() -> Recipe:
    return Recipe.model_validate({
        "name": HOSTILE_RECIPE,
        "plant": {"id": HOSTILE_ID, "species": "analytic"},
        "scan": {"cameras": [{"name": "cam0", "plugin": "sim"}], "turntable": {"plugin": "sim"},
                 "image_size": [320, 240], "images_per_revolution": 8},
    })


def _render_mask(calibration: Calibration, view: ViewRecord, labelled: LabelledMesh) -> np.ndarray:
    # the exact projection (cv2.fillPoly of the triangles would fill them by parity)
    from plantscan_sim.render import silhouette_mask

    mesh = labelled.mesh
    return silhouette_mask(mesh.vertices, mesh.faces, calibration.camera_for_view(view))


def make_scan(root: Path, calibration: Calibration, labelled: LabelledMesh,
              n_views: int = 8) -> tuple[ScanFolder, Silhouettes]:
    import cv2

    scan = ScanFolder.create(root, {"plant_id": HOSTILE_ID, "species": "analytic",
                                    "recipe_name": HOSTILE_RECIPE})
    sils = []
    for i in range(n_views):
        angle = i * 360.0 / n_views
        view = ViewRecord(i, "plant", "cam0", 0, 0.0, i, angle, None,
                          f"images/plant/cam0_t00_a{i:03d}.png")
        mask = _render_mask(calibration, view, labelled)
        image = np.full((240, 320, 3), (200, 190, 180), np.uint8)
        image[mask] = (40, 140, 50)
        scan.append_view(view, lambda p, img=image: cv2.imwrite(str(p), img))
        sils.append(Silhouette(view, mask))
    return scan, Silhouettes(sils)


def write_truth(scan: ScanFolder, labelled: LabelledMesh, truth_ids: dict[int, int]) -> None:
    """ground_truth/{traits.csv, plant_traits.json, plant.npz} with leaf ids renamed."""
    gt = scan.ground_truth_dir
    gt.mkdir(parents=True, exist_ok=True)
    analytic_traits(truth_ids).save(gt / "traits.csv", gt / "plant_traits.json")
    face_leaf_id = np.array([truth_ids.get(int(k), -1) if labelled.kinds.get(int(k)) == "leaf"
                             else -1 for k in labelled.face_labels])
    np.savez(gt / "plant.npz", vertices=labelled.mesh.vertices, faces=labelled.mesh.faces,
             face_leaf_id=face_leaf_id)


def synthetic_run_in(tmp_path: Path) -> RunResult:
    """A complete run: calibration, silhouettes, labelled mesh, traits (leaf 0 measured 5 %
    long), timings, ground truth whose leaf ids are swapped with respect to ours."""
    labelled = analytic_plant()
    calibration = make_calibration()
    scan, sils = make_scan(tmp_path / "scan", calibration, labelled)
    write_truth(scan, labelled, {0: 1, 1: 0})
    traits = analytic_traits()
    traits.leaves[0].length_mm *= 1.05
    traits.leaves[0].thick_share = 0.2
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    return RunResult(run_dir=run_dir, recipe=make_recipe(), scan=scan, calibration=calibration,
                     silhouettes=sils, mesh=labelled.mesh, labelled=labelled, traits=traits,
                     timings={"calibrate": 1.5, "segment": 2.25, "reconstruct": 4.0,
                              "mesh": 0.5, "segment_mesh": 0.75, "measure": 0.1},
                     reports={"measure": StageReport(warnings=[StageWarning(
                         "thick-leaf", "leaf 0: 20 % <thick> (phantom volume)", leaf=0)])})

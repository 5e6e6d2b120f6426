"""Exporter ``colmap``: the calibrated cameras as a COLMAP text model.

Writes ``colmap/cameras.txt``, ``colmap/images.txt`` and an empty
``colmap/points3D.txt`` into the run folder, so COLMAP (``colmap
point_triangulator``, ``patch_match_stereo`` after ``image_undistorter``),
nerfstudio, gaussian-splatting tools and others reuse our poses.  Give the scan
folder as the image path: image names are the view files relative to it
(``images/plant/cam0_t00_a000.png``).

Conventions, checked against COLMAP's ``src/colmap/sensor/models.h`` and
https://colmap.github.io/format.html:

* Our camera model is COLMAP's ``RADIAL`` model, parameters ``f, cx, cy, k1, k2``
  with the same distortion ``x_d = x (1 + k1 r² + k2 r⁴)`` on normalised coords.
* COLMAP puts the centre of the top-left pixel at (0.5, 0.5); we put it at
  (0, 0), so ``cx = cu + 0.5`` and ``cy = cv + 0.5``.
* Poses are world -> camera like ours (``x_cam = R X + t``), rotation as a unit
  quaternion ``QW QX QY QZ`` (Hamilton, scalar first), translation in mm (COLMAP
  has no unit; the turntable frame's millimetres carry over).
* One image per ``plant`` view, with the pose of that view (turntable angle
  applied); ``IMAGE_ID`` = view index + 1 (COLMAP ids start at 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord
from plantscan_core.scanfolder import atomic_write_text
from plantscan_core.stages import Exporter, RunResult, StageParams


def colmap_camera_params(model: CameraModel) -> tuple[str, list[float]]:
    """COLMAP model name and parameters of one of our camera models.

    ``RADIAL`` ``[f, cx, cy, k1, k2]`` for square pixels, else ``OPENCV``
    ``[fx, fy, cx, cy, k1, k2, 0, 0]``.
    """
    if model.aspect == 1.0:
        return "RADIAL", [model.f, model.cu + 0.5, model.cv + 0.5, model.d1, model.d2]
    return "OPENCV", [model.f, model.fy, model.cu + 0.5, model.cv + 0.5, model.d1, model.d2,
                      0.0, 0.0]


def colmap_qvec(pose: Pose) -> np.ndarray:
    """(4,) unit quaternion ``(qw, qx, qy, qz)`` of ``pose.R`` with ``qw >= 0``."""
    x, y, z, w = Rotation.from_matrix(pose.R).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def colmap_text_model(calibration: Calibration, views: list[ViewRecord],
                      image_size: tuple[int, int] | None = None) -> tuple[str, str, list[str]]:
    """``cameras.txt`` and ``images.txt`` contents, plus the views skipped (no pose).

    Parameters
    ----------
    calibration : Calibration
    views : list of ViewRecord
        The images to export (the scan's plant views).
    image_size : (width, height) px, optional
        Used for a camera model whose width/height is 0 (unknown).
    """
    camera_ids = {name: i for i, name in enumerate(calibration.camera_names, start=1)}
    cam_lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(camera_ids)}",
        "# plantscan: RADIAL (f, cx, cy, k1, k2), OPENCV if fx != fy; cx = cu + 0.5",
    ]
    for name, cid in camera_ids.items():
        model = calibration.models[name]
        width = model.width or (image_size[0] if image_size else 0)
        height = model.height or (image_size[1] if image_size else 0)
        kind, values = colmap_camera_params(model)
        params = " ".join(repr(float(p)) for p in values)
        cam_lines.append(f"{cid} {kind} {width} {height} {params}")
    image_lines: list[str] = []
    skipped: list[str] = []
    for view in views:
        try:
            camera = calibration.camera_for_view(view)
        except KeyError as exc:
            skipped.append(f"view {view.index} ({view.file}): {exc.args[0]}")
            continue
        q = colmap_qvec(camera.pose)
        t = camera.pose.t
        values = " ".join(repr(float(v)) for v in (*q, *t))
        image_lines.append(f"{view.index + 1} {values} {camera_ids[view.camera]} {view.file}")
        image_lines.append("")  # no 2D points: poses only
    header = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(image_lines) // 2}, mean observations per image: 0",
        "# plantscan: world = turntable frame, translations in mm; NAME relative to the scan",
    ]
    return "\n".join(cam_lines) + "\n", "\n".join(header + image_lines) + "\n", skipped


class ColmapExporter(Exporter):
    """``colmap/{cameras,images,points3D}.txt``: our calibration for every plant view."""

    name = "colmap"

    class Params(StageParams):
        folder: str = "colmap"
        """Sub-folder of the run folder that receives the text model."""

    def export(self, run: RunResult) -> list[Path]:
        if run.calibration is None or run.scan is None:
            return []
        views = run.scan.views_by_role("plant")
        size = tuple(run.recipe.scan.image_size) if run.recipe is not None else None
        cameras, images, skipped = colmap_text_model(run.calibration, views, size)
        if skipped:
            images = "".join(f"# skipped (no pose): {s}\n" for s in skipped) + images
        out = Path(run.run_dir) / self.params.folder
        paths = [out / "cameras.txt", out / "images.txt", out / "points3D.txt"]
        atomic_write_text(paths[0], cameras)
        atomic_write_text(paths[1], images)
        atomic_write_text(paths[2], "# 3D point list with one line of data per point:\n"
                                    "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as "
                                    "(IMAGE_ID, POINT2D_IDX)\n# Number of points: 0\n")
        return paths

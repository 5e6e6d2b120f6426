"""Compile the hull's numba kernels ahead of the first run (``plantscan warm-up``).

numba compiles a kernel on its first call and keeps the machine code in its
cache (``cache=True``: ``__pycache__`` beside the source).  With an empty
cache the first carve of a plant waits ~35 s of CPU for the compiler, the
next one 0.2 s.  ``make setup`` calls ``plantscan warm-up``, which carves and
meshes a small analytic phantom (a sphere on a post, 24 views) through the
real stages with their default parameters: every kernel the default recipe
path calls is compiled with the argument types a real run passes, so the
first ``plantscan demo`` reads them from the cache.
"""

from __future__ import annotations

import numpy as np

from plantscan_core.data import (
    Calibration,
    CameraModel,
    Pose,
    Silhouette,
    Silhouettes,
    ViewRecord,
)

# The phantom: a ball of leaves on a stem above the plate, seen from two heights.
_IMAGE_SIZE = (160, 120)  # px: small, so the warm-up's own work is a fraction of a second
_BALL = ((0.0, 0.0, 60.0), 30.0)  # centre mm, radius mm
_STEM = (6.0, 60.0)  # radius, height mm
_ELEVATIONS_DEG = (10.0, 40.0)
_ANGLES = 12


def _phantom_rig() -> tuple[Calibration, list[ViewRecord]]:
    w, h = _IMAGE_SIZE
    model = CameraModel(f=150.0, cu=(w - 1) / 2, cv=(h - 1) / 2, d1=-0.02, d2=0.0,
                        width=w, height=h)
    poses = {}
    for ti, el in enumerate(_ELEVATIONS_DEG):
        e = np.radians(el)
        centre = (400.0 * np.cos(e), 0.0, 50.0 + 400.0 * np.sin(e))
        poses[("cam0", ti)] = Pose.look_at(centre, (0.0, 0.0, 50.0))
    calibration = Calibration(models={"cam0": model}, poses=poses,
                              tilts_deg={ti: el for ti, el in enumerate(_ELEVATIONS_DEG)})
    views = [ViewRecord(index=ti * _ANGLES + a, role="plant", camera="cam0", tilt_index=ti,
                        tilt_deg=el, angle_index=a, commanded_angle_deg=360.0 * a / _ANGLES,
                        measured_angle_deg=None, file=f"warm-up/t{ti}_a{a:03d}.png")
             for ti, el in enumerate(_ELEVATIONS_DEG) for a in range(_ANGLES)]
    return calibration, views


def _silhouette(calibration: Calibration, view: ViewRecord) -> Silhouette:
    """Exact mask of ball + stem by sampling the solids and splatting their projections."""
    (cx, cy, cz), r = _BALL
    rng = np.random.default_rng(view.index)
    ball = rng.normal(size=(20000, 3))
    ball = np.array([cx, cy, cz]) + r * ball / np.linalg.norm(ball, axis=1, keepdims=True) \
        * rng.uniform(0, 1, (20000, 1)) ** (1 / 3)
    t, z = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(0.0, _STEM[1], 4000)
    stem = np.column_stack([_STEM[0] * np.cos(t), _STEM[0] * np.sin(t), z])
    uv = calibration.camera_for_view(view).project(np.vstack([ball, stem]))
    w, h = _IMAGE_SIZE
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    mask = np.zeros((h, w), bool)
    mask[v[ok], u[ok]] = True
    import cv2

    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    return Silhouette(view, mask.astype(bool))


def warm_up() -> str:
    """Carve and mesh the phantom with ``octree-hull`` and ``marching-cubes`` (defaults).

    Returns a one-line description of what ran.
    """
    from plantscan_hull import kernels
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull

    if not kernels.HAVE_NUMBA:
        return "numba not installed, the numpy path needs no compiling"
    calibration, views = _phantom_rig()
    silhouettes = Silhouettes([_silhouette(calibration, v) for v in views])
    volume = OctreeHull().reconstruct(silhouettes, calibration)
    mesh = MarchingCubesMesher().mesh(volume)
    return (f"kernels compiled or read from the cache (octree-hull on a "
            f"{len(views)}-view phantom, {len(mesh.faces)} faces)")

"""The hull of a real plant from another lab's turntable (PhenoArch maize, 12 side + 1 top view).

Their calibration (read by ``plantscan_calib.phenoarch``) and their silhouettes: no
truth mesh exists, so what is checked is what a lab adopting plantscan with its own
rig sees first: the hull explains its silhouettes, and a frame whose z = 0 is not the
turntable plate is reported instead of cutting the plant off.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plantscan_calib.phenoarch import load_corners, load_original_calibration, load_silhouettes
from plantscan_calib.solver import SolveOptions, calibrate_turntable
from plantscan_hull.bbox import BoundingBoxError
from plantscan_hull.stages import MarchingCubesMesher, OctreeHull
from plantscan_sim.render import silhouette_mask

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "phenoarch_maize_plant1"


@pytest.fixture(scope="module")
def data():
    """(detections, boards, image sizes, silhouettes) of the real plant."""
    if not (DATA / "bin").exists():
        pytest.skip(f"{DATA} not available")
    return (*load_corners(DATA / "chessboard" / "points"), load_silhouettes(DATA / "bin"))


def _original(boards):
    return load_original_calibration(DATA / "calibration" / "calibration_cameras.json",
                                     boards)[0]


@pytest.fixture(scope="module", params=["original", "ours"])
def real(request, data):
    """(calibration, silhouettes): the original software's calibration, or plantscan's own
    from the same real corners (the solver settings of tests/calib/test_realdata.py)."""
    dets, boards, sizes, sils = data
    if request.param == "original":
        return _original(boards), sils
    opt = SolveOptions(fix_distortion=True, fit_aspect=True, fit_angle_scale=True,
                       min_views=1, max_rejected_fraction=0.12)
    return calibrate_turntable(dets, boards, sizes, {0: 0.0}, opt, symmetric_boards=True), sils


def _iou_per_view(mesh, sils, cal) -> np.ndarray:
    out = []
    for s in sils:
        # the exact projection: cv2.fillPoly of the triangles fills by parity (overlaps empty)
        hull = silhouette_mask(mesh.vertices, mesh.faces, cal.camera_for_view(s.view))
        mask = s.mask
        out.append(np.count_nonzero(hull & mask) / np.count_nonzero(hull | mask))
    return np.array(out)


@pytest.mark.slow  # real data: a 384^3 hull of 13 PhenoArch views
def test_real_maize_hull_explains_its_silhouettes(real):
    cal, sils = real
    assert len(sils) == 13 and {s.view.camera for s in sils} == {"side", "top"}
    # their frame has z = 0 at the side camera's height, not at a plate: no floor
    volume = OctreeHull(OctreeHull.Params(resolution=384, k=1, floor_z_mm=None)
                        ).reconstruct(sils, cal)
    mesh = MarchingCubesMesher(MarchingCubesMesher.Params(pot="none")).mesh(volume)
    iou = _iou_per_view(mesh, sils, cal)
    # Measured 0.758 mean, 0.626 worst (side view at 30 deg) with their calibration, 0.760 /
    # 0.627 with ours from the same corners (0.745 / 0.746 mean when the hull was drawn by
    # cv2.fillPoly's parity, session 14's note). What is missing is the
    # outer half of drooping leaves far from the axis: with 13 views, each view that
    # disagrees by a few mm there (the data's turntable stops are off by a fraction of a
    # degree in places, its README) carves it. With a plate floor at z = 0 the plant was
    # cut at the camera's height (0.65 mean); with the angles' sign wrong, 0.37 (192^3).
    assert iou.mean() > 0.70 and iou.min() > 0.58, iou.round(3)


def test_real_maize_with_a_plate_floor_is_reported(data):
    _, boards, _, sils = data
    with pytest.raises(BoundingBoxError, match="reconstruct.params.floor_z_mm"):
        OctreeHull(OctreeHull.Params(resolution=64, k=1)).reconstruct(sils, _original(boards))

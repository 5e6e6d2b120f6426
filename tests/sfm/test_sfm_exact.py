"""The ``sfm`` solve on exact correspondences of the virtual paper-72 rig.

Stage 1 of the calibrator's error budget (docs/sfm.md, 'where the error comes
from'): points of the plate's top, its rim and the pot carrier, projected by the
virtual scanner's exact cameras, go through everything after the features --
initialisation from two-view geometry, the turntable bundle adjustment, the
plate's metric scale -- and must come back as the rig that made them.
"""

from __future__ import annotations

import numpy as np
import pytest

from plantscan_core.data import Calibration, rotation_z

SIZE = (1296, 864)


def _truth() -> Calibration:
    from plantscan_sim.rig import Rig, SimCameraParams

    cams = {"cam0": SimCameraParams(elevation_deg=8.0), "cam1": SimCameraParams(elevation_deg=48.0)}
    return Rig(cams, SIZE, [0.0], target_height_mm=220.0, arm_azimuth_deg=-90.0).calibration()


def _exact_tracks(truth: Calibration, stops: int, rng):
    """Views and tracks of plate-top, rim and carrier points (the plate 400 mm across, its
    rim 60 mm deep, the carrier 60 mm in radius and 30 mm high), seen where they face the
    camera; the pixels are the exact cameras' projections."""
    from plantscan_sfm.features import Tracks


    n_top, n_rim, n_car = 1200, 600, 200
    r = 200.0 * np.sqrt(rng.uniform(0.09, 0.98, n_top))
    a = rng.uniform(0, 2 * np.pi, n_top + n_rim + n_car)
    top = np.stack([r * np.cos(a[:n_top]), r * np.sin(a[:n_top]), np.zeros(n_top)], 1)
    ar, ac = a[n_top:n_top + n_rim], a[n_top + n_rim:]
    rim = np.stack([200 * np.cos(ar), 200 * np.sin(ar), rng.uniform(-58, -2, n_rim)], 1)
    car = np.stack([60 * np.cos(ac), 60 * np.sin(ac), rng.uniform(2, 28, n_car)], 1)
    pts = np.concatenate([top, rim, car])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (n_top, 1)),
                              np.c_[np.cos(ar), np.sin(ar), np.zeros(n_rim)],
                              np.c_[np.cos(ac), np.sin(ac), np.zeros(n_car)]])
    views, view, point, uv = _observe(truth, stops, pts, normals)
    seen = np.bincount(point, minlength=len(pts))[point] >= 2
    order = np.argsort(point[seen], kind="stable")
    _, track = np.unique(point[seen][order], return_inverse=True)
    return views, Tracks(view[seen][order], track, uv[seen][order])


def _observe(truth: Calibration, stops: int, pts: np.ndarray, normals: np.ndarray):
    """Photos of both cameras at ``stops`` turntable stops, and every point ``pts``
    (N, 3) seen where its surface (``normals``) faces the camera and it falls inside the
    image: views, then the observations' view (M,), point (M,) and exact pixel (M, 2)."""
    from plantscan_sfm.features import SfmView

    from plantscan_core.data import ViewRecord

    views, obs = [], []
    for k in range(stops):
        for cam in ("cam0", "cam1"):
            angle = 360.0 * k / stops
            i = len(views)
            views.append(SfmView(ViewRecord(i, "plant", cam, 0, 0.0, k, angle, None,
                                            f"images/{cam}_{k}.png"), f"{cam}/{k}.png"))
            camera = truth.camera_at(cam, 0, angle)
            uv = camera.project(pts)
            turn = rotation_z(angle)
            facing = np.sum((camera.pose.centre - pts @ turn.T) * (normals @ turn.T), 1) > 0
            inside = np.isfinite(uv).all(1) & (uv[:, 0] > 0) & (uv[:, 0] < SIZE[0] - 1) \
                & (uv[:, 1] > 0) & (uv[:, 1] < SIZE[1] - 1)
            obs += [(i, t, uv[t]) for t in np.flatnonzero(facing & inside)]
    return (views, np.array([o[0] for o in obs]), np.array([o[1] for o in obs]),
            np.array([o[2] for o in obs]))


@pytest.mark.slow
def test_exact_correspondences_give_back_the_rig():
    """The solve, the turntable frame and the plate's scale add no error of their own:
    from exact pixels the rig comes back exactly, with the observations capped
    (max_observations below the total: the seeded draw of whole tracks keeps the rim
    that gives the scale; the longest-first cap it replaced kept only the plate's top,
    and the centres came out 15-17 mm off).  Principal point free and without its prior
    (which, with nothing else to pull against, would hold it 0.3-0.5 px towards the
    image centre: 0.24 mm, 0.015 deg).  Measured: 1e-11 mm, 0 deg; the bounds are the
    solver's stopping tolerances with a margin, far below the issue's targets (0.5 mm,
    0.05 deg, 0.2 %, 0.3 px)."""
    from plantscan_calib.evaluate import compare_calibrations
    from plantscan_calib.synthetic import volume_points
    from plantscan_sfm.calibrate import SfmSettings, solve_tracks

    truth = _truth()
    views, tracks = _exact_tracks(truth, 24, np.random.default_rng(0))
    cap = int(0.7 * len(tracks.view))
    settings = SfmSettings(plate_diameter_mm=400.0, markers=None, refine_dots=False,
                           fix_principal_point=False, principal_point_prior=None,
                           max_observations=cap, threads=2)
    cal = solve_tracks(views, tracks, {"cam0": SIZE, "cam1": SIZE}, settings)
    res = compare_calibrations(cal, truth, volume_points(180.0, (0.0, 400.0), 400, 1))
    q = cal.quality
    assert q["features"]["observations_capped_from"] == len(tracks.view)
    assert q["scale"]["source"] == "rim"
    assert res["camera_centre_error_mm"]["max"] < 1e-3
    assert res["rotation_error_deg"]["max"] < 1e-4
    for cam, m in truth.models.items():
        e = cal.models[cam]
        assert abs(e.f / m.f - 1.0) < 1e-6
        assert abs(e.cu - m.cu) < 1e-3 and abs(e.cv - m.cv) < 1e-3
    assert res["volume_reprojection_px_rms"] < 1e-3

"""What the ``sfm`` solve does with wrong matches and with one board photo per camera.

The virtual paper-72 rig's exact correspondences (``test_sfm_exact``), thinned to a
third of the tracks and 12 stops so that each solve stays a few seconds, with what a
real scan adds: keypoint noise, wrong matches of a repeated print, and a lens whose
principal point is 5.2 px off the image centre in u and v.
"""

from __future__ import annotations

import numpy as np
from plantscan_calib.detect import BoardSpec
from plantscan_calib.evaluate import compare_calibrations
from plantscan_calib.synthetic import volume_points
from test_sfm_exact import SIZE, _exact_tracks, _truth

from plantscan_core.data import Calibration

STOPS = 12
NOISE_PX = 0.1          # refined dots: 0.06 px median on the virtual print (docs/sfm.md)


def _scene(seed: int = 0):
    from plantscan_sfm.features import Tracks

    truth = _truth()
    rng = np.random.default_rng(seed)
    views, tracks = _exact_tracks(truth, STOPS, rng)
    # every third track, then keypoint noise
    tracks = tracks.subset(tracks.track % 3 == 0)
    uv = tracks.uv + rng.normal(0.0, NOISE_PX, tracks.uv.shape)
    return truth, views, Tracks(tracks.view, tracks.track, uv), rng


def _inject_wrong_matches(tracks, rng, share: float = 0.3, px=(1.0, 1.5), lengths=(5, 8)):
    """``share`` of the tracks seen in ``lengths`` photos get one observation moved by
    ``px`` in a random direction (a keypoint taken on a feature beside its own).
    Returns the tracks and the moved observations."""
    from plantscan_sfm.features import Tracks

    length = np.bincount(tracks.track)
    long_tracks = np.flatnonzero((length >= lengths[0]) & (length <= lengths[1]))
    chosen = rng.choice(long_tracks, int(share * len(long_tracks)), replace=False)
    starts = np.searchsorted(tracks.track, chosen)
    moved = starts + rng.integers(0, length[chosen])
    ang = rng.uniform(0, 2 * np.pi, len(moved))
    uv = tracks.uv.copy()
    uv[moved] += rng.uniform(*px, len(moved))[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    return Tracks(tracks.view, tracks.track, uv), moved


def _solve(views, tracks, **settings) -> Calibration:
    from plantscan_sfm.calibrate import SfmSettings, solve_tracks

    st = SfmSettings(plate_diameter_mm=400.0, markers=None, refine_dots=False, threads=2,
                     **settings)
    return solve_tracks(views, tracks, {"cam0": SIZE, "cam1": SIZE}, st)


def _errors(cal: Calibration, truth: Calibration) -> dict:
    res = compare_calibrations(cal, truth, volume_points(180.0, (0.0, 400.0), 400, 1))
    return {"centre_mm": res["camera_centre_error_mm"]["max"],
            "rotation_deg": res["rotation_error_deg"]["max"],
            "focal": max(abs(cal.models[c].f / m.f - 1.0) for c, m in truth.models.items()),
            "volume_px": res["volume_reprojection_px_rms"]}


def _state_at_truth(truth: Calibration, views, tracks):
    """The bundle's state at the exact rig (mm), the points triangulated from the pixels."""
    from plantscan_sfm import bundle, initialise
    from plantscan_sfm.initialise import GroupPose

    poses = {g: GroupPose(p.R, p.centre) for g, p in truth.poses.items()}
    angles = np.array([v.view.angle_deg for v in views])
    pts, _ = initialise.triangulate(tracks, views, truth.models, poses, angles)
    return bundle.new_state(views, truth.models, poses, pts, ("cam1", 0))


def test_the_track_check_finds_wrong_matches_the_residual_bound_misses():
    """A third of the tracks seen in 5-8 photos get one keypoint moved 1.0-1.5 px (taken
    on a feature beside its own).  Against the point its own track fits, such a keypoint
    sits closer (the point leans towards it): 29 % of them under the bundle's residual
    bound (``outlier_px`` 1).  Against the point the track's *other* photos give it is
    10-15 sigma of the 0.1 px keypoint noise away.  The check must find at least 90 %
    of them (measured: all) and drop at most 3 % of the good keypoints (a 3-sigma bound
    drops 1.1 % of Gaussian noise; one wrong match also costs a neighbour now and then)."""
    from plantscan_sfm import bundle

    truth, views, tracks, rng = _scene()
    tracks, moved = _inject_wrong_matches(tracks, rng)
    state = _state_at_truth(truth, views, tracks)
    opt = bundle.BundleOptions(fix_principal_point=True, fix_distortion=True)
    keep = np.ones(len(tracks.view), bool)
    bundle.refine_points(state, views, tracks, keep, opt)
    plain = np.linalg.norm(bundle.residuals(state, views, tracks), axis=1)
    assert np.mean(plain[moved] < opt.outlier_px) > 0.2     # what the plain bound misses
    kept, info = bundle.reject_inconsistent(state, views, tracks, keep, opt, k_sigma=3.0)
    good = np.ones(len(tracks.view), bool)
    good[moved] = False
    assert np.mean(~kept[moved]) >= 0.9
    assert np.mean(~kept[good]) <= 0.03
    # the noise scale it measured is the keypoints' (0.1 px), not the wrong matches'
    assert 0.07 < info["sigma"]["cam0"] < 0.13


def test_wrong_matches_cost_little_with_the_check_on():
    """The same wrong matches through the whole solve with the check on (``reject_sigma``
    3) and the lens's principal point given: the rig close to the one the clean keypoints
    give.  On this thinned scene (a third of the tracks, 12 stops) the noise alone leaves
    0.28 mm, 0.002 deg, 0.03 %, 0.25 px, and the check itself costs a little (it drops
    1 % of good keypoints: 0.34 mm, 0.29 px), so the bounds are differences to the clean
    solve: 0.2 mm and 0.15 px, a fraction of the issue's targets (0.5 mm, 0.3 px); the
    rotation and the focal length within the targets themselves."""
    truth, views, clean, rng = _scene()
    tracks, _ = _inject_wrong_matches(clean, rng)
    pp = {c: (m.cu, m.cv) for c, m in truth.models.items()}
    ref = _errors(_solve(views, clean, principal_point_px=pp), truth)
    cal = _solve(views, tracks, principal_point_px=pp, reject_sigma=3.0)
    err = _errors(cal, truth)
    assert cal.quality["inconsistent_observations"]["rejected_observations"] > 0
    assert err["centre_mm"] < ref["centre_mm"] + 0.2
    assert err["volume_px"] < ref["volume_px"] + 0.15
    assert err["rotation_deg"] < 0.05
    assert err["focal"] < 0.002


def _board_views(truth: Calibration, rng) -> dict:
    """One photo of the chessboard calibrator's 12 x 9 board of 40 mm per camera, 0.9 m in
    front of it and turned 40 deg about the vertical, its corners projected by the exact
    camera (the lens's principal point, its distortion) with the keypoint noise."""
    obj = BoardSpec("chessboard", 12, 9, 40.0).object_points()
    obj = obj - obj.mean(axis=0)
    out = {}
    for k, (cam, model) in enumerate(truth.models.items()):
        c, s = np.cos(np.radians(40.0)), np.sin(np.radians(40.0))
        r = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        pts_cam = obj @ r.T + np.array([0.0, 0.0, 900.0])
        uv = model.project_camera_points(pts_cam) + rng.normal(0.0, NOISE_PX, (len(obj), 2))
        out[cam] = [(k, obj, uv)]
    return out


def test_one_board_view_per_camera_fixes_the_principal_point():
    """The principal point held at the image centre (the default) while the lens's is
    5.2 px off: the rig comes back turned (measured 0.22 deg, 5.1 mm, 3.4 px; the issue's
    targets are 0.05 deg, 0.5 mm, 0.3 px).  One board photo per camera, turned 40 deg,
    frees it and fixes it: its 1-sigma below 1 px (measured 0.2-0.6 px; a board square-on
    to the camera: 3-4 px in v) and the lens's within 3 sigma of it (measured 0.13-0.6 px
    off, 1.2 px in v for cam0 with other corner noise), and the rig within the issue's
    targets (measured 0.25 mm, 0.019 deg, 0.02 %, 0.16 px)."""
    truth, views, tracks, rng = _scene(1)
    held = _errors(_solve(views, tracks), truth)
    assert held["rotation_deg"] > 0.05            # what the board has to fix
    cal = _solve(views, tracks, board={"kind": "chessboard", "cols": 12, "rows": 9,
                                       "square_mm": 40.0},
                 board_corners=_board_views(truth, rng))
    err = _errors(cal, truth)
    for cam, m in truth.models.items():
        sd = cal.quality["sigma"]["models"][cam]
        assert sd["cu"] < 1.0 and sd["cv"] < 1.0
        assert abs(cal.models[cam].cu - m.cu) < 3 * sd["cu"] + 0.1
        assert abs(cal.models[cam].cv - m.cv) < 3 * sd["cv"] + 0.1
        assert cal.quality["board_views"][cam]["rms_px"] < 2 * NOISE_PX
    assert err["centre_mm"] < 0.5
    assert err["rotation_deg"] < 0.05
    assert err["focal"] < 0.002
    assert err["volume_px"] < 0.3


def test_a_board_on_the_turntable_gives_the_metric_scale_too():
    """Tied to the turntable (``board_on_turntable``: one board pose for both cameras,
    seen at the photo's turntable angle), the board's known squares give the scene's
    scale as well: against the plate's diameter they must agree within 0.5 % (the plate's
    radius comes from its rim's points; measured 0.1 % here and on the virtual
    paper-72 dicot), and the principal point and the rig as with a free board."""
    truth, views, tracks, rng = _scene(1)
    obj = BoardSpec("chessboard", 12, 9, 40.0).object_points()
    obj = obj - obj.mean(axis=0)
    a = np.radians(40.0)    # standing on the plate's centre, turned 40 deg from the cameras
    e1, e2 = np.array([np.cos(a), np.sin(a), 0.0]), np.array([0.0, 0.0, -1.0])
    on_plate = obj[:, :1] * e1 + obj[:, 1:2] * e2 + np.array([0.0, 0.0, 220.0])
    corners = {}
    for cam in truth.models:
        uv = truth.camera_at(cam, 0, 0.0).project(on_plate)
        assert np.isfinite(uv).all() and (uv >= 0).all() and (uv[:, 0] < SIZE[0]).all() \
            and (uv[:, 1] < SIZE[1]).all()
        corners[cam] = [(0, obj, uv + rng.normal(0.0, NOISE_PX, uv.shape), 0.0, (cam, 0))]
    cal = _solve(views, tracks, board={"kind": "chessboard", "cols": 12, "rows": 9,
                                       "square_mm": 40.0},
                 board_corners=corners, board_on_turntable=True)
    q = cal.quality
    assert all(b["on_turntable"] for c, b in q["board_views"].items() if c in truth.models)
    assert abs(q["board_views"]["scale_vs_plate"] - 1.0) < 0.005
    err = _errors(cal, truth)
    for cam, m in truth.models.items():
        sd = q["sigma"]["models"][cam]
        assert abs(cal.models[cam].cu - m.cu) < 3 * sd["cu"] + 0.1
        assert abs(cal.models[cam].cv - m.cv) < 3 * sd["cv"] + 0.1
    assert err["centre_mm"] < 0.5
    assert err["rotation_deg"] < 0.05
    assert err["volume_px"] < 0.3


def test_weighing_by_kind_measures_each_kinds_noise_and_follows_the_better_kind():
    """A third of the tracks on printed dots (0.03 px of keypoint noise: refined dots
    measured 0.025 px robust sigma on the virtual paper-72 dicot), the rest raw SIFT
    keypoints (0.3 px: measured 0.17-0.22 px; more here so that the two kinds differ as
    much as the real ones at their worst).  ``weigh_by_kind`` must find each kind's noise
    (the robust sigma of a few thousand residuals: within 15 %; the fit absorbs a little
    of it, 2 x 3 of the residual's dimensions per track) and, with the lens's principal
    point given, bring the rig closer to the truth than weighing every keypoint alike:
    measured 0.195 -> 0.098 mm, 0.21 -> 0.057 px of volume reprojection, 0.005 ->
    0.0007 deg; the bounds (half the volume error, three quarters of the centre's) leave
    room for another noise draw."""
    from plantscan_sfm.features import Tracks

    truth = _truth()
    rng = np.random.default_rng(2)
    views, tracks = _exact_tracks(truth, STOPS, rng)
    tracks = tracks.subset(tracks.track % 3 == 0)
    on_dot = (tracks.track % 3 == 0)
    sigma = np.where(on_dot, 0.03, 0.3)
    uv = tracks.uv + rng.normal(0.0, 1.0, tracks.uv.shape) * sigma[:, None]
    tracks = Tracks(tracks.view, tracks.track, uv, dot=on_dot)
    pp = {c: (m.cu, m.cv) for c, m in truth.models.items()}
    alike = _errors(_solve(views, tracks, principal_point_px=pp, weigh_by_kind=False), truth)
    cal = _solve(views, tracks, principal_point_px=pp, weigh_by_kind=True)
    weighed = _errors(cal, truth)
    for cam in truth.models:
        got = cal.quality["noise_by_kind"]
        assert abs(got[f"{cam}/dot"]["sigma_px"] / 0.03 - 1.0) < 0.15
        assert abs(got[f"{cam}/keypoint"]["sigma_px"] / 0.3 - 1.0) < 0.15
    assert weighed["volume_px"] < 0.5 * alike["volume_px"]
    assert weighed["centre_mm"] < 0.75 * alike["centre_mm"]


def test_stops_recorded_one_degree_off_are_found():
    """The issue's perturbed case: 20 % of the turntable stops recorded 1 deg off (two of
    12 here, one +1 and one -1 deg; each shared by both cameras).  The first solve holds
    the recorded angles and would drop those photos' observations as outliers for good;
    the stop-angle search must find both turns (to two of its 0.05 deg steps: the count
    it maximises is flat near its peak; a plain count of inliers found -1.10 deg), the
    solve then put the photos back (their solved angles within 0.02 deg of the truth:
    the angle's 1-sigma here is ~0.005 deg) and give the rig of the correctly recorded
    scan (the one-board test's bounds: the issue's targets, principal point given)."""
    import dataclasses

    truth, views, tracks, _ = _scene(3)
    off = {2: 1.0, 7: -1.0}
    recorded = [dataclasses.replace(v, view=dataclasses.replace(
        v.view, commanded_angle_deg=v.view.commanded_angle_deg + off.get(v.view.angle_index,
                                                                          0.0)))
        for v in views]
    pp = {c: (m.cu, m.cv) for c, m in truth.models.items()}
    cal = _solve(recorded, tracks, principal_point_px=pp)
    found = cal.quality["stops_found_off_deg"]
    assert len(found) == 2
    for v in recorded:
        if v.view.angle_index in off:
            key = f"0/{v.view.commanded_angle_deg:g}"
            assert abs(found[key] + off[v.view.angle_index]) <= 0.1 + 1e-9
            true_angle = v.view.commanded_angle_deg - off[v.view.angle_index]
            assert abs(cal.view_angles_deg[v.view.index] - true_angle) < 0.02
    err = _errors(cal, truth)
    assert err["centre_mm"] < 0.5
    assert err["rotation_deg"] < 0.05
    assert err["focal"] < 0.002
    assert err["volume_px"] < 0.3

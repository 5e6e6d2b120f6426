"""The compiled turntable bundle adjustment against its references, and the marker prints."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plantscan_core.data import CameraModel, Pose


def test_analytic_jacobian_is_the_projections_derivative():
    from plantscan_sfm.bundle import _project, _project_jac, _rotation_and_jacobian

    intr = np.array([1800.0, 640.0, 430.0, -0.07, 0.012, 1.01])
    pose = np.concatenate([[1.9, 0.1, -0.05], [10.0, -1300.0, 400.0]])
    x, stop, scale, theta = np.array([30.0, -20.0, 150.0]), 0.3, 1.0002, 40.0
    uv, jc, jp = np.empty(2), np.empty((2, 14)), np.empty((2, 3))
    rot, jl = _rotation_and_jacobian(pose[:3])
    assert _project_jac(intr, pose, rot, jl, stop, scale, x, theta, uv, jc, jp)
    ref = np.empty(2)
    _project(intr, pose, stop, scale, x, theta, ref)
    assert np.allclose(uv, ref, atol=1e-9)
    p = np.concatenate([intr, pose, [stop, scale], x])

    def proj(q):
        out = np.empty(2)
        _project(q[:6], q[6:12], q[12], q[13], q[14:17], theta, out)
        return out

    num = np.zeros((2, 17))
    for k in range(17):
        h = 1e-6 * max(1.0, abs(p[k]))
        e = np.zeros(17)
        e[k] = h
        num[:, k] = (proj(p + e) - proj(p - e)) / (2 * h)
    # Central differences of a smooth function at h ~ 1e-6: agree to ~1e-6 px per unit,
    # against entries of up to 2000 px per unit.
    assert np.allclose(num[:, :14], jc, atol=1e-5)
    assert np.allclose(num[:, 14:], jp, atol=1e-5)


def _synthetic(rng, n_points=150, noise=0.1, lab_points=0):
    """Two cameras round a turntable seeing points in a 300 mm cylinder, 12 stops."""
    from plantscan_sfm.features import SfmView, Tracks

    from plantscan_core.data import ViewRecord

    models = {c: CameraModel(900.0, 320.0 + d, 213.0 - d, -0.05, 0.01, 640, 427)
              for c, d in (("cam0", 2.0), ("cam1", -3.0))}
    poses = {}
    for c, elev in (("cam0", 15.0), ("cam1", 45.0)):
        e = math.radians(elev)
        centre = np.array([0.0, -1200.0 * math.cos(e), 200.0 + 1200.0 * math.sin(e)])
        poses[(c, 0)] = Pose.look_at(centre, np.array([0.0, 0.0, 150.0]))
    views = []
    for k in range(12):
        for c in models:
            views.append(SfmView(ViewRecord(len(views), "plant", c, 0, 0.0, k, 30.0 * k, None,
                                            f"images/{c}_{k}.png"), f"{c}/{k}.png"))
    r, a, z = 150 * np.sqrt(rng.random(n_points)), rng.random(n_points) * 2 * np.pi, \
        rng.random(n_points) * 300
    pts = np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)
    lab = np.stack([rng.uniform(-400, 400, lab_points), np.full(lab_points, 700.0),
                    rng.uniform(0, 600, lab_points)], axis=1)
    obs_v, obs_t, obs_uv, obs_lab = [], [], [], []
    from plantscan_core.data import Camera, rotation_z

    for i, v in enumerate(views):
        pose = poses[(v.view.camera, 0)]
        cam = Camera(models[v.view.camera], Pose(pose.R @ rotation_z(v.view.angle_deg),
                                                  pose.t))
        for t, (x, fixed) in enumerate([(p, False) for p in pts] + [(q, True) for q in lab]):
            world = x if not fixed else rotation_z(-v.view.angle_deg) @ x
            uv = cam.project(world[None])[0]
            if np.all(np.isfinite(uv)) and 0 < uv[0] < 640 and 0 < uv[1] < 427:
                obs_v.append(i)
                obs_t.append(t)
                obs_uv.append(uv + rng.normal(0, noise, 2))
                obs_lab.append(fixed)
    order = np.argsort(obs_t, kind="stable")
    tracks = Tracks(np.array(obs_v)[order], np.array(obs_t)[order], np.array(obs_uv)[order],
                    {}, None, None, np.array(obs_lab)[order] if lab_points else None)
    return views, models, poses, np.concatenate([pts, lab]), tracks


def _perturbed_state(views, models, poses, points, rng):
    from plantscan_sfm import bundle
    from plantscan_sfm.initialise import GroupPose

    start = {c: CameraModel(m.f * 1.01, m.cu, m.cv, 0.0, 0.0, m.width, m.height)
             for c, m in models.items()}
    gp = {g: GroupPose(p.R, p.centre + (rng.normal(0, 3, 3) if g[0] != "cam0" else 0))
          for g, p in poses.items()}
    return bundle.new_state(views, start, gp, points + rng.normal(0, 1.0, points.shape),
                            ("cam0", 0))


def test_compiled_solve_matches_the_ceres_reference():
    """Same problem, same start: the compiled LM and pyceres land on the same minimum."""
    from plantscan_sfm import bundle

    rng = np.random.default_rng(3)
    views, models, poses, points, tracks = _synthetic(rng)
    keep = np.ones(len(tracks.view), bool)
    out = {}
    for solver in ("lm", "ceres"):
        st = _perturbed_state(views, models, poses, points, np.random.default_rng(4))
        opt = bundle.BundleOptions(angle_sigma_deg=0.5, solver=solver, threads=1,
                                   max_iterations=100)
        rep = bundle.solve_lm(st, views, tracks, keep, opt, robust=False) if solver == "lm" \
            else bundle._solve(bundle._build(st, views, tracks, keep, opt, False)[0], opt)
        out[solver] = (st, rep)
    a, b = out["lm"][0], out["ceres"][0]
    # Ceres' cost is half the sum of squares
    assert out["lm"][1]["final_cost"] == pytest.approx(2 * out["ceres"][1]["final_cost"],
                                                       rel=1e-6)
    # Both stop at the same cost in a flat valley (a small synthetic rig leaves d2
    # loose): the parameters agree to what the stopping tolerances leave.
    for c in models:
        assert np.allclose(a.intrinsics[c][:3], b.intrinsics[c][:3], rtol=1e-5, atol=1e-4)
    for g in poses:
        assert np.allclose(a.poses[g][3:], b.poses[g][3:], atol=1e-3)   # mm
        assert np.allclose(a.poses[g][:3], b.poses[g][:3], atol=1e-6)   # rad


def test_lab_fixed_points_tie_the_cameras_and_the_solve_finds_the_rig():
    """Points fixed in the lab (a printed backdrop) are seen at angle 0 in every photo."""
    from plantscan_sfm import bundle

    rng = np.random.default_rng(5)
    views, models, poses, points, tracks = _synthetic(rng, lab_points=60, noise=0.05)
    assert tracks.lab.any()
    st = _perturbed_state(views, models, poses, points, np.random.default_rng(6))
    keep, rep = bundle.adjust(st, views, tracks, bundle.BundleOptions(threads=1), rounds=1)
    assert rep.solves[-1]["termination"] == "CONVERGENCE"
    assert keep.mean() > 0.97  # noise 0.05 px: nothing is an outlier but the tail
    sig = bundle.parameter_sigma(st, views, tracks, keep, bundle.BundleOptions(threads=1))
    # The residual's sigma is the noise put in; the errors are those the sigmas predict
    # (within 3 sigma), and the sigmas are small enough to mean something (1 %, 5 mm).
    assert sig["residual_sigma_px"] == pytest.approx(0.05, rel=0.25)
    for c, m in models.items():
        sf = sig["models"][c]["f"]
        assert 0 < sf < 0.01 * m.f and abs(st.intrinsics[c][0] - m.f) < 3 * sf
    c1 = st.pose(("cam1", 0)).centre
    sc = sig["poses"][("cam1", 0)]["centre_units"]   # the gauge holds cam0's centre
    assert 0 < sc < 5.0 and np.linalg.norm(c1 - poses[("cam1", 0)].centre) < 3 * sc


def test_marker_band_prints_markers_the_detector_reads():
    """The rim's band unrolled flat and imaged head-on: every marker is found, by id."""
    import cv2
    from plantscan_sfm.markers import detect_markers
    from plantscan_sim.texture import plate_textures

    rim = plate_textures("aruco-dots", 200.0, 60.0, 30.0, 10.0, 0)[0]
    px_per_mm = 2.0
    s = np.arange(0, 2 * math.pi * 200.0 / 3, 1 / px_per_mm)   # a third of the rim
    z = np.arange(0.0, -60.0, -1 / px_per_mm)
    ss, zz = np.meshgrid(s, z)
    p = np.stack([200 * np.cos(ss / 200), 200 * np.sin(ss / 200), zz], axis=-1)
    img = (rim.albedo(p.reshape(-1, 3)).reshape(ss.shape) * 255).astype(np.uint8)
    img = cv2.copyMakeBorder(img, 20, 20, 20, 20, cv2.BORDER_CONSTANT, value=255)
    found = detect_markers([img], "DICT_4X4_250")
    ids = sorted(set(found.marker_id.tolist()))
    assert ids == list(range(len(ids))) and len(ids) == rim.count // 3


def test_dot_centroids_find_blob_centres_to_a_few_hundredths_of_a_pixel():
    from plantscan_sfm.markers import dot_centroids, snap_to_dots

    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:200, 0:300].astype(float)
    centres = np.stack([rng.uniform(20, 280, 30), rng.uniform(20, 180, 30)], axis=1)
    centres = centres[np.min(np.linalg.norm(centres[:, None] - centres[None], axis=2)
                             + 1e3 * np.eye(30), axis=1) > 12]
    img = np.full((200, 300), 50.0)
    for cx, cy in centres:
        img += 150 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 1.5 ** 2))
    img += rng.normal(0, 1.0, img.shape)
    labels, found = dot_centroids(np.clip(img, 0, 255).astype(np.uint8))
    moved, ok = snap_to_dots(centres + rng.normal(0, 0.4, centres.shape), labels, found)
    assert ok.all()
    # symmetric blobs of sigma 1.5 px, 1 grey level of noise, 8-bit rounding: < 0.05 px
    assert np.abs(moved - centres).max() < 0.05


def test_static_markers_become_lab_tracks():
    from plantscan_sfm.features import SfmView
    from plantscan_sfm.markers import MarkerCorners, split_static

    from plantscan_core.data import ViewRecord

    views = [SfmView(ViewRecord(i, "plant", c, 0, 0.0, i, 10.0 * i, None, f"{c}{i}.png"),
                     f"{c}/{i}") for i, c in enumerate(["cam0"] * 4 + ["cam1"] * 4)]
    rows = []
    for i in range(8):
        for c in range(4):
            rows.append((i, 7, c, [100.0 + c, 50.0 + 0.1 * (i % 2)]))        # fixed
            rows.append((i, 3, c, [200.0 + 15.0 * i + c, 80.0]))             # turning
    corners = MarkerCorners(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                            np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))
    turning, lab = split_static(corners, views)
    assert set(turning.marker_id.tolist()) == {3}
    # one observation per camera and corner of marker 7, all of lab-fixed points
    assert lab.n_tracks == 4 and len(lab.view) == 8 and lab.lab.all()
    assert set((lab.marker // 4).tolist()) == {7}


def test_a_backdrop_marker_hidden_in_a_few_photos_stays_fixed():
    """The plant and its shadow turn across the backdrop: a fixed marker whose corners are
    pulled 1-12 px in a few photos (partly hidden) is still fixed; those photos are
    dropped from its lab observation, which stays the median of the clean ones.  (Called
    turning, it sat 360 px from the truth on the virtual paper-72 dicot.)"""
    from plantscan_sfm.features import SfmView
    from plantscan_sfm.markers import MarkerCorners, split_static

    from plantscan_core.data import ViewRecord

    views = [SfmView(ViewRecord(i, "plant", "cam0", 0, 0.0, i, 10.0 * i, None, f"{i}.png"),
                     f"cam0/{i}") for i in range(10)]
    rows = []
    for i in range(10):
        hidden = np.array([6.0, -4.0]) * (i in (2, 7))      # two photos of ten off by 7 px
        for c in range(4):
            rows.append((i, 9, c, np.array([300.0 + 40 * c, 100.0]) + hidden))
            rows.append((i, 3, c, [200.0 + 15.0 * i + c, 80.0]))          # turning
    corners = MarkerCorners(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                            np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))
    cam1 = [SfmView(ViewRecord(10 + i, "plant", "cam1", 0, 0.0, i, 10.0 * i, None,
                               f"b{i}.png"), f"cam1/{i}") for i in range(3)]
    rows1 = [(10 + i, 9, c, [500.0 + 30 * c, 60.0]) for i in range(3) for c in range(4)]
    both = MarkerCorners(*(np.concatenate([a, np.array(b)]) for a, b in zip(
        (corners.view, corners.marker_id, corners.corner, corners.uv),
        ([r[0] for r in rows1], [r[1] for r in rows1], [r[2] for r in rows1],
         [r[3] for r in rows1]), strict=True)))
    turning, lab = split_static(both, views + cam1)
    assert set(turning.marker_id.tolist()) == {3}
    assert lab.n_tracks == 4 and set((lab.marker // 4).tolist()) == {9}
    cam0_obs = lab.uv[lab.view < 10]
    assert np.allclose(np.sort(cam0_obs[:, 0]), [300.0, 340.0, 380.0, 420.0])
    assert np.allclose(cam0_obs[:, 1], 100.0)

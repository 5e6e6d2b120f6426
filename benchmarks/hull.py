"""Visual hull benchmark: octree-hull vs dense-hull vs Open3D's VoxelGrid.carve_silhouette.

    python benchmarks/hull.py [--views 360] [--size 1500x1000] [--res 128,256,512]
    python benchmarks/hull.py --run-masks RUN --scan SCAN [--baseline REV]   # memory
    python benchmarks/hull.py --mesh FIELD.npz[,FIELD2.npz] [--baseline REV]   # mesher
    python benchmarks/hull.py --prep-band   # per-view preparation, banded idea
    python benchmarks/hull.py --kernel-bench 256   # ns per test of the last levels' kernels

The second form measures the ``octree-hull`` reconstructor on the masks of a
processing run (``RUN/masks``, ``RUN/calibration.yaml``, the plant views of
``SCAN``: e.g. the 18 MP paper-360 scan segmented at ``segment.reduce=2``):
peak RSS per phase (masks loaded, tables prepared, box, carve), CPU time and
work counts, each revision in its own process.

Silhouettes: the virtual scanner's truth plant (plastic dicot) and pot,
rasterised (cv2.fillPoly of the projected triangles) in every view of the
truth rig scaled to ``--size``, ``--views`` turntable stops split over the
rig's two cameras.  Every case runs in its own process (peak RSS is that
process's ``ru_maxrss``: the silhouette tables included) on the same cached
masks.  Writes the table to stdout and, with ``--write``, to
docs/benchmarks/hull.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "plugins"))
CACHE = Path(tempfile.gettempdir()) / "plantscan_hull_bench"


# --------------------------------------------------------------------------- scene
def _frustum(z0, z1, r0, r1, n=96):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring0 = np.stack([r0 * np.cos(a), r0 * np.sin(a), np.full(n, z0)], 1)
    ring1 = np.stack([r1 * np.cos(a), r1 * np.sin(a), np.full(n, z1)], 1)
    v = np.concatenate([ring0, ring1, [[0, 0, z0], [0, 0, z1]]])
    i = np.arange(n)
    j = (i + 1) % n
    f = np.concatenate([np.stack([i, j, n + i], 1), np.stack([j, n + j, n + i], 1),
                        np.stack([i, j, np.full(n, 2 * n)], 1),
                        np.stack([n + i, n + j, np.full(n, 2 * n + 1)], 1)])
    return v, f


def make_scene(views: int, size: tuple[int, int]) -> Path:
    """Cache ``views`` truth-mesh silhouettes at ``size``; returns the cache folder."""
    import yaml

    from plantscan_core.data import Calibration, CameraModel, ViewRecord

    out = CACHE / f"dicot_{views}_{size[0]}x{size[1]}"  # filled masks (issue #28)
    if (out / "done").exists():
        return out
    out.mkdir(parents=True, exist_ok=True)
    scan_dir = CACHE / "scan"
    if not (scan_dir / "ground_truth" / "plant.npz").exists():
        from plantscan_sim.api import make_scan

        make_scan(scan_dir, "plastic-dicot", image_size=(480, 320), images_per_revolution=2,
                  roles=("plant",))
    gt = scan_dir / "ground_truth"
    truth = Calibration.load(gt / "calibration.yaml")
    with np.load(gt / "plant.npz") as z:
        pv, pf = z["vertices"], z["faces"]
    pot = yaml.safe_load((gt / "pot.yaml").read_text())["pot"]
    kv, kf = _frustum(pot["z_bottom_mm"], pot["z_top_mm"], pot["r_bottom_mm"], pot["r_top_mm"])
    verts = np.concatenate([pv, kv])
    faces = np.concatenate([pf, kf + len(pv)])
    factor = size[0] / truth.models["cam0"].width
    models = {n: m.scaled(factor) for n, m in truth.models.items()}
    models = {n: CameraModel(m.f, m.cu, m.cv, m.d1, m.d2, size[0], size[1])
              for n, m in models.items()}
    cal = Calibration(models, truth.poses, truth.tilts_deg)
    cal.save(out / "calibration.yaml")
    cams = sorted(models)
    records = []
    per_cam = views // len(cams)
    for a in range(per_cam):
        for cam in cams:
            ang = 360.0 * a / per_cam
            records.append(ViewRecord(len(records), "plant", cam, 0, 0.0, a, ang, None,
                                      f"images/plant/{cam}_t00_a{a:03d}.png"))
    return _save_scene(out, cal, records, verts, faces, size)


def _save_scene(out: Path, cal, records, verts: np.ndarray, faces: np.ndarray,
                size: tuple[int, int]) -> Path:
    """Rasterise the mesh in every view and cache the packed masks, the views and ``done``.

    One triangle at a time: ``cv2.fillPoly`` of many polygons fills by parity, so
    overlapping triangles and shared edges cancel out (until issue #28 the dicot's masks
    were drawn so: leaves full of holes along the mesh's edges, a wireframe).
    """
    import cv2

    packed = []
    for v in records:
        uv = cal.camera_for_view(v).project(verts)
        mask = np.zeros((size[1], size[0]), np.uint8)
        for tri in np.round(uv[faces] * 16).astype(np.int32):  # 4 fractional bits
            cv2.fillConvexPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=4)
        packed.append(np.packbits(mask.astype(bool)))
    np.save(out / "masks.npy", np.stack(packed))
    (out / "views.json").write_text(json.dumps([v.to_dict() for v in records]))
    (out / "done").write_text("")
    return out


# The shared synthetic scene (issue #28): an analytic plant with thin leaves on a ring of
# pinhole cameras, simple enough for any peer (Open3D, phenomenal) to take the same cameras.
SYNTH_TARGET = (0.0, 0.0, 140.0)  # mm: the cameras look here
SYNTH_DISTANCE = 900.0  # mm from the target
SYNTH_ELEVATIONS = {72: (10.0, 40.0), 360: (-5.0, 10.0, 25.0, 40.0, 55.0)}


def synthetic_plant() -> tuple[np.ndarray, np.ndarray]:
    """Vertices (mm) and faces of the shared synthetic plant: a 4 mm stem 260 mm tall and
    ten drooping elliptic leaves 0.5 mm thick (phyllotaxis 137.5 deg), closed surfaces."""
    parts = [_frustum(0.0, 260.0, 2.0, 1.6, n=24)]
    for i in range(10):
        z0 = 50.0 + 19.0 * i
        az = np.radians(137.5 * i)
        length, width = 100.0 - 5.0 * i, 34.0 - 1.5 * i
        rise = np.radians(35.0 - 2.5 * i)
        n_l, n_w = 24, 7
        t = np.linspace(0.0, 1.0, n_l)
        half = 0.5 * width * np.sin(np.pi * np.clip(t, 0.0, 1.0)) ** 0.7 + 0.3
        s = np.linspace(-1.0, 1.0, n_w)
        along = t[:, None] * length * np.ones_like(s)[None, :]
        across = half[:, None] * s[None, :]
        # Drooping: rises at ``rise`` then bends down along a parabola; cupped across.
        up = along * np.tan(rise) - 0.004 * along ** 2 + 3.0 * (s[None, :] ** 2)
        rows = []
        for off in (0.25, -0.25):
            x = along * np.cos(az) - across * np.sin(az)
            y = along * np.sin(az) + across * np.cos(az)
            rows.append(np.stack([x, y, z0 + up + off], axis=-1).reshape(-1, 3))
        v = np.concatenate(rows)
        n = n_l * n_w
        g = np.arange(n).reshape(n_l, n_w)
        q = np.stack([g[:-1, :-1], g[1:, :-1], g[1:, 1:], g[:-1, 1:]], -1).reshape(-1, 4)
        top = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        ring = np.concatenate([g[0], g[1:, -1], g[-1, ::-1][1:], g[::-1, 0][1:-1]])
        side = np.concatenate([np.stack([ring, np.roll(ring, -1), ring + n], 1),
                               np.stack([np.roll(ring, -1), np.roll(ring, -1) + n, ring + n], 1)])
        parts.append((v, np.concatenate([top, top[:, ::-1] + n, side])))
    verts, faces, count = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + count)
        count += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def make_synthetic_scene(views: int, size: tuple[int, int]) -> Path:
    """Cache the shared synthetic scene's silhouettes: ``views`` (72: 2 elevations x 36,
    360: 5 x 72) pinhole cameras ``SYNTH_DISTANCE`` from the plant, images ``size``."""

    from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord

    out = CACHE / f"synthetic_{views}_{size[0]}x{size[1]}"
    if (out / "done").exists():
        return out
    out.mkdir(parents=True, exist_ok=True)
    elevations = SYNTH_ELEVATIONS.get(views, (10.0, 40.0))
    per_tilt = views // len(elevations)
    w, h = size
    f = 0.8 * h * SYNTH_DISTANCE / 300.0  # the plant's ~300 mm fill 80 % of the height
    model = CameraModel(f=f, cu=(w - 1) / 2, cv=(h - 1) / 2, d1=0.0, d2=0.0, width=w, height=h)
    poses = {}
    for ti, el in enumerate(elevations):
        e = np.radians(el)
        centre = np.array(SYNTH_TARGET) + SYNTH_DISTANCE * np.array(
            [np.cos(e), 0.0, np.sin(e)])
        poses[("cam0", ti)] = Pose.look_at(centre, SYNTH_TARGET)
    cal = Calibration({"cam0": model}, poses, {ti: float(el) for ti, el in enumerate(elevations)})
    cal.save(out / "calibration.yaml")
    verts, faces = synthetic_plant()
    records = []
    for ti, el in enumerate(elevations):
        for a in range(per_tilt):
            records.append(ViewRecord(len(records), "plant", "cam0", ti, float(el), a,
                                      360.0 * a / per_tilt, None,
                                      f"images/plant/cam0_t{ti:02d}_a{a:03d}.png"))
    return _save_scene(out, cal, records, verts, faces, size)


def load_scene(folder: Path):
    from plantscan_core.data import Calibration, Silhouette, Silhouettes, ViewRecord

    cal = Calibration.load(folder / "calibration.yaml")
    records = [ViewRecord.from_dict(d) for d in json.loads((folder / "views.json").read_text())]
    packed = np.load(folder / "masks.npy", mmap_mode="r")
    m = cal.models[records[0].camera]
    n = m.width * m.height
    sils = [Silhouette(r, np.unpackbits(packed[i])[:n].reshape(m.height, m.width).astype(bool))
            for i, r in enumerate(records)]
    return Silhouettes(sils), cal


# --------------------------------------------------------------------------- cases
def _carve(views, grid, k, min_seen):
    """The stage's carve: the field in blocks where this revision of the plugin has them."""
    from plantscan_hull.carve import carve_octree

    try:
        return carve_octree(views, grid, k, 32, backend="numba", min_seen=min_seen, blocks=True)
    except TypeError:  # a revision before the block field
        return carve_octree(views, grid, k, 32, backend="numba", min_seen=min_seen)


def run_case(folder: Path, case: str, res: int, k: int, every: int = 1) -> dict:
    from plantscan_hull.bbox import auto_box
    from plantscan_hull.carve import Grid, carve_dense, carve_octree
    from plantscan_hull.views import prepare_views

    sils, cal = load_scene(folder)
    sils = list(sils)[::every]
    t0, c0 = time.perf_counter(), time.process_time()
    views = prepare_views(sils, cal)
    prep, prep_cpu = time.perf_counter() - t0, time.process_time() - c0
    del sils
    min_seen = max(k + 1, len(views) // 2)
    t0 = time.perf_counter()
    lo, hi, _ = auto_box(views, k, 5.0, coarse=min(128, res), backend="auto", min_seen=min_seen,
                         floor_z=0.0)
    box = time.perf_counter() - t0
    grid = Grid.from_box(lo, hi, res)
    out = {"case": case, "res": res, "views": len(views), "prep_s": prep,
           "prep_ms_per_view": 1000 * prep / len(views),
           "prep_cpu_ms_per_view": 1000 * prep_cpu / len(views), "bbox_s": box,
           "grid": list(grid.shape)}
    if case in ("octree", "carve"):
        _ = carve_octree(views, Grid.from_box(lo, hi, 16), k, 16, backend="numba")  # JIT warm-up
        rss0 = _reset_peak_rss()  # the carve's own peak (ru_maxrss holds the masks' earlier one)
        threads0 = _thread_cpu()
        t0, c0 = time.perf_counter(), time.process_time()
        phi, st = _carve(views, grid, k, min_seen)
        threads1 = _thread_cpu()
        busy = sorted((threads1[t] - threads0.get(t, 0.0) for t in threads1), reverse=True)
        out["thread_cpu_s"] = [round(b, 2) for b in busy if b > 0.005]
        out.update(carve_s=time.perf_counter() - t0, carve_cpu_s=time.process_time() - c0,
                   voxel_view_tests=st.voxel_view_tests,
                   cell_view_tests=st.cell_view_tests, inside=_inside(phi),
                   fine_voxels=st.fine_voxels, field_digest=_digest(phi),
                   load=os.getloadavg()[0],
                   seconds_per_level={str(a): round(b, 2)
                                      for a, b in st.seconds_per_level.items()})
        out["peak_rss_carve_mb"] = _status_mb("VmHWM")
        out["carve_added_mb"] = out["peak_rss_carve_mb"] - rss0
        out["field_mb"] = (phi.nbytes if hasattr(phi, "nbytes") else 0) / 2**20
        try:  # the pre-flight model of what the carve adds (the tables are already held)
            from plantscan_hull.stages import hull_peak_bytes
            out["model_added_mb"] = hull_peak_bytes(tuple(grid.shape), 0, True) / 2**20
        except ImportError:  # a revision before the model
            pass
    if case == "octree":
        _warm_mesh_kernels()
        t0, c0 = time.perf_counter(), time.process_time()
        from plantscan_hull.stages import MarchingCubesMesher

        from plantscan_core.data import Volume

        mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="auto"))
        rss0 = _reset_peak_rss()
        mesh = mesher.mesh(Volume(phi, grid.origin, grid.voxel_size))
        out["mesh_added_mb"] = _status_mb("VmHWM") - rss0
        out.update(mesh_s=time.perf_counter() - t0, mesh_cpu_s=time.process_time() - c0,
                   faces=len(mesh.faces),
                   watertight=mesher.report.figures["topology"]["watertight"])
    elif case in ("dense", "dense-numpy"):
        backend = "numba" if case == "dense" else "numpy"
        if backend == "numba":
            _ = carve_dense(views, Grid.from_box(lo, hi, 8), k, backend="numba")
        rss0 = _reset_peak_rss()
        t0, c0 = time.perf_counter(), time.process_time()
        phi, st = carve_dense(views, grid, k, backend=backend, min_seen=min_seen)
        out["carve_added_mb"] = _status_mb("VmHWM") - rss0
        out.update(carve_s=time.perf_counter() - t0, carve_cpu_s=time.process_time() - c0,
                   voxel_view_tests=st.voxel_view_tests,
                   cell_view_tests=0, inside=int((phi > 0).sum()))
    elif case == "open3d":
        out.update(open3d_carve(views, grid))
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def _thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of each thread of this process (Linux)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _slabs(field):
    """The field's float32 bytes in C order, 32 x-planes at a time (dense or in blocks)."""
    if isinstance(field, np.ndarray):
        yield np.ascontiguousarray(field).tobytes()
        return
    nx, ny, nz = field.shape
    for x in range(0, nx, 32):
        yield field.read((x, 0, 0), (min(nx, x + 32), ny, nz)).tobytes()


def _inside(field) -> int:
    if isinstance(field, np.ndarray):
        return int((field > 0).sum())
    nx, ny, nz = field.shape
    return sum(int((field.read((x, 0, 0), (min(nx, x + 32), ny, nz)) > 0).sum())
               for x in range(0, nx, 32))


def _digest(field) -> str:
    """Short hash of a field's bytes: equal digests = the same field to the bit (a field
    in blocks hashes as its dense grid)."""
    import hashlib

    h = hashlib.sha1()
    for part in _slabs(field):
        h.update(part)
    return h.hexdigest()[:12]


def open3d_carve(views, grid) -> dict:
    """Open3D VoxelGrid.carve_silhouette (pinhole only: the lens distortion is ignored)."""
    import open3d as o3d

    s = grid.voxel_size
    nx, ny, nz = grid.shape
    vg = o3d.geometry.VoxelGrid.create_dense(grid.lo, np.array([1.0, 1.0, 1.0]), s,
                                             nx * s, ny * s, nz * s)
    t0, c0 = time.perf_counter(), time.process_time()
    for v in views:
        cam = v.camera
        mask = np.zeros((v.height, v.width), np.float32)
        h, w = v.sd.shape
        mask[v.v0:v.v0 + h, v.u0:v.u0 + w] = (v.sd > 0)
        params = o3d.camera.PinholeCameraParameters()
        m = cam.model
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(v.width, v.height, m.f, m.f,
                                                             m.cu, m.cv)
        ext = np.eye(4)
        ext[:3, :3], ext[:3, 3] = cam.pose.R, cam.pose.t
        params.extrinsic = ext
        vg.carve_silhouette(o3d.geometry.Image(mask), params, keep_voxels_outside_image=True)
    return {"carve_s": time.perf_counter() - t0, "carve_cpu_s": time.process_time() - c0,
            "voxel_view_tests": nx * ny * nz * len(views),
            "cell_view_tests": 0, "inside": len(vg.get_voxels())}


def kernel_bench(folder: Path, res: int, k: int, rounds: int = 3) -> dict:
    """ns per test of the last levels' kernels, single-threaded, on the carve's own inputs.

    Carves at ``res`` with ``voxel_group`` / ``classify_group`` wrapped to keep the
    inputs and outputs of the fine voxels and of the last cell level (2-voxel cells),
    then runs ``kernels._voxel_range`` and ``_classify_range`` chunk by chunk
    (``GROUP_CHUNK`` parents) in this thread, ``rounds`` times, and checks their
    outputs against the carve's (to the bit; the lists of split cells).
    """
    from plantscan_hull import kernels
    from plantscan_hull.bbox import auto_box
    from plantscan_hull.carve import Grid, carve_octree
    from plantscan_hull.views import prepare_views

    sils, cal = load_scene(folder)
    views = prepare_views(list(sils), cal)
    min_seen = max(k + 1, len(views) // 2)
    lo, hi, _ = auto_box(views, k, 5.0, coarse=min(128, res), backend="auto",
                         min_seen=min_seen, floor_z=0.0)
    grid = Grid.from_box(lo, hi, res)
    voxels, cells, packed = [], [], []
    voxel_group, classify_group = kernels.voxel_group, kernels.classify_group

    def keep_voxels(pk, tree, centres, valid, consts, stats=None):
        out = voxel_group(pk, tree, centres, valid, consts, stats)
        packed[:] = [pk]
        voxels.append((tree, np.ascontiguousarray(centres), valid, consts, out))
        return out

    def keep_cells(pk, tree, centres, valid, consts, stats=None):
        decision, child = classify_group(pk, tree, centres, valid, consts, stats)
        if consts.half_size == consts.voxel_size:  # the last cell level: children of 2 voxels
            cells.append((tree, np.ascontiguousarray(centres), valid, consts, decision, child))
        return decision, child

    kernels.voxel_group, kernels.classify_group = keep_voxels, keep_cells
    try:
        carve_octree(views, grid, k, 32, backend="numba", min_seen=min_seen)
    finally:
        kernels.voxel_group, kernels.classify_group = voxel_group, classify_group
    chunk, out = kernels.GROUP_CHUNK, {"res": res}
    for rnd in range(rounds):
        c0, tests, same = time.process_time(), 0, True
        for tree, centres, valid, consts, ref in voxels:
            values = np.full(len(ref), np.float32(-1.0))
            for a in range(0, len(centres), chunk):
                tests += kernels._voxel_range(a, min(len(centres), a + chunk), centres, valid,
                                              tree, consts, packed[0], values)
            same &= bool(np.array_equal(values.view(np.int32), ref.view(np.int32)))
        dt = time.process_time() - c0
        out[f"voxel_ns_round{rnd + 1}"] = round(1e9 * dt / tests, 2)
        c0, n_cell, same_cells = time.process_time(), 0, True
        for tree, centres, valid, consts, ref, child in cells:
            counts = kernels.cell_counts(8 * len(centres),
                                         kernels._offsets(np.repeat(np.diff(tree.start), 8)))
            for b in range(0, len(centres), chunk):
                n_cell += kernels._classify_range(b, min(len(centres), b + chunk), centres,
                                                  valid, tree, consts, packed[0], counts)
            split = kernels._split_tree(counts)
            same_cells &= bool(np.array_equal(counts.decision, ref)
                               and np.array_equal(split.views, child.views))
        dt = time.process_time() - c0
        out[f"cell_ns_round{rnd + 1}"] = round(1e9 * dt / n_cell, 2)
    out.update(voxel_view_tests=tests, cell_view_tests_last_level=n_cell,
               voxels_identical=same, cells_identical=same_cells)
    return out


def prep_full_size(n: int = 24) -> dict:
    """Per-view preparation (signed distance) at 3000 x 2000 px on ``n`` views."""
    from plantscan_hull.views import prepare_views

    folder = make_scene(n, (3000, 2000))
    sils, cal = load_scene(folder)
    prepare_views(list(sils)[:2], cal)  # thread pool and caches warm
    t0, c0 = time.perf_counter(), time.process_time()
    views = prepare_views(list(sils), cal)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    roi = np.mean([v.sd.size for v in views]) / (3000 * 2000)
    return {"ms_per_view": 1000 * dt / len(views), "cpu_ms_per_view": 1000 * cpu / len(views),
            "roi_fraction": float(roi),
            "table_mb_per_view": float(np.mean([v.sd.nbytes for v in views]) / 2**20)}


def _region_masks(n: int = 8) -> list[np.ndarray]:
    """The tables' regions of interest (mask box + margin) of ``n`` 3000 x 2000 views."""
    from plantscan_hull.views import _checked_region

    sils, cal = load_scene(make_scene(24, (3000, 2000)))
    out = []
    for s in list(sils)[:n]:
        _, (u0, v0, u1, v1) = _checked_region(s, cal.camera_for_view(s.view))
        region = np.zeros((v1 - v0, u1 - u0), bool)
        ch, cw = s.crop.shape
        region[s.v0 - v0:s.v0 - v0 + ch, s.u0 - u0:s.u0 - u0 + cw] = s.crop
        out.append(region)
    return out


def _banded_table(region: np.ndarray, out: np.ndarray, band_px: float) -> np.ndarray:
    """The banded idea of issue #6 (evaluated, not adopted): the exact 5x5 chamfer of
    the inverse mask only within ~2 ``band_px`` of the plant, a conservative bound beyond.

    Blocks of 4 x 4 px with a plant pixel seed a coarse chamfer transform ``dc``
    (block units); ``L = 0.98 (4 dc / 1.02 - 3 sqrt(2))`` px bounds every pixel's
    distance from below (chamfer within 2 % of Euclidean, 3 sqrt(2) px of offsets within
    the two blocks), ``U = 1.02 (4 dc / 0.98 + 3 sqrt(2))`` from above.  Pixels with
    ``L >= 2.083 band + 9.83`` become seeds of the fine transform (its cost follows
    the nonzero pixels): every pixel with ``L < band`` has ``U <= 1.083 band + 8.83``, so
    such seeds are more than ``band`` away from it and its value is exact when below
    ``band``.  Blocks without a plant pixel then take ``min(table, 16 - 32 L)``.
    """
    import cv2
    from plantscan_hull.views import _scratch_buffers

    s = 4
    h, w = region.shape
    hp, wp = -(-h // s) * s, -(-w // s) * s
    padded = _scratch_buffers((hp, wp))[2]  # the tables' per-thread buffers
    d_in, d_out, _, inv = _scratch_buffers((h, w))  # contiguous (h, w) views of the same
    padded[h:] = 0
    padded[:h, w:] = 0
    np.copyto(padded[:h, :w], region, casting="unsafe")
    m = padded[:h, :w]
    words = padded.view(np.uint32)  # one word = 4 pixels of a row
    coarse = (words[0::4] | words[1::4] | words[2::4] | words[3::4]) != 0
    dc = cv2.distanceTransform((~coarse).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
    lower = np.maximum(0.98 * (s * dc / 1.02 - (s - 1) * np.sqrt(2)), 0)
    bound = np.where(coarse, 32767, np.clip(np.rint(16 - 32 * lower), -32768, 32767))
    bound_up = cv2.resize(bound.astype(np.int16), (wp, hp),
                          interpolation=cv2.INTER_NEAREST)[:h, :w]
    far = cv2.compare(bound_up, int(np.rint(16 - 32 * (2.083 * band_px + 9.83))),
                      cv2.CMP_LE)
    cv2.bitwise_or(m, far, dst=inv)
    cv2.compare(inv, 0, cv2.CMP_EQ, dst=inv)  # 0 on the plant and on the far seeds
    cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_5, dst=d_in)
    cv2.distanceTransform(inv, cv2.DIST_L2, cv2.DIST_MASK_5, dst=d_out)
    cv2.subtract(d_in, m, dst=d_in, dtype=cv2.CV_32F)
    cv2.addWeighted(d_in, 32.0, d_out, -32.0, 16.0, dst=out, dtype=cv2.CV_16S)
    cv2.min(out, bound_up, dst=out)
    return out


def prep_band(band_px: float = 24.0, rounds: int = 3) -> dict:
    """Per-view table at 3000 x 2000: the tables' own code vs the banded idea, one process.

    Single-threaded, outputs already written once (no first-touch page faults, which
    ``prepare_views`` pays on its fresh buffer and ``prep_full_size`` measures), best of
    ``rounds`` alternating rounds.  Also checks the banded table: equal to the exact one
    wherever the exact one is within ``band_px`` of the outline, closer to 0 (never
    beyond it) elsewhere, and at least ``band_px - 0.5`` px out there.
    """
    import cv2
    from plantscan_hull.views import signed_distance_table

    regions = _region_masks()
    outs = [np.empty(r.shape, np.int16) for r in regions]
    checks = []
    for r, o in zip(regions, outs, strict=True):
        exact = signed_distance_table(r).astype(np.int32)
        banded = _banded_table(r, o, band_px).astype(np.int32)
        near = exact > -32 * (band_px - 0.5)
        checks.append(bool(np.array_equal(exact[near], banded[near])
                           and np.all(banded[~near] >= exact[~near])
                           and np.all(banded[~near] <= -32 * (band_px - 0.5) + 1)))

    def cpu_ms(fn) -> float:
        c = time.process_time()
        for r, o in zip(regions, outs, strict=True):
            fn(r, o)
        return 1000 * (time.process_time() - c) / len(regions)

    parts = {"dt_mask": lambda r, o: cv2.distanceTransform(r.view(np.uint8), cv2.DIST_L2, 5),
             "dt_inverse": lambda r, o: cv2.distanceTransform(r.view(np.uint8) ^ 1,
                                                              cv2.DIST_L2, 5)}
    best = {"exact": np.inf, "banded": np.inf, **{k: np.inf for k in parts}}
    for _ in range(rounds):
        best["exact"] = min(best["exact"], cpu_ms(lambda r, o: signed_distance_table(r, o)))
        best["banded"] = min(best["banded"], cpu_ms(lambda r, o: _banded_table(r, o, band_px)))
        for k, fn in parts.items():
            best[k] = min(best[k], cpu_ms(fn))
    return {"band_px": band_px, "views": len(regions), "checks_ok": all(checks),
            "roi_mp": float(np.mean([r.size for r in regions]) / 1e6),
            **{f"{k}_cpu_ms": round(v, 2) for k, v in best.items()}}


def _warm_mesh_kernels() -> None:
    """Load the mesher's compiled kernels (numba's cache: 0.3-0.7 s at a process's first
    call) so that the mesher's timings are its own work."""
    from plantscan_hull import kernels

    if kernels.HAVE_NUMBA:
        kernels.component_sizes(np.array([0, 1, 5], np.int64), (4, 4, 4))
        kernels.nonmanifold_vertices(np.array([[0, 1, 2]], np.int64), 3)


def mesh_case(field_path: Path, repeats: int = 5) -> dict:
    """``marching-cubes`` (pot auto) on a saved field: best CPU / wall of ``repeats`` runs,
    JIT warm, and a digest of the mesh (same digest = same mesh to the bit)."""
    import hashlib

    from plantscan_hull.stages import MarchingCubesMesher

    from plantscan_core.data import BlockField, Volume

    saved = Volume.load(field_path)  # a dense field or one in blocks, as the run saved it
    field = saved.blocks if saved.blocks is not None else np.ascontiguousarray(
        saved.field, dtype=np.float32)
    origin, voxel = np.asarray(saved.origin, float), float(saved.voxel_size)
    _warm_mesh_kernels()
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="auto"))
    walls, cpus = [], []
    for _ in range(repeats):
        own = field.copy() if isinstance(field, np.ndarray) else BlockField(
            field.shape, field.block, field.index.copy(), field.values.copy())
        vol = Volume(own, origin, voxel)
        t0, c0 = time.perf_counter(), time.process_time()
        mesh = mesher.mesh(vol)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    digest = hashlib.sha1(np.ascontiguousarray(mesh.vertices).tobytes()
                          + np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return {"field": str(field_path), "grid": list(field.shape), "mesh_s": min(walls),
            "mesh_cpu_s": min(cpus), "first_s": walls[0], "first_cpu_s": cpus[0],
            "faces": len(mesh.faces), "digest": digest.hexdigest()[:12],
            "pot": len(mesher.report.figures["pot"]),
            "watertight": mesher.report.figures["topology"]["watertight"]}


def mesh_main(args) -> int:
    """Each revision's mesher (``--baseline`` first, then this tree) in its own process,
    alternating for two rounds, on each field of ``--mesh``."""
    revisions = [("now", None)]
    if args.baseline:
        revisions.insert(0, (args.baseline, _extract(args.baseline)))
    rows = []
    for field in args.mesh.split(","):
        for rnd in (1, 2):
            for label, plugins in revisions:
                row = _run_child(["--mesh", field, "--case", "mesh"], plugins, f"{label} {field}")
                if row is None:
                    continue
                row.update(revision=label, round=rnd, load=round(os.getloadavg()[0], 1))
                rows.append(row)
                print(json.dumps(row), flush=True)
    print("\n| field | grid | revision | round (load) | first call s CPU / wall "
          "| best of 5 s CPU / wall | faces | pot | watertight | mesh digest |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {Path(r['field']).parent.name}/{Path(r['field']).name} | "
              f"{'x'.join(map(str, r['grid']))} | {r['revision']} | {r['round']} ({r['load']}) "
              f"| {r['first_cpu_s']:.2f} / {r['first_s']:.2f} | {r['mesh_cpu_s']:.2f} / "
              f"{r['mesh_s']:.2f} | {r['faces']} | {r['pot']} | {r['watertight']} "
              f"| {r['digest']} |")
    return 0


# --------------------------------------------------------------------------- run masks
def _rss_mb() -> float:
    return _status_mb("VmRSS")


def _status_mb(key: str) -> float:
    """A field of /proc/self/status (VmRSS, VmHWM: the peak since the last reset), MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak_rss() -> float:
    """Reset the process's peak RSS (VmHWM) to its current RSS (Linux); returns that, MB.

    The heap's freed pages are given back first (``malloc_trim``): otherwise the carve
    reuses the pages the masks held, and what it adds would read as nothing.
    """
    import ctypes

    ctypes.CDLL("libc.so.6").malloc_trim(0)
    Path("/proc/self/clear_refs").write_text("5")
    return _rss_mb()


class _RssProbe:
    """Peak resident memory per named phase, sampled every 5 ms on a thread (Linux)."""

    def __init__(self):
        import threading

        self.phase, self.peaks, self.stop = "start", {}, False
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        while not self.stop:
            self.mark()
            time.sleep(0.005)

    def mark(self, phase: str | None = None):
        r = _rss_mb()
        self.peaks[self.phase] = max(self.peaks.get(self.phase, 0.0), r)
        if phase is not None:
            self.phase = phase
            self.peaks[phase] = r


def run_masks_case(run: Path, scan: Path, res: int, reduce: int, k: int) -> dict:
    """``octree-hull`` on a run's masks, as the pipeline calls it, with RSS per phase."""
    from concurrent.futures import ThreadPoolExecutor

    import plantscan_hull.stages as hull_stages
    from plantscan_hull.stages import OctreeHull

    from plantscan_core.data import Calibration, Silhouette, Silhouettes, ViewRecord
    from plantscan_core.runfolder import read_mask
    from plantscan_core.steps import calibration_for_masks

    probe = _RssProbe()
    records = [ViewRecord.from_dict(json.loads(line))
               for line in (scan / "views.jsonl").read_text().splitlines() if line.strip()]
    records = [v for v in records if v.role == "plant"]
    with ThreadPoolExecutor(2) as pool:
        masks = list(pool.map(lambda v: read_mask(run / "masks" / f"{v.index:05d}.png"),
                              records))
    sils = Silhouettes([Silhouette(v, m) for v, m in zip(records, masks, strict=True)])
    del masks
    cal = calibration_for_masks(Calibration.load(run / "calibration.yaml"), sils, reduce)
    try:  # JIT warm-up on 12 views (numba's cache may hold another signature)
        OctreeHull(OctreeHull.Params(resolution=16, bbox=[-300, -300, 0, 300, 300, 500])
                   ).reconstruct(Silhouettes(sils.items[::30]), cal)
    except Exception:  # noqa: BLE001 - a clipped warm-up box is fine: the kernels are compiled
        pass
    probe.mark("masks loaded")
    base = _rss_mb()
    prepare, carve = hull_stages.prepare_views, hull_stages.carve_octree
    tables = {}

    def timed_prepare(*a, **kw):
        probe.mark("prepare tables")
        views = prepare(*a, **kw)
        tables["mb"] = sum(v.sd.nbytes for v in views) / 2**20
        probe.mark("bounding box")
        return views

    def timed_carve(*a, **kw):
        probe.mark("carve")
        out = carve(*a, **kw)
        probe.mark("after carve")
        return out

    hull_stages.prepare_views, hull_stages.carve_octree = timed_prepare, timed_carve
    t0, c0 = time.perf_counter(), time.process_time()
    # k given: the stage's default changed in session 4 (k 'auto'), the baseline's is 3.
    hull = OctreeHull(OctreeHull.Params(resolution=res, k=k))
    vol = hull.reconstruct(sils, cal)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    probe.mark("returned")
    probe.stop = True
    st = {**hull.report.counts, **hull.report.figures}
    h, w = sils[0].shape
    return {"case": "run masks", "res": res, "k": k, "views": len(sils), "size": f"{w}x{h}",
            "wall_s": wall, "cpu_s": cpu, "prep_s": st["prep_seconds"],
            "bbox_s": st["bbox_seconds"], "carve_s": st["carve_seconds"],
            "masks_mb": base, "tables_mb": tables.get("mb", float("nan")),
            "phase_peak_rss_mb": {k: round(v) for k, v in probe.peaks.items()},
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "voxel_view_tests": st["voxel_view_tests"], "cell_view_tests": st["cell_view_tests"],
            "inside": int((vol.field > 0).sum()), "grid": st["grid_shape"]}


def run_masks_main(args) -> int:
    """Each revision (``--baseline`` first, then this tree) in its own process."""
    rows = []
    plugin_dirs = [("now", None)]
    if args.baseline:
        plugin_dirs.insert(0, (args.baseline, _extract(args.baseline)))
    for label, plugins in plugin_dirs:
        for res in [r for r in args.res.split(",") if r]:
            row = _run_child(["--run-masks", str(args.run_masks), "--scan", str(args.scan),
                              "--reduce", str(args.reduce), "--k", str(args.k),
                              "--case", f"masks:{res}"], plugins, f"{label} {res}")
            if row is None:
                continue
            row["revision"] = label
            rows.append(row)
            print(json.dumps(row), flush=True)
    load = os.getloadavg()
    print(f"\nload average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}\n")
    print("| revision | grid | views | masks | reconstruct s wall | s CPU | prep s | carve s "
          "| voxel-view tests | cell-view tests | inside voxels | tables MB | RSS with masks "
          "MB | peak RSS MB (phase) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        phase = max(r["phase_peak_rss_mb"], key=r["phase_peak_rss_mb"].get)
        print(f"| {r['revision']} | {r['res']} ({'x'.join(map(str, r['grid']))}) | "
              f"{r['views']} | {r['size']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
              f"{r['prep_s']:.1f} | {r['carve_s']:.1f} | {r['voxel_view_tests']:.3g} | "
              f"{r['cell_view_tests']:.3g} | {r['inside']} | {r['tables_mb']:.0f} | "
              f"{r['masks_mb']:.0f} | {r['peak_rss_mb']:.0f} ({phase}) |")
    return 0


def _run_child(args: list[str], plugins: Path | None, label: str) -> dict | None:
    """This script with ``args`` in a new process (``plugins``: a revision's plugin dir);
    its last stdout line as JSON, or None (its stderr printed) when it failed."""
    cmd = [sys.executable, __file__, *args] + (["--plugins", str(plugins)] if plugins else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        print(f"{label}: failed\n{proc.stderr[-2000:]}", file=sys.stderr)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _extract(rev: str) -> Path:
    """``plugins/plantscan_hull`` of git revision ``rev`` in a temporary folder."""
    base_dir = Path(tempfile.mkdtemp(prefix="hull_baseline_"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "plugins/plantscan_hull"],
                             capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(base_dir)], input=archive.stdout, check=True)
    return base_dir / "plugins"


# --------------------------------------------------------------------------- scaling
def fit_exponent(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x: y ~ x^slope."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def scaling_main(args) -> int:
    """Carve-only cases at every ``--res`` with all views and at the largest ``--res`` with
    1/8, 1/4, 1/2 of the views, each in its own process; a table and fitted exponents."""
    res_list = [int(r) for r in args.res.split(",") if r]
    rows = []
    plan = [(r, 1) for r in res_list] + [(res_list[-1], e) for e in (8, 4, 2)]
    for res, every in plan:
        row = _run_child(["--views", str(args.views), "--size", args.size, "--k", str(args.k),
                          "--scene", args.scene, "--every", str(every),
                          "--case", f"carve:{res}"], None, f"{res} 1/{every}")
        if row is None:
            continue
        row["every"] = every
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(scaling_markdown(rows, args))
    return 0


def scaling_markdown(rows: list[dict], args) -> str:
    lines = [f"Scaling, scene {args.scene}, {args.size} px, k = {args.k} (carve only; each row "
             "its own process; load = 1-min load average at the end of the case):", "",
             "| grid | views | carve s CPU | carve s wall | CPU / wall | load | voxel-view tests "
             "| cell-view tests | carve added MB | field digest |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['res']} ({'x'.join(map(str, r['grid']))}) | {r['views']} | "
                     f"{r['carve_cpu_s']:.2f} | {r['carve_s']:.2f} | "
                     f"{r['carve_cpu_s'] / r['carve_s']:.2f} | {r['load']:.1f} | "
                     f"{r['voxel_view_tests']:.3g} | {r['cell_view_tests']:.3g} | "
                     f"{r['carve_added_mb']:.0f} | {r['field_digest']} |")
    full = [r for r in rows if r["every"] == 1]
    top = max(r["res"] for r in rows) if rows else 0
    by_views = [r for r in rows if r["res"] == top]
    lines.append("")
    for label, sel, key in (("resolution", full, "res"), ("views", by_views, "views")):
        if len({r[key] for r in sel}) < 2:
            continue
        x = [r[key] for r in sel]
        tests = [r["voxel_view_tests"] + r["cell_view_tests"] for r in sel]
        lines.append(f"Fitted exponents in {label} ({', '.join(map(str, x))}): tests ~ "
                     f"{label}^{fit_exponent(x, tests):.2f}, carve CPU ~ "
                     f"{label}^{fit_exponent(x, [r['carve_cpu_s'] for r in sel]):.2f}, "
                     f"carve added memory ~ "
                     f"{label}^{fit_exponent(x, [max(r['carve_added_mb'], 1) for r in sel]):.2f}.")
    return "\n".join(lines)


# --------------------------------------------------------------------------- driver
def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=360)
    ap.add_argument("--size", default="1500x1000")
    ap.add_argument("--res", default="128,256,512")
    ap.add_argument("--dense-res", default="128,256")
    ap.add_argument("--open3d-res", default="128")
    ap.add_argument("--k", type=int, default=3)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--plugins", help=argparse.SUPPRESS)
    ap.add_argument("--baseline", default="",
                    help="git revision whose plantscan_hull is also run (octree at every "
                         "--res, before each case of ours), e.g. 2459b3ff: before/after in "
                         "the same run")
    ap.add_argument("--carve-only", action="store_true",
                    help="octree cases without mesh and pot (bounding box, tables, carve)")
    ap.add_argument("--write", action="store_true", help="write docs/benchmarks/hull.md")
    ap.add_argument("--run-masks", type=Path,
                    help="a processing run folder (masks/, calibration.yaml): memory case")
    ap.add_argument("--scan", type=Path, help="the scan folder of --run-masks (views.jsonl)")
    ap.add_argument("--reduce", type=int, default=2, help="segment.reduce of --run-masks")
    ap.add_argument("--mesh", help="saved field(s) (.npz with field, origin, voxel_size), "
                    "comma-separated: the mesher alone, before/after")
    ap.add_argument("--kernel-bench", type=int, metavar="RES",
                    help="ns per test of the last levels' kernels, single-threaded, on the "
                         "inputs of a RES^3 carve")
    ap.add_argument("--prep-band", action="store_true",
                    help="per-view preparation: tables vs the banded idea")
    ap.add_argument("--scene", choices=("dicot", "synthetic"), default="dicot",
                    help="dicot: the virtual scanner's plastic dicot on its rig; synthetic: "
                         "the shared analytic thin-leaf plant on a ring of pinhole cameras "
                         "(the peer comparison's scene)")
    ap.add_argument("--every", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--scaling", action="store_true",
                    help="carve only, at every --res and at 1/8, 1/4, 1/2 and all of the "
                         "views (every 8th... view): CPU, wall and tests with fitted exponents")
    args = ap.parse_args()
    if args.mesh:
        if args.case:
            if args.plugins:
                sys.path.insert(0, args.plugins)
            print(json.dumps(mesh_case(Path(args.mesh))))
            return 0
        return mesh_main(args)
    if args.prep_band:
        print(json.dumps(prep_band()))
        return 0
    if args.kernel_bench:
        size = tuple(int(x) for x in args.size.split("x"))
        print(json.dumps(kernel_bench(make_scene(args.views, size), args.kernel_bench, args.k)))
        return 0
    if args.run_masks:
        if args.case:
            if args.plugins:
                sys.path.insert(0, args.plugins)
            res = int(args.case.split(":")[1])
            print(json.dumps(run_masks_case(args.run_masks, args.scan, res, args.reduce,
                                            args.k)))
            return 0
        return run_masks_main(args)
    size = tuple(int(x) for x in args.size.split("x"))
    folder = (make_synthetic_scene if args.scene == "synthetic" else make_scene)(args.views, size)
    if args.case:  # child process: one case
        if args.plugins:  # an older revision of the plugin (the "before" column)
            sys.path.insert(0, args.plugins)
        case, res = args.case.split(":")
        print(json.dumps(run_case(folder, case, int(res), args.k, args.every)))
        return 0
    if args.scaling:
        return scaling_main(args)
    rows = []
    octree = "carve" if args.carve_only else "octree"
    cases = [(octree, r) for r in args.res.split(",") if r] + \
            [("dense", r) for r in args.dense_res.split(",") if r] + \
            [("open3d", r) for r in args.open3d_res.split(",") if r]
    base_dir = None
    if args.baseline:
        base_dir = _extract(args.baseline)
        at = [i for i, c in enumerate(cases) if c[0] == octree]  # alternate: load drifts
        for i in reversed(at):
            cases.insert(i, ("baseline", cases[i][1]))
    for case, res in cases:
        cmd = [sys.executable, __file__, "--views", str(args.views), "--size", args.size,
               "--k", str(args.k), "--scene", args.scene,
               "--case", f"{octree if case == 'baseline' else case}:{res}"]
        if case == "baseline":
            cmd += ["--plugins", str(base_dir)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{case} {res}: failed\n{proc.stderr[-2000:]}", file=sys.stderr)
            rows.append({"case": case, "res": int(res), "error": proc.stderr.strip()[-200:]})
            continue
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        if case == "baseline":
            row["case"] = f"octree @ {args.baseline}"
        rows.append(row)
        print(json.dumps(row), flush=True)
    prep = prep_full_size()
    print(json.dumps({"prep_3000x2000": prep}))
    table = render_markdown(rows, prep, args, size)
    print(table)
    if args.write:
        (ROOT / "docs" / "benchmarks").mkdir(parents=True, exist_ok=True)
        (ROOT / "docs" / "benchmarks" / "hull.md").write_text(table)
    return 0


def render_markdown(rows, prep, args, size) -> str:
    import numba

    load = os.getloadavg()
    lines = [
        "# Visual hull benchmark (`benchmarks/hull.py`)",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
        f"(load average at the end of the run {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}: "
        f"shared with other jobs), numba {numba.__version__} on "
        f"{numba.get_num_threads()} threads, Python {platform.python_version()}.",
        f"Silhouettes: virtual scanner truth plant (plastic dicot) + pot, {args.views} views "
        f"({size[0]}x{size[1]} px, 2 cameras at 8 and 48 deg elevation), k = {args.k}, "
        "views must see a voxel in half the views.  Each case in its own process; peak RSS "
        "includes the silhouette tables.  CPU = process CPU time (all threads).",
        "",
        "| method | grid (effective) | carve s wall | carve s CPU | voxel-view tests | "
        "cell-view tests | inside voxels | field digest | load | peak RSS MB | "
        "mesh + pot s wall | mesh + pot s CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['res']} | failed: {r['error']} | | | | | | | | | |")
            continue
        mesh = f"{r['mesh_s']:.2f}" if "mesh_s" in r else ""
        mesh_cpu = f"{r['mesh_cpu_s']:.2f}" if "mesh_cpu_s" in r else ""
        cpu = f"{r['carve_cpu_s']:.2f}" if "carve_cpu_s" in r else ""
        lines.append(f"| {r['case']} | {r['res']} ({'x'.join(map(str, r['grid']))}) | "
                     f"{r['carve_s']:.2f} | {cpu} | {r['voxel_view_tests']:.3g} | "
                     f"{r['cell_view_tests']:.3g} | {r.get('inside', '')} | "
                     f"{r.get('field_digest', '')} | {r.get('load', float('nan')):.1f} | "
                     f"{r['peak_rss_mb']:.0f} | {mesh} | {mesh_cpu} |")
    ok = [r for r in rows if "prep_ms_per_view" in r]
    if ok:
        lines += ["", f"Per-view preparation (signed distance tables) at {size[0]}x{size[1]}: "
                  + ", ".join(f"{r['case']} {r['prep_ms_per_view']:.1f} ms/view wall, "
                              f"{r.get('prep_cpu_ms_per_view', float('nan')):.1f} CPU"
                              for r in ok)
                  + "; bounding box (frustum LP + 128^3 carve on 48 views): "
                  + ", ".join(f"{r['case']} {r['bbox_s']:.2f} s" for r in ok) + "."]
    lines += [f"Per-view preparation at 3000x2000 (24 views): {prep['ms_per_view']:.1f} ms/view "
              f"wall, {prep['cpu_ms_per_view']:.1f} ms CPU (ROI "
              f"{100 * prep['roi_fraction']:.0f} % of the image, "
              f"{prep['table_mb_per_view']:.1f} MB table per view).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())

"""Leaf segmentation + measurement: speed and accuracy, side by side with the simplest methods.

    python benchmarks/leaves.py                      # voxelised truth of the plastic dicot
    python benchmarks/leaves.py --run RUN --truth GT # a real run's mesh.npz vs a virtual scan
    python benchmarks/leaves.py --run RUN --truth GT --recipe recipes/wheat.yaml
                                                     # ... with that recipe's leaf parameters
    python benchmarks/leaves.py --hull SCAN [--resolution 512]
        # visual hull of a virtual scan from its exact masks and cameras (ground_truth/),
        # built once with the committed hull stages and cached under /tmp
    python benchmarks/leaves.py --plate SCAN [--plate-k 3 6] [--plate-thickness 0.5 2]
        # an analytic elliptical plate through the real hull chain (SCAN's cameras)

Meshes:

* ``voxelised``: the virtual scanner's truth plastic dicot (12 leaves, 0.5 mm
  thick) turned into a hull-like closed surface: marching cubes at
  ``--voxel`` mm of ``offset - distance`` to the truth mesh (slabs
  ``0.5 + 2 offset`` mm thick).  Its leaves' flat traits are the truth grown by
  ``offset`` (see ``phantoms.voxelise_mesh``); errors are reported against that.
* ``--run``: any ``mesh.npz`` (e.g. a visual hull of a virtual scan) with
  the scan's ``ground_truth/``.
* ``--plate``: a flat elliptical plate (semi-axes 60 x 30 mm, ``--plate-thickness``
  mm thick) placed like a leaf, its masks rendered exactly (a pixel is in when its
  centre is) in every plant view of SCAN (its exact cameras), carved by
  ``octree-hull`` (``--plate-k``, voxel ``--plate-voxel``) and meshed by
  ``marching-cubes``: the hull chain on a leaf of analytic truth.  Reports the
  trait errors and the **rim inset** (how far inside the true outline the hull
  surface is, from rays cast in the plate's plane towards its rim).

Methods:

* ``curvature-regions + leaf-geometry`` (this plugin);
* ``components + naive``: connected components as leaves (the simplest
  segmentation), measured naively: area = half the closed surface, length /
  width = extents along the principal axes, perimeter = convex-hull
  perimeter of the points projected on the leaf's best plane;
* ``curvature-regions + naive``: our segmentation, naive measures (isolates
  what the measurement itself brings).

Times are wall clock and CPU (``process_time``) of this process: on a shared
machine, CPU is the fair figure.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from plantscan_leaves.evaluate import match_leaves, trait_errors
from plantscan_leaves.geometry import face_adjacency_operator, topology
from plantscan_leaves.measure import LeafGeometryParams, measure_plant
from plantscan_leaves.segment import CurvatureRegionsParams, segment_leaves
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

from plantscan_core.data import LabelledMesh, LeafTraits, Mesh, Traits


def components_segmentation(mesh: Mesh) -> LabelledMesh:
    """Every connected component of the mesh is a leaf (the simplest alternative)."""
    n, lab = connected_components(face_adjacency_operator(len(mesh.faces),
                                                          topology(mesh.faces).face_pairs))
    return LabelledMesh(mesh, lab + 1, {i + 1: "leaf" for i in range(n)})


def naive_measure(labelled: LabelledMesh) -> Traits:
    leaves = []
    for lab in labelled.leaf_labels:
        sub = labelled.submesh(lab)
        if len(sub.faces) < 20:
            continue
        p = sub.vertices - sub.vertices.mean(axis=0)
        _, _, vt = np.linalg.svd(p, full_matrices=False)
        q = p @ vt.T
        hull2d = ConvexHull(q[:, :2])
        leaves.append(LeafTraits(lab, float(np.ptp(q[:, 0])), float(np.ptp(q[:, 1])),
                                 sub.area() / 2.0, float(hull2d.area)))
    return Traits(leaves)


def run_method(name, seg, meas, mesh, truth_traits, tv, tf, tid):
    t0, c0 = time.perf_counter(), time.process_time()
    labelled = seg(mesh)
    t1, c1 = time.perf_counter(), time.process_time()
    traits = meas(labelled)
    t2, c2 = time.perf_counter(), time.process_time()
    m = match_leaves(labelled, tv, tf, tid)
    err = trait_errors(truth_traits, traits, m["pairs"])["mean_relative_error"]
    return {
        "method": name, "faces": len(mesh.faces),
        "segment_wall_s": t1 - t0, "segment_cpu_s": c1 - c0,
        "measure_wall_s": t2 - t1, "measure_cpu_s": c2 - c1,
        "leaves_found": len(m["pairs"]), "leaves_truth": len(m["truth_ids"]),
        "merged": len(m["merged"]), "extra": len(m["extra"]),
        **{f"err_{k}": v for k, v in err.items()},
    }


def grown(truth: Traits, offset: float) -> Traits:
    """Flat traits of each truth leaf grown by ``offset`` mm all round."""
    return Traits([LeafTraits(t.leaf_id, t.length_mm + 2 * offset, t.width_mm + 2 * offset,
                              t.area_mm2 + t.perimeter_mm * offset + np.pi * offset**2,
                              t.perimeter_mm + 2 * np.pi * offset) for t in truth.leaves])


def exact_mask_hull(scan_dir: Path, resolution: int, thin_rims: bool = False) -> Path:
    """Octree hull + marching cubes of a virtual scan's exact masks and cameras (cached)."""
    out = Path("/tmp") / (f"plantscan_leaves_hull_{scan_dir.resolve().name}_{resolution}"
                          + ("_thin_rims" if thin_rims else ""))
    if (out / "mesh.npz").exists():
        return out
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull

    from plantscan_core.data import Calibration, Silhouette, Silhouettes
    from plantscan_core.scanfolder import ScanFolder, read_image

    scan = ScanFolder.open(scan_dir)
    gt = scan_dir / "ground_truth"
    sils = Silhouettes([Silhouette(v, read_image(gt / "masks" / f"{v.index:05d}.png",
                                                 grayscale=True) > 127)
                        for v in scan.views if v.role == "plant"])
    volume = OctreeHull(OctreeHull.Params(resolution=resolution)).reconstruct(
        sils, Calibration.load(gt / "calibration.yaml"))
    out.mkdir(parents=True, exist_ok=True)
    MarchingCubesMesher(MarchingCubesMesher.Params(thin_rims=thin_rims)).mesh(volume).save(
        out / "mesh.npz")
    return out


def plate_hull_run(scan_dir: Path, thickness: float, voxel: float, k: int,
                   a: float = 60.0, b: float = 30.0, incl_deg: float = 25.0,
                   thin_rims: bool = False) -> dict:
    """An analytic plate through masks -> octree-hull -> marching-cubes -> leaf-geometry."""
    import math

    import open3d as o3d
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull
    from plantscan_leaves.phantoms import EllipseLeaf

    from plantscan_core.data import (
        Calibration,
        Silhouette,
        Silhouettes,
        rotation_about_axis,
    )
    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(scan_dir)
    cal = Calibration.load(scan_dir / "ground_truth" / "calibration.yaml")
    # placed like a dicot leaf: 25 deg up from horizontal, rolled 10 deg, at leaf height
    rot = (rotation_about_axis((0, 0, 1), 30.0) @ rotation_about_axis((0, 1, 0), -incl_deg)
           @ rotation_about_axis((1, 0, 0), 10.0))
    centre = np.array([40.0, 10.0, 230.0])
    s = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    ring = np.stack([a * np.cos(s), b * np.sin(s), np.zeros_like(s)], axis=1)
    solid = np.concatenate([ring + [0, 0, thickness / 2], ring - [0, 0, thickness / 2]])
    solid = solid @ rot.T + centre
    sils = []
    for view in (v for v in scan.views if v.role == "plant"):
        cam = cal.camera_for_view(view)
        poly = cv2.convexHull(cam.project(solid).astype(np.float32))[:, 0].astype(float)
        mask = np.zeros((cam.model.height, cam.model.width), bool)
        u0, v0 = np.maximum(np.floor(poly.min(axis=0)).astype(int), 0)
        u1, v1 = np.ceil(poly.max(axis=0)).astype(int)
        uu, vv = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
        e0, e1 = poly, np.roll(poly, -1, axis=0)
        side = ((e1[:, 0] - e0[:, 0])[:, None, None] * (vv - e0[:, 1, None, None])
                - (e1[:, 1] - e0[:, 1])[:, None, None] * (uu - e0[:, 0, None, None]))
        # a pixel is in the mask when its centre is in the (convex) projected plate
        inside = np.all(side >= 0, axis=0) | np.all(side <= 0, axis=0)
        mask[v0:v1 + 1, u0:u1 + 1] = inside[: mask.shape[0] - v0, : mask.shape[1] - u0]
        sils.append(Silhouette(view, mask))
    lo, hi = solid.min(axis=0) - 6.0, solid.max(axis=0) + 6.0
    hull = OctreeHull(OctreeHull.Params(resolution=int(math.ceil((hi - lo).max() / voxel)),
                                        bbox=[*lo, *hi], floor_z_mm=None, k=k))
    volume = hull.reconstruct(Silhouettes(sils), cal)
    mesher = MarchingCubesMesher(MarchingCubesMesher.Params(pot="none", thin_rims=thin_rims))
    mesh = mesher.mesh(volume)
    labelled = LabelledMesh(mesh, np.ones(len(mesh.faces), np.int64), {1: "leaf"})
    measured = measure_plant(labelled)[0].leaves[0]
    truth = EllipseLeaf(a, b)
    # rim inset: rays in the plate's mid-plane from 3 mm outside towards each rim point (the
    # nearest hit over 11 heights across the plate's thickness +-0.5 mm)
    rim = (ring @ rot.T) + centre
    out = np.stack([np.cos(s) / a, np.sin(s) / b, np.zeros_like(s)], axis=1)
    out = (out / np.linalg.norm(out, axis=1)[:, None]) @ rot.T
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    hit = np.full(len(rim), np.inf)
    for dz in np.linspace(-0.5, 0.5, 11):
        origin = rim + 3.0 * out + dz * rot[:, 2]
        rays = np.concatenate([origin, -out], axis=1).astype(np.float32)
        hit = np.minimum(hit, scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    inset = hit[np.isfinite(hit)] - 3.0
    rel = {name: getattr(measured, f) / getattr(truth, f) - 1.0
           for name, f in [("length", "length_mm"), ("width", "width_mm"),
                           ("area", "area_mm2"), ("perimeter", "perimeter_mm")]}
    return {"thickness_mm": thickness, "voxel_mm": volume.voxel_size, "k": k,
            "thin_rims": thin_rims,
            "rim_inset_mm": float(np.mean(inset)), "faces": len(mesh.faces),
            **{f"err_{n}": v for n, v in rel.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, help="run folder with mesh.npz")
    ap.add_argument("--truth", type=Path, help="ground_truth/ folder of the scan")
    ap.add_argument("--preset", default="plastic-dicot")
    ap.add_argument("--voxel", type=float, default=1.0, help="voxelised truth: voxel, mm")
    ap.add_argument("--offset", type=float, default=0.6, help="voxelised truth: offset, mm")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/plantscan_leaves_bench.npz"))
    ap.add_argument("--hull", type=Path, help="virtual scan folder: mesh its exact-mask hull")
    ap.add_argument("--resolution", type=int, default=512, help="--hull: grid resolution")
    ap.add_argument("--thin-rims", action="store_true",
                    help="--hull, --plate: mesh with marching-cubes' thin_rims")
    ap.add_argument("--plate", type=Path, help="virtual scan folder: its cameras see a plate")
    ap.add_argument("--plate-k", type=int, nargs="+", default=[3], help="--plate: hull k")
    ap.add_argument("--plate-thickness", type=float, nargs="+", default=[0.5, 2.0],
                    help="--plate: plate thickness, mm")
    ap.add_argument("--plate-voxel", type=float, nargs="+", default=[1.0],
                    help="--plate: voxel size, mm")
    ap.add_argument("--recipe", type=Path,
                    help="take segment_mesh/measure params from this recipe (else defaults)")
    ap.add_argument("--segment-params", type=json.loads, default=None,
                    help='segment_mesh params as JSON, over the recipe\'s (e.g. grass defaults: '
                         '\'{"stem_sheet_ratio": 0.25, "crumb_merge_rounds": 20}\')')
    ap.add_argument("--measure-params", type=json.loads, default=None,
                    help="measure params as JSON, over the recipe's")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run our method this many times; the table shows the fastest (CPU)")
    ap.add_argument("--json", type=Path, help="write the results here too")
    args = ap.parse_args()

    if args.plate:
        print("| plate thickness mm | voxel mm | k | rim inset mm | ε length | ε width | ε area "
              "| ε perimeter |\n|---|---|---|---|---|---|---|---|")
        for t in args.plate_thickness:
            for vox in args.plate_voxel:
                for k in args.plate_k:
                    r = plate_hull_run(args.plate, t, vox, k, thin_rims=args.thin_rims)
                    print(f"| {t:g} | {r['voxel_mm']:.2f} | {k} | {r['rim_inset_mm']:+.2f} | "
                          + " | ".join(f"{100 * r[f'err_{n}']:+.2f} %"
                                       for n in ("length", "width", "area", "perimeter"))
                          + " |", flush=True)
        return
    if args.hull:
        args.run = exact_mask_hull(args.hull, args.resolution, args.thin_rims)
        args.truth = args.hull / "ground_truth"
    if args.run:
        mesh = Mesh.load(args.run / "mesh.npz")
        with np.load(args.truth / "plant.npz") as z:
            tv, tf, tid = z["vertices"], z["faces"], z["face_leaf_id"]
        truth = Traits.load(args.truth / "traits.csv")
        source = f"run {args.run}"
    else:
        from plantscan_leaves.phantoms import voxelise_mesh
        from plantscan_sim.plants import build_plant

        plant = build_plant(args.preset, 1, 0.0)
        tv, tf, tid = plant.mesh.vertices, plant.mesh.faces, plant.mesh.face_attr
        key = f"{args.preset}-{args.voxel}-{args.offset}"
        if args.cache.exists() and str(np.load(args.cache)["key"]) == key:
            with np.load(args.cache) as z:
                mesh = Mesh(z["vertices"], z["faces"])
        else:
            mesh = voxelise_mesh(tv, tf, args.voxel, args.offset)
            np.savez(args.cache, vertices=mesh.vertices, faces=mesh.faces, key=key)
        truth = grown(plant.traits(), args.offset)
        source = f"voxelised truth {args.preset}, voxel {args.voxel} mm, offset {args.offset} mm"

    seg_params, meas_params = CurvatureRegionsParams(), LeafGeometryParams()
    if args.recipe:
        import yaml

        raw = yaml.safe_load(args.recipe.read_text())
        seg_params = CurvatureRegionsParams(**(raw.get("segment_mesh", {}).get("params") or {}))
        meas_params = LeafGeometryParams(**(raw.get("measure", {}).get("params") or {}))
    if args.segment_params:
        seg_params = CurvatureRegionsParams(**{**seg_params.model_dump(), **args.segment_params})
    if args.measure_params:
        meas_params = LeafGeometryParams(**{**meas_params.model_dump(), **args.measure_params})
    # the stages' own imports (scipy.spatial, cv2, ...) are not part of the timed work
    import cv2  # noqa: F401
    import scipy.ndimage  # noqa: F401
    import scipy.spatial  # noqa: F401

    def ours_seg(m):
        return segment_leaves(m, seg_params)[0]

    def ours_meas(lm):
        return measure_plant(lm, meas_params)[0]

    ours = [run_method("curvature-regions + leaf-geometry", ours_seg, ours_meas, mesh, truth,
                       tv, tf, tid) for _ in range(max(args.repeat, 1))]
    rows = [
        min(ours, key=lambda r: r["segment_cpu_s"] + r["measure_cpu_s"]),
        run_method("components + naive", components_segmentation, naive_measure, mesh, truth,
                   tv, tf, tid),
        run_method("curvature-regions + naive", ours_seg, naive_measure, mesh, truth, tv, tf,
                   tid),
    ]
    import os

    print(f"# {source}: {len(mesh.faces)} faces; load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} cores\n")
    print("| method | leaves found / truth (merged, extra) | ε length | ε width | ε area "
          "| ε perimeter | segment s (cpu) | measure s (cpu) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['method']} | {r['leaves_found']}/{r['leaves_truth']} ({r['merged']}, "
              f"{r['extra']}) | {100 * r['err_length']:.2f} % | {100 * r['err_width']:.2f} % | "
              f"{100 * r['err_area']:.2f} % | {100 * r['err_perimeter']:.2f} % | "
              f"{r['segment_wall_s']:.1f} ({r['segment_cpu_s']:.1f}) | "
              f"{r['measure_wall_s']:.1f} ({r['measure_cpu_s']:.1f}) |")
    if len(ours) > 1:
        print("\nours, segment + measure CPU s of each run: "
              + ", ".join(f"{r['segment_cpu_s'] + r['measure_cpu_s']:.1f}" for r in ours))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()

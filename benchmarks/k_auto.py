"""``reconstruct.params.k`` against the number of views: the hull's accuracy for 12-72 views.

    python benchmarks/k_auto.py --scan SCAN [--scan SCAN ...] [--resolution 256] \
        [--views 12 18 24 36 72] [--k 0 1 2 3] [--run RUN ...] [--json out.json]

For each virtual scan (72 plant views or more) the views are thinned to N evenly spread
turntable stops per camera; the hull is carved from

* ``truth``: the virtual scanner's exact masks and cameras (what an imported scan with a
  good calibration and clean silhouettes gives), or
* ``segmented``: the masks a run of the scan made (``--run``: its recipe's segmenter,
  ``lab-shadow``) with the exact cameras (a virtual scan through plantscan's own
  segmentation),

and meshed; figures against the truth plant (``plantscan_hull.evaluate``): the mean
distance of the truth's rim points to the mesh (the accuracy a silhouette method can have,
in voxels), how far the mesh stands off the truth (phantom volume), and the leaves lost.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "plugins"))


def evaluate(mesh, truth_dir: Path, voxel: float) -> dict:
    from plantscan_hull.evaluate import _distance, _scene, rim_points, truth_views

    from plantscan_core.data import Mesh

    with np.load(truth_dir / "plant.npz") as z:
        tv, tf, leaf_id = z["vertices"], z["faces"], z["face_leaf_id"]
    if mesh.is_empty:
        return {"mean_surface_distance_voxels": None, "leaves_lost": int(leaf_id.max() + 1)}
    scene = _scene(mesh)
    rim = rim_points(tv, truth_views(truth_dir))
    d = _distance(scene, tv) / voxel
    covered = _distance(scene, tv, signed_outside=True) / voxel <= 1.5
    lost = sum(1 for leaf in np.unique(leaf_id[leaf_id >= 0])
               if covered[np.unique(tf[leaf_id == leaf])].mean() < 0.5)
    off = _distance(_scene(Mesh(tv, tf)), mesh.vertices) / voxel
    return {"mean_surface_distance_voxels": float(d[rim].mean()),
            "hull_to_truth_mean_voxels": float(off.mean()), "leaves_lost": int(lost)}


def run_scan(scan_dir: Path, run_dir: Path | None, views_list, ks, resolution: int
             ) -> list[dict]:
    from plantscan_hull.evaluate import truth_silhouettes
    from plantscan_hull.stages import MarchingCubesMesher, OctreeHull

    from plantscan_core.data import Silhouette, Silhouettes
    from plantscan_core.scanfolder import ScanFolder

    scan = ScanFolder.open(scan_dir)
    truth_sils, truth_cal = truth_silhouettes(scan)
    plant = {v.index: v for v in scan.views_by_role("plant")}
    truth_sils = Silhouettes([s for s in truth_sils if s.view.index in plant])
    sets = {"truth": truth_sils}
    if run_dir is not None:
        from plantscan_core.runfolder import MASKS_DIR, read_mask

        sets["segmented"] = Silhouettes([
            Silhouette(s.view, read_mask(run_dir / MASKS_DIR / f"{s.view.index:05d}.png"))
            for s in truth_sils])
    rows = []
    stops = sorted({plant[s.view.index].angle_index for s in truth_sils})
    cams = sorted({plant[s.view.index].camera for s in truth_sils})
    for n in views_list:
        per_cam = max(1, n // len(cams))
        pick = set(np.array(stops)[np.round(np.linspace(0, len(stops), per_cam,
                                                        endpoint=False)).astype(int)])
        for kind, sils in sets.items():
            sub = Silhouettes([s for s in sils if plant[s.view.index].angle_index in pick])
            for k in ks:
                t0 = time.perf_counter()
                hull = OctreeHull(OctreeHull.Params(resolution=resolution, k=k))
                volume = hull.reconstruct(sub, truth_cal)
                mesh = MarchingCubesMesher(MarchingCubesMesher.Params()).mesh(volume)
                row = {"scan": scan_dir.name, "views": len(sub), "masks": kind, "k": k,
                       "seconds": time.perf_counter() - t0,
                       **evaluate(mesh, scan.ground_truth_dir, float(volume.voxel_size))}
                rows.append(row)
                print(json.dumps(row), flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scan", action="append", required=True)
    ap.add_argument("--views", type=int, nargs="+", default=[12, 18, 24, 36, 72])
    ap.add_argument("--k", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--run", action="append", help="a run of each scan, in order: its "
                    "masks are the 'segmented' set")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    runs = args.run or []
    for i, s in enumerate(args.scan):
        rows += run_scan(Path(s), Path(runs[i]) if i < len(runs) else None, args.views, args.k,
                         args.resolution)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Render speed of the virtual scanner: CPU and wall seconds per image at 1 MP and 18 MP.

Side by side, same views, noise off:

* ``fast`` (the default): adaptive anti-aliasing; the backdrop intersected
  analytically, Open3D rays only inside the turntable scene's footprint and
  where the shadow map says a shadow may fall (``Renderer._trace``);
* ``open3d``: the same adaptive anti-aliasing with every ray cast by Open3D
  (``Renderer._shade``; the default before the fast path);
* ``full``: ``ss x ss`` Open3D rays through every pixel (the plain reference;
  1 MP only unless ``--full``: ~480 Mrays per 18 MP image).

Plant views use 3 x 3 samples, calibration (board) views 6 x 6, as the scans
do.  Reports how far each image is from the ``open3d`` one (mean |difference|
in 8-bit levels, truth-mask pixels differing), so speed is not bought with
accuracy, plus Open3D rays and analytic (backdrop) rays per image.

    python benchmarks/render.py            # 1 MP and 18 MP
    python benchmarks/render.py --quick    # 1 MP only
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
from plantscan_sim.api import scan_recipe, sim_manager
from plantscan_sim.plants import build_plant
from plantscan_sim.rig import Rig
from plantscan_sim.scene import SimScene

from plantscan_core.recipe import validate_recipe
from plantscan_core.stages import StageContext

SIZES = {"1 MP": (1224, 816), "18 MP": (5184, 3456)}


def scene_for(size: tuple[int, int]) -> SimScene:
    raw = scan_recipe("plastic-dicot", image_size=size)
    manager = sim_manager()
    recipe = validate_recipe({k: raw[k] for k in ("name", "plant", "scan")}, manager.registry)
    scene = SimScene(SimScene.Params(**raw["scan"]["scene"]["params"]), StageContext(recipe))
    p = scene.params
    scene.rig = Rig(scene._camera_params(recipe), size, [0.0], p.target_height_mm,
                    p.arm_azimuth_deg)
    scene.plant = build_plant("plastic-dicot", 0, scene.soil_z)
    scene._build_world()
    scene.camera_order = ["cam0", "cam1"]
    return scene


def run(label: str, size: tuple[int, int], n_images: int, modes: list[str]) -> list[str]:
    scene = scene_for(size)
    r = scene.renderer
    rows = []
    for role in ("plant", "calibration"):
        ss = 6 if role == "calibration" else 3
        images = {}
        for mode in modes:
            n = n_images if mode != "full" else 1
            r.rays_cast = r.rays_analytic = 0
            # the first image of a lens fills the ray cache (once per process): not timed
            r.render(role, scene.rig.camera("cam0", 0.0, 0.0), 0.0, 1, fast=mode == "fast")
            r.rays_cast = r.rays_analytic = 0
            t0, c0 = time.perf_counter(), time.process_time()
            for i in range(n):
                cam = scene.rig.camera("cam1" if i % 2 else "cam0", 0.0, 10.0 * i)
                img, cov = r.render(role, cam, 10.0 * i, ss, 0.0, None, True,
                                    adaptive=mode != "full", fast=mode == "fast")
                if i == 0:
                    images[mode] = (img, cov)
            wall, cpu = (time.perf_counter() - t0) / n, (time.process_time() - c0) / n
            if mode == "open3d" or "open3d" not in images:
                diff = ""
            else:
                (a, ca), (b, cb) = images[mode], images["open3d"]
                d = np.abs(a.astype(np.int16) - b.astype(np.int16)).mean()
                m = 100.0 * float(np.mean((ca >= 0.5) != (cb >= 0.5)))
                diff = f"{d:.2g} / {m:.4f} %"
            rows.append(f"| {label} ({size[0]}x{size[1]}) | {role} ({ss}x{ss}) | {mode} | {n} "
                        f"| {cpu:.2f} | {wall:.2f} | {r.rays_cast / n / 1e6:.1f} "
                        f"| {r.rays_analytic / n / 1e6:.1f} | {diff} |")
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="1 MP only")
    ap.add_argument("--full", action="store_true", help="the full-supersampling reference "
                    "at 18 MP too")
    ap.add_argument("--images", type=int, default=2, help="images per mode at 18 MP")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    print("| image | view | renderer | images | CPU s/image | wall s/image | Open3D Mrays "
          "| analytic Mrays | vs open3d: mean abs diff / mask differing |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, size in SIZES.items():
        if args.quick and label != "1 MP":
            continue
        big = label != "1 MP"
        modes = ["open3d", "fast"] + (["full"] if not big or args.full else [])
        run(label, size, args.images if big else 4, modes)
    print(f"load at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()

"""Render speed of the virtual scanner: images/s at 1 MP and 18 MP.

Side by side: adaptive anti-aliasing (one ray per pixel, ``ss x ss`` rays only
where the 3 x 3 neighbourhood changes: the default) and the plain reference
(``ss x ss`` rays through every pixel).  Also reports how far the adaptive
images are from the reference (mean |difference| in 8-bit levels, noise off)
and the truth-mask disagreement, so the speed-up is not bought with accuracy.

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


def run(label: str, size: tuple[int, int], n_images: int, ss: int = 3) -> list[str]:
    scene = scene_for(size)
    r = scene.renderer
    rows = []
    images = {}
    for adaptive in (True, False):
        n = n_images if adaptive else max(1, n_images // 3)
        r.rays_cast = 0
        t0 = time.perf_counter()
        for i in range(n):
            cam = scene.rig.camera("cam1" if i % 2 else "cam0", 0.0, 10.0 * i)
            img, cov = r.render("plant", cam, 10.0 * i, ss, 0.0, None, True, adaptive=adaptive)
            if i == 0:
                images[adaptive] = (img, cov)
        dt = time.perf_counter() - t0
        rows.append(f"| {label} ({size[0]}x{size[1]}) | {'adaptive' if adaptive else 'full'} "
                    f"{ss}x{ss} | {n} | {n / dt:.3f} | {r.rays_cast / n / 1e6:.1f} |")
    (a, ca), (b, cb) = images[True], images[False]
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).mean()
    mask_diff = float(np.mean((ca >= 0.5) != (cb >= 0.5)))
    rows.append(f"| {label} | adaptive vs full: mean abs diff {diff:.3f} levels, "
                f"mask pixels differing {100 * mask_diff:.3f} % | | | |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    print("| image | anti-aliasing | images | images/s | Mrays/image |")
    print("|---|---|---|---|---|")
    for label, size in SIZES.items():
        if args.quick and label != "1 MP":
            continue
        for row in run(label, size, 6 if label == "1 MP" else 1):
            print(row, flush=True)


if __name__ == "__main__":
    main()

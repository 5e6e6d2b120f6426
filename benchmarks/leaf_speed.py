"""Leaf stages' time per family: segmentation + measurement, the piece judge off vs on.

The issue's speed target (#22): mesh segmentation + measurement <= 10 s at 512^3 for
every family on 2 cores.  Each run folder's ``mesh.npz`` (a population.py run) is
segmented with its family recipe's ``segment_mesh`` parameters, the judge off (the
rules alone: the simpler alternative) and on, then measured; ``--repeat`` rounds
alternate the two, and the table keeps every round::

    python benchmarks/leaf_speed.py --run RUNS/branched/seed-1000=recipes/branched.yaml \\
        --run RUNS/grass/seed-1000=recipes/grass.yaml
"""

from __future__ import annotations

import argparse
import copy
import os
import time
from pathlib import Path

import yaml


def time_run(run: Path, recipe: Path, repeat: int) -> list[str]:
    from plantscan_leaves.geometry import forget_meshes
    from plantscan_leaves.plugin import CurvatureRegions, LeafGeometry

    from plantscan_core.data import Mesh

    r = yaml.safe_load(recipe.read_text())
    mesh = Mesh.load(run / "mesh.npz")
    rows = []
    for rnd in range(repeat):
        for judge in (False, True):
            p = copy.deepcopy(r["segment_mesh"]["params"])
            p["judge_pieces"] = judge
            forget_meshes()  # no scene or unit left from the round before
            w0, c0 = time.perf_counter(), time.process_time()
            labelled = CurvatureRegions(CurvatureRegions.Params(**p)).segment(mesh)
            w1, c1 = time.perf_counter(), time.process_time()
            traits = LeafGeometry(LeafGeometry.Params(**r["measure"]["params"])).measure(labelled)
            w2, c2 = time.perf_counter(), time.process_time()
            rows.append(f"| {run.parent.name} {run.name} | {len(mesh.faces):,} | "
                        f"{'on' if judge else 'off'} | {rnd + 1} | {len(traits.leaves)} | "
                        f"{w1 - w0:.1f} ({c1 - c0:.1f}) | {w2 - w1:.1f} ({c2 - c1:.1f}) | "
                        f"**{w2 - w0:.1f}** |")
            print(rows[-1], flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", required=True, metavar="RUN=RECIPE")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {load:.1f} before\n")
    print("| run | faces | judge | round | leaves | segment s wall (CPU) | "
          "measure s wall (CPU) | total s wall |")
    print("|---|---|---|---|---|---|---|---|")
    for item in args.run:
        run, recipe = item.split("=", 1)
        time_run(Path(run), Path(recipe), args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

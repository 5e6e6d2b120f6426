"""Batch throughput: plants per minute with 1 and 2 Dask workers, beside a plain serial loop.

    python benchmarks/batch.py [--plants 4] [--resolution 96] [--work DIR]

Makes ``--plants`` small virtual scans (different seeds; cached in ``--work``),
then processes the same scans three ways, each into fresh run folders (no stage
cache hits):

* ``serial``: ``plantscan_core.pipeline.process`` in a for loop in this process
  (the simplest correct alternative; no Dask);
* ``dask-1``: ``run_batch`` on a local cluster of 1 worker process;
* ``dask-2``: ``run_batch`` on a local cluster of 2 worker processes.

Wall times include the cluster start; the machine's load average is printed,
since other processes share the cores.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests" / "batch"), str(ROOT / "plugins")]


def main() -> int:
    from batch_fixtures import SCAN_ARGS, write_recipe
    from plantscan_sim import make_scan

    from plantscan_core.batch import run_batch
    from plantscan_core.pipeline import process
    from plantscan_core.plugins import load_plugins
    from plantscan_core.recipe import load_recipe

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=96, help="hull voxels along the box")
    ap.add_argument("--work", default="/tmp/plantscan-bench-batch")
    args = ap.parse_args()

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    scans = []
    for i in range(args.plants):
        scan = work / f"plant{i:02d}"
        if not (scan / "views.jsonl").exists() or not (scan / "ground_truth").exists():
            shutil.rmtree(scan, ignore_errors=True)
            make_scan(scan, seed=100 + i, **SCAN_ARGS)
        scans.append(scan)
    recipe = write_recipe(work / "recipe.yaml")
    overrides = [f"reconstruct.params.resolution={args.resolution}"]
    print(f"{args.plants} plants, hull resolution {args.resolution}, {os.cpu_count()} cores, "
          f"load average before: {os.getloadavg()[0]:.1f}")

    rows = []  # (method, workers, wall s, plants ok, sum of plant seconds, CPU s per plant)
    manager = load_plugins()
    r = load_recipe(recipe, overrides, manager.registry)
    # Warm-up, untimed: compiles the numba kernels into their on-disk cache, which every
    # later process (serial or Dask worker) loads instead of compiling again.
    shutil.rmtree(work / "warm-up", ignore_errors=True)
    process(scans[0], r, work / "warm-up", manager, overrides=overrides, workers=1)
    out = work / "serial"
    shutil.rmtree(out, ignore_errors=True)
    t0, cpu0 = time.perf_counter(), time.process_time()
    for scan in scans:
        process(scan, r, out / scan.name, manager, overrides=overrides, workers=1)
    wall = time.perf_counter() - t0
    rows.append(("serial (for loop, no Dask)", 1, wall, args.plants, wall,
                 (time.process_time() - cpu0) / args.plants))

    for workers in (1, 2):
        out = work / f"dask-{workers}"
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        summary = run_batch(scans, recipe, out, overrides=overrides, workers=workers,
                            progress=False)
        rows.append(("run_batch, local cluster", workers, time.perf_counter() - t0,
                     summary.succeeded, sum(p.seconds for p in summary.plants),
                     sum(p.cpu_seconds for p in summary.plants) / len(summary.plants)))
        if summary.failed:
            print(summary)
            return 1

    base = rows[1][2]
    # Concurrency = sum of the plants' own seconds / wall time: how many plants were being
    # processed at once on average (cluster start and plugin loading included in the wall).
    # CPU s per plant: the work one plant costs; equal across rows = no overhead from Dask.
    print("\n| method | workers | plants ok | wall (s) | plants/min | speed-up vs dask-1 "
          "| concurrency | CPU s / plant |")
    print("|---|---|---|---|---|---|---|---|")
    for name, workers, seconds, ok, task_s, cpu in rows:
        print(f"| {name} | {workers} | {ok} | {seconds:.1f} | {60 * ok / seconds:.1f} | "
              f"{base / seconds:.2f}x | {task_s / seconds:.2f} | {cpu:.1f} |")
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

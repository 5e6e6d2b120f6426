"""Leaf stages' time per family: segmentation + measurement, the piece judge off vs on.

The issue's speed target (#22): mesh segmentation + measurement <= 10 s at 512^3 for
every family on 2 cores.  Each run folder's ``mesh.npz`` (a population.py run) is
segmented with its family recipe's ``segment_mesh`` parameters, the judge off (the
rules alone: the simpler alternative) and on, then measured; ``--repeat`` rounds
alternate the two, and the table keeps every round::

    python benchmarks/leaf_speed.py --run RUNS/branched/seed-1000=recipes/branched.yaml \\
        --run RUNS/grass/seed-1000=recipes/grass.yaml

``--code DIR`` times another checkout's leaf stages beside this one's in the same run
(``git worktree add DIR COMMIT``; its plugins imported in a child process), each round
this code then that one, the same mesh and parameters::

    python benchmarks/leaf_speed.py --run RUNS/dicot/seed-1000=recipes/dicot.yaml \\
        --judge on --repeat 3 --code /tmp/before

Every timing starts from warm imports (Open3D, numba's cached kernels, the piece
model) and empty per-mesh caches, as the second plant of a batch would.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
JUDGE = {"off": (False,), "on": (True,), "both": (False, True)}


def warm_up(recipe: dict) -> None:
    """Imports and compiled kernels loaded before any timing (what every plant after the
    first finds ready)."""
    import numpy as np
    import open3d  # noqa: F401
    from plantscan_leaves import geometry, pieces

    tetra = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    geometry.topology(tetra)
    for kernel, args in (("averaging_operator", (4, tetra[:, :2])),  # absent before 6c4f266
                         ("triangle_union_mask", (np.zeros((1, 3, 2)), (2, 2)))):
        if hasattr(geometry, kernel):
            getattr(geometry, kernel)(*args)
    pieces.load_model(recipe["segment_mesh"]["params"].get("piece_model"))


def time_round(run: Path, recipe: Path, judges: tuple[bool, ...]) -> list[dict]:
    """One round: the leaf stages on ``run``'s mesh for each judge setting, seconds."""
    from plantscan_leaves.plugin import CurvatureRegions, LeafGeometry

    from plantscan_core.data import Mesh

    try:  # absent from checkouts before the caches
        from plantscan_leaves.geometry import forget_meshes
    except ImportError:
        def forget_meshes() -> None:
            return None

    r = yaml.safe_load(recipe.read_text())
    warm_up(r)
    mesh = Mesh.load(run / "mesh.npz")
    out = []
    for judge in judges:
        p = copy.deepcopy(r["segment_mesh"]["params"])
        p["judge_pieces"] = judge
        forget_meshes()  # no scene or unit left from the round before
        w0, c0 = time.perf_counter(), time.process_time()
        labelled = CurvatureRegions(CurvatureRegions.Params(**p)).segment(mesh)
        w1, c1 = time.perf_counter(), time.process_time()
        traits = LeafGeometry(LeafGeometry.Params(**r["measure"]["params"])).measure(labelled)
        w2, c2 = time.perf_counter(), time.process_time()
        out.append({"run": f"{run.parent.name} {run.name}", "faces": len(mesh.faces),
                    "judge": judge, "leaves": len(traits.leaves), "seg": (w1 - w0, c1 - c0),
                    "meas": (w2 - w1, c2 - c1), "load": os.getloadavg()[0]})
    return out


def _commit(checkout: Path) -> str:
    return subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True).stdout.strip() or str(checkout)


def _round_in(checkout: Path, run: Path, recipe: Path, judge: str) -> list[dict]:
    """``time_round`` with ``checkout``'s plugins, in a child process."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(checkout / "plugins"),
                                                        str(checkout)]))
    res = subprocess.run([sys.executable, __file__, "--child", f"{run}={recipe}",
                          "--judge", judge], env=env, capture_output=True, text=True,
                         cwd=str(checkout))
    if res.returncode:
        raise RuntimeError(f"{checkout}: {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", default=[], metavar="RUN=RECIPE")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--judge", choices=tuple(JUDGE), default="both")
    ap.add_argument("--code", type=Path, metavar="DIR",
                    help="another checkout whose leaf stages are timed beside this one's")
    ap.add_argument("--child", metavar="RUN=RECIPE", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        run, recipe = args.child.split("=", 1)
        print(json.dumps(time_round(Path(run), Path(recipe), JUDGE[args.judge])))
        return 0
    codes = [REPO] + ([args.code.resolve()] if args.code else [])
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"load {os.getloadavg()[0]:.1f} before, {os.cpu_count()} cores\n")
    print("| run | faces | code | judge | round | leaves | segment s wall (CPU) | "
          "measure s wall (CPU) | total s wall (CPU) | load |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for item in args.run:
        run, recipe = (Path(x) for x in item.split("=", 1))
        for rnd in range(args.repeat):
            for code in codes:
                for row in _round_in(code, run.resolve(), recipe.resolve(), args.judge):
                    (ws, cs), (wm, cm) = row["seg"], row["meas"]
                    print(f"| {row['run']} | {row['faces']:,} | {_commit(code)} | "
                          f"{'on' if row['judge'] else 'off'} | {rnd + 1} | {row['leaves']} | "
                          f"{ws:.1f} ({cs:.1f}) | {wm:.1f} ({cm:.1f}) | "
                          f"**{ws + wm:.1f}** ({cs + cm:.1f}) | {row['load']:.1f} |",
                          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

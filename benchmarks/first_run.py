"""The first ``plantscan demo`` with and without ``plantscan warm-up``, and the second.

Usage::

    python benchmarks/first_run.py [--doc docs/benchmarks/first_run.md]

numba compiles the hull's and the renderer's kernels on first use and caches
them.  Each case runs in child processes that share one fresh, empty numba
cache (``NUMBA_CACHE_DIR``), so "first" is the first run on a new install:

* ``no warm-up``: ``plantscan demo`` on an empty cache (what a user got before
  ``make setup`` ran the warm-up: the simplest correct alternative, compiling
  on demand);
* ``warm-up``: ``plantscan warm-up`` on an empty cache, then ``plantscan demo``
  (what ``make demo`` on a clean clone does now);
* ``second demo``: ``plantscan demo`` again on that cache, into a new folder;
* with ``--clone``, also what a new user does: ``git clone`` of this repository,
  ``make setup`` (system packages checked, a new ``.venv``, ``pip install`` from
  pip's cache, the warm-up), ``make demo``, then ``.venv/bin/plantscan demo``
  again; numba's cache is the clone's own (``__pycache__``, no
  ``NUMBA_CACHE_DIR``), empty after the clone.

Every demo renders its own virtual scan and processes it; the table gives the
command's wall time, the scan's share and the processing time (``run.json``),
with the hull stage separately (where the compile wait was).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PLANTSCAN = [sys.executable, "-m", "plantscan_core.cli"]


def timed(cmd: list[str], env: dict[str, str], cwd: Path,
          log: Path | None = None) -> tuple[float, str]:
    """Wall seconds and stdout of ``cmd``; its stdout and stderr also to ``log``."""
    t0 = time.perf_counter()
    out = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    if log is not None:
        log.write_text(f"$ {' '.join(cmd)}\n{out.stdout}\n--- stderr\n{out.stderr}")
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}")
    return time.perf_counter() - t0, out.stdout


def demo(env: dict[str, str], work: Path, name: str, cmd: list[str] | None = None) -> dict:
    wall, _ = timed(cmd or PLANTSCAN + ["demo", "--out", str(work / name)], env, work,
                    work / f"{name}.log")
    info = json.loads((work / name / "run" / "run.json").read_text())
    evaluation = json.loads((work / name / "run" / "evaluation.json").read_text())
    t, cpu = info["timings_s"], info.get("cpu_s", {})
    return {"wall": wall, "process": t["total"], "process_cpu": cpu.get("total", float("nan")),
            "reconstruct": t["reconstruct"], "reconstruct_cpu": cpu.get("reconstruct",
                                                                        float("nan")),
            "traits": evaluation.get("traits", {})}


def clean_clone(work: Path) -> list[tuple[str, float | None, dict]]:
    """``git clone``, ``make setup``, ``make demo``, a second demo: the rows of a new user."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "VIRTUAL_ENV", "PYTHONPATH")}
    clone = work / "clone"
    timed(["git", "clone", "-q", str(REPO), str(clone)], env, work)
    setup, _ = timed(["make", "setup"], env, clone, work / "make-setup.log")
    plantscan = [str(clone / ".venv/bin/plantscan")]
    first = demo(env, clone, "demo-out", ["make", "demo"])
    second = demo(env, clone, "demo-2", plantscan + ["demo", "--out", "demo-2"])
    return [("clean clone: `make demo`", setup, first),
            ("clean clone: second `plantscan demo`", None, second)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--doc", default=str(REPO / "docs/benchmarks/first_run.md"))
    ap.add_argument("--keep", help="work in a new folder under KEEP and keep it (the demos' "
                    "logs and outputs); default a temporary folder")
    ap.add_argument("--clone", action="store_true",
                    help="also a clean clone: make setup, make demo, a second demo")
    ap.add_argument("--clone-only", action="store_true",
                    help="only the clean clone (when the machine's time is short)")
    args = ap.parse_args(argv)
    rows = []
    load0 = os.getloadavg()[0]
    if args.keep:
        Path(args.keep).mkdir(parents=True, exist_ok=True)
    with (contextlib.nullcontext(tempfile.mkdtemp(prefix="first-run-", dir=args.keep))
          if args.keep else tempfile.TemporaryDirectory(prefix="plantscan-first-run-")) as tmp:
        work = Path(tmp)
        for case in () if args.clone_only else ("no warm-up", "warm-up"):
            cache = work / f"numba-{case.replace(' ', '-')}"
            cache.mkdir()
            env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
            warm = None
            if case == "warm-up":
                warm, _ = timed(PLANTSCAN + ["warm-up"], env, work)
            rows.append((case, warm, demo(env, work, f"demo-{len(rows)}")))
            if case == "warm-up":
                rows.append(("second demo", None, demo(env, work, f"demo-{len(rows)}")))
            shutil.rmtree(cache)
        if args.clone or args.clone_only:
            rows += clean_clone(work)
    load1 = os.getloadavg()[0]
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# First run: the numba compile wait (`benchmarks/first_run.py`)",
        "",
        "`plantscan demo` (the shipped plastic-dicot recipe: 640×427 px, 2 cameras, 36",
        "angles, 110 images), each case on an empty numba cache"
        + (" (the clean clone's own, `__pycache__` beside its source), so its first demo"
           " is the first of a new user." if args.clone_only else
           " (`NUMBA_CACHE_DIR`; the clean clone's own `__pycache__`), so the first demo of"
           " a case is the first on a new install."),
        "Cells: wall seconds (CPU seconds in brackets). \"demo\" is the whole command",
        "(Python start-up, the virtual scan, processing, evaluation); \"processing\" and",
        "\"hull\" come from the run's `run.json`. On a shared machine compare the CPU",
        "seconds: the wall seconds follow the other users' load.",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, load {load0:.1f}–{load1:.1f}"
        f" (shared); {when}.",
        "",
        "| case | warm-up (clone: `make setup`) | demo | processing | hull (reconstruct) |",
        "|---|---|---|---|---|",
    ]
    for case, warm, r in rows:
        lines.append(f"| {case} | {'—' if warm is None else f'{warm:.1f}'} | {r['wall']:.1f} | "
                     f"{r['process']:.1f} ({r['process_cpu']:.1f}) | "
                     f"{r['reconstruct']:.1f} ({r['reconstruct_cpu']:.1f}) |")
    lines += ["", "`make setup` runs `plantscan warm-up` once, so `make demo` on a clean clone "
              "is the \"warm-up\" row and a later `plantscan demo` the \"second demo\" row"
              + (" (the clean-clone rows measure exactly that; `make setup` there includes "
                 "creating the venv and `pip install` from pip's cache: a machine without "
                 "that cache downloads the wheels first)."
                 if args.clone or args.clone_only else "."), ""]
    traits = rows[-1][2]["traits"]
    if traits:
        mre = traits.get("mean_relative_error", {})
        lines += [
            "What the demo measures (one plant: the plastic dicot, seed 0, the plant its recipe "
            "was tuned on, so a development figure, not a population one; "
            "docs/benchmarks/population.md has those): "
            f"{traits.get('leaves_found')} of {traits.get('leaves_truth')} leaves found, "
            f"{traits.get('leaves_merged')} merged, {traits.get('leaves_extra')} extra pieces; "
            "ε length / width / area / perimeter "
            + " / ".join(f"{100 * mre.get(k, float('nan')):.2f}"
                         for k in ("length", "width", "area", "perimeter")) + " %.", ""]
    Path(args.doc).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

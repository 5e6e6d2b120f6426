"""End-to-end speed and memory: a virtual 18 MP scan from images to traits + report.

Usage::

    python benchmarks/end_to_end.py --scan /work/e2e_scans/paper-72 \
        [--config NAME:PATH=VALUE,PATH=VALUE ...] [--doc docs/benchmarks/end_to_end.md]

Each configuration is processed by ``plantscan process --profile`` in its own
process (so peak memory is that run's own) into a fresh run folder, then
``plantscan evaluate`` compares it with the scan's truth. Printed per run:
seconds per stage (wall and CPU), the command's total wall time (imports
included), peak resident memory, and the trait errors, so speed never hides
an accuracy loss.

The scans are rendered (not timed) by ``benchmarks/make_e2e_scans.py``; without
``--scan`` the paper-72 scan is taken from (or rendered into) its cache.

Configurations default to: the recipe as stored in the scan (what a user
gets: ``segment.reduce: auto``, i.e. 1/2 at 18 MP, and a 256^3 hull), every
image decoded and segmented at full resolution (``segment.reduce=1``, the
simplest correct way), the 512^3 hull, and the 512^3 hull with the session's
calibration reused (``--calibration``; a config item ``@calibration`` takes the
calibration.yaml of this scan's first run, as a lab that calibrates once per
session would).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PLANTSCAN = [sys.executable, "-m", "plantscan_core.cli"]
STAGES = ("calibrate", "segment", "reconstruct", "mesh", "segment_mesh", "measure")


def _parse_config(text: str) -> tuple[str, list[str]]:
    name, _, sets = text.partition(":")
    return name, [s for s in sets.split(",") if s]


def run_one(scan: Path, out: Path, overrides: list[str],
            calibration: Path | None = None) -> dict:
    """Process ``scan`` into ``out`` in a child process; timings, memory and trait errors."""
    if out.exists():
        shutil.rmtree(out)
    cmd = PLANTSCAN + ["process", str(scan), "--out", str(out), "--profile"]
    if calibration is not None:
        cmd += ["--calibration", str(calibration)]
    for o in overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    info = json.loads((out / "run.json").read_text())
    ev = subprocess.run(PLANTSCAN + ["evaluate", str(out)], capture_output=True, text=True)
    metrics = json.loads(ev.stdout) if ev.returncode == 0 else {}
    traits = metrics.get("traits", {})
    return {
        "overrides": overrides,
        "wall_s": wall,
        "cpu_s": (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime),
        # ru_maxrss of RUSAGE_CHILDREN is the largest child so far: runs go largest-last
        # only by chance, so the run's own figure (run.json) is the one reported.
        "peak_rss_mb": info.get("peak_rss_mb", {}).get("total"),
        "stages_wall": {s: info["timings_s"].get(s) for s in STAGES},
        "stages_cpu": {s: info.get("cpu_s", {}).get(s) for s in STAGES},
        "process_total_s": info["timings_s"].get("total"),
        "export_s": sum(v for k, v in info["timings_s"].items() if k.startswith("export")),
        "errors": traits.get("mean_relative_error", {}),
        "leaves": (traits.get("leaves_found"), traits.get("leaves_truth"),
                   traits.get("leaves_merged")),
        "height_error": traits.get("plant", {}).get("height_mm", {}).get("relative_error"),
        "silhouettes": metrics.get("silhouettes", {}),
        "profile": proc.stdout,
    }


def _pct(x):
    return None if x is None else 100 * x


def _fmt(x, nd=1):
    return "–" if x is None else f"{x:.{nd}f}"


def table(scan: Path, results: dict[str, dict]) -> str:
    head = ("| config | " + " | ".join(STAGES) + " | export | process total | command wall "
            "| CPU | peak RSS MB | leaves (found/truth, merged) | ε L / W / A / P % "
            "| height % (both above the pot's rim when a pot was removed) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in results.items():
        stages = " | ".join(f"{_fmt(r['stages_wall'][s])} ({_fmt(r['stages_cpu'][s])})"
                            for s in STAGES)
        e = r["errors"]
        errs = " / ".join(_fmt(100 * e[k], 2) if k in e else "–"
                          for k in ("length", "width", "area", "perimeter"))
        found, truth, merged = r["leaves"]
        lines.append(f"| {name} | {stages} | {_fmt(r['export_s'])} | {_fmt(r['process_total_s'])} "
                     f"| {_fmt(r['wall_s'])} | {_fmt(r['cpu_s'])} | {_fmt(r['peak_rss_mb'], 0)} "
                     f"| {found}/{truth}, {merged} | {errs} "
                     f"| {_fmt(_pct(r.get('height_error')), 1)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scan", type=Path, action="append",
                    help="virtual scan folder (repeatable; default: the paper-72 18 MP scan of "
                         "benchmarks/make_e2e_scans.py, rendered there if missing)")
    ap.add_argument("--config", action="append", default=[],
                    help="NAME:PATH=VALUE,PATH=VALUE (recipe overrides); repeatable")
    ap.add_argument("--runs", type=Path, default=Path("/tmp/plantscan-e2e-runs"))
    ap.add_argument("--json", type=Path, help="append the results to this JSON file")
    args = ap.parse_args(argv)

    scans = args.scan
    if not scans:
        sys.path.insert(0, str(Path(__file__).parent))
        import make_e2e_scans

        scans = [make_e2e_scans.make(make_e2e_scans.DEFAULT_OUT, "paper-72")]
    # The scans store the recipe they were made with; the shipped recipe's leaf parameter
    # (recipes/plastic-dicot.yaml) came later, so it is applied as an override.
    leaf = "segment_mesh.params.concave_curvature_per_mm=0.06"
    hull512 = "reconstruct.params.resolution=512"
    configs = dict(_parse_config(c) for c in args.config) or {
        "recipe as scanned (reduce auto, hull 256)": [leaf],
        "full-resolution decode (reduce 1, hull 256)": ["segment.reduce=1", leaf],
        "hull 512": [hull512, leaf],
        "hull 512, session calibration": [hull512, leaf, "@calibration"]}
    for scan in scans:
        n_images = sum(1 for p in (scan / "images").rglob("*") if p.is_file())
        print(f"scan {scan} ({n_images} images), {platform.machine()}, {os.cpu_count()} cores, "
              f"load {os.getloadavg()[0]:.1f}")
        results = {}
        for i, (name, items) in enumerate(configs.items()):
            overrides = [o for o in items if o != "@calibration"]
            session = args.runs / "run0" / "calibration.yaml" if "@calibration" in items else None
            if session is not None and (i == 0 or not session.exists()):
                raise SystemExit(f"{name}: @calibration needs an earlier run of this scan")
            r = run_one(scan, args.runs / f"run{i}", overrides, session)
            results[name] = r
            print(f"\n== {name} {overrides}\n{r['profile']}")
            print(f"command wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, "
                  f"peak RSS {r['peak_rss_mb']} MB, leaves {r['leaves']}, errors {r['errors']}")
        print()
        print(table(scan, results))
        print(f"load after: {os.getloadavg()[0]:.1f}")
        if args.json:
            old = json.loads(args.json.read_text()) if args.json.exists() else {}
            old[str(scan)] = {k: {kk: vv for kk, vv in v.items() if kk != "profile"}
                              for k, v in results.items()}
            args.json.write_text(json.dumps(old, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

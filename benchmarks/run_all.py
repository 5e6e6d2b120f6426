"""Run every benchmark in this folder, then assemble docs/benchmarks.md.

Each benchmark ``benchmarks/<name>.py`` writes its own figures to
``docs/benchmarks/<name>.md``; this script runs them one after the other (they
are not tests: big renders, minutes each) and concatenates the pages, so
``docs/benchmarks.md`` always shows the figures of the last run of each.

    python benchmarks/run_all.py            # all
    python benchmarks/run_all.py hull leaves  # some
    python benchmarks/run_all.py --assemble   # only rebuild docs/benchmarks.md
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ORDER = ["population", "render", "calibration", "segmentation", "hull", "leaves", "batch",
         "store", "experiment", "end_to_end", "first_run"]


def assemble() -> Path:
    pages = sorted((ROOT / "docs/benchmarks").glob("*.md"),
                   key=lambda p: (ORDER.index(p.stem) if p.stem in ORDER else 99, p.stem))
    header = (ROOT / "docs/benchmarks/_header.md.in")
    parts = [header.read_text() if header.exists() else "# Benchmarks\n"]
    for p in pages:
        # the pages link docs/img as ../img; the assembled page sits in docs/
        parts.append(p.read_text().strip().replace("](../img/", "](img/") + "\n")
    out = ROOT / "docs/benchmarks.md"
    out.write_text("\n".join(parts))
    return out


def main(argv: list[str]) -> int:
    if argv == ["--assemble"]:
        print(assemble())
        return 0
    names = argv or [n for n in ORDER if (ROOT / f"benchmarks/{n}.py").exists()]
    failed = []
    for name in names:
        t0 = time.perf_counter()
        print(f"== benchmarks/{name}.py", flush=True)
        rc = subprocess.call([sys.executable, str(ROOT / f"benchmarks/{name}.py")], cwd=ROOT)
        print(f"== {name}: exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
        if rc:
            failed.append(name)
    print(assemble())
    if failed:
        print(f"failed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

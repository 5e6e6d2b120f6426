"""Render (and cache) the 18 MP virtual scans of the end-to-end benchmark.

Scans of a virtual plant (seed 0) at 5184 x 3456 JPEG, through the real
acquisition code (``plantscan_sim.make_scan``), rendering not timed by the
benchmark that reads them (issue #10).  The default plastic dicot:

* ``paper-72``: ``recipes/plastic-dicot.yaml`` as shipped (2 cameras, tilt 0,
  36 stops = 72 plant images, 36 calibration board views, 2 background plates:
  110 images).
* ``paper-360``: no recipe is shipped for it, so it is the same recipe with the
  overrides its header documents: ``scan.protocol=paper-360`` and
  ``scan.tilts_deg=[-10,0,10,20,30]`` (2 cameras x 5 tilts x 36 stops = 360
  plant images, 180 board views, 10 background plates: 550 images).

``--preset wheat`` / ``--preset sorghum``: the shipped grass recipe
(``recipes/<preset>.yaml``) at 18 MP, the same protocol overrides (issue #7: a grass
plant at a DSLR's resolution, full chain).  Their recipes already use the sim's
default 9x6-corner x 25 mm board, the one the dicot e2e scans calibrate with at 18 MP
(~0.2 mm), so the recipe is used as shipped.

A finished scan is skipped (``<out>/<name>.done.json`` records how it was made);
an interrupted one resumes where it stopped.  The two scans may run in two
processes at once (``--protocol paper-72`` and ``--protocol paper-360``).

    python benchmarks/make_e2e_scans.py [--out /work/e2e_scans] [--protocol both]
        [--preset plastic-dicot|wheat|sorghum]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = Path(os.environ.get("PLANTSCAN_E2E_SCANS", Path.home() / ".cache/plantscan/e2e"))
SIZE = (5184, 3456)
PRESETS = ("plastic-dicot", "wheat", "sorghum")
PROTOCOLS = ("paper-72", "paper-360")


def protocol_overrides(preset: str, protocol: str) -> list[str]:
    """Recipe overrides (``key=value``) that turn a shipped paper-72 recipe into ``protocol``."""
    if protocol == "paper-72":
        return []
    return ["scan.protocol=paper-360", "scan.tilts_deg=[-10,0,10,20,30]",
            f"name={preset}-paper-360"]


def e2e_recipe(out: Path) -> Path:
    """The shipped plastic-dicot recipe with the sim's default 10x7 x 25 mm board.

    The e2e scans were rendered with that board (at 18 MP it calibrates to ~0.2 mm); the
    shipped recipe later moved to a larger board for 640x427. Pinned here so a resumed or
    re-rendered scan matches the cached ones (resume compares the scan section).
    """
    raw = yaml.safe_load((ROOT / "recipes" / "plastic-dicot.yaml").read_text())
    params = raw["scan"]["scene"]["params"]
    params.pop("board_squares", None)
    params.pop("board_square_mm", None)
    raw["calibrate"]["params"] = {"board": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0,
                                  "lowest_corner_height_mm": 172.122}
    path = out / "plastic-dicot-e2e.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def scan_name(protocol: str, size: tuple[int, int], preset: str = "plastic-dicot") -> str:
    return f"{preset}-{protocol}-{size[0]}x{size[1]}"


def make(out: Path, protocol: str, size: tuple[int, int] = SIZE,
         preset: str = "plastic-dicot") -> Path:
    """Render one scan into ``out/<name>`` unless its ``.done.json`` says it is complete."""
    from plantscan_sim import make_scan

    name = scan_name(protocol, size, preset)
    folder, done = out / name, out / f"{name}.done.json"
    if done.exists():
        print(f"{name}: cached ({done})", flush=True)
        return folder
    resume = (folder / "views.jsonl").exists()
    print(f"{name}: rendering into {folder}{' (resuming)' if resume else ''}", flush=True)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # the renderer this run imported
    t0, c0 = time.perf_counter(), time.process_time()
    recipe = e2e_recipe(out) if preset == "plastic-dicot" else ROOT / "recipes" / f"{preset}.yaml"
    scan = make_scan(folder, preset=preset, recipe=recipe, image_size=size,
                     images_per_revolution=None, image_format="jpg",
                     overrides=protocol_overrides(preset, protocol), resume=resume)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    n = len(scan.views)
    info = {"scan": str(folder), "preset": preset, "recipe": str(recipe), "protocol": protocol,
            "image_size": list(size),
            "images": n, "roles": {r: len(scan.views_by_role(r))
                                       for r in ("calibration", "background", "plant")},
            "render_wall_s": round(wall, 1), "render_cpu_s": round(cpu, 1),
            "load_average_at_end": os.getloadavg()[0], "git_commit": commit,
            "resumed": resume}
    done.write_text(json.dumps(info, indent=1) + "\n")
    print(f"{name}: {n} images in {wall:.0f} s wall, {cpu:.0f} s CPU", flush=True)
    return folder


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help="scan cache (default $PLANTSCAN_E2E_SCANS or ~/.cache/plantscan/e2e)")
    ap.add_argument("--protocol", choices=[*PROTOCOLS, "both"], default="both")
    ap.add_argument("--preset", choices=PRESETS, default="plastic-dicot",
                    help="virtual plant and its shipped recipe (default plastic-dicot)")
    ap.add_argument("--size", default=f"{SIZE[0]}x{SIZE[1]}", help="WxH pixels")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    for protocol in (PROTOCOLS if args.protocol == "both" else [args.protocol]):
        make(args.out, protocol, size, args.preset)


if __name__ == "__main__":
    sys.exit(main())

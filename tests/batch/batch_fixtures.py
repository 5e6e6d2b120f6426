"""Virtual scans and a cheap recipe for the batch tests.

Two small virtual scans of different plants (seeds 1 and 2) and a third that is
the first with its plant images overwritten by garbage (a corrupt scan).  The
recipe uses the virtual scanner's exact calibration and masks (``truth``,
``truth-masks``) and a coarse hull so one plant takes a few seconds.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import yaml

PLUGINS = Path(__file__).resolve().parents[2] / "plugins"
if str(PLUGINS) not in sys.path:  # until the editable install maps every plugin package
    sys.path.insert(0, str(PLUGINS))

SCAN_ARGS = dict(image_size=(240, 160), images_per_revolution=8, roles=("background", "plant"),
                 supersampling=1)
PROCESSING = {
    "calibrate": {"plugin": "truth"},
    "segment": {"plugin": "truth-masks"},
    # The plastic dicot spans ~500 x 450 x 300 mm above the pot: a fixed box keeps the coarse
    # hull from chasing its bounding box with only 16 views.
    "reconstruct": {"plugin": "octree-hull",
                    "params": {"resolution": 48, "k": 3, "bbox": [-300, -300, 0, 300, 300, 480]}},
    "mesh": {"plugin": "marching-cubes"},
    "segment_mesh": {"plugin": "curvature-regions"},
    # 16 plant views where the recipe asks for 36: every plant is flagged (fewer than half)
    "measure": {"plugin": "leaf-geometry", "params": {"min_plant_views": 36}},
    "export": [{"plugin": "csv"}, {"plugin": "html-report", "params": {"thumbnails": 2}}],
}


def write_recipe(path: Path) -> Path:
    """The scan recipe of the virtual scans plus the cheap processing stages."""
    from plantscan_sim import scan_recipe

    raw = scan_recipe(seed=1, **SCAN_ARGS)
    raw.update(PROCESSING)
    raw["name"] = "batch-test"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def make_scans(root: Path) -> dict[str, Path]:
    """{"good1", "good2", "corrupt"} -> scan folder."""
    from plantscan_sim import make_scan

    scans = {}
    for name, seed in (("good1", 1), ("good2", 2)):
        scans[name] = make_scan(root / name, seed=seed, **SCAN_ARGS).root
    corrupt = root / "corrupt"
    shutil.copytree(scans["good1"], corrupt)
    for image in sorted((corrupt / "images" / "plant").iterdir()):
        image.write_bytes(b"not a PNG: the card reader failed")
    scans["corrupt"] = corrupt
    return scans


def crash_on_scan_named_crash(scan_dir: str, recipe_path: str, overrides, run_dir: str,
                              threads: int = 1):
    """A per-plant task that kills its worker process on the scan named ``crash``."""
    import os

    from plantscan_core.batch import PlantOutcome

    if Path(scan_dir).name == "crash":
        os._exit(17)  # like a segfault in a native library: no exception, the process is gone
    return PlantOutcome(scan=scan_dir, status="ok", run_dir=run_dir, leaf_count=0)

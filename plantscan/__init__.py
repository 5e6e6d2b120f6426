"""plantscan: turntable 3D scanning and leaf measurement for plant phenotyping.

The Python API (docs/api.md has the worked example)::

    import plantscan

    run = plantscan.process("scans/p001")            # the scan's own recipe
    df = run.traits.to_dataframe()                   # one row per leaf, mm and mm2
    run = plantscan.load_run("scans/p001-run")       # a finished run, read back
    mask = plantscan.build_stage("segmenter", "lab-shadow").segment(image, background)

The framework is ``plantscan_core`` (contracts, recipes, scan folders, the
pipeline); every algorithm is a plugin (``plantscan_hull``, ``plantscan_leaves``...).
"""

from __future__ import annotations

from plantscan_core import __version__
from plantscan_core.api import acquire, build_stage, load_recipe, load_run, process
from plantscan_core.data import (
    Calibration,
    LabelledMesh,
    LeafTraits,
    Mesh,
    Silhouette,
    Silhouettes,
    Traits,
    Volume,
)
from plantscan_core.errors import PlantScanError
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.stages import RunResult

__all__ = [
    "__version__", "acquire", "build_stage", "load_recipe", "load_run", "process",
    "Calibration", "LabelledMesh", "LeafTraits", "Mesh", "Silhouette", "Silhouettes", "Traits",
    "Volume", "PlantScanError", "ScanFolder", "RunResult",
]

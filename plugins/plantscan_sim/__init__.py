"""plantscan's virtual scanner: synthetic plants, rig, calibration board and exact truth.

Python API (see docs/virtual-scanner.md)::

    from plantscan_sim import make_scan
    scan = make_scan(tmp_path / "scan", preset="plastic-dicot", image_size=(480, 320),
                     images_per_revolution=12)
    scan.ground_truth_dir  # calibration.yaml, cameras.jsonl, masks/, plant.npz, traits.csv ...
"""

from __future__ import annotations

from plantscan_sim.api import make_scan, scan_recipe, sim_manager
from plantscan_sim.families import FAMILIES
from plantscan_sim.plants import PRESETS
from plantscan_sim.scene import RigError, finalize_truth, read_truth_cameras

__all__ = ["make_scan", "scan_recipe", "sim_manager", "PRESETS", "FAMILIES", "RigError",
           "finalize_truth", "read_truth_cameras"]

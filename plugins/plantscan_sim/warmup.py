"""Compile the virtual scanner's numba render kernels ahead of the first scan.

``plantscan warm-up`` (called by ``make setup``) acquires a tiny virtual scan
of the demo plant (64 x 43 px, two angles per role) into a temporary folder
through the real acquisition code, so the first ``plantscan demo`` renders
with kernels read from numba's cache instead of compiling them (~20 s).
"""

from __future__ import annotations

import tempfile
from pathlib import Path


def warm_up() -> str:
    """Render the tiny scan; returns a one-line description of what ran."""
    from plantscan_sim import render
    from plantscan_sim.api import make_scan

    if not render.HAVE_NUMBA:
        return "numba not installed, nothing to compile"
    with tempfile.TemporaryDirectory(prefix="plantscan-warm-up-") as tmp:
        scan = make_scan(Path(tmp) / "scan", image_size=(64, 43), images_per_revolution=2)
        n = len(scan.views)
    return f"render kernels compiled or read from the cache ({n}-image virtual scan)"

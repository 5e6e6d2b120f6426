from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def sim_scans(tmp_path_factory):
    """Small virtual scans with hard shadows: plastic dicot and wheat (plant + plates only)."""
    from plantscan_sim import make_scan

    root = tmp_path_factory.mktemp("segment-scans")
    return {
        preset: make_scan(root / preset, preset=preset, image_size=(960, 640),
                          images_per_revolution=2, roles=["background", "plant"])
        for preset in ("plastic-dicot", "wheat")
    }

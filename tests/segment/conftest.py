from __future__ import annotations

import pytest


def _scan(root, preset, size, views):
    from plantscan_sim import make_scan

    return make_scan(root / f"{preset}-{size[0]}", preset=preset, image_size=size,
                     images_per_revolution=views, roles=["background", "plant"])


@pytest.fixture(scope="session")
def sim_scans(tmp_path_factory):
    """Small virtual scans with hard shadows: plastic dicot and wheat (plant + plates only)."""
    root = tmp_path_factory.mktemp("segment-scans")
    return {preset: _scan(root, preset, (480, 320), 4) for preset in ("plastic-dicot", "wheat")}


@pytest.fixture(scope="session")
def wheat_recipe_size(tmp_path_factory):
    """Wheat at the recipes' 1200 x 800 px, one view per camera (its leaves are 4-8 px wide)."""
    return _scan(tmp_path_factory.mktemp("segment-wheat"), "wheat", (1200, 800), 1)

from __future__ import annotations

import pytest

# One small virtual scan shared by the tests of this folder (rendering is the slow part).
SMALL = dict(preset="plastic-dicot", image_size=(360, 240), images_per_revolution=6,
             calibration_images_per_revolution=2)


@pytest.fixture(scope="session")
def small_scan(tmp_path_factory):
    from plantscan_sim import make_scan

    return make_scan(tmp_path_factory.mktemp("sim") / "scan", **SMALL)

"""The one-file camera plugin of docs/plugin-guide.md, registered in-process and used in a scan."""

from __future__ import annotations

from pathlib import Path

import pytest

from plantscan_core.acquire import acquire, plan
from plantscan_core.errors import HardwareError
from plantscan_core.recipe import validate_recipe
from plantscan_core.testing import plugin_file, tiny_recipe

EXAMPLE = Path(__file__).resolve().parents[2] / "docs/examples/plantscan_dropfolder.py"


@pytest.fixture
def dropfolder(tiny_rig_manager):
    with plugin_file(tiny_rig_manager, EXAMPLE, "plantscan_dropfolder"):
        yield tiny_rig_manager


def test_guide_embeds_the_example_file_verbatim():
    guide = (EXAMPLE.parents[1] / "plugin-guide.md").read_text()
    assert EXAMPLE.read_text().strip() in guide


def test_example_camera_scans_with_the_real_orchestrator(dropfolder, tmp_path, monkeypatch):
    import cv2
    import numpy as np

    tether, shots = tmp_path / "tether", tmp_path / "shots"
    tether.mkdir()
    shots.mkdir()
    cv2.imwrite(str(tether / "OLD_0000.png"), np.full((8, 8, 3), 255, np.uint8))  # not ours
    raw = tiny_recipe()
    raw["scan"]["cameras"] = [{"name": "cam0", "plugin": "dropfolder",
                               "params": {"folder": str(tether), "pattern": "*.png",
                                          "timeout_s": 0.5}}]
    recipe = validate_recipe(raw, dropfolder.registry)
    n = len(plan(recipe))
    for i in range(n):  # what the camera's own software will save, one per trigger
        cv2.imwrite(str(shots / f"IMG_{i:04d}.png"), np.full((8, 8, 3), i, np.uint8))

    cls = dropfolder.registry.get("camera", "dropfolder").cls
    original_open = cls.open

    def open_then_shoot(self):
        original_open(self)  # remembers OLD_0000.png as already there
        for f in sorted(shots.iterdir()):
            f.rename(tether / f.name)

    monkeypatch.setattr(cls, "open", open_then_shoot)
    scan = acquire(recipe, tmp_path / "scan", dropfolder, raw_recipe=raw)
    assert len(scan.views) == n
    assert [int(scan.read_image(v)[0, 0, 0]) for v in scan.views] == list(range(n))


def test_example_camera_reports_a_missing_folder(dropfolder, tmp_path):
    raw = tiny_recipe()
    raw["scan"]["cameras"] = [{"name": "cam0", "plugin": "dropfolder",
                               "params": {"folder": str(tmp_path / "nowhere")}}]
    recipe = validate_recipe(raw, dropfolder.registry)
    with pytest.raises(HardwareError, match="nowhere is not a folder"):
        acquire(recipe, tmp_path / "scan", dropfolder, raw_recipe=raw)
    # Nothing was captured, and the failed scan can be resumed once the folder exists.
    assert (tmp_path / "scan/views.jsonl").read_text() == ""

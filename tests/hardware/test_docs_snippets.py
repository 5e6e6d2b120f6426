"""Every recipe snippet in docs/hardware/*.md validates against the plugins it documents."""

from __future__ import annotations

import re
from pathlib import Path

import hwfakes
import pytest
import yaml
from plantscan_gphoto import plugin as gphoto_plugin
from plantscan_opencvcam import plugin as opencv_plugin
from plantscan_phidget import plugin as phidget_plugin
from plantscan_serial import plugin as serial_plugin

from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe

DOCS = Path(__file__).resolve().parents[2] / "docs" / "hardware"
SNIPPETS = [
    pytest.param(block, id=f"{page.name}#{i}")
    for page in sorted(DOCS.glob("*.md"))
    for i, block in enumerate(re.findall(r"```yaml\n(.*?)```", page.read_text(), re.S))
]


@pytest.fixture(scope="module")
def registry():
    m = new_manager()
    for mod, name in ((gphoto_plugin, "gphoto"), (phidget_plugin, "phidget"),
                      (serial_plugin, "serial"), (opencv_plugin, "opencvcam"),
                      (hwfakes, "fakes")):
        m.register(mod, name=name)
    return m.registry


def test_there_are_snippets():
    assert len(SNIPPETS) >= 4


@pytest.mark.parametrize("block", SNIPPETS)
def test_snippet_validates(block, registry):
    doc = yaml.safe_load(block)
    assert "scan" in doc
    scan = {"cameras": [{"name": "cam0", "plugin": "fake"}], "turntable": {"plugin": "fake"},
            **doc["scan"]}
    raw = {"scan": scan}
    if len(scan.get("tilts_deg", [0])) > 1 and "tilt_arm" not in scan:
        scan["tilt_arm"] = {"plugin": "fake"}
    validate_recipe(raw, registry)  # RecipeError lists every wrong parameter

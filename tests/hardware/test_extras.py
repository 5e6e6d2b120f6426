"""Hardware libraries are extras: without one, its backend says which extra to install.

``pip install plantscan`` must process data on a PC with no camera library; the
backends still load (recipes naming them validate) and fail only when a device
is opened, naming the ``pip install 'plantscan[...]'`` line.  The library is hidden
by a ``None`` entry in ``sys.modules`` (what Python does for a blocked import).
"""

from __future__ import annotations

import sys

import pytest

from plantscan_core.errors import HardwareError
from plantscan_core.plugins import load_plugins


@pytest.mark.parametrize("module, extra, open_device", [
    ("gphoto2", "gphoto2", lambda: __import__("plantscan_gphoto.camera").camera._gp()),
    ("Phidget22", "phidget", lambda: __import__("plantscan_phidget.stepper").stepper
     .Phidget22Port()),
    ("serial", "serial", lambda: __import__("plantscan_serial.grbl").grbl
     .GrblConnection("/dev/null-port", 115200, 0.1)),
])
def test_missing_library_names_its_extra(monkeypatch, module, extra, open_device):
    for name in [m for m in sys.modules if m == module or m.startswith(module + ".")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(HardwareError, match=rf"pip install 'plantscan\[{extra}\]'"):
        open_device()


def test_plugins_load_without_the_hardware_libraries(monkeypatch):
    for module in ("gphoto2", "Phidget22", "serial"):
        monkeypatch.setitem(sys.modules, module, None)
    for name in [m for m in sys.modules if m.startswith(("plantscan_gphoto", "plantscan_phidget",
                                                         "plantscan_serial"))]:
        monkeypatch.delitem(sys.modules, name)
    manager = load_plugins()
    assert manager.failed == []
    assert {("camera", "gphoto2"), ("axis", "phidget"), ("axis", "grbl")} <= {
        (r.stage, r.name) for r in manager.registry}

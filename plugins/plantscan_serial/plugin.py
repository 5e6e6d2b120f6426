"""Registers the ``grbl`` axis."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_serial.grbl import GrblAxis


@hookimpl
def plantscan_register_stages(registry):
    registry.add(GrblAxis)

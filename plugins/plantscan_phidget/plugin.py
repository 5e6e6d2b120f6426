"""Registers the ``phidget`` axis."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_phidget.stepper import PhidgetAxis


@hookimpl
def plantscan_register_stages(registry):
    registry.add(PhidgetAxis)

"""Registers the ``opencv`` camera."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_opencvcam.camera import OpenCVCamera


@hookimpl
def plantscan_register_stages(registry):
    registry.add(OpenCVCamera)

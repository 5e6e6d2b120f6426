"""Registers the ``gphoto2`` camera."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_gphoto.camera import GPhotoCamera


@hookimpl
def plantscan_register_stages(registry):
    registry.add(GPhotoCamera)

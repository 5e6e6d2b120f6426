"""Bounding box, octree visual hull, pot removal and marching cubes (plantscan default plugin)."""

from __future__ import annotations

__version__ = "0.1.0"

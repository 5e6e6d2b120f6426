"""View planning: where more views would carve the visual hull (plantscan default plugin)."""

from __future__ import annotations

__version__ = "0.1.0"

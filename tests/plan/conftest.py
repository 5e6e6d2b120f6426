"""Planner tests: make the plugins importable from the source tree.

The editable install maps only the packages that existed when it was made;
until it is refreshed (``pip install -e .``), fall back to ``plugins/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

try:
    import plantscan_plan  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))

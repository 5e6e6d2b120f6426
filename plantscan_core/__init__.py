"""plantscan: turntable 3D scanning and leaf measurement for plant phenotyping.

``plantscan_core`` is the framework (contracts, recipes, scan folders, the
pipeline and the CLI); every algorithm lives in a plugin.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("plantscan")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"

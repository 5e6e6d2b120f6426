"""Make ``plantscan_sfm`` importable when the editable install predates its folder.

The editable finder maps only the packages that existed at ``pip install -e``
time; re-installing fixes it (see docs/calibration.md).  Until then the
``plugins`` folder is put on ``sys.path`` for these tests.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

if importlib.util.find_spec("plantscan_sfm") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "plugins"))

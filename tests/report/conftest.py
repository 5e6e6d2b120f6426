"""Fixtures of the report tests (helpers live in report_fixtures.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from report_fixtures import synthetic_run_in

from plantscan_core.stages import RunResult


@pytest.fixture
def synthetic_run(tmp_path: Path) -> RunResult:
    """A complete synthetic run (see report_fixtures.synthetic_run_in)."""
    return synthetic_run_in(tmp_path)

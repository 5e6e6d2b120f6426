"""Fixtures of the batch tests (helpers live in batch_fixtures.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from batch_fixtures import make_scans, write_recipe


@pytest.fixture(scope="session")
def batch_inputs(tmp_path_factory) -> tuple[dict[str, Path], Path]:
    """Three virtual scans (two good, one corrupt) and the recipe, made once per session."""
    root = tmp_path_factory.mktemp("batch-scans")
    return make_scans(root), write_recipe(root / "recipe.yaml")


@pytest.fixture(scope="session")
def batch_recipe(tmp_path_factory) -> Path:
    """Only the recipe (for tests that need no scan)."""
    return write_recipe(tmp_path_factory.mktemp("batch-recipe") / "recipe.yaml")

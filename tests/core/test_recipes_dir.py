"""Every shipped recipe validates against the installed plugins."""

from __future__ import annotations

from pathlib import Path

import pytest

from plantscan_core.plugins import load_plugins
from plantscan_core.recipe import load_recipe

RECIPES = sorted((Path(__file__).resolve().parents[2] / "recipes").glob("*.yaml"))


def test_there_are_recipes():
    assert any(p.name == "default.yaml" for p in RECIPES)


@pytest.mark.parametrize("path", RECIPES, ids=[p.stem for p in RECIPES])
def test_recipe_is_valid(path):
    manager = load_plugins(strict=False)
    load_recipe(path, registry=manager.registry)

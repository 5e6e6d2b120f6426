"""The new-stage example of docs/plugin-guide.md, registered in-process and run by process()."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from plantscan_core import iostats
from plantscan_core.errors import PluginError, RecipeError
from plantscan_core.pipeline import process
from plantscan_core.recipe import validate_recipe
from plantscan_core.testing import plugin_file, tiny_processing_plugin, tiny_recipe

EXAMPLE = Path(__file__).resolve().parents[2] / "docs/examples/plantscan_colour.py"
# The tiny rig paints its sphere (B, G, R) = (30, 90, 40) without anti-aliasing on a plate
# of 200 and the dark-pixel segmenter takes exactly the sphere's pixels, all of one colour.
SPHERE_RGB = (40.0, 90.0, 30.0)


@pytest.fixture
def colour_manager(tiny_rig_manager):
    import plantscan_hull.plugin

    tiny_rig_manager.register(tiny_processing_plugin, name="tiny-processing")
    tiny_rig_manager.register(plantscan_hull.plugin, name="hull")
    with plugin_file(tiny_rig_manager, EXAMPLE, "plantscan_colour"):
        yield tiny_rig_manager


def _raw(colour: bool = True) -> dict:
    raw = tiny_recipe()
    raw["calibrate"] = {"plugin": "tiny-exact"}
    raw["segment"] = {"plugin": "tiny-dark"}
    if colour:
        raw["colour"] = {"plugin": "mean-colour"}
    # numpy backend: no kernel to compile for a 32^3 hull of 12 small views
    raw["reconstruct"] = {"plugin": "octree-hull",
                          "params": {"resolution": 32, "backend": "numpy", "top_cell": 8}}
    return raw


def test_guide_embeds_the_stage_example_verbatim():
    guide = (EXAMPLE.parents[1] / "plugin-guide.md").read_text()
    assert EXAMPLE.read_text().strip() in guide


def test_added_stage_runs_between_segment_and_reconstruct(colour_manager, tiny_scan, tmp_path):
    raw = _raw()
    recipe = validate_recipe(raw, colour_manager.registry)
    run = tmp_path / "run"
    iostats.reset()
    result = process(tiny_scan.root, recipe, run, colour_manager, raw_recipe=raw)
    info = json.loads((run / "run.json").read_text())
    assert list(info["stages"]) == ["calibrate", "segment", "colour", "reconstruct"]
    # its photos are segmentation's: no photo is decoded twice
    assert max(iostats.decodes.values()) == 1
    colour = json.loads((run / "colour.json").read_text())
    assert result.results["colour"] == colour
    assert [colour["red"], colour["green"], colour["blue"]] == pytest.approx(SPHERE_RGB)
    plant_px = sum(s.area for s in result.silhouettes)
    said = info["stages"]["colour"]["info"]
    assert said == {"counts": {"plant_pixels": plant_px}, "figures": {}, "warnings": []}
    assert result.volume is not None and result.reports["colour"].counts["plant_pixels"] > 0

    # Again: loaded from the cache, with its report, and the stages after it too.
    process(tiny_scan.root, recipe, run, colour_manager, raw_recipe=raw)
    info = json.loads((run / "run.json").read_text())
    assert info["stages"]["colour"]["cached"] and info["stages"]["reconstruct"]["cached"]
    assert info["stages"]["colour"]["info"] == said


def test_added_stage_names_the_views_it_leaves_out(colour_manager, tiny_scan, tmp_path):
    raw = _raw()
    raw["colour"]["params"] = {"min_plant_px": 10**6}  # more than any tiny view has
    recipe = validate_recipe(raw, colour_manager.registry)
    result = process(tiny_scan.root, recipe, tmp_path / "run", colour_manager, raw_recipe=raw)
    warned = result.reports["colour"].warnings_about(code="few-plant-pixels")
    assert [w.view for w in warned] == [s.view.index for s in result.silhouettes]


def test_a_recipe_without_the_section_skips_it(colour_manager, tiny_scan, tmp_path):
    raw = _raw(colour=False)
    recipe = validate_recipe(raw, colour_manager.registry)
    process(tiny_scan.root, recipe, tmp_path / "run", colour_manager, raw_recipe=raw)
    info = json.loads((tmp_path / "run/run.json").read_text())
    assert "colour" in info["skipped"] and "reconstruct" in info["stages"]
    assert not (tmp_path / "run/colour.json").exists()


def test_the_section_is_unknown_without_the_plugin(colour_manager):
    module = sys.modules["plantscan_colour"]
    colour_manager.unregister(module)
    try:
        assert "colour" not in colour_manager.registry.steps.sections
        with pytest.raises(RecipeError) as e:
            validate_recipe(_raw(), colour_manager.registry)
        assert [p for p, _ in e.value.errors] == ["colour"]
    finally:
        colour_manager.register(module, name="plantscan_colour")


def test_a_step_cannot_take_a_section_twice(colour_manager):
    step = colour_manager.registry.steps["colour"]
    with pytest.raises(PluginError, match="already has a step 'colour'"):
        colour_manager.registry.add_step(step)


def test_a_step_gets_the_photos_at_the_reduction_it_names(colour_manager, tiny_scan, tmp_path):
    import dataclasses
    import types

    from plantscan_core.hookspecs import hookimpl

    module = sys.modules["plantscan_colour"]
    seen = {}

    class HalfSizeColour(module.MeanColour):
        name = "half-size-colour"

        def measure(self, photos, silhouettes):
            seen["reduce"], seen["shape"] = photos.reduce, photos.image(0).shape
            return {}

    step = dataclasses.replace(module.COLOUR_STEP, section="colour_half", photos=2,
                               run=lambda plugin, run: plugin.measure(run.context.photos, None))
    plugin = types.SimpleNamespace()

    @hookimpl
    def plantscan_register_stages(registry):
        registry.add_step(step, after="colour")
        registry.add(HalfSizeColour)

    plugin.plantscan_register_stages = plantscan_register_stages
    colour_manager.register(plugin, name="half")
    try:
        raw = _raw()
        raw["colour_half"] = {"plugin": "half-size-colour"}
        recipe = validate_recipe(raw, colour_manager.registry)
        process(tiny_scan.root, recipe, tmp_path / "run", colour_manager, raw_recipe=raw)
    finally:
        colour_manager.unregister(plugin)
    assert seen == {"reduce": 2, "shape": (32, 48, 3)}  # the tiny rig's 96 x 64 at 1/2

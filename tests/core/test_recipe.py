"""Recipe validation: every error at once with its path; overrides; plugin resolution."""

from __future__ import annotations

import pytest
import yaml

from plantscan_core.cli import main
from plantscan_core.errors import RecipeError
from plantscan_core.recipe import apply_overrides, load_recipe, validate_recipe
from plantscan_core.testing import tiny_recipe


def test_three_mistakes_are_reported_together(tiny_rig_manager):
    raw = tiny_recipe()
    raw["scan"]["images_per_revolution"] = 0              # 1: out of range
    raw["scan"]["cameras"][1]["plugin"] = "no-such-cam"    # 2: unknown plugin
    raw["scan"]["turntable"]["params"] = {"speed": 3}      # 3: unknown parameter
    with pytest.raises(RecipeError) as info:
        validate_recipe(raw, tiny_rig_manager.registry)
    paths = [p for p, _ in info.value.errors]
    assert "scan.images_per_revolution" in paths
    assert "scan.cameras.1.plugin" in paths
    assert "scan.turntable.params.speed" in paths
    assert len(paths) == 3
    msg = dict(info.value.errors)["scan.cameras.1.plugin"]
    assert "available: tiny" in msg


def test_cli_recipe_check_prints_all_three_and_fails(tmp_path, capsys, monkeypatch,
                                                     tiny_rig_manager):
    from plantscan_core import plugins

    monkeypatch.setattr(plugins, "_default", tiny_rig_manager)
    raw = tiny_recipe()
    raw["scan"]["image_size"] = [4, 4]
    raw["scan"]["cameras"][0]["plugin"] = "nope"
    raw["calibrate"] = {"plugin": "no-calibrator", "params": {}}
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(raw))
    rc = main(["recipe", "check", str(f)])
    err = capsys.readouterr().err
    assert rc != 0
    assert "scan.image_size: " in err
    assert "scan.cameras.0.plugin: no camera plugin named 'nope'; available: tiny" in err
    assert "calibrate.plugin: no calibrator plugin named 'no-calibrator'" in err
    assert "3 error(s)" in err


def test_protocol_errors(tiny_rig_manager):
    raw = tiny_recipe()
    raw["scan"]["tilts_deg"] = [0, 30, 120]
    with pytest.raises(RecipeError) as info:
        validate_recipe(raw, tiny_rig_manager.registry)
    msgs = dict(info.value.errors)
    assert "3 tilts need a tilt_arm axis" in msgs["scan.tilt_arm"]
    assert "120" in msgs["scan.tilts_deg.2"]


def test_overrides_apply_and_are_validated(tiny_rig_manager):
    raw = apply_overrides(tiny_recipe(), ["scan.image_size=[120,80]", "scan.cameras.0.name=left",
                                          "plant.id=p-42"])
    recipe = validate_recipe(raw, tiny_rig_manager.registry)
    assert recipe.scan.image_size == (120, 80)
    assert recipe.scan.cameras[0].name == "left"
    assert recipe.plant.id == "p-42"
    with pytest.raises(RecipeError, match="scan.cameras.5"):
        apply_overrides(tiny_recipe(), ["scan.cameras.5.name=x"])
    with pytest.raises(RecipeError, match="scan.images_per_revolution"):
        validate_recipe(apply_overrides(tiny_recipe(), ["scan.images_per_revolution=-3"]),
                        tiny_rig_manager.registry)


def test_plugin_names_never_resolve_as_import_paths(tiny_rig_manager):
    raw = tiny_recipe()
    raw["scan"]["turntable"]["plugin"] = "plantscan_core.testing:TinyAxis"
    with pytest.raises(RecipeError, match="no axis plugin named"):
        validate_recipe(raw, tiny_rig_manager.registry)


def test_missing_file_and_bad_yaml_are_named(tmp_path):
    with pytest.raises(RecipeError, match="nope.yaml"):
        load_recipe(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("scan: [unclosed")
    with pytest.raises(RecipeError, match="not valid YAML"):
        load_recipe(bad)


def test_schema_command_prints_json_schema(capsys):
    import json

    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert "scan" in schema["properties"]

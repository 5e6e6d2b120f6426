"""Shipped recipes by name from any folder; the positional recipe of ``plantscan scan``."""

from __future__ import annotations

import json

from plantscan_core.cli import main


def test_shipped_name_works_outside_the_checkout(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no recipes/ folder here
    assert main(["recipe", "check", "plastic-dicot"]) == 0
    assert "plastic-dicot: OK" in capsys.readouterr().out
    assert main(["recipe", "list"]) == 0
    names = capsys.readouterr().out.split()
    assert {"plastic-dicot", "wheat", "sorghum"} <= set(names)


def test_a_checkout_path_used_elsewhere_points_to_the_shipped_name(tmp_path, monkeypatch,
                                                                   capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["recipe", "check", "recipes/plastic-dicot.yaml"]) != 0
    err = capsys.readouterr().err
    assert "recipes/plastic-dicot.yaml: no such file" in err and "use `plastic-dicot`" in err


def test_scan_takes_the_recipe_as_positional_argument_or_option(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["scan", "plastic-dicot", "--out", "s", "--dry-run"]) == 0
    positional = capsys.readouterr().out
    assert main(["scan", "--recipe", "plastic-dicot", "--out", "s", "--dry-run"]) == 0
    assert capsys.readouterr().out == positional and "plant" in positional
    assert main(["scan", "--out", "s", "--dry-run"]) != 0
    assert "RECIPE: required" in capsys.readouterr().err
    assert main(["scan", "wheat", "--recipe", "plastic-dicot", "--dry-run"]) != 0
    assert "given twice" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()  # a dry run writes nothing


def test_recipe_schema_is_the_schema_command(capsys):
    assert main(["recipe", "schema"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert main(["schema"]) == 0
    assert json.loads(capsys.readouterr().out) == a

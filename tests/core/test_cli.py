"""The ``plantscan`` command: every command and subcommand prints its own help."""

from __future__ import annotations

import argparse

import pytest

from plantscan_core.cli import EXIT_USER_ERROR, build_parser, main, profile_table


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """(words, parser) of every command and subcommand below ``parser``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield prefix + (name,), sub
                yield from _commands(sub, prefix + (name,))


COMMANDS = [words for words, _ in _commands(build_parser())]


def test_the_list_covers_the_core_and_the_plugins_commands():
    assert {("recipe",), ("recipe", "check"), ("process",), ("demo",)} <= set(COMMANDS)
    assert ("import", "colmap") in COMMANDS  # added by the hull plugin


@pytest.mark.parametrize("words", COMMANDS, ids=" ".join)
def test_every_command_prints_its_own_help(words, capsys):
    with pytest.raises(SystemExit) as e:
        main([*words, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: plantscan {' '.join(words)}")


GROUPS = sorted({words[:-1] for words in COMMANDS if len(words) > 1})


@pytest.mark.parametrize("words", GROUPS, ids=" ".join)
def test_a_command_without_its_action_prints_its_own_help(words, capsys):
    # `plantscan recipe` once printed the help of `plantscan batch` (a lambda bound late)
    assert main(list(words)) == EXIT_USER_ERROR
    assert capsys.readouterr().out.startswith(f"usage: plantscan {' '.join(words)}")


def test_profile_counts_each_stage_s_warnings():
    info = {"timings_s": {"segment": 1.0, "measure": 2.0, "total": 3.0},
            "cpu_s": {"segment": 1.5, "measure": 2.0, "total": 3.5},
            "peak_rss_mb": {"segment": 100, "measure": 120, "total": 120},
            "stages": {"segment": {"cached": True, "info": {"warnings": []}},
                       "measure": {"cached": False, "info": {"warnings": [
                           {"code": "thick-leaf", "message": "leaf 3", "leaf": 3}] * 2}}}}
    rows = {line.split()[0]: line.split()[1:] for line in profile_table(info).splitlines()}
    assert rows["segment"] == ["1.00", "1.50", "100", "yes"]
    assert rows["measure"] == ["2.00", "2.00", "120", "2"]


def test_profile_names_exporters_by_their_plugin():
    # `--profile` listed export.0 ... export.5: which was the slow one?
    info = {"timings_s": {"export.0": 0.5, "export.1": 2.0, "total": 2.5},
            "stages": {"export.0": {"plugin": "csv"}, "export.1": {"plugin": "html-report"}}}
    labels = [line.split()[:2] for line in profile_table(info).splitlines()[1:-1]]
    assert labels == [["export", "csv"], ["export", "html-report"]]
    assert "export.0" not in profile_table(info)

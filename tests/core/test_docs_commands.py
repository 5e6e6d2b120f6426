"""Every shell command the docs show works as shown, against the installed CLI.

Commands are taken from README.md, docs/**/*.md and the shipped recipes'
comments: lines of fenced code blocks and inline code spans that start with
``plantscan``, ``make``, ``pip install`` or ``python <script>``.  Each
``plantscan`` command is parsed by the real argument parser (an unknown command
or option, a missing required argument fail), then:

* cheap, read-only commands run for real (``plugins``, ``recipe check|list|schema``,
  ``schema``), and ``scan`` runs with ``--dry-run`` (the recipe is checked in
  full; nothing moves, nothing is written);
* every other command (``process``, ``demo``, ``batch``...) runs ``--help``:
  parsing above already checked its options.

They run in an empty folder, not in the checkout: a shipped recipe is named, a
user's own recipe file (``my-recipe.yaml``) is a copy of a shipped one put there.
Synopsis placeholders (``SCAN``, ``RECIPE``, ``[--set PATH=VALUE ...]``) and
fragments (``plantscan scan ... --resume``) are only parsed for their options.
"""

from __future__ import annotations

import argparse
import functools
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from plantscan_core.cli import build_parser, main
from plantscan_core.recipe import RECIPES_DIR

REPO = Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
RUN = {("plugins",), ("recipe", "check"), ("recipe", "list"), ("recipe", "schema"), ("schema",)}
PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z0-9_]*(?:\.\.\.)?|\.\.\.|<[^>]*>|[A-Z_]+=[A-Z_]+)$")


def _fenced_lines(text: str) -> list[str]:
    lines = []
    for block in re.findall(r"^```(?:sh|bash|console|shell)?\n(.*?)^```", text, re.S | re.M):
        for line in re.sub(r"\s*\\\n\s*", " ", block).splitlines():
            lines.append(line.strip().removeprefix("$ "))
    return lines


def doc_commands() -> list[tuple[str, str]]:
    """(where, command) of every command shown in the docs and the recipes' comments."""
    found: dict[str, str] = {}
    sources = [(p, p.read_text()) for p in PAGES if p.name != "benchmarks.md"]  # assembled copy
    for path, text in sources:
        rel = path.relative_to(REPO)
        candidates = _fenced_lines(text) + re.findall(r"`([^`\n]+)`", text)
        for c in candidates:
            c = c.split(" #", 1)[0].strip()
            if re.match(r"^(plantscan |plantscan$|make |pip install |python (benchmarks|scripts)/)",
                        c):
                found.setdefault(c, str(rel))
    for recipe in sorted(RECIPES_DIR.glob("*.yaml")):
        text = "\n".join(line.lstrip("# ") for line in recipe.read_text().splitlines()
                         if line.startswith("#"))
        for c in re.findall(r"`?(plantscan [^`\n]+?)`?(?:\s{2,}|$|\s+lists)",
                            re.sub(r"\s*\\\n\s*", " ", text), re.M):
            found.setdefault(c.strip(), f"recipes/{recipe.name}")
    return [(where, cmd) for cmd, where in found.items()]


COMMANDS = doc_commands()


def test_the_docs_show_commands():
    commands = [c for _, c in COMMANDS]
    assert sum(c.startswith("plantscan ") for c in commands) >= 20
    assert any(c.startswith("plantscan scan plastic-dicot") for c in commands)


def _subcommand(tokens: list[str]) -> tuple[tuple[str, ...], argparse.ArgumentParser]:
    parser = build_parser()
    path: list[str] = []
    current = parser
    for tok in tokens:
        sub = next((a for a in current._actions if a.__class__.__name__ == "_SubParsersAction"),
                   None)
        if sub is None or tok not in sub.choices:
            break
        path.append(tok)
        current = sub.choices[tok]
    return tuple(path), current


def _options(parser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


@pytest.mark.parametrize("where, command", [pytest.param(w, c, id=f"{w}: {c}"[:90])
                                            for w, c in COMMANDS if c.startswith("plantscan")])
def test_plantscan_command_works_as_shown(where, command, tmp_path, monkeypatch, capsys):
    text = re.sub(r"\s\[[^\]]*\](?=\s|$)", " ", " " + command).strip()  # [optional] synopsis
    argv = shlex.split(text)[1:]
    path, sub = _subcommand(argv)
    assert path or not argv, f"{where}: `{command}`: unknown command {argv[:1]}"
    for tok in argv[len(path):]:
        if tok.startswith("--"):
            assert tok.split("=", 1)[0] in _options(sub), \
                f"{where}: `{command}`: `plantscan {' '.join(path)}` has no option {tok}"
    monkeypatch.chdir(tmp_path)
    args = argv[len(path):]
    # a synopsis (placeholders) or a mention in prose (`plantscan process --profile`: options
    # without the arguments) is checked for its command and options only
    sketch = (any(PLACEHOLDER.match(t) for t in argv) or "*" in text
              or all(t.startswith("-") for t in args))
    if not args or sketch:
        with pytest.raises(SystemExit) as done:  # --help exits 0
            main([*path, "--help"])
        assert done.value.code == 0, f"{where}: `plantscan {' '.join(path)} --help` failed"
        return
    for tok in args:  # a user's own recipe file: a copy of a shipped one
        if tok.endswith(".yaml") and not Path(tok).exists() and "/" not in tok:
            shutil.copy(RECIPES_DIR / "plastic-dicot.yaml", tmp_path / tok)
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{where}: `{command}` does not parse: {capsys.readouterr().err.strip()}"
                    f" (exit {exc.code})")
    if path in RUN:
        rc = main(argv)
    elif path == ("scan",):
        rc = main(argv + ([] if "--dry-run" in argv else ["--dry-run"]))
        assert not any(p for p in tmp_path.iterdir() if p.is_dir()), "a dry run wrote a folder"
    else:
        with pytest.raises(SystemExit) as done:
            main([*path, "--help"])
        rc = done.value.code
    err = capsys.readouterr().err
    assert rc == 0, f"{where}: `{command}` exited {rc}: {err.strip()[-800:]}"


@pytest.mark.parametrize("where, command", [pytest.param(w, c, id=f"{w}: {c}"[:90])
                                            for w, c in COMMANDS if not c.startswith("plantscan")])
def test_other_command_refers_to_what_exists(where, command):
    tokens = shlex.split(command)
    if tokens[0] == "make":
        targets = set(re.findall(r"^([a-z][\w-]*):", (REPO / "Makefile").read_text(), re.M))
        assert set(tokens[1:]) <= targets, f"{where}: `{command}`: no such make target"
    elif tokens[:2] == ["pip", "install"]:
        pyproject = (REPO / "pyproject.toml").read_text()
        extras = set(re.findall(r"^([a-z0-9_-]+) = \[", pyproject.split(
            "[project.optional-dependencies]")[1].split("\n[")[0], re.M))
        for tok in tokens[2:]:
            m = re.match(r"^\.?\[([\w,-]+)\]$", tok.split("plantscan")[-1].lstrip("."))
            if m:
                assert set(m.group(1).split(",")) <= extras, f"{where}: `{command}`: no such extra"
    else:  # python benchmarks/x.py or scripts/x.py
        script = REPO / tokens[1]
        assert script.exists(), f"{where}: `{command}`: {tokens[1]} does not exist"
        rc, err = _script_help(str(script))
        assert rc == 0, f"{where}: `{tokens[1]} --help` failed: {err}"


@functools.cache
def _script_help(script: str) -> tuple[int, str]:
    """``python SCRIPT --help`` once per script (several commands share one)."""
    out = subprocess.run([sys.executable, script, "--help"], capture_output=True, text=True,
                         timeout=120, cwd=REPO)
    return out.returncode, out.stderr[-800:]

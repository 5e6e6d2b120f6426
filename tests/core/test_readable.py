"""The modules issue #20 made readable stay readable: short functions, few parameters.

Limits of the issue: no function longer than 80 lines (docstring included) and none
taking more than 8 parameters (``self`` / ``cls`` not counted); numba kernels take
their scalars as one record (``plantscan_hull.kernels``) instead of long positional
lists. Nested functions count as functions of their own.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = [
    "plugins/plantscan_hull/kernels.py",
    "plugins/plantscan_calib/solver.py",
    "plugins/plantscan_calib/model.py",
    "plugins/plantscan_calib/initialise.py",
    "plugins/plantscan_leaves/segment.py",
    "plugins/plantscan_leaves/measure.py",
    "plantscan_core/steps.py",
]
MAX_LINES = 80
MAX_PARAMS = 8


def _functions(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
            n = len(names) + (a.vararg is not None) + (a.kwarg is not None)
            if names and names[0] in ("self", "cls"):
                n -= 1
            yield node.name, node.lineno, node.end_lineno - node.lineno + 1, n


@pytest.mark.parametrize("module", MODULES)
def test_functions_are_short_and_take_few_parameters(module):
    found = list(_functions(ROOT / module))
    assert found, module  # the module is still where this test looks
    long = [(name, line, n) for name, line, n, _ in found if n >= MAX_LINES]
    wide = [(name, line, k) for name, line, _, k in found if k > MAX_PARAMS]
    assert not long, f"{module}: functions of {MAX_LINES}+ lines (name, line, lines): {long}"
    assert not wide, f"{module}: functions of >{MAX_PARAMS} parameters: {wide}"

"""Every pluggy hook of plantscan.  The contracts are mostly in the docstrings.

Hook calls are not type-checked by pluggy, so ``plantscan_core.plugins``
calls them only through small typed wrappers.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:
    from plantscan_core.plugins import StageRegistry
    from plantscan_core.stages import Stage, StageContext

PROJECT = "plantscan"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def plantscan_register_stages(registry: StageRegistry) -> None:
    """Register stage implementations: call ``registry.add(cls)`` once per class.

    Called once per plugin when the plugin manager loads.  ``cls`` must
    subclass one of the bases in ``plantscan_core.stages`` and set ``name``;
    a (stage, name) pair that another plugin already registered is an error
    naming both distributions.  Return value ignored.
    """


@hookspec
def plantscan_before_stage(stage: str, plugin: Stage, context: StageContext) -> None:
    """Observer: ``stage`` (e.g. ``"segmenter"``) is about to run ``plugin``.  Ignored result."""


@hookspec
def plantscan_after_stage(
    stage: str, plugin: Stage, context: StageContext, seconds: float, cached: bool
) -> None:
    """Observer: ``stage`` finished after ``seconds`` (``cached`` when loaded from the cache)."""


@hookspec
def plantscan_on_stage_error(
    stage: str, plugin: Stage, context: StageContext, error: BaseException
) -> None:
    """Observer: ``stage`` raised ``error`` (it is re-raised afterwards, wrapped in StageError)."""


@hookspec
def plantscan_evaluate(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    """Compare a run folder with a virtual scanner's ``ground_truth`` folder.

    Return a dict of sections (``{"silhouettes": {...}}``) for the stages this
    plugin knows how to evaluate, or None.  Results of all plugins are merged
    into the one JSON object that ``plantscan evaluate`` prints; a section is
    absent when its stage or truth is absent.
    """


@hookspec
def plantscan_add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add sub-commands to the ``plantscan`` CLI (e.g. ``plantscan import colmap``).

    A command sets ``func`` with ``parser.set_defaults(func=...)``; ``func(args)``
    returns the exit status.
    """


@hookspec
def plantscan_warm_up() -> str | None:
    """Do now the one-time work a plugin would otherwise do on its first real use.

    Called by ``plantscan warm-up`` (which ``make setup`` runs): a plugin with
    just-in-time compiled kernels (numba ``cache=True``) runs them once on a
    small input with the argument types a real run passes, so that the first
    scan or processing run reads them from the cache instead of compiling.
    Return one line saying what was done (printed), or None.  Every plugin's
    result is collected; one that raises is reported and the others still run.
    """

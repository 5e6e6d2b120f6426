"""plantscan plugin: reconstructors ``octree-hull``, ``dense-hull``; mesher ``marching-cubes``;
``plantscan import colmap``; the ``hull`` section of ``plantscan evaluate``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from plantscan_core.hookspecs import hookimpl
from plantscan_hull.stages import DenseHull, MarchingCubesMesher, OctreeHull


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(OctreeHull)
    registry.add(DenseHull)
    registry.add(MarchingCubesMesher)


@hookimpl
def plantscan_add_commands(subparsers) -> None:
    from plantscan_hull.colmap import add_import_command

    add_import_command(subparsers)


@hookimpl
def plantscan_evaluate(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    from plantscan_hull.evaluate import evaluate_hull

    section = evaluate_hull(Path(run_dir), Path(truth_dir))
    return None if section is None else {"hull": section}


@hookimpl
def plantscan_warm_up() -> str:
    from plantscan_hull.warmup import warm_up

    return warm_up()

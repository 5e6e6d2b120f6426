"""The Python API (``import plantscan``): what the CLI does, from a script or a notebook.

Every function here is a thin layer over the same code the ``plantscan``
command runs; docs/api.md is the worked example (executed by
``tests/core/test_api_example.py``).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from plantscan_core.data import Calibration, LabelledMesh, Mesh, Silhouette, Silhouettes, Traits
from plantscan_core.errors import DataError, PlantScanError
from plantscan_core.plugins import get_manager
from plantscan_core.recipe import (
    Recipe,
    apply_overrides,
    read_recipe_file,
    resolve_recipe_path,
    validate_recipe,
)
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.stages import RunResult, Stage, StageContext, StageReport

RecipeLike = str | Path | Recipe | dict


def load_recipe(recipe: RecipeLike, overrides: Sequence[str] = ()) -> tuple[Recipe, dict]:
    """A validated recipe and its raw dict, from a shipped name, a file, a dict or a Recipe.

    Parameters
    ----------
    recipe : str, Path, dict or Recipe
        ``"plastic-dicot"`` (a shipped recipe, ``plantscan recipe list``), a YAML
        file, the recipe as a dict (as in YAML), or an already validated ``Recipe``.
    overrides : sequence of str
        ``"PATH=VALUE"`` changes, as ``--set`` on the command line.

    Raises
    ------
    RecipeError
        every error at once, each with its path (``segment.params.alpha: ...``).
    """
    manager = get_manager()
    if isinstance(recipe, Recipe):
        raw = recipe.model_dump(mode="json")
        source = f"recipe {recipe.name!r}"
    elif isinstance(recipe, dict):
        raw, source = copy.deepcopy(recipe), "recipe dict"
    else:
        path = resolve_recipe_path(recipe)
        raw, source = read_recipe_file(path), str(path)
    raw = apply_overrides(raw, list(overrides))
    return validate_recipe(raw, manager.registry, source), raw


def acquire(recipe: RecipeLike, out: str | Path, *, overrides: Sequence[str] = (),
            resume: bool = False, progress: bool = False) -> ScanFolder:
    """Scan with the recipe's rig (real or virtual) into the scan folder ``out``.

    As ``plantscan scan RECIPE --out OUT``: the recipe is checked in full before
    any motor moves; ``resume=True`` continues an interrupted scan.  Returns the
    ``ScanFolder`` (``.views``, ``.read_image(view)``, ``.ground_truth_dir``).
    """
    from plantscan_core.acquire import acquire as _acquire

    recipe_obj, raw = load_recipe(recipe, overrides)
    return _acquire(recipe_obj, Path(out), get_manager(), raw_recipe=raw, resume=resume,
                    progress=progress)


def process(scan: str | Path | ScanFolder, recipe: RecipeLike | None = None,
            out: str | Path | None = None, *, overrides: Sequence[str] = (),
            calibration: str | Path | None = None, progress: bool = False,
            workers: int | None = None) -> RunResult:
    """Process a scan folder into a run folder, as ``plantscan process SCAN``.

    Parameters
    ----------
    scan : path or ScanFolder
    recipe : shipped name, file, dict, Recipe, or None
        None: the recipe stored in the scan's ``scan.yaml`` (the one it was
        scanned with), with ``overrides`` applied.
    out : path or None
        The run folder (default ``SCAN-run`` beside the scan).  Stages whose
        inputs and parameters did not change are read from its cache.
    calibration : path or None
        A saved calibration YAML used instead of calibrating.
    progress : bool
        Show progress bars (for a terminal; a notebook shows them too).

    Returns
    -------
    RunResult
        ``.traits`` (``.to_dataframe()``), ``.labelled``, ``.mesh``,
        ``.calibration``, ``.silhouettes``, ``.volume``, ``.timings``, ``.info``
        (run.json); fields of stages that did not run are None.
    """
    from plantscan_core.pipeline import process as _process

    scan_dir = Path(scan.root if isinstance(scan, ScanFolder) else scan)
    if recipe is None:
        raw = apply_overrides(copy.deepcopy(ScanFolder.open(scan_dir).recipe_dict),
                              list(overrides))
        recipe_obj = validate_recipe(raw, get_manager().registry, f"{scan_dir}/scan.yaml recipe")
    else:
        recipe_obj, raw = load_recipe(recipe, overrides)
    run_dir = Path(out) if out is not None else scan_dir.with_name(scan_dir.name + "-run")
    return _process(scan_dir, recipe_obj, run_dir, get_manager(), raw_recipe=raw,
                    overrides=list(overrides), progress=progress, workers=workers,
                    calibration_path=Path(calibration) if calibration is not None else None)


def load_run(path: str | Path, *, silhouettes: bool = False, volume: bool = False
             ) -> RunResult:
    """Read a run folder written by ``process`` (or ``plantscan process``) back.

    The small results are read: calibration, mesh, labelled mesh, traits, the
    run record (``info``, ``timings``) and every stage's report (``reports``:
    counts, figures, warnings).  ``silhouettes=True`` also reads every
    mask (one bool image per plant view: large for 18 MP scans) and
    ``volume=True`` the hull's field (512 MB at 512^3).  A result whose file is
    absent (its stage did not run) is None.

    Raises
    ------
    DataError
        ``path`` is not a run folder (no ``run.json``), or a file is unreadable.
    """
    from plantscan_core.data import Volume
    from plantscan_core.runfolder import MASKS_DIR, read_mask

    run_dir = Path(path)
    record = run_dir / "run.json"
    if not record.exists():
        raise DataError(f"{run_dir}: not a run folder (no run.json)")
    try:
        info = json.loads(record.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{record}: unreadable ({exc})") from exc
    scan = None
    scan_root = Path(info.get("scan", ""))
    if (scan_root / "scan.yaml").exists():
        scan = ScanFolder.open(scan_root)
    recipe = validate_recipe(copy.deepcopy(info["recipe"]), None, f"{record} recipe") \
        if info.get("recipe") else None
    result = RunResult(run_dir=run_dir, recipe=recipe, scan=scan, info=info)
    result.timings = {k: float(v) for k, v in info.get("timings_s", {}).items() if k != "total"}

    def present(name: str) -> Path | None:
        p = run_dir / name
        return p if p.exists() else None

    try:
        if p := present("calibration.yaml"):
            result.calibration = Calibration.load(p)
        if p := present("mesh.npz"):
            result.mesh = Mesh.load(p)
        if p := present("labelled.npz"):
            result.labelled = LabelledMesh.load(p)
        if p := present("traits.csv"):
            result.traits = Traits.load(p, run_dir / "plant_traits.json")
        if volume and (p := present("volume.npz")):
            result.volume = Volume.load(p)
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{run_dir}: cannot read a result ({type(exc).__name__}: {exc})") from exc
    if silhouettes and scan is not None and (run_dir / MASKS_DIR).is_dir():
        views = scan.views_by_role("plant")
        masks = [(v, run_dir / MASKS_DIR / f"{v.index:05d}.png") for v in views]
        result.silhouettes = Silhouettes([Silhouette(v, read_mask(m)) for v, m in masks
                                          if m.exists()])
    # what every stage said of its work, as the run that wrote the folder had it
    for section, record in info.get("stages", {}).items():
        if isinstance(record, dict) and "info" in record:
            result.reports[section] = StageReport.from_dict(record["info"])
    for name in RunResult.STEP_RESULTS:
        if getattr(result, name) is not None:
            result.results[name] = getattr(result, name)
    return result


def build_stage(stage: str, name: str, params: dict[str, Any] | None = None, *,
                context: StageContext | None = None) -> Stage:
    """One stage implementation, to use on your own arrays.

    ``build_stage("segmenter", "lab-shadow").segment(image, background)`` returns
    a mask; ``build_stage("reconstructor", "octree-hull", {"resolution": 128})``
    a hull carver.  ``stage`` is a stage kind (``plantscan plugins`` lists them
    with their names); ``params`` are checked by the plugin's ``Params``.

    Raises
    ------
    PluginError
        no such (stage, name) is registered (the message lists the valid names).
    pydantic.ValidationError
        a parameter is wrong.
    """
    return get_manager().build(stage, name, params, context)


__all__ = ["load_recipe", "acquire", "process", "load_run", "build_stage", "PlantScanError"]

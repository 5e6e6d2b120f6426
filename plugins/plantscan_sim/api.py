"""``make_scan``: a small virtual scan in one call, through the real acquisition code."""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from plantscan_core.errors import RecipeError
from plantscan_core.recipe import (
    PROCESSING_SECTIONS,
    apply_overrides,
    read_recipe_file,
    resolve_recipe_path,
    validate_recipe,
)
from plantscan_core.scanfolder import ScanFolder

PRESET_RECIPES = {"plastic-dicot": "plastic-dicot", "wheat": "wheat", "sorghum": "sorghum",
                  "mesh": "plastic-dicot", "dicot": "dicot", "rosette": "rosette",
                  "branched": "branched", "grass": "grass", "seedling": "seedling"}


def sim_manager():
    """A plugin manager with only the virtual scanner registered (no entry points loaded)."""
    from plantscan_core.plugins import new_manager
    from plantscan_sim import plugin

    manager = new_manager()
    manager.register(plugin, name="sim", distribution="plantscan")
    return manager


def scan_recipe(
    preset: str = "plastic-dicot",
    *,
    recipe: str | Path | None = None,
    image_size: tuple[int, int] | None = None,
    images_per_revolution: int | None = None,
    calibration_images_per_revolution: int | None = None,
    tilts_deg: Sequence[float] | None = None,
    seed: int | None = None,
    noise_sigma: float | None = None,
    supersampling: int | None = None,
    image_format: str | None = None,
    scene: dict[str, Any] | None = None,
    roles: Sequence[str] | None = None,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """The raw recipe dict ``make_scan`` would run (shipped recipe + these changes)."""
    if recipe is None and preset not in PRESET_RECIPES:
        raise RecipeError([("scan.scene.params.preset", f"unknown plant preset {preset!r}; "
                            f"valid: {', '.join(PRESET_RECIPES)}")], "make_scan")
    path = resolve_recipe_path(recipe or PRESET_RECIPES[preset])
    raw = copy.deepcopy(read_recipe_file(path))
    s = raw.setdefault("scan", {})
    sc = s.setdefault("scene", {"plugin": "sim", "params": {}})
    params = sc.setdefault("params", {}) or {}
    sc["params"] = params
    params["preset"] = preset
    if seed is not None:
        params["seed"] = int(seed)
    if noise_sigma is not None:
        params["noise_sigma"] = float(noise_sigma)
    if supersampling is not None:
        params["supersampling"] = int(supersampling)
    params.update(scene or {})
    if image_size is not None:
        s["image_size"] = [int(image_size[0]), int(image_size[1])]
    if images_per_revolution is not None:
        s["images_per_revolution"] = int(images_per_revolution)
    if tilts_deg is not None:
        s["tilts_deg"] = [float(t) for t in tilts_deg]
    if image_format is not None:
        s["image_format"] = image_format
    if calibration_images_per_revolution is not None or roles is not None:
        r = s.setdefault("roles", {"calibration": {}, "background": {"images_per_revolution": 1},
                                   "plant": {}})
        for name in ("calibration", "background", "plant"):
            r.setdefault(name, {})
            if r[name] is None:
                r[name] = {}
        if calibration_images_per_revolution is not None:
            r["calibration"]["images_per_revolution"] = int(calibration_images_per_revolution)
        if roles is not None:
            for name in ("calibration", "background", "plant"):
                r[name]["enabled"] = name in roles
    return apply_overrides(raw, list(overrides))


def make_scan(
    out_dir: str | Path,
    preset: str = "plastic-dicot",
    *,
    recipe: str | Path | None = None,
    image_size: tuple[int, int] | None = (480, 320),
    images_per_revolution: int | None = 12,
    calibration_images_per_revolution: int | None = None,
    tilts_deg: Sequence[float] | None = None,
    seed: int | None = None,
    noise_sigma: float | None = None,
    supersampling: int | None = None,
    image_format: str | None = None,
    scene: dict[str, Any] | None = None,
    roles: Sequence[str] | None = None,
    overrides: Sequence[str] = (),
    resume: bool = False,
    stop_after: int | None = None,
    manager=None,
) -> ScanFolder:
    """Acquire a virtual scan into ``out_dir`` with the real ``acquire`` orchestrator.

    Starts from the shipped recipe of ``preset`` (``recipes/<preset>.yaml``) or
    ``recipe``, changes what the arguments set (``None`` keeps the recipe's
    value; ``calibration_images_per_revolution=None`` follows
    ``images_per_revolution`` when that is given), then ``overrides``
    (``"scan.scene.params.board=charuco"``).  Only the
    scan section is checked against plugins, so it works before the processing
    plugins exist; the full recipe is stored in ``scan.yaml``.

    Returns the ``ScanFolder``; ``ground_truth/`` holds the truth (docs/formats.md).
    """
    from plantscan_core.acquire import acquire

    if calibration_images_per_revolution is None and images_per_revolution is not None:
        calibration_images_per_revolution = images_per_revolution
    raw = scan_recipe(preset, recipe=recipe, image_size=image_size,
                      images_per_revolution=images_per_revolution,
                      calibration_images_per_revolution=calibration_images_per_revolution,
                      tilts_deg=tilts_deg, seed=seed, noise_sigma=noise_sigma,
                      supersampling=supersampling, image_format=image_format, scene=scene,
                      roles=roles, overrides=overrides)
    if len(raw["scan"].get("tilts_deg") or [0]) > 1 and not raw["scan"].get("tilt_arm"):
        raw["scan"]["tilt_arm"] = {"plugin": "sim", "params": {"axis": "tilt"}}
    manager = manager if manager is not None else sim_manager()
    scan_only = {k: v for k, v in raw.items() if k not in PROCESSING_SECTIONS and k != "export"}
    recipe_obj = validate_recipe(scan_only, manager.registry, "make_scan recipe")
    try:
        full = validate_recipe(copy.deepcopy(raw), None, "make_scan recipe")
    except RecipeError:
        full = recipe_obj
    return acquire(full, Path(out_dir), manager, raw_recipe=raw, resume=resume,
                   stop_after=stop_after)

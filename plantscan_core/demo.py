"""``plantscan demo``: a virtual scan of a plant, the whole pipeline, the report, the errors."""

from __future__ import annotations

import json
from pathlib import Path

from plantscan_core.errors import RecipeError
from plantscan_core.plugins import get_manager
from plantscan_core.recipe import (
    apply_overrides,
    check_plugins,
    read_recipe_file,
    resolve_recipe_path,
    validate_recipe,
)
from plantscan_core.steps import CORE_TABLE


def run_demo(out: Path, overrides: list[str], recipe_name: str = "plastic-dicot",
             display=None) -> int:
    """Scan (virtual), process and evaluate; print where the report is and the trait errors.

    Processing stops before the first stage whose plugin is not installed,
    saying which one; the scan part of the recipe must be complete.
    """
    from plantscan_core.acquire import acquire
    from plantscan_core.pipeline import process

    manager = get_manager()
    path = resolve_recipe_path(recipe_name)
    raw = apply_overrides(read_recipe_file(path), overrides)
    if not raw.get("store"):  # the demo keeps its run in the zero-set-up SQLite store
        raw["store"] = {"plugin": "sqlite", "params": {"path": "results.sqlite"}}
    recipe = validate_recipe(raw, None, str(path))
    errors = check_plugins(recipe, manager.registry)
    scan_errors = [e for e in errors if e[0].startswith("scan.")]
    if scan_errors:
        raise RecipeError(scan_errors, str(path))
    missing = [e for e in errors if not e[0].startswith("scan.")]
    if missing:
        order = CORE_TABLE.sections  # pipeline order, exporters and store included
        first = min(order.index(e[0].split(".")[0]) for e in missing)
        for section in order[first:]:
            if section == "export":
                raw["export"] = [s for s in raw.get("export") or []
                                 if not any(e[0].startswith("export.") for e in missing)]
            else:
                raw[section] = None
        for p, msg in missing:
            print(f"demo: {p}: {msg}")
        print(f"demo: processing stops before '{order[first]}' (plugin missing, see above)")
        recipe = validate_recipe(raw, manager.registry, str(path))

    out = Path(out)
    scan_dir, run_dir = out / "scan", out / "run"
    resume = (scan_dir / "scan.yaml").exists()
    print(f"demo: virtual scan -> {scan_dir}{' (resuming)' if resume else ''}")
    if display is None:
        from plantscan_core.progress import Display

        display = Display("auto")
    scan = acquire(recipe, scan_dir, manager, raw_recipe=raw, resume=resume, progress=display)
    print(f"demo: {len(scan.views)} images; processing -> {run_dir}")
    result = process(scan_dir, recipe, run_dir, manager, raw_recipe=raw, overrides=overrides,
                     progress=display)
    from plantscan_core.cli import profile_table

    print(profile_table(result.info))
    metrics = {}
    if scan.ground_truth_dir.is_dir():
        with display.step("evaluate against the truth"):
            metrics = manager.evaluate(run_dir, scan.ground_truth_dir)
    display.close()
    (run_dir / "evaluation.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
    report = run_dir / "report.html"
    if report.exists():
        print(f"demo: report {report.resolve()}")
    traits = metrics.get("traits")
    if traits:
        mre = traits.get("mean_relative_error", {})
        print("demo: trait errors against truth (mean relative error): " + ", ".join(
            f"{k} {100 * v:.2f} %" for k, v in mre.items()))
        inst = traits.get("instances")
        if inst:
            print(f"demo: leaves found {inst['found']} of {inst['truth']} truth leaves, "
                  f"{inst['measured']} measured: merged {inst['merged']}, split {inst['split']} "
                  f"({inst['split_pieces']} extra pieces of split leaves), extra {inst['extra']} "
                  f"(debris {inst['debris_area_mm2']:.0f} mm², "
                  f"{100 * inst['debris_share']:.1f} % of the measured leaf area), "
                  f"missed {inst['missed']}")
        else:
            print(f"demo: leaves found {traits.get('leaves_found')} of "
                  f"{traits.get('leaves_truth')}, merged {traits.get('leaves_merged')}")
        warned = traits.get("leaves_warned", 0)
        if warned:
            quiet = traits.get("mean_relative_error_unwarned", {})
            print(f"demo: {warned} of the {traits.get('leaves_found')} leaves matched to the "
                  "truth are warned about (see the report); the others: "
                  + ", ".join(f"{k} {100 * v:.2f} %" for k, v in quiet.items()))
    else:
        print("demo: no trait errors (the leaf stages did not run)")
    print(f"demo: evaluation {run_dir / 'evaluation.json'}")
    stored = result.info.get("stored")
    if stored:
        print(f"demo: {stored['leaves']} leaves of {stored['plant_id']} stored in "
              f"{stored['store']}; try: plantscan query --db {stored['store']} --level leaf")
    return 0

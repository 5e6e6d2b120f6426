"""The store as the last stage of a real run, and ``plantscan store`` / ``plantscan query``.

One small virtual scan is made with a sample sheet (``plantscan scan
--sample-sheet``: the metadata go into ``scan.yaml``) and processed once per
module with the cheap recipe of the batch tests (exact calibration and masks, a
coarse hull) and ``store: {plugin: sqlite}``; what the store holds is compared
with the run folder's own ``traits.csv`` and the sheet.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from plantscan_store import Store

from plantscan_core.cli import main
from plantscan_core.data import Traits

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "batch"))
from batch_fixtures import PROCESSING, SCAN_ARGS  # noqa: E402

CLOCK = "2026-05-06T08:30:00Z"  # the virtual scanner's clock: day 5 of the experiment
SHEET = ("plant_id,genotype,treatment,replicate,sowing_date,factor.watering,study_id\n"
         "dicot-7,Col-0,drought,2,2026-05-01,30%,drought-2026\n")


@pytest.fixture(scope="module")
def stored_run(tmp_path_factory):
    """(scan folder, run folder, SQLite store, sheet) of one plant scanned with a sample sheet
    (``plantscan scan --sample-sheet``) and processed with the recipe's ``store:``."""
    from plantscan_sim import scan_recipe

    root = tmp_path_factory.mktemp("store-run")
    raw = scan_recipe(seed=1, overrides=["plant.id=dicot-7", "plant.species=plastic dicot",
                                         f"scan.scene.params.clock_start={CLOCK}"],
                      **SCAN_ARGS)
    raw.update(PROCESSING)
    raw["export"] = [{"plugin": "csv", "params": {"parquet": False}}]
    raw["store"] = {"plugin": "sqlite", "params": {"path": "results.sqlite"}}
    recipe = root / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(raw, sort_keys=False))
    sheet = root / "sheet.csv"
    sheet.write_text(SHEET)
    scan = root / "scans" / "dicot-7"
    assert main(["scan", "--recipe", str(recipe), "--out", str(scan),
                 "--sample-sheet", str(sheet)]) == 0
    run = root / "runs" / "dicot-7"
    assert main(["process", str(scan), "--out", str(run)]) == 0  # the scan's own recipe
    return scan, run, root / "runs" / "results.sqlite", sheet


def test_a_processed_run_lands_in_the_store_with_its_sheet_metadata(stored_run):
    scan, run, db, _ = stored_run
    traits = Traits.load(run / "traits.csv", run / "plant_traits.json")
    info = json.loads((run / "run.json").read_text())
    assert info["stored"]["leaves"] == len(traits.leaves) > 0
    with Store(db) as store:
        leaves = store.leaf_traits(study="drought-2026", genotype="Col-0")
        plants = store.plant_traits()
    assert list(leaves.leaf_id) == [leaf.leaf_id for leaf in traits.leaves]
    assert list(leaves.area_mm2) == pytest.approx([leaf.area_mm2 for leaf in traits.leaves])
    row = plants.iloc[0]
    assert (row.plant_id, row.treatment, row.replicate, row["factor.watering"]) == \
        ("dicot-7", "drought", 2, "30%")
    assert row.total_leaf_area_mm2 == pytest.approx(traits.plant["total_leaf_area_mm2"])
    # the scan time is the scan's own (the virtual scanner's clock, UTC), not processing's
    assert row.scan_time == pd.Timestamp("2026-05-06 08:30:00")
    assert row.days_after_sowing == pytest.approx(5 + 8.5 / 24)
    recorded = yaml.safe_load((scan / "scan.yaml").read_text())
    assert recorded["plant"]["genotype"] == "Col-0" and recorded["plant"]["replicate"] == 2
    assert recorded["experiment"]["study_id"] == "drought-2026"
    # every leaf has its centroid (for matching leaves between days)
    assert leaves.centroid_z_mm.notna().all()
    # the same run stored again from its folder (as after a batch) is the same run
    assert main(["store", str(run), "--db", str(db)]) == 0
    with Store(db) as store:
        assert store.counts()["runs"] == 1


def test_store_and_query_commands_on_both_backends(stored_run, store_target, tmp_path, capsys):
    _, run, _, sheet = stored_run
    for _ in range(2):  # stored twice: once in the store
        assert main(["store", str(run.parent), "--db", store_target,
                     "--sample-sheet", str(sheet)]) == 0
    assert "the store holds 1 runs of 1 plants" in capsys.readouterr().out
    out = tmp_path / "leaves.parquet"
    assert main(["query", "--db", store_target, "--level", "leaf", "--genotype", "Col-0",
                 "--out", str(out)]) == 0
    df = pd.read_parquet(out)
    traits = Traits.load(run / "traits.csv")
    assert list(df.area_mm2) == pytest.approx([leaf.area_mm2 for leaf in traits.leaves])
    assert set(df.study_id) == {"drought-2026"}
    assert main(["query", "--db", store_target, "--genotype", "Ler"]) == 0
    assert "no rows match" in capsys.readouterr().out
    assert main(["query", "--db", store_target, "--since", "May 4th"]) == 2
    assert "'May 4th' is not a date (YYYY-MM-DD)" in capsys.readouterr().err


def test_store_refuses_a_folder_without_runs(tmp_path, capsys):
    assert main(["store", str(tmp_path), "--db", str(tmp_path / "r.sqlite")]) == 2
    assert "neither a run folder nor a folder of run folders" in capsys.readouterr().err

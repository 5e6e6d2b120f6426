"""Plant and experiment metadata: the recipe's sections, sample sheets and their errors."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest

from plantscan_core.cli import main
from plantscan_core.metadata import (
    ExperimentSpec,
    PlantSpec,
    SampleSheetError,
    check_plant_consistency,
    load_sample_sheet,
    resolve_metadata,
)
from plantscan_core.recipe import apply_overrides, validate_recipe
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.testing import tiny_recipe


def _scan(root: Path, plant_id: str, **plant) -> Path:
    ScanFolder.create(root, {"plant_id": plant_id, "plant": {"id": plant_id, **plant}})
    return root


def test_the_recipe_takes_miappe_fields_from_set():
    # the new user's first try (issue 25): --set plant.genotype=Col-0
    raw = apply_overrides(tiny_recipe(), ["plant.genotype=Col-0", "plant.sowing_date=2026-05-01",
                                          "plant.factors.watering=30%", "plant.replicate=2",
                                          "experiment.study_id=drought-1"])
    recipe = validate_recipe(raw)
    assert recipe.plant.genotype == "Col-0"
    assert recipe.plant.sowing_date == dt.date(2026, 5, 1)
    assert recipe.plant.factors == {"watering": "30%"} and recipe.plant.replicate == 2
    assert recipe.experiment.study_id == "drought-1"


def test_bad_metadata_in_a_recipe_is_named():
    raw = apply_overrides(tiny_recipe(), ["plant.sowing_date=20260501", "plant.replicate=0",
                                          "plant.genotpye=Col-0"])
    with pytest.raises(Exception) as err:
        validate_recipe(raw)
    text = str(err.value)
    assert "plant.sowing_date: Value error, 20260501 is not a date (write it as YYYY-MM-DD)" \
        in text
    assert "plant.replicate: Input should be greater than or equal to 1" in text
    assert "plant.genotpye: Extra inputs are not permitted" in text


def test_resolution_order_recipe_then_scan_then_sheet(tmp_path):
    scan = _scan(tmp_path / "day1" / "P1", "P1", genotype="Col-0", treatment="")
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("scan,treatment,replicate,factor.watering,extra.tray\n"
                     "day1/P1,drought,2,30%,T7\n")
    recipe_plant = PlantSpec(id="plant", species="Arabidopsis thaliana", genotype="Ler",
                             treatment="control")
    md = load_sample_sheet(sheet).metadata_for(recipe_plant, ExperimentSpec(study_id="S1"),
                                               scan, ScanFolder.open(scan).info)
    p = md.plant
    # species from the recipe, id and genotype from the scan, the rest from the sheet
    assert (p.id, p.species, p.genotype, p.treatment, p.replicate) == \
        ("P1", "Arabidopsis thaliana", "Col-0", "drought", 2)
    assert p.factors == {"watering": "30%"} and p.extra == {"tray": "T7"}
    assert md.experiment.study_id == "S1"


def test_rows_by_plant_id_apply_to_every_scan_of_the_plant(tmp_path):
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("plant_id,genotype,sowing_date\nP1,Col-0,2026-05-01\nP2,Ler,2026-05-02\n")
    s = load_sample_sheet(sheet)
    for day in (1, 2):
        scan = _scan(tmp_path / f"day{day}" / "P2", "P2")
        md = s.metadata_for(PlantSpec(), ExperimentSpec(), scan, ScanFolder.open(scan).info)
        assert (md.plant.id, md.plant.genotype, md.plant.sowing_date) == \
            ("P2", "Ler", dt.date(2026, 5, 2))


def test_a_bad_sheet_names_every_problem_before_anything_runs(tmp_path):
    # the four mistakes of issue 25, in one sheet: every one named with its line
    _scan(tmp_path / "P1", "P1")
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("scan,plant_id,genotype,sowing_date,genotpye\n"
                     "P1,P1,Col-0,2026-05-01,x\n"
                     "P9,P9,Col-0,2026-05-01,\n"
                     ",P1,Ler,2026-05-01,\n"
                     ",P5,Col-0,01/05/2026,\n"
                     "P1,P1,Col-0,,\n")
    with pytest.raises(SampleSheetError) as err:
        load_sample_sheet(sheet)
    messages = [f"{w}: {m}" for w, m in err.value.errors]
    assert messages == [
        f"{sheet}:1: column 5 'genotpye': unknown column; valid: scan, plant_id, species, "
        "genotype, accession, biological_material_id, treatment, replicate, sowing_date, "
        "investigation_id, investigation_title, study_id, study_title, description, location, "
        "start_date, factor.NAME, extra.KEY",
        f"{sheet}:3: scan 'P9': no such scan folder ({tmp_path / 'P9'})",
        f"{sheet}:5: column 'sowing_date': '01/05/2026' is not a date (write it as YYYY-MM-DD)",
        f"{sheet}:6: scan '{tmp_path / 'P1'}' already has a row (line 2)",
        f"{sheet}:4: plant_id 'P1' has genotype 'Ler' here but 'Col-0' on line 2: one plant "
        "id is one plant (give the other plant its own id)",
    ]
    # a scan that is to be made (plantscan scan) need not exist yet
    sheet.write_text("scan,plant_id\nP9,P9\n")
    assert load_sample_sheet(sheet, require_scans=False).rows[0].plant_id == "P9"


def test_the_cli_refuses_a_bad_sheet_before_processing(tmp_path, capsys):
    scan = _scan(tmp_path / "P1", "P1")
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("scan,sowing_date\nP1,next tuesday\n")
    out = tmp_path / "run"
    assert main(["process", str(scan), "--recipe", str(_recipe_file(tmp_path)),
                 "--sample-sheet", str(sheet), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{sheet}:2: column 'sowing_date': 'next tuesday' is not a date (write it as " \
        "YYYY-MM-DD)" in err
    assert not out.exists()


def _recipe_file(tmp_path: Path) -> Path:
    import yaml
    from plantscan_sim import scan_recipe

    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(scan_recipe()))
    return path


def test_two_scans_cannot_make_one_plant_two_genotypes():
    a = resolve_metadata(PlantSpec(id="P1", genotype="Col-0"), ExperimentSpec(study_id="S"))
    b = resolve_metadata(PlantSpec(id="P1", genotype="Ler"), ExperimentSpec(study_id="S"))
    c = resolve_metadata(PlantSpec(id="P1", genotype="Ler"), ExperimentSpec(study_id="T"))
    assert check_plant_consistency([("scan-a", a), ("scan-b", b), ("scan-c", c)]) == [
        ("scan-b", "plant 'P1' has genotype 'Ler' but 'Col-0' in scan-a")]


def test_batch_checks_the_sheet_against_every_scan_before_any_work(tmp_path):
    from plantscan_core.batch import sheet_metadata
    from plantscan_core.recipe import validate_recipe

    a = _scan(tmp_path / "day1" / "A", "P1", genotype="Col-0")
    b = _scan(tmp_path / "day2" / "A", "P1")
    sheet = tmp_path / "sheet.csv"
    # the second day's scan is given another genotype: the same plant cannot change
    sheet.write_text("scan,genotype\nday2/A,Ler\n")
    recipe = validate_recipe(tiny_recipe())
    with pytest.raises(SampleSheetError) as err:
        sheet_metadata(sheet, [a, b], recipe)
    assert err.value.errors == [(str(b), f"plant 'P1' has genotype 'Ler' but 'Col-0' in {a}")]
    sheet.write_text("scan,treatment\nday2/A,drought\nday1/A,drought\n")
    got = sheet_metadata(sheet, [a, b, tmp_path / "not-a-scan"], recipe)
    assert [(m.plant.genotype, m.plant.treatment) for m in got[:2]] == [("Col-0", "drought"),
                                                                       ("", "drought")]
    assert got[2] is None  # an unreadable scan fails alone later, as without a sheet


def test_yaml_dates_in_a_raw_recipe_go_into_run_json_as_text():
    # `sowing_date: 2026-05-01` unquoted is a date to YAML; run.json keeps the raw recipe
    import json

    from plantscan_core.data import plain

    raw = {"plant": {"sowing_date": dt.date(2026, 5, 1)},
           "scan": {"scene": {"params": {"clock_start": dt.datetime(2026, 5, 6, 8, 30)}}}}
    assert json.loads(json.dumps(plain(raw))) == {
        "plant": {"sowing_date": "2026-05-01"},
        "scan": {"scene": {"params": {"clock_start": "2026-05-06T08:30:00"}}}}

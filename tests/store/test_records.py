"""Reading run folders into records: what the run recorded, corrected by a sample sheet."""

from __future__ import annotations

import json

import pytest
from plantscan_store.records import find_run_dirs, record_from_run_dir

from plantscan_core.errors import DataError
from plantscan_core.metadata import load_sample_sheet


def _run_folder(root, plant="P1", genotype="Ler"):
    """A run folder as the pipeline writes it, its scan folder long gone (archived)."""
    root.mkdir(parents=True)
    (root / "run.json").write_text(json.dumps({
        "plantscan_version": "0.1.0", "scan": str(root.parent / "gone" / plant),
        "plant_id": plant,
        "metadata": {"plant": {"id": plant, "genotype": genotype, "treatment": "control"},
                     "experiment": {"study_id": "S1"}},
        "scan_record": {"uid": "u1", "path": "/archive/P1", "acquired_at":
                        "2026-05-06T10:30:00+02:00", "protocol": "paper-72", "views": 72},
        "recipe": {"name": "r"},
        "stages": {"measure": {"plugin": "leaf-geometry", "params": {}, "info": {
            "warnings": [{"code": "thick-leaf", "message": "leaf 1 is thick", "leaf": 1}]}},
                   "export.0": {"plugin": "csv", "params": {}}}}))
    (root / "traits.csv").write_text("leaf_id,length_mm,width_mm,area_mm2,perimeter_mm,"
                                     "thick_share,confidence,confidence_reasons,quality\n"
                                     "0,100,40,3000,250,0.01,0.9,,ok\n"
                                     "1,80,30,2000,200,0.2,0.4,thick;short-outline,check\n")
    (root / "plant_traits.json").write_text(json.dumps({"height_mm": 150.0,
                                                        "total_leaf_area_mm2": 5000.0,
                                                        "quality": "check",
                                                        "quality_reasons": [
                                                            "1 of 2 leaves low confidence",
                                                            "leaf 1 is thick"]}))
    return root


def test_a_run_folder_without_its_scan_reads_from_what_it_recorded(tmp_path):
    r = record_from_run_dir(_run_folder(tmp_path / "runs" / "P1"))
    assert (r.plant_id, r.metadata.plant.genotype, r.metadata.experiment.study_id) == \
        ("P1", "Ler", "S1")
    assert r.scan.acquired_at.isoformat() == "2026-05-06T08:30:00"  # UTC
    assert [(leaf.leaf_id, leaf.confidence, leaf.quality_flag) for leaf in r.leaves] == \
        [(0, 0.9, "ok"), (1, 0.4, "check")]
    assert [leaf.confidence_reasons for leaf in r.leaves] == [None, "thick;short-outline"]
    assert r.quality_flag == "check" and r.plant_traits["leaf_count"] == 2.0
    assert r.quality_reasons == "1 of 2 leaves low confidence; leaf 1 is thick"
    assert [(w.stage, w.code, w.leaf_id) for w in r.warnings] == [("measure", "thick-leaf", 1)]


def test_a_sheet_at_store_time_corrects_what_the_run_recorded(tmp_path):
    run = _run_folder(tmp_path / "runs" / "P1")
    sheet = tmp_path / "sheet.csv"
    sheet.write_text("plant_id,treatment,replicate\nP1,drought,3\n")
    r = record_from_run_dir(run, load_sample_sheet(sheet))
    p = r.metadata.plant
    assert (p.genotype, p.treatment, p.replicate) == ("Ler", "drought", 3)


def test_the_run_key_ignores_exporters_and_the_store(tmp_path):
    a = record_from_run_dir(_run_folder(tmp_path / "a"))
    info = json.loads((tmp_path / "a" / "run.json").read_text())
    info["stages"]["store"] = {"plugin": "sqlite", "params": {"path": "x.sqlite"}}
    info["stages"]["export.1"] = {"plugin": "html-report", "params": {}}
    (tmp_path / "a" / "run.json").write_text(json.dumps(info))
    assert record_from_run_dir(tmp_path / "a").run_key == a.run_key
    info["stages"]["measure"]["params"] = {"pixel_mm": 0.5}
    (tmp_path / "a" / "run.json").write_text(json.dumps(info))
    assert record_from_run_dir(tmp_path / "a").run_key != a.run_key


def test_bad_run_folders_are_named(tmp_path):
    run = _run_folder(tmp_path / "r")
    (run / "traits.csv").write_text("leaf_id,quality\n0,excellent\n")
    with pytest.raises(DataError, match=r"traits.csv:2: quality flag 'excellent' is not one of "
                       "ok, check, fail"):
        record_from_run_dir(run)
    with pytest.raises(DataError, match="no such run folder"):
        find_run_dirs([tmp_path / "nope"])

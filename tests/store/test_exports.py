"""ISA-Tab export (checked against its own stated columns) and the experiment report."""

from __future__ import annotations

import csv

import pytest
from plantscan_store.isatab import (
    ASSAY_COLUMNS,
    STUDY_COLUMNS,
    IsaTabError,
    export_isatab,
    validate_isatab,
)
from store_fixtures import make_record

from plantscan_core.cli import main


@pytest.fixture
def experiment(store):
    """Two studies; 8 plants x 3 days in S1 (one run flagged 'fail'), 2 plants in S2."""
    runs = [make_record(plant=p, day=d, quality_flag="fail" if (p, d) == (3, 2) else "ok",
                        replicate=p // 4 + 1) for p in range(8) for d in range(3)]
    runs[3 * 3 + 2].quality_reasons = "only 12 of 48 views see the plant"
    store.put_many(runs)
    store.put_many(make_record(plant=p, study="S2") for p in range(2))
    return store


def _table(path):
    with path.open() as f:
        return list(csv.DictReader(f, delimiter="\t"))


def test_isatab_export_matches_its_stated_columns(experiment, tmp_path):
    files = export_isatab(experiment, tmp_path / "isa")
    assert sorted(p.name for p in files) == sorted([
        "i_investigation.txt", "s_S1.txt", "a_S1_phenotyping.txt", "d_S1_traits.txt",
        "tdf_S1.txt", "s_S2.txt", "a_S2_phenotyping.txt", "d_S2_traits.txt", "tdf_S2.txt"])
    validate_isatab(tmp_path / "isa")
    study = _table(tmp_path / "isa" / "s_S1.txt")
    assert len(study) == 8 and list(study[0]) == [*STUDY_COLUMNS, "Factor Value[watering]"]
    assert {r["Sample Name"] for r in study} == {f"P{p:04d}" for p in range(8)}
    assay = _table(tmp_path / "isa" / "a_S1_phenotyping.txt")
    assert len(assay) == 24 and list(assay[0]) == list(ASSAY_COLUMNS)
    # the flagged run says why; the others say nothing
    assert {(r["Comment[Quality flag]"], r["Comment[Quality reasons]"]) for r in assay} == {
        ("ok", ""), ("fail", "only 12 of 48 views see the plant")}
    data = _table(tmp_path / "isa" / "d_S1_traits.txt")
    plant_rows = [r for r in data if not r["Leaf ID"]]
    assert len(plant_rows) == 24 and len(data) == 24 + 24 * 20
    units = {r["Variable ID"]: r["Scale"] for r in _table(tmp_path / "isa" / "tdf_S1.txt")}
    assert units["total_leaf_area_mm2"] == "mm2" and units["leaf_length_mm"] == "mm"


def test_the_check_finds_what_an_edited_export_breaks(experiment, tmp_path):
    export_isatab(experiment, tmp_path / "isa", study="S1")
    data = tmp_path / "isa" / "d_S1_traits.txt"
    lines = data.read_text().splitlines()
    lines[0] += "\tleaf_colour"
    lines[1] += "\tgreen"
    data.write_text("\n".join(lines) + "\n")
    (tmp_path / "isa" / "tdf_S1.txt").write_text("Variable ID\tTrait\n")
    with pytest.raises(IsaTabError) as err:
        validate_isatab(tmp_path / "isa")
    text = str(err.value)
    assert "tdf_S1.txt: columns ['Variable ID', 'Trait'] are not the stated" in text
    assert "d_S1_traits.txt: column 'leaf_colour' is not a variable of tdf_S1.txt" in text


def test_experiment_report_and_commands(experiment, store_target, tmp_path, capsys):
    out = tmp_path / "experiment.html"
    assert main(["query", "--db", store_target, "--study", "S1", "--report", str(out)]) == 0
    page = out.read_text()
    assert "plantscan experiment: S1" in page and "8 plants, 24 scans" in page
    assert "quality flags: fail 1, ok 23" in page
    assert '<span class="flag-fail">fail</span> 1' in page  # the flagged plant's row says so
    # offline: plotly.js inline once; outside it no script source and no URL
    from plotly.offline import get_plotlyjs

    assert page.count(get_plotlyjs()) == 1 and "Plotly.newPlot" in page
    rest = page.replace(get_plotlyjs(), "")
    assert "<script src" not in rest and "http://" not in rest and "https://" not in rest
    assert main(["query", "--db", store_target, "--isa-tab", str(tmp_path / "isa")]) == 0
    assert main(["query", "--db", store_target, "--level", "timeseries", "--plant", "P0001",
                 "--out", str(tmp_path / "leaves.csv")]) == 0
    rows = list(csv.DictReader((tmp_path / "leaves.csv").open()))
    # the synthetic leaves do not move between days: each keeps its track
    assert {(r["track"], r["leaf_id"]) for r in rows} == {(str(i + 1), str(i))
                                                          for i in range(20)}
    assert main(["query", "--db", store_target, "--report", str(out), "--trait", "nope"]) == 2
    assert "no plant trait 'nope' in the store" in capsys.readouterr().err

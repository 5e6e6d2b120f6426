"""The experiment chain on the virtual truth, without rendering.

2 genotypes (the dicot and branched families) x 2 treatments x 3 replicates x
5 daily scans of growing plants (``plantscan_sim.experiment``): the truth's
traits, stored as runs with the sample sheet's metadata, must come back out of
the store, the growth series, the experiment report's curves and the ISA-Tab
export as the truth has them, plant by plant and day by day; and the truth's
own leaves, numbered anew and turned at random every day, must be followed
from scan to scan by the leaf matching.  (The rendered, processed experiment
is ``benchmarks/experiment.py``.)
"""

from __future__ import annotations

import csv

import numpy as np
import pandas as pd
import pytest
from plantscan_sim.experiment import (
    FIRST_SCAN,
    SOWN,
    STUDY_ID,
    WATERING,
    sample_sheet,
)
from plantscan_store import Store
from plantscan_store.isatab import export_isatab, validate_isatab
from plantscan_store.report import experiment_figures, write_experiment_report
from plantscan_store.timeseries import leaf_series, plant_series
from virtual_truth import design, read_truth_table, records, truth_rows

from plantscan_core.metadata import load_sample_sheet


@pytest.fixture(scope="module")
def truth() -> list[dict]:
    return read_truth_table()


@pytest.fixture(scope="module")
def truth_plants(truth) -> pd.DataFrame:
    """Per plant and day: the truth's total leaf area, days after sowing, group."""
    df = pd.DataFrame(truth)
    per = df.groupby(["plant_id", "day"]).agg(total_leaf_area_mm2=("area_mm2", "sum"),
                                              leaves=("leaf_id", "size")).reset_index()
    planned = {(s.plant_id, s.day): s for s in design()}
    per["genotype"] = [planned[k].genotype for k in zip(per.plant_id, per.day)]
    per["treatment"] = [planned[k].treatment for k in zip(per.plant_id, per.day)]
    per["x_day"] = [(planned[k].scan_time - pd.Timestamp(SOWN)).total_seconds() / 86400
                    for k in zip(per.plant_id, per.day)]
    return per


@pytest.fixture(scope="module")
def experiment(tmp_path_factory, truth):
    folder = tmp_path_factory.mktemp("virtual-experiment")
    sheet = folder / "samples.csv"
    sheet.write_text(sample_sheet(design()))
    runs, truth_leaf = records(truth, load_sample_sheet(sheet, require_scans=False))
    store = Store(folder / "results.sqlite")
    store.put_many(runs)
    try:
        yield store, truth_leaf, folder
    finally:
        store.close()


def test_the_truth_table_is_the_simulators():
    """The stored table is what the virtual scanner builds today (two plants rebuilt)."""
    table = pd.DataFrame(read_truth_table())
    for scan in design():
        if (scan.plant_id, scan.day) not in {("G1-control-r3", 4), ("G2-drought-r1", 0)}:
            continue  # two cheap plans, one per genotype, the oldest and the youngest
        fresh = pd.DataFrame(truth_rows(scan))
        mine = table[(table.plant_id == scan.plant_id) & (table.day == scan.day)]
        assert list(mine.leaf_id) == list(fresh.leaf_id), (
            "the virtual scanner changed: regenerate tests/store/data/virtual_growth_truth.csv "
            "(python tests/store/virtual_truth.py)")
        # the table holds 4 decimals
        np.testing.assert_allclose(mine.drop(columns=["plant_id"]).to_numpy(float),
                                   fresh.drop(columns=["plant_id"]).to_numpy(float), atol=1e-4)


def test_growth_series_are_the_truths(experiment, truth, truth_plants):
    store, _, _ = experiment
    assert store.counts()["runs"] == 60 and store.counts()["plants"] == 12
    assert store.counts()["leaves"] == len(truth)
    series = plant_series(store.plant_traits(study=STUDY_ID))
    assert len(series) == 60
    series["day_index"] = (series.scan_time - pd.Timestamp(FIRST_SCAN)).dt.days
    m = series.merge(truth_plants, left_on=["plant_id", "day_index"],
                     right_on=["plant_id", "day"], suffixes=("", "_truth"))
    assert len(m) == 60
    # who each plant is comes from the sample sheet, unchanged
    assert (m.genotype == m.genotype_truth).all() and (m.treatment == m.treatment_truth).all()
    assert (m["factor.watering"] == m.treatment.map(WATERING)).all()
    np.testing.assert_allclose(m.days_after_sowing, m.x_day, atol=1e-6)
    # the trait of every plant and day is the truth's (stored as float64)
    np.testing.assert_allclose(m.total_leaf_area_mm2, m.total_leaf_area_mm2_truth, rtol=1e-12)
    assert (m.leaf_count == m.leaves).all()
    # growth rate: ln of the day-to-day ratio, per day (scans 24 h apart)
    m = m.sort_values(["plant_id", "day_index"])
    expected = np.log(m.total_leaf_area_mm2_truth).groupby(m.plant_id).diff()
    np.testing.assert_allclose(m.relative_growth_rate, expected, rtol=1e-9)
    # the design's premise: the drought plants grow more slowly than their control twins
    last = m[m.day_index == 4].set_index("plant_id").total_leaf_area_mm2
    for pid in last.index[last.index.str.contains("control")]:
        assert last[pid.replace("control", "drought")] < last[pid]


def test_report_curves_are_the_truths(experiment, truth_plants):
    store, _, folder = experiment
    page = write_experiment_report(store, folder / "experiment.html", study=STUDY_ID,
                                   truth=truth_plants).read_text()
    assert "12 plants, 60 scans" in page and "2026-05-04 to 2026-05-08" in page
    series = plant_series(store.plant_traits(study=STUDY_ID))
    series = series.assign(x_day=series.days_after_sowing)
    per_plant, per_group = experiment_figures(series, "total_leaf_area_mm2")
    drawn = 0
    for trace in per_plant.data:
        plant = trace.text[0].split(" ")[0]
        t = truth_plants[truth_plants.plant_id == plant].sort_values("x_day")
        np.testing.assert_allclose(trace.x, t.x_day, atol=1e-6)
        np.testing.assert_allclose(trace.y, t.total_leaf_area_mm2, rtol=1e-12)
        drawn += 1
    assert drawn == 12
    # each group's curve: the mean and standard deviation of its 3 plants' truth, per day
    groups = truth_plants.assign(group=truth_plants.genotype + " / " + truth_plants.treatment,
                                 day_bin=truth_plants.x_day.round())
    for trace in per_group.data:
        g = groups[groups.group == trace.name].groupby("day_bin").total_leaf_area_mm2
        np.testing.assert_allclose(trace.y, g.mean(), rtol=1e-12)
        np.testing.assert_allclose(trace.error_y.array, g.std(), rtol=1e-9)
    assert sorted(t.name for t in per_group.data) == sorted(set(groups.group))


def test_isatab_holds_the_truth(experiment, truth, truth_plants):
    store, _, folder = experiment
    export_isatab(store, folder / "isa", study=STUDY_ID)
    validate_isatab(folder / "isa")

    def table(name):
        with (folder / "isa" / name).open() as f:
            return list(csv.DictReader(f, delimiter="\t"))

    study = {r["Sample Name"]: r for r in table(f"s_{STUDY_ID}.txt")}
    planned = {s.plant_id: s for s in design()}
    assert set(study) == set(planned)
    for pid, row in study.items():
        s = planned[pid]
        assert (row["Characteristics[Genotype]"], row["Factor Value[treatment]"],
                row["Factor Value[watering]"], row["Characteristics[Replicate]"],
                row["Comment[Sowing date]"]) == (s.genotype, s.treatment,
                                                 WATERING[s.treatment], str(s.replicate),
                                                 str(SOWN))
    data = table(f"d_{STUDY_ID}_traits.txt")
    plant_rows = [r for r in data if not r["Leaf ID"]]
    assert len(plant_rows) == 60 and len(data) - len(plant_rows) == len(truth)
    day = {r["Date"]: (pd.Timestamp(r["Date"]) - pd.Timestamp(FIRST_SCAN)).days
           for r in plant_rows}
    expected = truth_plants.set_index(["plant_id", "day"]).total_leaf_area_mm2
    for r in plant_rows:
        assert float(r["total_leaf_area_mm2"]) == pytest.approx(
            expected[(r["Sample Name"], day[r["Date"]])], rel=1e-12)


def link_figures(tracked: pd.DataFrame) -> dict[str, tuple[int, int, int]]:
    """Per genotype: (day-to-day links of one truth leaf, links kept in one track, tracks
    holding two truth leaves)."""
    out = {}
    for genotype, g in tracked.groupby("genotype"):
        links = kept = 0
        for _, leaf in g.sort_values("scan_time").groupby(["plant_id", "truth"]):
            t = leaf.track.to_numpy()
            links += len(t) - 1
            kept += int((t[1:] == t[:-1]).sum())
        joins = int((g.groupby(["plant_id", "track"]).truth.nunique() > 1).sum())
        out[genotype] = (links, kept, joins)
    return out


def test_leaves_keep_their_track_on_the_growing_families(experiment):
    store, truth_leaf, _ = experiment
    leaves = store.leaf_traits(study=STUDY_ID)
    tracked = leaf_series(leaves)
    tracked["truth"] = [truth_leaf[u][int(i)] for u, i in zip(tracked.scan_uid, tracked.leaf_id)]
    figures = link_figures(tracked)
    # the dicot (spiral, opposite or distichous simple leaves): every leaf followed
    assert figures["G1"][1] == figures["G1"][0] and figures["G1"][2] == 0
    # the branched family's leaves are the leaflets of compound leaves: a leaf's leaflets
    # share its azimuth and rise together, only their distance from the axis tells them
    # apart.  On these 6 plants 3 of 222 links break: two leaflets born on one day 3 mm
    # apart swap the next (2 links), and a plant with a single leaf on its first scan has
    # no shape to fix its turn by the next day (1 link).  Any further break fails.
    links, kept, joins = figures["G2"]
    assert links == 222 and links - kept <= 3 and joins <= 3, figures


def test_a_development_design_draws_no_validation_seed():
    # Tuning on the experiment (benchmarks/experiment.py --seed0 0) must not see a validation
    # plant (seeds >= 1000); the design is otherwise the same plants, days and ages.
    from plantscan_sim.experiment import VALIDATION_SEED0, growth_design

    genotypes = {"G1": "dicot", "G2": "branched"}
    validation = growth_design(genotypes)
    development = growth_design(genotypes, seed0=0)
    assert min(s.seed for s in validation) > VALIDATION_SEED0
    assert max(s.seed for s in development) < VALIDATION_SEED0
    assert [(s.plant_id, s.day, s.age) for s in development] == [
        (s.plant_id, s.day, s.age) for s in validation]

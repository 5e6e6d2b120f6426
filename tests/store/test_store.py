"""The results store on SQLite and PostgreSQL: schema, idempotence, writers at once, kills, load.

Every test runs on both back-ends (``store_target``).  The runs are synthetic
(``store_fixtures.make_record``) with values that encode plant, day and leaf,
so a row read back is checked against exactly what was stored.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from plantscan_store import ResultsStoreError, Store
from plantscan_store.schema import metadata
from sqlalchemy import event
from store_fixtures import leaf_area, make_record

HERE = Path(__file__).resolve().parent


def test_migrations_build_exactly_the_schema_module(store):
    # schema.py is what the queries use and the migrations are what a database gets: a column
    # in one and not the other would fail only in the field.
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    with store.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), metadata)
    assert diff == []
    assert store.revision() == "0002"


def test_the_store_knows_every_column_of_the_core_traits_table():
    # The trait dictionary is derived from the core's table; the leaves table is a schema
    # (a migration), so a leaf trait added to the core without its column fails here, not
    # in a lab's database.
    from plantscan_store.schema import leaves
    from plantscan_store.traitdefs import BY_NAME, LEAF_NUMBERS

    from plantscan_core.data import LEAF_COLUMNS, PLANT_TRAITS

    for c in (*LEAF_COLUMNS, *PLANT_TRAITS):
        assert BY_NAME[c.name, c.level].unit == c.unit
    assert set(LEAF_NUMBERS) <= set(leaves.c.keys())
    assert {"confidence", "thick_share", "length_mm"} <= set(LEAF_NUMBERS)


def test_a_run_reads_back_with_its_metadata_and_scan_time(store):
    record = make_record(plant=7, day=2, replicate=3)
    store.put(record)
    leaves = store.leaf_traits()
    assert len(leaves) == 20
    row = leaves.iloc[5]
    assert (row.plant_id, row.genotype, row.treatment, row.study_id) == \
        ("P0007", "Col-0", "control", "S1")
    assert row.replicate == 3 and row["factor.watering"] == "100%"
    assert row.area_mm2 == leaf_area(7, 2, 5)
    assert row.scan_time == record.scan.acquired_at
    # scanned 2026-05-06 09:07, sown 2026-05-01
    assert row.days_after_sowing == pytest.approx(5 + (9 * 60 + 7) / 1440)
    plants = store.plant_traits()
    assert len(plants) == 1
    assert plants.iloc[0].total_leaf_area_mm2 == pytest.approx(
        sum(leaf_area(7, 2, i) for i in range(20)))
    assert plants.iloc[0].warnings == 1


def test_a_run_stored_twice_appears_once_and_a_rerun_replaces_it(store):
    store.put(make_record(plant=1))
    store.put(make_record(plant=1))
    assert store.counts()["runs"] == 1 and store.counts()["leaves"] == 20
    store.put(make_record(plant=1, n_leaves=12))  # re-processed: fewer leaves found
    counts = store.counts()
    assert (counts["runs"], counts["leaves"], counts["plant_traits"], counts["run_warnings"]) \
        == (1, 12, 3, 1)
    store.put(make_record(plant=1, recipe_hash="recipe-b"))  # another recipe: another run
    assert store.counts()["runs"] == 2
    assert len(store.plant_traits(runs="all")) == 2
    assert len(store.plant_traits()) == 1  # the scan's latest run


def test_one_plant_id_cannot_change_genotype(store):
    store.put(make_record(plant=3, genotype="Col-0"))
    with pytest.raises(ResultsStoreError, match=r"plant 'P0003' of study 'S1': genotype 'Ler' "
                       r"in this run but 'Col-0' in the store"):
        store.put(make_record(plant=3, day=1, genotype="Ler"))
    assert store.counts()["runs"] == 1  # nothing of the refused run was kept
    # the same plant id in another study is another plant
    store.put(make_record(plant=3, study="S2", genotype="Ler"))
    assert store.counts()["plants"] == 2


def test_filters(store):
    store.put_many(make_record(plant=p, day=d, quality_flag=("ok", "check", "fail")[p % 3])
                   for p in range(8) for d in range(3))
    assert len(store.plant_traits()) == 24
    assert set(store.plant_traits(genotype="Ler").plant_id) == {"P0000", "P0002", "P0004",
                                                                 "P0006"}
    assert set(store.plant_traits(treatment=["drought"]).plant_id) == {"P0000", "P0001",
                                                                        "P0004", "P0005"}
    # day 1 is 2026-05-05: a date covers its whole day
    assert set(store.plant_traits(since="2026-05-05", until="2026-05-05")
               .scan_time.dt.day) == {5}
    assert len(store.plant_traits(since="2026-05-05")) == 16
    assert set(store.plant_traits(quality=["check", "fail"]).plant_quality_flag) == \
        {"check", "fail"}
    assert len(store.leaf_traits(plant="P0003", quality="fail")) == 0
    assert len(store.leaf_traits(plant="P0003", quality="ok")) == 60
    with pytest.raises(ValueError, match="unknown quality flag"):
        store.plant_traits(quality="good")


def test_leaf_flags_and_unflagged_rows(store):
    flags = ["fail" if i < 4 else None for i in range(20)]
    store.put(make_record(plant=1, quality_flag=None, leaf_flags=flags))
    assert len(store.leaf_traits(quality="fail")) == 4
    assert len(store.leaf_traits(quality="none")) == 16



def test_why_to_trust_a_number_less_is_stored_per_leaf_and_plant(store):
    record = make_record(plant=2, quality_flag="check")
    record.leaves[3].confidence, record.leaves[3].quality_flag = 0.3, "check"
    record.leaves[3].confidence_reasons = "short-outline;area-mismatch"
    record.quality_reasons = "2 of 20 leaves have low confidence; leaf 3 is thick"
    store.put(record)
    leaves = store.leaf_traits().set_index("leaf_id")
    assert (leaves.loc[3, "confidence"], leaves.loc[3, "confidence_reasons"]) == \
        (0.3, "short-outline;area-mismatch")
    assert leaves.drop(index=3).confidence_reasons.isna().all()  # none given: none stored
    plant = store.plant_traits().iloc[0]
    assert (plant.plant_quality_flag, plant.plant_quality_reasons) == \
        ("check", "2 of 20 leaves have low confidence; leaf 3 is thick")


def test_a_store_of_the_first_schema_is_upgraded_keeping_its_runs(store_target):
    # a lab's database made before the reasons were stored: downgraded to 0001 here, with a
    # run in it, then opened again
    from alembic import command
    from alembic.config import Config
    from plantscan_store import Store
    from plantscan_store.store import MIGRATIONS

    with Store(store_target) as s:
        s.put(make_record(plant=1))
        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        with s.engine.begin() as conn:
            cfg.attributes["connection"] = conn
            command.downgrade(cfg, "0001")
        assert s.revision() == "0001"
    with Store(store_target) as s:
        assert s.revision() == "0002"
        leaves = s.leaf_traits()
        assert len(leaves) == 20 and leaves.confidence_reasons.isna().all()
        assert s.plant_traits().plant_quality_reasons.isna().all()
        s.put(make_record(plant=1))  # stored again: replaced, not doubled
        assert s.counts()["runs"] == 1 and s.counts()["leaves"] == 20

WRITER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    sys.path.insert(0, {here!r})
    from store_fixtures import make_record
    from plantscan_store import Store
    target, worker, go = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
    store = Store(target)
    print("ready", flush=True)
    while not go.exists():
        time.sleep(0.01)
    # plants 0-29 are written by both workers (the same runs), the others by one each
    plants = list(range(30)) + list(range(100 * (worker + 1), 100 * (worker + 1) + 20))
    for p in plants:
        store.put(make_record(plant=p, n_leaves=5))  # one transaction per run, as workers do
    print("done", flush=True)
""")


def test_two_writers_at_once_lose_nothing_and_store_shared_runs_once(store_target, tmp_path):
    Store(store_target).close()  # created before, as a batch does
    go = tmp_path / "go"
    script = WRITER.format(here=str(HERE))
    workers = [subprocess.Popen([sys.executable, "-c", script, store_target, str(w), str(go)],
                                stdout=subprocess.PIPE, text=True) for w in (0, 1)]
    for w in workers:
        assert w.stdout.readline().strip() == "ready"
    go.touch()  # both start writing at the same moment
    for w in workers:
        out, _ = w.communicate(timeout=300)
        assert w.returncode == 0 and out.strip() == "done"
    with Store(store_target) as store:
        counts = store.counts()
        # 30 shared plants once + 20 own plants per worker, 5 leaves each
        assert (counts["plants"], counts["scans"], counts["runs"], counts["leaves"]) == \
            (70, 70, 70, 350)
        leaves = store.leaf_traits()
    expected = {(f"P{p:04d}", i, leaf_area(p, 0, i)) for p in
                [*range(30), *range(100, 120), *range(200, 220)] for i in range(5)}
    assert set(zip(leaves.plant_id, leaves.leaf_id, leaves.area_mm2)) == expected


KILLED = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {here!r})
    from sqlalchemy import event
    from store_fixtures import make_record
    from plantscan_store import Store
    store = Store(sys.argv[1])
    store.put(make_record(plant=1))

    def pause(conn, cursor, statement, *args):
        # the old run is deleted and the new run's row written; its leaves are not
        if statement.lstrip().upper().startswith("INSERT INTO RUNS"):
            print("mid-write", flush=True)
            time.sleep(600)

    event.listen(store.engine, "after_cursor_execute", pause)
    # plant 1 re-processed (12 leaves instead of 20) and plant 2, in one transaction
    store.put_many([make_record(plant=1, n_leaves=12), make_record(plant=2)])
""")


def test_a_writer_killed_mid_run_leaves_no_partial_run(store_target):
    writer = subprocess.Popen([sys.executable, "-c", KILLED.format(here=str(HERE)),
                               store_target], stdout=subprocess.PIPE, text=True)
    try:
        line = writer.stdout.readline().strip()
        assert line == "mid-write", line
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait(timeout=30)
    with Store(store_target) as store:
        deadline = time.monotonic() + 30
        # PostgreSQL notices the dead client's connection and rolls back its transaction
        while store.counts()["runs"] != 1 and time.monotonic() < deadline:
            time.sleep(0.2)
        counts = store.counts()
        # the first run as it was: not deleted, not half replaced; nothing of plant 2
        assert (counts["runs"], counts["leaves"], counts["scans"], counts["plants"]) == \
            (1, 20, 1, 1)
        assert list(store.plant_traits().leaf_count) == [20]
        store.put(make_record(plant=2))  # the store is not left locked
        assert store.counts()["runs"] == 2


def test_load_1000_plants_of_20_leaves(store):
    # The time is the benchmark's (benchmarks/store.py, docs/benchmarks.md); the test checks
    # that everything arrives and that the statements sent do not grow with the runs: the
    # bulk path sends a fixed number per group of 100 runs, not one per leaf.
    statements = []
    event.listen(store.engine, "before_cursor_execute",
                 lambda conn, cursor, statement, *a: statements.append(statement))
    t0 = time.perf_counter()
    n = store.put_many(make_record(plant=p, n_leaves=20) for p in range(1000))
    seconds = time.perf_counter() - t0
    counts = store.counts()
    assert n == 1000
    assert (counts["plants"], counts["runs"], counts["leaves"], counts["plant_traits"]) == \
        (1000, 1000, 20_000, 3000)
    # 10 groups x (plant select, plant insert, plant select, scan upsert, run select, run
    # insert, leaves, plant traits, warnings) + trait definitions + the experiment, BEGINs;
    # executemany chunks at most 1000 rows per statement on either driver.
    assert len(statements) <= 10 * 16, len(statements)
    print(f"\n{store.dialect}: 1000 plants x 20 leaves stored in {seconds:.2f} s")
    leaves = store.leaf_traits(plant="P0999")
    assert list(leaves.area_mm2) == [leaf_area(999, 0, i) for i in range(20)]


def test_bad_targets_are_named(tmp_path):
    with pytest.raises(ResultsStoreError, match="does not exist"):
        Store(tmp_path / "no-such-folder" / "results.sqlite")
    with pytest.raises(ResultsStoreError, match="unsupported database 'mysql'"):
        Store("mysql://lab@db/phenomics")
    with pytest.raises(ResultsStoreError, match="cannot open the results store"):
        Store("postgresql://nobody@127.0.0.1:1/none")

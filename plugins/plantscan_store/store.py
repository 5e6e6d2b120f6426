"""The results store: one database of experiments, plants, scans, runs and their traits.

``Store(target)`` opens (and creates or upgrades, with the alembic migrations)
an embedded SQLite file or a PostgreSQL database:

* a path, or ``sqlite:///path``: a SQLite file, zero set-up.  It is opened in
  WAL mode (readers never wait for a writer) and every write transaction
  starts with ``BEGIN IMMEDIATE``: writers queue for the file's write lock
  (``busy_timeout``) instead of failing half-way with "database is locked".
  Keep it on a local disk: SQLite's locks are unreliable on network file
  systems (a centre with several machines uses PostgreSQL).
* ``postgresql://user@host:port/dbname``: a PostgreSQL server (psycopg 3).
  The password comes from libpq's usual places (``PGPASSWORD``,
  ``~/.pgpass``), never from a recipe.

``put(record)`` stores one run in one transaction: all of it or, when the
writer dies half-way, none of it.  A run whose key (scan + recipe) is already
in the store replaces the old one.  Several writers at once (batch workers)
lose nothing: the experiment and plant rows are inserted with ``ON CONFLICT DO
NOTHING`` and the scan row is upserted, which on PostgreSQL locks it until the
transaction ends, so two writers of runs of the same scan take turns.
"""

from __future__ import annotations

import datetime as _dt
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from sqlalchemy import bindparam, create_engine, delete, event, func, select, text, update
from sqlalchemy.engine import URL, Connection, Engine, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, IntegrityError, OperationalError

from plantscan_core.errors import PlantScanError
from plantscan_core.metadata import PLANT_IDENTITY_FIELDS, ExperimentSpec
from plantscan_store import schema as S
from plantscan_store.records import RunRecord
from plantscan_store.traitdefs import LEAF_NUMBERS, definition

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
SQLITE_BUSY_TIMEOUT_MS = 120_000  # a writer waits up to 2 min for the file's write lock
_PG_MIGRATION_LOCK = 0x706C616E  # advisory lock id held while migrating ("plan")
_RETRIES = 4


class ResultsStoreError(PlantScanError):
    """The results store cannot be opened or refuses a run (message names the store or run)."""


def store_url(target: str | Path) -> URL:
    """The SQLAlchemy URL of a store target: a SQLite path, ``sqlite:///...`` or ``postgresql://``."""
    text_target = str(target)
    if "://" not in text_target:
        path = Path(text_target).expanduser().resolve()
        if not path.parent.is_dir():
            raise ResultsStoreError(f"{path}: cannot create the store, folder {path.parent} "
                                    "does not exist")
        return URL.create("sqlite", database=str(path))
    try:
        url = make_url(text_target)
    except ArgumentError as exc:
        raise ResultsStoreError(f"{text_target}: not a database URL ({exc})") from None
    backend = url.get_backend_name()
    if backend == "sqlite":
        return url
    if backend in ("postgresql", "postgres"):
        return url.set(drivername="postgresql+psycopg")
    raise ResultsStoreError(f"{url.render_as_string(hide_password=True)}: unsupported database "
                            f"{backend!r}; valid: a SQLite path or sqlite:///PATH, postgresql://")


def _sqlite_events(engine: Engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record) -> None:
        # Transactions are begun by us (below), not by the sqlite3 module, so that a write
        # transaction takes the write lock at BEGIN: no deadlock between two readers-turned-
        # writers, no "database is locked" in the middle of a run.
        dbapi_connection.isolation_level = None
        cur = dbapi_connection.cursor()
        cur.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
        cur.execute("PRAGMA journal_mode = WAL")
        cur.execute("PRAGMA foreign_keys = ON")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        read_only = conn.get_execution_options().get("plantscan_read_only", False)
        conn.exec_driver_sql("BEGIN" if read_only else "BEGIN IMMEDIATE")


class Store:
    """A results store (SQLite file or PostgreSQL database), migrated to the current schema.

    Parameters
    ----------
    target : str or Path
        A SQLite file path (created when missing), ``sqlite:///PATH`` or
        ``postgresql://user@host:port/dbname``.
    """

    def __init__(self, target: str | Path) -> None:
        self.url = store_url(target)
        self.name = self.url.render_as_string(hide_password=True)
        self.dialect = self.url.get_backend_name()
        kwargs: dict[str, Any] = {}
        if self.dialect == "sqlite":
            kwargs["connect_args"] = {"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}
        self.engine = create_engine(self.url, **kwargs)
        if self.dialect == "sqlite":
            _sqlite_events(self.engine)
        self._reader = self.engine.execution_options(plantscan_read_only=True)
        self._sql = _Statements(self._insert)
        self._experiments: dict[tuple[str, str], int] = {}
        self._trait_names: set[str] = set()
        self._lock = threading.Lock()
        self._migrate()

    # ------------------------------------------------------------------ life cycle
    def _migrate(self) -> None:
        from alembic import command
        from alembic.config import Config
        from alembic.runtime.migration import MigrationContext
        from alembic.script import ScriptDirectory

        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        head = ScriptDirectory.from_config(cfg).get_current_head()
        try:
            with self.engine.begin() as conn:
                if self.dialect == "postgresql":
                    # two workers opening a new database at once: one migrates, one waits
                    conn.execute(text("SELECT pg_advisory_xact_lock(:k)"),
                                 {"k": _PG_MIGRATION_LOCK})
                current = MigrationContext.configure(conn).get_current_revision()
                if current == head:
                    return
                cfg.attributes["connection"] = conn
                command.upgrade(cfg, "head")
        except OperationalError as exc:
            raise ResultsStoreError(f"{self.name}: cannot open the results store "
                                    f"({_first_line(exc)})") from exc

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Store({self.name!r})"

    # ------------------------------------------------------------------ writing
    def put(self, record: RunRecord) -> int:
        """Store one run in one transaction (replacing a run with the same key); its row id.

        ``ResultsStoreError`` when the run's plant is already in the store with
        another genotype (species, treatment, ... ``PLANT_IDENTITY_FIELDS``).
        """
        return self._transaction([record])[0]

    def put_many(self, records: Iterable[RunRecord], group: int = 100) -> int:
        """Store runs, ``group`` runs per transaction; how many were stored.

        Each group is stored whole or not at all (a killed writer leaves no
        partial run, nor a partial group); the groups before a failing one are
        kept.  One transaction per run costs one disk flush per run (about
        10 ms here): grouping is what makes 1,000 runs take seconds
        (docs/benchmarks.md).
        """
        if group < 1:
            raise ValueError(f"group must be >= 1, got {group}")
        n, chunk = 0, []
        for record in records:
            chunk.append(record)
            if len(chunk) == group:
                n += len(self._transaction(chunk))
                chunk = []
        if chunk:
            n += len(self._transaction(chunk))
        return n

    def _transaction(self, records: list[RunRecord]) -> list[int]:
        for attempt in range(_RETRIES):
            try:
                with self.engine.begin() as conn:
                    return self._put(conn, records)
            except (IntegrityError, OperationalError) as exc:
                # a concurrent writer won a race on a unique key, or PostgreSQL picked this
                # transaction as a deadlock victim: nothing of it was kept; do it again
                if attempt == _RETRIES - 1 or not _retryable(exc):
                    first = records[0]
                    what = (f"the run of {first.plant_id} ({first.run_dir or first.run_key})"
                            if len(records) == 1 else f"{len(records)} runs")
                    raise ResultsStoreError(f"{self.name}: cannot store {what}: "
                                            f"{_first_line(exc)}") from exc
                with self._lock:
                    self._experiments.clear()
        raise AssertionError("unreachable")

    def _put(self, conn: Connection, records: list[RunRecord]) -> list[int]:
        """Store ``records`` in the open transaction ``conn``: a fixed number of statements
        whatever the number of runs and leaves (each statement carries every row of the group).
        """
        sql = self._sql
        keys = [r.run_key for r in records]
        by_key = dict(zip(keys, records))  # the same run twice in a group: the last one
        group = list(by_key.items())
        plant_refs = self._plants(conn, [r for _, r in group])
        scans = {r.scan.uid: {"plant_ref": plant_refs[id(r)], "scan_uid": r.scan.uid,
                              "path": r.scan.path, "acquired_at": r.scan.acquired_at,
                              "protocol": r.scan.protocol, "views": r.scan.views}
                 for _, r in group}
        scan_refs = dict(conn.execute(sql.upsert_scan, list(scans.values())).all())
        old = conn.execute(sql.runs_by_key, {"keys": list(by_key)}).scalars().all()
        if old:
            for stmt in sql.delete_runs:
                conn.execute(stmt, {"refs": list(old)})
        stored_at = _utcnow()
        run_refs = dict(conn.execute(sql.insert_run, [{
            "scan_ref": scan_refs[r.scan.uid], "run_key": key, "run_dir": r.run_dir,
            "recipe_name": r.recipe_name, "recipe_hash": r.recipe_hash,
            "plantscan_version": r.plantscan_version, "plugins": r.plugins,
            "provenance": r.provenance, "quality_flag": r.quality_flag,
            "quality_reasons": r.quality_reasons, "leaf_count": len(r.leaves),
            "stored_at": stored_at} for key, r in group]).all())
        self._bulk(conn, S.leaves, [_leaf_row(run_refs[key], leaf) for key, r in group
                                    for leaf in r.leaves])
        self._bulk(conn, S.plant_traits, [{"run_ref": run_refs[key], "trait": k, "value": v}
                                          for key, r in group for k, v in r.plant_traits.items()])
        self._bulk(conn, S.run_warnings, [
            {"run_ref": run_refs[key], "stage": w.stage, "code": w.code, "message": w.message,
             "leaf_id": w.leaf_id} for key, r in group for w in r.warnings])
        self._define_traits(conn, [r for _, r in group])
        return [run_refs[key] for key in keys]

    def _bulk(self, conn: Connection, table, rows: list[dict[str, Any]]) -> None:
        """Insert many rows: sqlite3's executemany; PostgreSQL's COPY.

        psycopg's executemany sends one INSERT per row, and a multi-row INSERT of
        1,000 rows costs psycopg more to parse than the server to run; COPY
        streams the rows in one command, inside the same transaction.
        """
        if not rows:
            return
        if self.dialect != "postgresql":
            conn.execute(table.insert(), rows)
            return
        columns = [c.name for c in table.columns if c.name in rows[0]]
        cursor = conn.connection.driver_connection.cursor()
        try:
            with cursor.copy(f"COPY {table.name} ({', '.join(columns)}) FROM STDIN") as copy:
                for row in rows:
                    copy.write_row([row[c] for c in columns])
        finally:
            cursor.close()

    def _insert(self, table):
        if self.dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert
        return insert(table)

    def _experiment(self, conn: Connection, e: ExperimentSpec) -> int:
        key = (e.investigation_id, e.study_id)
        with self._lock:
            if key in self._experiments:
                return self._experiments[key]
        values = {"investigation_id": e.investigation_id, "study_id": e.study_id,
                  "investigation_title": e.investigation_title, "study_title": e.study_title,
                  "description": e.description, "location": e.location,
                  "start_date": e.start_date, "extra": dict(e.extra)}
        conn.execute(self._insert(S.experiments).values(**values).on_conflict_do_nothing())
        row = conn.execute(select(S.experiments).where(
            S.experiments.c.investigation_id == e.investigation_id,
            S.experiments.c.study_id == e.study_id)).mappings().one()
        # fill in what an earlier run of the study did not say
        fill = {k: v for k, v in values.items() if v not in ("", None, {}) and not row[k]}
        if fill:
            conn.execute(update(S.experiments).where(S.experiments.c.id == row["id"])
                         .values(**fill))
        with self._lock:
            self._experiments[key] = row["id"]
        return row["id"]

    def _plants(self, conn: Connection, records: list[RunRecord]) -> dict[int, int]:
        """Row id of every record's plant (``id(record)`` -> id), inserting new plants.

        ``ResultsStoreError`` when a record's plant is in the store (or earlier in
        the group) with another genotype, species, treatment...
        """
        wanted: dict[tuple[int, str], tuple[dict[str, Any], RunRecord]] = {}
        refs: dict[int, tuple[int, str]] = {}
        for r in records:
            p = r.metadata.plant
            key = (self._experiment(conn, r.metadata.experiment), p.id)
            values = {"experiment_ref": key[0], "plant_id": p.id, "species": p.species,
                      "genotype": p.genotype, "accession": p.accession,
                      "biological_material_id": p.biological_material_id,
                      "treatment": p.treatment, "factors": dict(p.factors),
                      "replicate": p.replicate, "sowing_date": p.sowing_date,
                      "extra": dict(p.extra)}
            if key in wanted:
                self._check_plant(values, wanted[key][0], r, "another run of this group")
                values = {k: v if _given(v) else wanted[key][0][k] for k, v in values.items()}
            wanted[key] = (values, r)
            refs[id(r)] = key
        rows = self._plant_rows(conn, list(wanted))
        missing = [values for key, (values, _) in wanted.items() if key not in rows]
        if missing:
            conn.execute(self._sql.insert_plant, missing)
            rows.update(self._plant_rows(conn, [k for k in wanted if k not in rows]))
        for key, (values, record) in wanted.items():
            row = rows[key]
            self._check_plant(values, row, record, "the store")
            fill = {k: v for k, v in values.items() if _given(v) and not _given(row[k])}
            extra = {**(row["extra"] or {}), **values["extra"]}
            if extra != (row["extra"] or {}):
                fill["extra"] = extra
            if fill:
                conn.execute(update(S.plants).where(S.plants.c.id == row["id"]).values(**fill))
        return {rid: rows[key]["id"] for rid, key in refs.items()}

    def _plant_rows(self, conn: Connection, keys: list[tuple[int, str]]
                    ) -> dict[tuple[int, str], Any]:
        out = {}
        for experiment_ref in sorted({k[0] for k in keys}):
            ids = [k[1] for k in keys if k[0] == experiment_ref]
            for row in conn.execute(self._sql.plants, {"experiment_ref": experiment_ref,
                                                       "plant_ids": ids}).mappings():
                out[(experiment_ref, row["plant_id"])] = row
        return out

    def _check_plant(self, values: dict[str, Any], row, record: RunRecord, where: str) -> None:
        conflicts = [f"{name} {values[name]!r} in this run but {row[name]!r} in {where}"
                     for name in PLANT_IDENTITY_FIELDS
                     if _given(values[name]) and _given(row[name]) and values[name] != row[name]]
        if conflicts:
            study = record.metadata.experiment.study_id or "(no study)"
            raise ResultsStoreError(
                f"{self.name}: plant {values['plant_id']!r} of study {study!r}: "
                f"{'; '.join(conflicts)} (run {record.run_dir or record.run_key}); one plant "
                "id is one plant: fix the sample sheet or give the other plant its own id")

    def _define_traits(self, conn: Connection, records: list[RunRecord]) -> None:
        names = [(n, "plant") for r in records for n in r.plant_traits]
        names += [(n, "leaf") for n in LEAF_NUMBERS]
        new = list(dict.fromkeys((n, lvl) for n, lvl in names if n not in self._trait_names))
        if not new:
            return
        rows = []
        for n, lvl in new:
            d = definition(n, lvl)
            rows.append({"name": d.name, "level": d.level, "unit": d.unit,
                         "description": d.description, "method": d.method})
        conn.execute(self._insert(S.trait_definitions).on_conflict_do_nothing(), rows)
        with self._lock:
            self._trait_names.update(n for n, _ in new)

    def delete_run(self, run_key: str) -> bool:
        """Remove one run (by key) and its rows; whether it was there."""
        with self.engine.begin() as conn:
            old = conn.execute(self._sql.runs_by_key, {"keys": [run_key]}).scalars().all()
            if not old:
                return False
            for stmt in self._sql.delete_runs:
                conn.execute(stmt, {"refs": list(old)})
        return True

    # ------------------------------------------------------------------ reading
    def connect(self) -> Connection:
        """A read connection (on SQLite it does not wait for writers)."""
        return self._reader.connect()

    def counts(self) -> dict[str, int]:
        """Rows per table (what a test or a user checks after a batch)."""
        with self.connect() as conn:
            return {t.name: conn.execute(select(func.count()).select_from(t)).scalar_one()
                    for t in S.metadata.sorted_tables}

    def revision(self) -> str | None:
        """The schema revision the database is at (alembic)."""
        from alembic.runtime.migration import MigrationContext

        with self.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    def leaf_traits(self, **filters: Any):
        """One row per leaf of the matching runs: metadata, scan time, traits (pandas).

        See ``plantscan_store.query.leaf_traits`` for the filters.
        """
        from plantscan_store.query import leaf_traits

        return leaf_traits(self, **filters)

    def plant_traits(self, **filters: Any):
        """One row per run: metadata, scan time, plant-level traits as columns (pandas)."""
        from plantscan_store.query import plant_traits

        return plant_traits(self, **filters)


class _Statements:
    """The statements of ``put``, built once per store (building them costs more than running).

    The INSERTs of many rows have RETURNING: SQLAlchemy then sends them as
    multi-row INSERTs ("insertmanyvalues") instead of one INSERT per row.
    """

    def __init__(self, insert) -> None:
        ins = insert(S.scans)
        self.upsert_scan = ins.on_conflict_do_update(
            index_elements=[S.scans.c.scan_uid],
            set_={c: ins.excluded[c] for c in ("plant_ref", "path", "acquired_at", "protocol",
                                                "views")}
        ).returning(S.scans.c.scan_uid, S.scans.c.id)
        self.runs_by_key = select(S.runs.c.id).where(
            S.runs.c.run_key.in_(bindparam("keys", expanding=True)))
        refs = bindparam("refs", expanding=True)
        self.delete_runs = [delete(t).where(t.c.run_ref.in_(refs)) for t in S.RUN_CHILDREN] + [
            delete(S.runs).where(S.runs.c.id.in_(refs))]
        self.insert_run = S.runs.insert().returning(S.runs.c.run_key, S.runs.c.id)
        self.plants = select(S.plants).where(
            S.plants.c.experiment_ref == bindparam("experiment_ref"),
            S.plants.c.plant_id.in_(bindparam("plant_ids", expanding=True)))
        self.insert_plant = insert(S.plants).on_conflict_do_nothing().returning(S.plants.c.id)


def _given(v: Any) -> bool:
    return v not in ("", None, {})


def _leaf_row(run_ref: int, leaf) -> dict[str, Any]:
    c = leaf.centroid_mm or (None, None, None)
    return {"run_ref": run_ref, "leaf_id": leaf.leaf_id, "length_mm": leaf.length_mm,
            "width_mm": leaf.width_mm, "area_mm2": leaf.area_mm2,
            "perimeter_mm": leaf.perimeter_mm, "thick_share": leaf.thick_share,
            "confidence": leaf.confidence, "quality_flag": leaf.quality_flag,
            "confidence_reasons": leaf.confidence_reasons, "centroid_x_mm": c[0],
            "centroid_y_mm": c[1], "centroid_z_mm": c[2]}


def _utcnow() -> _dt.datetime:
    return _dt.datetime.now(_dt.UTC).replace(tzinfo=None, microsecond=0)


def _first_line(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None) or exc
    return str(orig).strip().splitlines()[0] if str(orig).strip() else type(orig).__name__


def _retryable(exc: DBAPIError) -> bool:
    if isinstance(exc, IntegrityError):
        return True
    code = getattr(getattr(exc, "orig", None), "sqlstate", None)
    return code in ("40001", "40P01")  # serialization failure, deadlock detected

"""Registers the results stores ``sqlite`` and ``postgresql`` and the store/query commands."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, field_validator

from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import ResultsStore, RunResult, StageParams


def _store_run(target: str | Path, run: RunResult) -> dict[str, Any]:
    from plantscan_store.records import record_from_run_dir
    from plantscan_store.store import Store

    record = record_from_run_dir(Path(run.run_dir))
    with Store(target) as store:
        store.put(record)
        name = store.name
    return {"store": name, "run_key": record.run_key, "plant_id": record.plant_id,
            "leaves": len(record.leaves)}


class SqliteStore(ResultsStore):
    """An embedded SQLite file (the default: zero set-up, one machine)."""

    name = "sqlite"

    class Params(StageParams):
        path: str = Field("results.sqlite", min_length=1, description="the SQLite file; a "
                          "relative path is taken from the folder that holds the run folder "
                          "(a batch's --out, or beside the scan for `plantscan process`)")

    def target(self, run_dir: Path) -> Path:
        p = Path(self.params.path).expanduser()
        return p if p.is_absolute() else Path(run_dir).resolve().parent / p

    def store(self, run: RunResult) -> dict[str, Any]:
        return _store_run(self.target(Path(run.run_dir)), run)


class PostgresStore(ResultsStore):
    """A PostgreSQL database (a centre's shared store; several machines write to it)."""

    name = "postgresql"

    class Params(StageParams):
        url: str = Field(description="postgresql://USER@HOST:PORT/DBNAME; the password "
                         "comes from PGPASSWORD or ~/.pgpass, never from the recipe")

        @field_validator("url")
        @classmethod
        def _postgres_url(cls, v: str) -> str:
            from sqlalchemy.engine import make_url
            from sqlalchemy.exc import ArgumentError

            try:
                url = make_url(v)
            except ArgumentError:
                raise ValueError(f"{v!r} is not a database URL "
                                 "(postgresql://USER@HOST:PORT/DBNAME)") from None
            if url.get_backend_name() not in ("postgresql", "postgres"):
                raise ValueError(f"{v!r} is not a postgresql:// URL")
            if url.password:
                raise ValueError("the URL holds a password: put it in PGPASSWORD or ~/.pgpass, "
                                 "not in the recipe")
            return v

    def store(self, run: RunResult) -> dict[str, Any]:
        return _store_run(self.params.url, run)


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(SqliteStore)
    registry.add(PostgresStore)


@hookimpl
def plantscan_add_commands(subparsers) -> None:
    from plantscan_store.cli import add_commands

    add_commands(subparsers)

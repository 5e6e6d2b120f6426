"""Exporter ``csv``: the traits table (``traits.csv``, ``plant_traits.json``, ``traits.parquet``).

``traits.csv`` and ``plant_traits.json`` follow docs/formats.md (the same files
the measure stage writes, so the exporter also works on a run rebuilt from
disk).  ``traits.parquet`` is added when pyarrow is importable: one row per
leaf with the plant id, recipe name, scan time (UTC) and the plant's metadata
(study, genotype, treatment, replicate, sowing date, ``factor.NAME``; from
``run.json``) as columns, and the plant-level traits as columns repeated on
every row, so many plants' files concatenate into one table.
"""

from __future__ import annotations

import importlib.util
import io
from pathlib import Path

from plantscan_core.data import LEAF_TRAIT_COLUMNS, Traits
from plantscan_core.scanfolder import atomic_write_bytes
from plantscan_core.stages import Exporter, RunResult, StageParams


def plant_id_of(run: RunResult) -> str:
    """The plant id of a run: its resolved metadata's (``run.json``), else the scan's
    ``plant_id``, else the recipe's ``plant.id``."""
    resolved = ((run.info or {}).get("metadata") or {}).get("plant", {}).get("id")
    if resolved:
        return str(resolved)
    scan_id = run.scan.info.get("plant_id") if run.scan is not None else None
    if scan_id:
        return str(scan_id)
    return str(run.recipe.plant.id) if run.recipe is not None else ""


def parquet_available() -> bool:
    return importlib.util.find_spec("pyarrow") is not None


IDENTITY_COLUMNS = ("investigation_id", "study_id", "species", "genotype", "accession",
                    "treatment", "replicate", "sowing_date")


def identity_of(run: RunResult) -> dict[str, object]:
    """Scan time and the plant's metadata of a run (``run.json``: ``scan_record``, ``metadata``)."""
    info = run.info or {}
    md = info.get("metadata") or {}
    merged = {**(md.get("experiment") or {}), **(md.get("plant") or {})}
    out: dict[str, object] = {"scan_time": (info.get("scan_record") or {}).get("acquired_at", "")}
    out.update({c: merged.get(c) for c in IDENTITY_COLUMNS})
    out.update({f"factor.{k}": v for k, v in sorted((merged.get("factors") or {}).items())})
    return out


def traits_parquet_bytes(traits: Traits, plant_id: str, recipe_name: str,
                         identity: dict[str, object] | None = None) -> bytes:
    """Parquet file (bytes) of the per-leaf table: plant id, recipe, scan time and metadata
    (``identity``), leaf traits, plant-level traits."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = len(traits.leaves)
    columns: dict[str, list] = {"plant_id": [plant_id] * n, "recipe": [recipe_name] * n}
    for key, value in (identity or {}).items():
        columns[key] = [value] * n
    for name in LEAF_TRAIT_COLUMNS:
        columns[name] = [getattr(leaf, name) for leaf in traits.leaves]
    for key, value in sorted(traits.plant.items()):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue  # flags and lists (the quality record) are not columns
        # counts stay integers (leaf_count), measurements floats
        count = isinstance(value, int) or key.endswith("_count")
        columns[f"plant_{key}"] = [int(value) if count else float(value)] * n
    table = pa.table(columns)
    buf = io.BytesIO()
    pq.write_table(table, buf)
    return buf.getvalue()


class CsvExporter(Exporter):
    """``traits.csv`` + ``plant_traits.json`` (+ ``traits.parquet`` with pyarrow)."""

    name = "csv"

    class Params(StageParams):
        parquet: bool = True
        """Also write ``traits.parquet`` when pyarrow is importable."""

    def export(self, run: RunResult) -> list[Path]:
        if run.traits is None:
            return []
        run_dir = Path(run.run_dir)
        csv_path, json_path = run_dir / "traits.csv", run_dir / "plant_traits.json"
        run.traits.save(csv_path, json_path)
        written = [csv_path, json_path]
        if self.params.parquet and parquet_available():
            path = run_dir / "traits.parquet"
            recipe_name = run.recipe.name if run.recipe is not None else ""
            atomic_write_bytes(path, traits_parquet_bytes(run.traits, plant_id_of(run),
                                                          recipe_name, identity_of(run)))
            written.append(path)
        return written

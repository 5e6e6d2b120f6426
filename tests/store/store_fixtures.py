"""Synthetic runs for the store tests: records whose every value is known.

A record's leaves have areas that encode plant, day and leaf (``leaf_area``),
so a test can tell any row it reads back from any other.
"""

from __future__ import annotations

import datetime as _dt
import hashlib

from plantscan_store.records import LeafRecord, RunRecord, ScanRecord, WarningRecord

from plantscan_core.metadata import ExperimentSpec, Metadata, PlantSpec

DAY0 = _dt.datetime(2026, 5, 4, 9, 0, 0)


def leaf_area(plant: int, day: int, leaf: int) -> float:
    return 1000.0 * plant + 10.0 * day + leaf + 0.5


def make_record(plant: int = 1, day: int = 0, n_leaves: int = 20, *, study: str = "S1",
                genotype: str | None = None, treatment: str | None = None,
                replicate: int | None = None, recipe_hash: str = "recipe-a",
                quality_flag: str | None = "ok", leaf_flags: list[str | None] | None = None,
                sowing_date: _dt.date | None = _dt.date(2026, 5, 1)) -> RunRecord:
    """The run of plant ``plant`` on day ``day`` of study ``study`` (everything synthetic)."""
    genotype = genotype if genotype is not None else ("Col-0" if plant % 2 else "Ler")
    treatment = treatment if treatment is not None else ("drought" if plant % 4 < 2
                                                         else "control")
    md = Metadata(
        PlantSpec(id=f"P{plant:04d}", species="Arabidopsis thaliana", genotype=genotype,
                  treatment=treatment, replicate=replicate, sowing_date=sowing_date,
                  factors={"watering": "30%" if treatment == "drought" else "100%"}),
        ExperimentSpec(investigation_id="INV1", study_id=study, study_title=f"study {study}"))
    uid = hashlib.sha256(f"{study}/{plant}/{day}".encode()).hexdigest()[:32]
    scan = ScanRecord(uid, f"/scans/{study}/P{plant:04d}/day{day}", DAY0 +
                      _dt.timedelta(days=day, minutes=plant), "paper-72", 72)
    flags = leaf_flags or [None] * n_leaves
    leaves = [LeafRecord(i, 100.0 + i, 40.0 + i, leaf_area(plant, day, i), 250.0 + i, 0.01,
                         0.9, flags[i], (10.0 * i, -5.0 * i, 100.0 + i))
              for i in range(n_leaves)]
    return RunRecord(
        metadata=md, scan=scan, recipe_name="test-recipe", recipe_hash=recipe_hash,
        leaves=leaves,
        plant_traits={"leaf_count": float(n_leaves), "height_mm": 100.0 + day,
                      "total_leaf_area_mm2": sum(leaf.area_mm2 for leaf in leaves)},
        quality_flag=quality_flag,
        warnings=[WarningRecord("measure", "leaf 3 is thick", "thick-leaf", 3)],
        run_dir=f"/runs/{study}/P{plant:04d}/day{day}", plantscan_version="test",
        plugins={"measure": {"plugin": "leaf-geometry", "version": "0"}},
        provenance={"created": "2026-05-04T09:00:00+00:00"})

"""The virtual growth experiment's truth as a table, and store records made from it.

The design is ``plantscan_sim.experiment.growth_design`` (2 genotypes = the
dicot and branched families, 2 treatments, 3 replicates = validation seeds,
5 days).  Building its 60 truth plants costs 15-30 s (the mature plans'
crossing checks), so the tests read the truth from ``data/virtual_growth_truth.csv``,
written by this module, and ``test_the_truth_table_is_the_simulators`` rebuilds
plants of it to catch a table the virtual scanner no longer agrees with.
Regenerate it with::

    .venv/bin/python tests/store/virtual_truth.py
"""

from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TRUTH_CSV = HERE / "data" / "virtual_growth_truth.csv"
GENOTYPES = {"G1": "dicot", "G2": "branched"}
DAYS, REPLICATES, FIRST_AGE = 5, 3, 14.0
KEY_COLUMNS = ("plant_id", "day", "leaf_id")


def design():
    from plantscan_sim.experiment import growth_design

    return growth_design(GENOTYPES, DAYS, REPLICATES, FIRST_AGE)


def truth_rows(scan) -> list[dict]:
    """The table's rows of one planned scan: one per truth leaf, with the plant's height."""
    from plantscan_sim.experiment import truth_leaves, truth_plant

    plant = truth_plant(scan)
    height = plant.traits().plant["height_mm"]
    return [{"plant_id": scan.plant_id, "day": scan.day, "height_mm": height, **leaf}
            for leaf in truth_leaves(plant)]


def write_truth_table(path: Path = TRUTH_CSV) -> int:
    rows = [r for scan in design() for r in truth_rows(scan)]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: f"{v:.4f}" if isinstance(v, float) else v for k, v in r.items()})
    return len(rows)


def read_truth_table(path: Path = TRUTH_CSV) -> list[dict]:
    with path.open() as f:
        return [{k: (v if k == "plant_id" else int(v) if k in KEY_COLUMNS else float(v))
                 for k, v in r.items()} for r in csv.DictReader(f)]


def turned(rows: list[dict], degrees: float) -> list[dict]:
    """``rows`` with the plant turned about the turntable axis (its pot put back at another
    angle): centroids rotated by ``degrees``."""
    a = np.radians(degrees)
    out = []
    for r in rows:
        x, y = r["centroid_x_mm"], r["centroid_y_mm"]
        out.append({**r, "centroid_x_mm": x * np.cos(a) - y * np.sin(a),
                    "centroid_y_mm": x * np.sin(a) + y * np.cos(a)})
    return out


def records(truth: list[dict], sheet, seed: int = 0):
    """One ``RunRecord`` per planned scan, its traits the truth's.

    Metadata come from the experiment's sample sheet (``sheet``, a loaded
    ``SampleSheet``), as ``plantscan batch --sample-sheet`` resolves them; the
    pot is put back at a random angle every day and the leaves are numbered in
    a random order, as a measurer numbers them (``truth_leaf`` keeps the truth's
    id: ``{record.scan.uid: {leaf_id: truth id}}``).
    """
    from plantscan_store.records import LeafRecord, RunRecord, ScanRecord

    from plantscan_core.metadata import ExperimentSpec, PlantSpec

    rng = np.random.default_rng(seed)
    by_scan: dict[tuple[str, int], list[dict]] = {}
    for r in truth:
        by_scan.setdefault((r["plant_id"], r["day"]), []).append(r)
    out, truth_leaf = [], {}
    for scan in design():
        rows = by_scan[(scan.plant_id, scan.day)]
        if scan.day:
            rows = turned(rows, float(rng.uniform(-180.0, 180.0)))
        order = rng.permutation(len(rows))
        metadata = sheet.metadata_for(PlantSpec(id=scan.plant_id), ExperimentSpec(), None,
                                      None)
        uid = hashlib.sha256(f"{scan.plant_id}/{scan.day}".encode()).hexdigest()[:32]
        leaves = [LeafRecord(n + 1, r["length_mm"], r["width_mm"], r["area_mm2"],
                             r["perimeter_mm"], centroid_mm=(r["centroid_x_mm"],
                                                             r["centroid_y_mm"],
                                                             r["centroid_z_mm"]))
                  for n, r in enumerate(rows[i] for i in order)]
        truth_leaf[uid] = {n + 1: rows[i]["leaf_id"] for n, i in enumerate(order)}
        out.append(RunRecord(
            metadata=metadata,
            scan=ScanRecord(uid, f"/virtual/day{scan.day + 1}/{scan.plant_id}",
                            scan.scan_time, "paper-72", 72),
            recipe_name=f"virtual-growth-{scan.family}", recipe_hash=scan.family,
            leaves=leaves,
            plant_traits={"height_mm": rows[0]["height_mm"], "leaf_count": float(len(rows)),
                          "total_leaf_area_mm2": float(sum(r["area_mm2"] for r in rows))},
            run_dir=f"/virtual/runs/day{scan.day + 1}/{scan.plant_id}",
            plantscan_version="test",
            provenance={"created": _dt.datetime(2026, 5, 9).isoformat()}))
    return out, truth_leaf


if __name__ == "__main__":
    n = write_truth_table(Path(sys.argv[1]) if len(sys.argv) > 1 else TRUTH_CSV)
    print(f"{n} truth leaves -> {TRUTH_CSV}")

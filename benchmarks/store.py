"""Results store load: 1,000 plants x 20 leaves, SQLite and PostgreSQL, beside a CSV file.

    python benchmarks/store.py [--plants 1000] [--leaves 20] [--repeats 3]

Stores the same synthetic runs (``tests/store/store_fixtures.make_record``)
into a fresh store each time, by:

* **CSV append** -- the simplest correct alternative: one ``traits_all.csv``
  row per leaf written with ``csv.writer`` (no idempotence, no concurrency
  safety, no query);
* **put_many** -- ``Store.put_many`` (100 runs per transaction; what
  ``plantscan store`` does);
* **put per run** -- ``Store.put`` (one transaction per run; what each batch
  worker does at the end of its plant).

PostgreSQL is a throw-away server on this machine (``TempPostgres``).  Writes
``docs/benchmarks/store.md``.  The issue's target: 1,000 x 20 in <= 10 s on each.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "store"))

from plantscan_store import Store  # noqa: E402
from plantscan_store.pgserver import TempPostgres  # noqa: E402
from store_fixtures import make_record  # noqa: E402


def csv_append(records, path: Path) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", "scan_time", "genotype", "treatment", "leaf_id", "length_mm",
                    "width_mm", "area_mm2", "perimeter_mm"])
        for r in records:
            p = r.metadata.plant
            for leaf in r.leaves:
                w.writerow([p.id, r.scan.acquired_at.isoformat(), p.genotype, p.treatment,
                            leaf.leaf_id, leaf.length_mm, leaf.width_mm, leaf.area_mm2,
                            leaf.perimeter_mm])
        f.flush()
        os.fsync(f.fileno())


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--plants", type=int, default=1000)
    ap.add_argument("--leaves", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    records = [make_record(plant=p, n_leaves=args.leaves) for p in range(args.plants)]
    results: dict[str, list[float]] = {}
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(dir="/work/cache" if Path("/work/cache").is_dir()
                                     else None) as tmp, TempPostgres() as pg:
        tmp = Path(tmp)
        for rep in range(args.repeats):
            results.setdefault("CSV append", []).append(
                timed(lambda rep=rep: csv_append(records, tmp / f"traits-{rep}.csv")))
            for backend in ("SQLite", "PostgreSQL"):
                for method in ("put_many", "put per run"):
                    name = f"{backend} {method}"
                    target = (str(tmp / f"{method.replace(' ', '-')}-{rep}.sqlite")
                              if backend == "SQLite" else
                              pg.create_database(f"b_{method.replace(' ', '_')}_{rep}"))
                    store = Store(target)  # schema created outside the timing
                    if method == "put_many":
                        seconds = timed(lambda store=store: store.put_many(records))
                    else:
                        seconds = timed(lambda store=store: [store.put(r) for r in records])
                    counts = store.counts()
                    assert counts["runs"] == args.plants
                    assert counts["leaves"] == args.plants * args.leaves
                    store.close()
                    results.setdefault(name, []).append(seconds)
                    print(f"{name}: {seconds:.2f} s", flush=True)
    load1 = os.getloadavg()[0]
    rows = "\n".join(
        f"| {name} | {statistics.median(v):.2f} | {min(v):.2f} | {max(v):.2f} | "
        f"{args.plants * args.leaves / statistics.median(v):,.0f} |"
        for name, v in results.items())
    page = f"""# Results store load (`benchmarks/store.py`)

{args.plants} plants x {args.leaves} leaves (synthetic runs with full metadata, 3 plant
traits and a warning each) stored into a fresh store, {args.repeats} repeats; median, min
and max seconds.  *CSV append* is the simplest correct alternative (one CSV row per leaf,
fsynced once): no idempotence, no concurrent writers, no query.  PostgreSQL 15 is a
throw-away server on the same machine (127.0.0.1), default settings (durable commits).
`put_many` stores 100 runs per transaction (`plantscan store`); *put per run* is one
transaction per run (what each batch worker does for its plant).  Target (issue 25):
1,000 x 20 in <= 10 s on each back-end.

Machine load average {load0:.1f} before, {load1:.1f} after (2 cores shared with other jobs).

| method | median s | min s | max s | leaves / s |
|---|---|---|---|---|
{rows}

One transaction per run costs a disk flush per run (about 10 ms on this machine's disk),
hence the grouped `put_many` for bulk loads; each group is still stored whole or not at all.
On PostgreSQL the leaves go by COPY (psycopg's executemany sends one INSERT per row:
docs/decisions.md).
"""
    out = ROOT / "docs" / "benchmarks" / "store.md"
    out.write_text(page)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

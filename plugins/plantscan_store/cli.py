"""``plantscan store`` and ``plantscan query``: run folders in, traits (and reports) out."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from plantscan_core.errors import PlantScanError

DEFAULT_DB = "results.sqlite"


def _db_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", default=DEFAULT_DB,
                   help="the results store: a SQLite file (default results.sqlite) or "
                   "postgresql://USER@HOST:PORT/DBNAME")


def cmd_store(args) -> int:
    from plantscan_core.metadata import SampleSheetError, load_sample_sheet
    from plantscan_store.records import find_run_dirs, record_from_run_dir
    from plantscan_store.store import Store

    sheet = load_sample_sheet(args.sample_sheet) if args.sample_sheet else None
    run_dirs = find_run_dirs([Path(p) for p in args.runs])
    # Read every run (and check the sheet against them) before writing anything.
    records, errors = [], []
    for run_dir in run_dirs:
        try:
            records.append(record_from_run_dir(run_dir, sheet))
        except PlantScanError as exc:
            errors.append((str(run_dir), str(exc)))
    if errors and not args.skip_bad:
        raise SampleSheetError(errors, "plantscan store") if sheet else PlantScanError(
            "\n".join(f"{w}: {m}" for w, m in errors))
    with Store(args.db) as store:
        n = store.put_many(records)
        counts = store.counts()
    for where, msg in errors:
        print(f"skipped {where}: {msg}", file=sys.stderr)
    print(f"{store.name}: stored {n} run(s) ({sum(len(r.leaves) for r in records)} leaves); "
          f"the store holds {counts['runs']} runs of {counts['plants']} plants, "
          f"{counts['leaves']} leaves")
    return 1 if errors else 0


def _filters(args) -> dict:
    return {"investigation": args.investigation, "study": args.study or None,
            "plant": args.plant or None, "genotype": args.genotype or None,
            "treatment": args.treatment or None, "since": args.since, "until": args.until,
            "quality": args.quality or None, "runs": args.runs}


def cmd_query(args) -> int:
    from plantscan_store.store import Store

    with Store(args.db) as store:
        filters = _filters(args)
        try:
            if args.isa_tab:
                from plantscan_store.isatab import export_isatab, validate_isatab

                files = export_isatab(store, Path(args.isa_tab), **filters)
                validate_isatab(Path(args.isa_tab))
                print(f"{args.isa_tab}: ISA-Tab, {len(files)} files: "
                      + ", ".join(p.name for p in files))
                return 0
            if args.report:
                from plantscan_store.report import write_experiment_report

                out = write_experiment_report(store, Path(args.report), trait=args.trait,
                                              **filters)
                print(f"{out}: experiment report")
                return 0
            if args.level == "leaf":
                df = store.leaf_traits(**filters)
            elif args.level == "plant":
                df = store.plant_traits(**filters)
            else:
                from plantscan_store.timeseries import leaf_series

                df = leaf_series(store.leaf_traits(**filters))
        except ValueError as exc:
            raise PlantScanError(f"query: {exc}") from None
    if args.out:
        return _write(df, Path(args.out))
    if df.empty:
        print("no rows match")
        return 0
    _print(df, args.level)
    return 0


def _write(df, out: Path) -> int:
    if out.suffix == ".parquet":
        try:
            df.to_parquet(out, index=False)
        except ImportError as exc:
            raise PlantScanError(f"{out}: Parquet needs pyarrow (pip install pyarrow)") from exc
    elif out.suffix in (".csv", ".tsv"):
        df.to_csv(out, index=False, sep="\t" if out.suffix == ".tsv" else ",")
    else:
        raise PlantScanError(f"{out}: unknown output format {out.suffix!r}; valid: .csv, "
                             ".tsv, .parquet")
    print(f"{out}: {len(df)} rows")
    return 0


def _print(df, level: str) -> None:
    from rich.console import Console
    from rich.table import Table

    keep = ["study_id", "plant_id", "genotype", "treatment", "scan_time"]
    if level == "leaf":
        keep += ["leaf_id", "length_mm", "width_mm", "area_mm2", "perimeter_mm", "confidence",
                 "quality_flag"]
    elif level == "plant":
        keep += [c for c in ("leaf_count", "total_leaf_area_mm2", "height_mm") if c in df]
        keep += ["plant_quality_flag", "warnings"]
    else:
        keep += ["track", "leaf_id", "length_mm", "area_mm2", "quality_flag"]
    table = Table()
    for c in keep:
        table.add_column(c)
    for _, row in df[keep].iterrows():
        table.add_row(*(_cell(row[c]) for c in keep))
    Console().print(table)
    print(f"{len(df)} rows; --out FILE.csv or .parquet for every column")


def _cell(v) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return ""
    if isinstance(v, float):
        return f"{v:.2f}"
    if hasattr(v, "isoformat"):
        return v.isoformat(sep=" ") if hasattr(v, "hour") else v.isoformat()
    return str(v)


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("store", help="put run folders (or batch folders) in a results "
                              "store (SQLite or PostgreSQL)")
    p.add_argument("runs", nargs="+", help="run folders, or folders of run folders (a batch)")
    _db_arg(p)
    p.add_argument("--sample-sheet", help="CSV of plant metadata per scan or plant id; "
                   "overrides what the runs recorded (docs/experiments.md)")
    p.add_argument("--skip-bad", action="store_true",
                   help="store the readable runs and list the others (exit 1)")
    p.set_defaults(func=cmd_store)

    p = subparsers.add_parser("query", help="traits from a results store: print, CSV, Parquet, "
                              "ISA-Tab, experiment report")
    _db_arg(p)
    p.add_argument("--level", choices=("leaf", "plant", "timeseries"), default="plant",
                   help="one row per leaf, per plant scan (default), or per leaf with its "
                   "track: the same leaf across the scans of its plant")
    p.add_argument("--investigation", help="MIAPPE investigation id")
    p.add_argument("--study", action="append", help="MIAPPE study id (repeatable)")
    p.add_argument("--plant", action="append", help="plant id (repeatable)")
    p.add_argument("--genotype", action="append", help="genotype (repeatable)")
    p.add_argument("--treatment", action="append", help="treatment (repeatable)")
    p.add_argument("--since", help="scans from this date/time on (YYYY-MM-DD or ISO 8601, UTC)")
    p.add_argument("--until", help="scans up to this date (whole day) or time")
    p.add_argument("--quality", action="append", choices=("ok", "check", "fail", "none"),
                   help="quality flag (repeatable; none = no flag)")
    p.add_argument("--runs", choices=("latest", "all"), default="latest",
                   help="each scan's latest stored run (default) or every run")
    p.add_argument("--out", help="write the table: .csv, .tsv or .parquet")
    p.add_argument("--isa-tab", metavar="DIR", help="write a MIAPPE/ISA-Tab export of the "
                   "matching runs into DIR (checked against its stated columns)")
    p.add_argument("--report", metavar="HTML", help="write the experiment report: growth "
                   "curves per plant and per treatment group, quality flags shown")
    p.add_argument("--trait", default="total_leaf_area_mm2",
                   help="plant-level trait of the report (default total_leaf_area_mm2)")
    p.set_defaults(func=cmd_query)

"""plantscan's results store: experiments, plants, scans, runs and traits in SQLite or PostgreSQL.

>>> from plantscan_store import Store
>>> store = Store("results.sqlite")                   # or "postgresql://lab@db/phenomics"
>>> df = store.leaf_traits(study="drought-2026", genotype="Col-0")   # a pandas DataFrame
>>> growth = store.plant_traits(study="drought-2026")                # one row per scan

``plantscan store`` puts run folders in a store, ``plantscan query`` gets traits
out (CSV, Parquet, ISA-Tab, an experiment report); docs/experiments.md.
"""

from __future__ import annotations

from plantscan_store.records import RunRecord, find_run_dirs, record_from_run_dir
from plantscan_store.store import ResultsStoreError, Store, store_url

__all__ = ["ResultsStoreError", "RunRecord", "Store", "find_run_dirs", "record_from_run_dir",
           "store_url"]

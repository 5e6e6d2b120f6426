"""Getting traits out of a store as pandas DataFrames, filtered by experiment, plant, date, flag.

Every row carries the plant's identity and metadata (study, plant id,
genotype, treatment, replicate, sowing date, ``factor.NAME`` columns), its
scan time (``scan_time``, UTC) and ``days_after_sowing`` when the sowing date
is known.  By default each scan contributes its latest stored run (a scan
processed with two recipes has two runs: ``runs="all"`` returns both, with
``recipe_name`` telling them apart).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from sqlalchemy import Select, func, literal, or_, select

from plantscan_store import schema as S

if TYPE_CHECKING:
    import pandas as pd

    from plantscan_store.store import Store

PLANT_COLUMNS = ("investigation_id", "study_id", "plant_id", "species", "genotype", "accession",
                 "biological_material_id", "treatment", "replicate", "sowing_date")
LEAF_TRAITS = ("length_mm", "width_mm", "area_mm2", "perimeter_mm")
LEAF_QUALITY = ("thick_share", "confidence", "confidence_reasons", "quality_flag")
UNFLAGGED = "none"  # the quality filter's name for rows without a flag


def _as_list(v: str | Iterable[str] | None) -> list[str] | None:
    if v is None:
        return None
    return [v] if isinstance(v, str) else list(v)


def _as_time(v: Any) -> tuple[_dt.datetime, bool] | None:
    """(naive UTC time, whether ``v`` was a whole day) of a date, datetime or ISO string."""
    if v is None or v == "":
        return None
    if isinstance(v, str):
        text = v.strip()
        try:
            v = _dt.datetime.fromisoformat(text) if len(text) > 10 else \
                _dt.date.fromisoformat(text)
        except ValueError:
            raise ValueError(f"{text!r} is not a date (YYYY-MM-DD) or an ISO 8601 time") from None
    if isinstance(v, _dt.datetime):
        if v.tzinfo is not None:
            v = v.astimezone(_dt.UTC).replace(tzinfo=None)
        return v, False
    if isinstance(v, _dt.date):
        return _dt.datetime.combine(v, _dt.time()), True
    raise ValueError(f"{v!r} is not a date or a time")


def _base(runs: str) -> Select:
    if runs not in ("latest", "all"):
        raise ValueError(f"runs must be 'latest' or 'all', got {runs!r}")
    r, s, p, e = S.runs, S.scans, S.plants, S.experiments
    q = (select(e.c.investigation_id, e.c.study_id, p.c.plant_id, p.c.species, p.c.genotype,
                p.c.accession, p.c.biological_material_id, p.c.treatment, p.c.replicate,
                p.c.sowing_date, p.c.factors, s.c.acquired_at.label("scan_time"),
                s.c.scan_uid, s.c.path.label("scan_path"), r.c.recipe_name, r.c.recipe_hash,
                r.c.run_key, r.c.run_dir, r.c.id.label("run_ref"),
                r.c.quality_flag.label("plant_quality_flag"),
                r.c.quality_reasons.label("plant_quality_reasons"))
         .select_from(r.join(s, r.c.scan_ref == s.c.id).join(p, s.c.plant_ref == p.c.id)
                      .join(e, p.c.experiment_ref == e.c.id)))
    if runs == "latest":
        latest = select(func.max(r.c.id)).group_by(r.c.scan_ref).scalar_subquery()
        q = q.where(r.c.id.in_(latest))
    return q


def _filtered(q: Select, *, investigation=None, study=None, plant=None, genotype=None,
              treatment=None, since=None, until=None) -> Select:
    e, p, s = S.experiments, S.plants, S.scans
    for column, value in ((e.c.investigation_id, investigation), (e.c.study_id, study),
                          (p.c.plant_id, plant), (p.c.genotype, genotype),
                          (p.c.treatment, treatment)):
        values = _as_list(value)
        if values is not None:
            q = q.where(column.in_(values))
    start, end = _as_time(since), _as_time(until)
    if start is not None:
        q = q.where(s.c.acquired_at >= start[0])
    if end is not None:  # a date as the end: the whole day is in
        t, whole_day = end
        q = q.where(s.c.acquired_at < t + _dt.timedelta(days=1) if whole_day
                    else s.c.acquired_at <= t)
    return q


def _quality_clause(column, quality):
    flags = _as_list(quality)
    if flags is None:
        return None
    bad = sorted(set(flags) - set(S.QUALITY_FLAGS) - {UNFLAGGED})
    if bad:
        raise ValueError(f"unknown quality flag(s) {bad}; valid: "
                         f"{', '.join((*S.QUALITY_FLAGS, UNFLAGGED))}")
    named = [f for f in flags if f != UNFLAGGED]
    parts = [column.in_(named)] if named else []
    if UNFLAGGED in flags:
        parts.append(column.is_(None))
    return or_(*parts) if parts else literal(False)


def _frame(store: Store, q: Select):
    import pandas as pd

    with store.connect() as conn:
        rows = conn.execute(q).mappings().all()
    df = pd.DataFrame([dict(r) for r in rows])
    if df.empty:
        return df
    factors = df.pop("factors")
    names = sorted({k for f in factors if f for k in f})
    for name in names:
        df[f"factor.{name}"] = [(f or {}).get(name, "") for f in factors]
    df["scan_time"] = pd.to_datetime(df["scan_time"])
    sow = pd.to_datetime(df["sowing_date"])
    df["days_after_sowing"] = (df["scan_time"] - sow).dt.total_seconds() / 86400.0
    df["replicate"] = df["replicate"].astype("Int64")
    return df


def leaf_traits(store: Store, *, investigation: str | None = None,
                study: str | Iterable[str] | None = None, plant: str | Iterable[str] | None = None,
                genotype: str | Iterable[str] | None = None,
                treatment: str | Iterable[str] | None = None, since: Any = None,
                until: Any = None, quality: str | Iterable[str] | None = None,
                runs: str = "latest") -> pd.DataFrame:
    """One row per leaf: plant metadata, ``scan_time``, leaf traits (mm, mm²) and flags.

    Parameters
    ----------
    investigation, study, plant, genotype, treatment : str or list of str, optional
        Keep rows whose value is one of these.
    since, until : date, datetime or ISO string, optional
        Scan time range, inclusive (a date covers its whole day; UTC).
    quality : str or list of {"ok", "check", "fail", "none"}, optional
        Keep leaves whose flag (the leaf's own, else its plant's) is one of
        these; ``"none"``: no flag.
    runs : {"latest", "all"}
        Each scan's latest stored run, or every run.

    Returns
    -------
    DataFrame
        Columns ``PLANT_COLUMNS``, ``factor.NAME``..., ``scan_time``,
        ``days_after_sowing``, ``recipe_name``, ``run_key``, ``leaf_id``,
        ``length_mm``, ``width_mm``, ``area_mm2``, ``perimeter_mm``,
        ``thick_share``, ``confidence``, ``confidence_reasons``, ``quality_flag``
        (leaf), ``plant_quality_flag``, ``plant_quality_reasons``,
        ``centroid_{x,y,z}_mm``; sorted by study, plant, scan time and leaf id.
    """
    lv = S.leaves
    q = _base(runs).add_columns(
        lv.c.leaf_id, *(lv.c[c] for c in LEAF_TRAITS), *(lv.c[c] for c in LEAF_QUALITY),
        lv.c.centroid_x_mm, lv.c.centroid_y_mm, lv.c.centroid_z_mm,
    ).join_from(S.runs, lv, lv.c.run_ref == S.runs.c.id)
    q = _filtered(q, investigation=investigation, study=study, plant=plant, genotype=genotype,
                  treatment=treatment, since=since, until=until)
    clause = _quality_clause(func.coalesce(lv.c.quality_flag, S.runs.c.quality_flag), quality)
    if clause is not None:
        q = q.where(clause)
    q = q.order_by(S.experiments.c.study_id, S.plants.c.plant_id, S.scans.c.acquired_at,
                   S.runs.c.id, lv.c.leaf_id)
    return _frame(store, q)


def plant_traits(store: Store, *, investigation: str | None = None,
                 study: str | Iterable[str] | None = None,
                 plant: str | Iterable[str] | None = None,
                 genotype: str | Iterable[str] | None = None,
                 treatment: str | Iterable[str] | None = None, since: Any = None,
                 until: Any = None, quality: str | Iterable[str] | None = None,
                 runs: str = "latest") -> pd.DataFrame:
    """One row per run (scan): plant metadata, ``scan_time`` and plant-level traits as columns.

    Filters as ``leaf_traits`` (``quality`` on the plant's flag).  Trait
    columns are every plant-level trait stored (``height_mm``,
    ``total_leaf_area_mm2``, ``leaf_count``...); ``warnings`` counts what the
    stages warned about.
    """
    import pandas as pd

    q = _filtered(_base(runs), investigation=investigation, study=study, plant=plant,
                  genotype=genotype, treatment=treatment, since=since, until=until)
    clause = _quality_clause(S.runs.c.quality_flag, quality)
    if clause is not None:
        q = q.where(clause)
    q = q.order_by(S.experiments.c.study_id, S.plants.c.plant_id, S.scans.c.acquired_at,
                   S.runs.c.id)
    df = _frame(store, q)
    if df.empty:
        return df
    refs = [int(x) for x in df["run_ref"]]
    t, w = S.plant_traits, S.run_warnings
    with store.connect() as conn:
        traits = conn.execute(select(t.c.run_ref, t.c.trait, t.c.value)
                              .where(t.c.run_ref.in_(refs))).all()
        warns = dict(conn.execute(select(w.c.run_ref, func.count()).where(w.c.run_ref.in_(refs))
                                  .group_by(w.c.run_ref)).all())
    wide = pd.DataFrame(traits, columns=["run_ref", "trait", "value"]).pivot(
        index="run_ref", columns="trait", values="value")
    df = df.join(wide, on="run_ref")
    df["warnings"] = [int(warns.get(r, 0)) for r in refs]
    return df


def runs_of(store: Store, **filters: Any) -> list[dict[str, Any]]:
    """The runs (latest per scan) matching ``filters`` as plain rows (no pandas)."""
    q = _filtered(_base("latest"), **filters)
    with store.connect() as conn:
        return [dict(r) for r in conn.execute(q).mappings().all()]



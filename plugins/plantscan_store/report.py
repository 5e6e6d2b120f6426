"""The experiment report: growth curves per plant and per treatment group, one offline HTML page.

Like the plant report, plotly.js is inline (no CDN: the page opens on an
offline lab machine).  Each plant's curve is a plant-level trait over days
(after sowing when the sowing date is known, else since the plant's first
scan), coloured by its group (genotype x treatment); each point's marker is
its quality flag (circle ok, triangle check, cross fail, open circle unflagged)
and hovering it names the plant, the scan time, the flag, why the measurer
flagged it and how many warnings the stages gave.  A second figure shows each group's mean and
standard deviation per day; a table lists every plant.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING, Any

from plantscan_core.scanfolder import atomic_write_text
from plantscan_store.timeseries import plant_series

if TYPE_CHECKING:
    import pandas as pd

    from plantscan_store.store import Store

FLAG_SYMBOLS = {"ok": "circle", "check": "triangle-up", "fail": "x", None: "circle-open"}
PALETTE = ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d",
           "#666666")

_CSS = """
body{font-family:system-ui,sans-serif;margin:0;color:#222}
header{background:#1b5e20;color:#fff;padding:14px 24px}header h1{margin:0;font-size:22px}
main{padding:8px 24px}table{border-collapse:collapse;font-size:13px}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#f2f2f2}
td.t{text-align:left}.flag-check{color:#b36b00}.flag-fail{color:#c62828;font-weight:bold}
.note{color:#555;font-size:13px}
"""


def _esc(v: Any) -> str:
    return html.escape("" if v is None else str(v))


def _replicate(v: Any) -> str:
    import pandas as pd

    return "" if v is None or pd.isna(v) else str(int(v))


def _groups(df: pd.DataFrame) -> list[str]:
    return [f"{g or '?'} / {t or '?'}" for g, t in zip(df["genotype"], df["treatment"])]


def experiment_figures(series: pd.DataFrame, trait: str, truth: pd.DataFrame | None = None):
    """(per-plant figure, per-group figure) of ``trait`` over ``day`` (plotly Figures)."""
    import plotly.graph_objects as go

    series = series.assign(group=_groups(series))
    colours = {g: PALETTE[i % len(PALETTE)] for i, g in enumerate(sorted(set(series.group)))}
    per_plant = go.Figure()
    shown: set[str] = set()
    for (study, plant), p in series.groupby(["study_id", "plant_id"], sort=True):
        group = p.group.iloc[0]
        flags = [f if isinstance(f, str) else None for f in p.plant_quality_flag]
        reasons = (p["plant_quality_reasons"] if "plant_quality_reasons" in p
                   else [None] * len(p))
        per_plant.add_trace(go.Scatter(
            x=p["x_day"], y=p[trait], mode="lines+markers", name=group, legendgroup=group,
            showlegend=group not in shown, line={"color": colours[group], "width": 1.5},
            marker={"symbol": [FLAG_SYMBOLS.get(f, "circle-open") for f in flags], "size": 9,
                    "color": colours[group]},
            text=[f"{plant} ({study})<br>{t:%Y-%m-%d %H:%M} UTC<br>flag: {f or 'none'}, "
                  f"{w} warning(s)" + (f"<br>{html.escape(why)}" if isinstance(why, str) else "")
                  for t, f, w, why in zip(p.scan_time, flags, p.warnings, reasons)],
            hovertemplate="%{text}<br>%{y:.1f}<extra></extra>"))
        shown.add(group)
        if truth is not None:
            tp = truth[truth.plant_id == plant].sort_values("x_day")
            if not tp.empty:
                per_plant.add_trace(go.Scatter(
                    x=tp["x_day"], y=tp[trait], mode="lines", legendgroup="truth",
                    name="virtual truth", showlegend="truth" not in shown,
                    line={"color": colours[group], "dash": "dot", "width": 1},
                    hovertemplate=f"{plant} truth<br>%{{y:.1f}}<extra></extra>"))
                shown.add("truth")
    xlabel = series.attrs.get("x_label", "day")
    per_plant.update_layout(template="plotly_white", height=480, xaxis_title=xlabel,
                            yaxis_title=trait, title=f"{trait} per plant",
                            legend_title="genotype / treatment")
    per_group = go.Figure()
    series = series.assign(day_bin=series["x_day"].round())
    for group, g in series.groupby("group", sort=True):
        stats = g.groupby("day_bin")[trait].agg(["mean", "std", "count"]).reset_index()
        per_group.add_trace(go.Scatter(
            x=stats["day_bin"], y=stats["mean"], mode="lines+markers", name=group,
            line={"color": colours[group]},
            error_y={"type": "data", "array": stats["std"].fillna(0.0).to_numpy(),
                     "visible": True},
            text=[f"n = {n}" for n in stats["count"]],
            hovertemplate=f"{group}<br>day %{{x}}: %{{y:.1f}} (%{{text}})<extra></extra>"))
    per_group.update_layout(template="plotly_white", height=420, xaxis_title=xlabel,
                            yaxis_title=f"{trait} (mean ± sd)",
                            title=f"{trait} per group (mean ± standard deviation of the plants)")
    return per_plant, per_group


def _x_days(series: pd.DataFrame) -> pd.DataFrame:
    if series["days_after_sowing"].notna().all():
        series = series.assign(x_day=series["days_after_sowing"])
        series.attrs["x_label"] = "days after sowing"
    else:
        series = series.assign(x_day=series["day"])
        series.attrs["x_label"] = "days since the plant's first scan"
    return series


def write_experiment_report(store: Store, out: Path, *, trait: str = "total_leaf_area_mm2",
                            truth: pd.DataFrame | None = None, **filters: Any) -> Path:
    """Write the experiment report of the runs matching ``filters`` to ``out`` (HTML).

    ``truth`` (optional, the virtual scanner's): a DataFrame with ``plant_id``,
    ``x_day`` and ``trait``, drawn dotted beside each plant's measured curve.
    """
    from plotly.offline import get_plotlyjs

    plants = store.plant_traits(**filters)
    if plants.empty:
        raise ValueError("no stored run matches: nothing to report")
    if trait not in plants:
        traits = [c for c in plants.columns if c.endswith(("_mm", "_mm2", "_mm3", "count"))]
        raise ValueError(f"no plant trait {trait!r} in the store; traits: {', '.join(traits)}")
    series = _x_days(plant_series(plants, trait))
    fig_plant, fig_group = experiment_figures(series, trait, truth)
    studies = ", ".join(sorted({s or "(no study)" for s in series.study_id}))
    flags = series.plant_quality_flag.fillna("none").value_counts().to_dict()
    rows = []
    for (study, plant), p in series.groupby(["study_id", "plant_id"], sort=True):
        last = p.iloc[-1]
        counts = p.plant_quality_flag.fillna("none").value_counts()
        flag_cell = ", ".join(f'<span class="flag-{f}">{f}</span> {n}'
                              for f, n in sorted(counts.items()))
        rows.append(
            f"<tr><td class=t>{_esc(study)}</td><td class=t>{_esc(plant)}</td>"
            f"<td class=t>{_esc(last.genotype)}</td><td class=t>{_esc(last.treatment)}</td>"
            f"<td>{_esc(_replicate(last.replicate))}</td>"
            f"<td>{len(p)}</td><td>{p.scan_time.min():%Y-%m-%d}</td>"
            f"<td>{p.scan_time.max():%Y-%m-%d}</td><td>{last[trait]:.1f}</td>"
            f"<td class=t>{flag_cell}</td><td>{int(p.warnings.sum())}</td></tr>")
    body = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>plantscan experiment: {_esc(studies)}</title><style>{_CSS}</style>",
        f'<script type="text/javascript">{get_plotlyjs()}</script></head><body>',
        f"<header><h1>plantscan experiment: {_esc(studies)}</h1>"
        f"<p>{series.plant_id.nunique()} plants, {len(series)} scans, "
        f"{series.scan_time.min():%Y-%m-%d} to {series.scan_time.max():%Y-%m-%d} (UTC); "
        f"quality flags: {', '.join(f'{k} {v}' for k, v in sorted(flags.items()))}</p></header>",
        "<main>",
        "<p class=note>Marker = the plant's quality flag for that scan (circle ok, triangle "
        "check, cross fail, open circle: not flagged). Hover a point for the plant, the scan "
        "time and the number of warnings.</p>",
        fig_plant.to_html(full_html=False, include_plotlyjs=False),
        fig_group.to_html(full_html=False, include_plotlyjs=False),
        "<h2>Plants</h2><table><tr><th>study</th><th>plant</th><th>genotype</th>"
        "<th>treatment</th><th>replicate</th><th>scans</th><th>first</th><th>last</th>"
        f"<th>last {_esc(trait)}</th><th>flags</th><th>warnings</th></tr>",
        *rows, "</table></main></body></html>"]
    out = Path(out)
    atomic_write_text(out, "\n".join(body))
    return out

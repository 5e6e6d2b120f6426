"""Plots of a calibrator's free-form quality report (``Calibration.quality``).

``quality`` is whatever the calibrator chose to report, so the report reads
shapes, not names (docs/report.md lists them for calibrator authors):

* a scalar (number, short string, bool) -> a row of the quality table, with its
  dotted path (``per_tilt.0.rms_px``);
* a mapping of >= 2 numbers (``{"cam0/t0": 0.21, "cam0/t1": 0.25}``) -> a bar chart;
* a list of records (``[{"camera": "cam0", "tilt_index": 0, "rms_px": 0.2}, ...]``)
  -> a bar chart of its first numeric field whose name says residual, rms or
  error, one bar per record labelled by the record's other non-numeric fields
  and integer indices;
* a residual field: a mapping with equal-length number lists ``u, v, du, dv``
  (pixel position and residual vector, px) -> arrows over the image plane,
  coloured by residual length (``camera``/``name`` strings in it name the plot);
* a list of >= 8 numbers -> a histogram.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

MAX_FIGURES = 8
_RESIDUAL_WORDS = ("residual", "rms", "error", "reproj")


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(float(v))


def _numeric_list(v: Any) -> bool:
    return isinstance(v, (list, tuple, np.ndarray)) and len(v) > 0 and all(_is_number(x)
                                                                          for x in np.ravel(v))


def quality_rows(quality: dict[str, Any], limit: int = 60) -> list[tuple[str, str]]:
    """(dotted path, value text) of every scalar in ``quality`` (first ``limit``)."""
    rows: list[tuple[str, str]] = []

    def walk(node: Any, path: str) -> None:
        if len(rows) >= limit:
            return
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(node, (list, tuple)):
            if node and all(isinstance(r, dict) for r in node) and len(node) > 3:
                rows.append((path, f"{len(node)} records"))
            elif _numeric_list(node):
                arr = np.asarray(node, dtype=float).ravel()
                rows.append((path, f"{arr.size} values, mean {arr.mean():.4g}, "
                                   f"max {arr.max():.4g}"))
            elif len(node) <= 12:
                for i, v in enumerate(node):
                    walk(v, f"{path}.{i}")
            else:
                rows.append((path, f"list of {len(node)} items"))
        elif _is_number(node):
            rows.append((path, f"{float(node):.6g}"))
        elif isinstance(node, (str, bool)) or node is None:
            text = str(node)
            rows.append((path, text if len(text) <= 120 else text[:117] + "..."))

    walk(quality, "")
    return rows


def _record_label(record: dict[str, Any], value_key: str) -> str:
    parts = [f"{v}" if not isinstance(v, int) or isinstance(v, bool) else f"{k}={v}"
             for k, v in record.items()
             if k != value_key and (isinstance(v, str) or (isinstance(v, int)
                                                           and not isinstance(v, bool)))]
    return " ".join(parts) or "?"


def quality_figures(quality: dict[str, Any]) -> list[tuple[str, Any]]:
    """(title, plotly Figure) for every plottable shape found in ``quality``."""
    import plotly.graph_objects as go

    figures: list[tuple[str, Any]] = []

    def add(title: str, fig: Any) -> None:
        if len(figures) < MAX_FIGURES:
            fig.update_layout(title=None, margin=dict(l=50, r=20, t=20, b=50), height=320)
            figures.append((title, fig))

    def walk(node: Any, path: str) -> None:
        if len(figures) >= MAX_FIGURES:
            return
        if isinstance(node, dict):
            field = {k: node.get(k) for k in ("u", "v", "du", "dv")}
            if all(_numeric_list(x) for x in field.values()) and len(
                    {len(np.ravel(x)) for x in field.values()}) == 1:
                add(_field_title(node, path), residual_field_figure(*(
                    np.asarray(field[k], dtype=float).ravel() for k in ("u", "v", "du", "dv"))))
                return
            numeric = {str(k): float(v) for k, v in node.items() if _is_number(v)}
            if len(numeric) >= 2 and len(numeric) == len(node):
                fig = go.Figure(go.Bar(x=list(numeric), y=list(numeric.values())))
                fig.update_yaxes(title_text=path.rsplit(".", 1)[-1] or "value")
                add(path or "quality", fig)
                return
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(node, (list, tuple)) and node:
            if all(isinstance(r, dict) for r in node):
                keys = [k for k in node[0] if all(_is_number(r.get(k)) for r in node)
                        and any(w in str(k).lower() for w in _RESIDUAL_WORDS)]
                if keys:
                    labels = [_record_label(r, keys[0]) for r in node]
                    fig = go.Figure(go.Bar(x=labels, y=[float(r[keys[0]]) for r in node]))
                    fig.update_yaxes(title_text=keys[0])
                    add(f"{path}: {keys[0]}", fig)
                    return
                for i, r in enumerate(node[:12]):
                    walk(r, f"{path}.{i}")
            elif _numeric_list(node) and len(np.ravel(node)) >= 8:
                fig = go.Figure(go.Histogram(x=np.asarray(node, dtype=float).ravel()))
                fig.update_xaxes(title_text=path.rsplit(".", 1)[-1])
                fig.update_yaxes(title_text="count")
                add(f"{path} (histogram)", fig)

    walk(quality, "")
    return figures


def _field_title(node: dict[str, Any], path: str) -> str:
    names = [str(node[k]) for k in ("camera", "name", "tilt_index") if k in node]
    return f"residual field {' '.join(names)} ({path or 'quality'})"


def residual_field_figure(u: np.ndarray, v: np.ndarray, du: np.ndarray, dv: np.ndarray,
                          max_arrows: int = 4000):
    """Arrows from each observed pixel (u, v) along its residual (du, dv), px.

    Residuals are magnified so the longest drawn arrow spans ~5 % of the field
    (the scale is written in the legend); markers are coloured by |residual|.
    """
    import plotly.graph_objects as go

    if len(u) > max_arrows:  # a regular subsample keeps the field readable and the file small
        step = int(np.ceil(len(u) / max_arrows))
        u, v, du, dv = u[::step], v[::step], du[::step], dv[::step]
    mag = np.hypot(du, dv)
    extent = max(float(np.ptp(u)), float(np.ptp(v)), 1.0)
    scale = 0.05 * extent / max(float(mag.max()) if mag.size else 0.0, 1e-9)
    xs = np.column_stack([u, u + du * scale, np.full_like(u, np.nan)]).ravel()
    ys = np.column_stack([v, v + dv * scale, np.full_like(v, np.nan)]).ravel()
    fig = go.Figure([
        go.Scatter(x=xs, y=ys, mode="lines", line=dict(width=1, color="#555"),
                   name=f"residual x{scale:.3g}", hoverinfo="skip"),
        go.Scatter(x=u, y=v, mode="markers", name="|residual| px",
                   marker=dict(size=4, color=mag, colorscale="Viridis", showscale=True,
                               colorbar=dict(title="px")),
                   text=[f"{m:.3f} px" for m in mag], hoverinfo="text"),
    ])
    fig.update_xaxes(title_text="u (px)")
    fig.update_yaxes(title_text="v (px)", autorange="reversed", scaleanchor="x")
    fig.update_layout(showlegend=True, legend=dict(orientation="h", y=1.12))
    return fig

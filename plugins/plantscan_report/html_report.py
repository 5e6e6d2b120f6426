"""Exporter ``html-report``: one self-contained, offline ``report.html`` per run.

What a technician checks at a glance that a scan worked: the 3D plant with its
leaves coloured (plotly ``Mesh3d``), the traits table, the calibration and its
residual plots, a strip of silhouettes over their images, timings per stage,
and, when the scan has ground truth (virtual scanner), measured-vs-truth plots
per trait.  Every section is present only when its stage ran.

plotly.js is embedded once, inline (no CDN: the report opens on an offline lab
PC); images are small JPEG thumbnails embedded as base64.  All user-supplied
text (plant id, recipe name, file names, quality keys) is HTML-escaped, and the
figure JSON is escaped against ``</script>``.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from plantscan_core.data import (
    LEAF_COLUMNS,
    PLANT_COLUMN,
    TRAIT_NAMES,
    LabelledMesh,
    Mesh,
    TraitColumn,
    Traits,
    mean_relative_error,
)
from plantscan_core.errors import PlantScanError
from plantscan_core.scanfolder import atomic_write_text, now_iso
from plantscan_core.stages import Exporter, RunResult, StageParams
from plantscan_report import quality as quality_plots
from plantscan_report import verdict as trust
from plantscan_report.colours import PLAIN_RGB, hex_colour, label_colours
from plantscan_report.tables import plant_id_of
from plantscan_report.truth import match_leaves, read_truth_traits

REPORT_NAME = "report.html"
_TRAIT_UNITS = {c.trait: c.shown_unit for c in LEAF_COLUMNS if c.trait}

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#222;
background:#fafafa}
header{background:#2f5d3a;color:#fff;padding:14px 24px}
header h1{margin:0;font-size:1.5em} header p{margin:4px 0 0;opacity:.9}
main{padding:8px 24px 40px;max-width:1400px}
section{background:#fff;border:1px solid #ddd;border-radius:6px;margin:16px 0;padding:8px 16px}
h2{font-size:1.2em;margin:8px 0} h3{font-size:1em;margin:10px 0 4px}
table{border-collapse:collapse;margin:6px 0;font-size:.9em}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:right}
th{background:#f0f0f0} td.l,th.l{text-align:left} #traits td.l{white-space:nowrap}
.swatch{display:inline-block;width:12px;height:12px;border-radius:2px;margin-right:6px;
vertical-align:middle;border:1px solid #888}
.strip{display:flex;flex-wrap:wrap;gap:8px}
figure{margin:0;font-size:.8em;text-align:center} figure img{display:block;width:240px;height:auto}
.grid{display:flex;flex-wrap:wrap;gap:12px} .grid>div{flex:1 1 420px;min-width:320px}
.note{color:#666;font-size:.85em} .bad{color:#a00}
#verdict{border-width:2px} #verdict h2{display:flex;align-items:center;gap:10px}
.flag{display:inline-block;padding:2px 10px;border-radius:12px;color:#fff;font-weight:600;
font-size:.9em;text-transform:uppercase;letter-spacing:.03em}
.flag-ok{background:#2e7d32} .flag-check{background:#b26a00} .flag-fail{background:#b00020}
.flag-na{background:#757575} .lvl{font-weight:600} .lvl-ok{color:#2e7d32}
.lvl-check{color:#b26a00} .lvl-fail{color:#b00020}
#verdict ul{margin:4px 0 8px;padding-left:20px} #verdict li{margin:2px 0}
tr.warned td{background:#fff4e0} td.reason{text-align:left;font-size:.85em;color:#7a4a00;
min-width:14em} #traits .grid>div:first-child{flex:3 1 760px;overflow-x:auto}
details>summary{cursor:pointer;color:#2f5d3a;margin:6px 0}
"""


def _esc(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _script_json(obj: Any) -> str:
    """JSON safe inside a ``<script>`` element (no ``</script>``/``<!--`` break-out)."""
    return obj.replace("</", "<\\/").replace("<!--", "<\\!--")


class _Figures:
    """Numbers the figure divs and renders each figure as a div + Plotly.newPlot call."""

    def __init__(self) -> None:
        self.count = 0

    def html(self, fig: Any, height: int | None = None) -> str:
        self.count += 1
        div = f"fig{self.count}"
        fig.update_layout(template="plotly_white")
        if height is not None:
            fig.update_layout(height=height)
        payload = _script_json(fig.to_json())
        style = f"height:{height}px" if height else ""
        # Drawn once the whole page is laid out, so each plot gets its final width; a plot
        # inside a closed <details> is resized when it opens (the page's toggle handler).
        return (f'<div id="{div}" class="plot" style="{style}"></div>\n'
                f"<script>(function(){{var f={payload};"
                f'document.addEventListener("DOMContentLoaded",function(){{Plotly.newPlot('
                f'"{div}",f.data,f.layout,{{responsive:true,displaylogo:false}});}});'
                f"}})();</script>")


def _table(header: list[str], rows: list[list[str]], left: int = 1) -> str:
    """HTML table; cells are already-escaped HTML; the first ``left`` columns left-aligned."""
    head = "".join(f'<th class="{"l" if i < left else ""}">{h}</th>' for i, h in enumerate(header))
    body = "".join(
        "<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
        + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


# --------------------------------------------------------------------------- sections
def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray,
                     cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex clustering per group: every vertex moves to the mean of its grid cell.

    Open3D's ``simplify_vertex_clustering`` (average contraction) applied to
    each group's faces separately, in one pass over the whole mesh: a vertex
    shared by two groups (a leaf and the stem) is clustered once per group, so
    no cluster mixes groups.  Faces that collapse (two corners in one cell)
    and repeated faces are dropped.

    Parameters
    ----------
    vertices : (V, 3) float, mm
    faces : (F, 3) int
    groups : (F,) int, a group (label) per face
    cell : float, mm, the grid's cell side

    Returns
    -------
    vertices : (V', 3) float64, mm
    faces : (F', 3) int64
    groups : (F',) the group of each kept face
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    _, group_id = np.unique(np.asarray(groups), return_inverse=True)
    group_id = group_id.reshape(-1).astype(np.int64)
    n_groups = int(group_id.max()) + 1 if group_id.size else 1
    # The grid starts half a cell below the lowest vertex, as Open3D's does.
    q = np.floor((vertices - (vertices.min(axis=0) - cell / 2)) / cell).astype(np.int64)
    dims = q.max(axis=0) + 1
    _, vertex_cell = np.unique((q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2],
                               return_inverse=True)
    n_cells = int(vertex_cell.max()) + 1
    # A corner's cluster: its vertex's cell within its face's group; the keys are dense
    # (< cells x groups), so clusters are numbered by a table, not by sorting 3 F keys.
    corner_key = (vertex_cell.reshape(-1)[faces] * n_groups + group_id[:, None]).reshape(-1)
    used = np.zeros(n_cells * n_groups, bool)
    used[corner_key] = True
    number = np.cumsum(used) - 1
    corner_cluster = number[corner_key]
    n_clusters = int(number[-1]) + 1
    # Each (vertex, group) pair counts once in its cluster's mean, as in Open3D.
    pair_seen = np.zeros(len(vertices) * n_groups, bool)
    pair_seen[(faces * n_groups + group_id[:, None]).reshape(-1)] = True
    pairs = np.flatnonzero(pair_seen)
    pair_vertex = pairs // n_groups
    members = number[vertex_cell.reshape(-1)[pair_vertex] * n_groups + pairs % n_groups]
    count = np.bincount(members, minlength=n_clusters)
    out_vertices = np.stack([np.bincount(members, weights=vertices[pair_vertex, d],
                                         minlength=n_clusters) for d in range(3)],
                            axis=1) / count[:, None]
    out_faces = corner_cluster.reshape(-1, 3)
    keep = ((out_faces[:, 0] != out_faces[:, 1]) & (out_faces[:, 1] != out_faces[:, 2])
            & (out_faces[:, 0] != out_faces[:, 2]))
    out_faces, kept_groups = out_faces[keep], np.asarray(groups)[keep]
    # Repeated faces (the same three clusters, either orientation) keep their first copy.
    ordered = np.sort(out_faces, axis=1)
    n = np.int64(n_clusters)
    _, first_face = np.unique((ordered[:, 0] * n + ordered[:, 1]) * n + ordered[:, 2],
                              return_index=True)
    first_face.sort()
    return out_vertices, out_faces[first_face], kept_groups[first_face]


def _decimate(mesh: Mesh, target_faces: int,
              groups: np.ndarray | None = None) -> tuple[Mesh, np.ndarray]:
    """About ``target_faces`` faces for the report's viewer (never the data).

    Vertex clustering (``cluster_vertices``) on a grid sized from the surface
    area, per group (label) so that leaves keep their own faces: ~20x faster
    than quadric decimation (4.7 s vs 0.26 s CPU for 300 k faces, measured),
    and the viewer cannot show the difference; grids are coarsened until the
    budget holds (one or two passes).  Returns the mesh and each face's group.
    """
    groups = np.zeros(len(mesh.faces), np.int64) if groups is None else np.asarray(groups)
    if len(mesh.faces) <= target_faces:
        return mesh, groups
    # A clustered surface has ~2 triangles per occupied cell of side `cell`.
    cell = math.sqrt(2.0 * mesh.area() / max(int(target_faces), 4))
    for _ in range(8):
        v, f, g = cluster_vertices(mesh.vertices, mesh.faces, groups, cell)
        if len(f) <= target_faces:
            break
        cell *= 1.05 * math.sqrt(len(f) / target_faces)
    return Mesh(v, f), g


def _label_anchor(mesh: Mesh) -> np.ndarray:
    """(3,) a point on ``mesh`` for its number: the vertex nearest its vertices' centroid
    (the centroid of a curved leaf floats off it)."""
    v = mesh.vertices
    return v[int(np.argmin(np.sum((v - v.mean(axis=0)) ** 2, axis=1)))]


def _mesh_traces(run: RunResult, max_faces: int) -> list[Any]:
    """One Mesh3d trace per label (leaf, stem, pot, debris, unassigned) or one for a plain
    mesh, then one text trace numbering the leaves as in the traits table."""
    import plotly.graph_objects as go

    parts: list[tuple[str, Mesh, str]] = []
    numbers: list[tuple[int, np.ndarray]] = []
    if run.labelled is not None and not run.labelled.mesh.is_empty:
        labelled: LabelledMesh = run.labelled
        colours = label_colours(labelled)
        # One clustering of the whole mesh, per label: each label keeps its share of the
        # face budget, so small leaves stay visible.
        small = LabelledMesh(*_decimate(labelled.mesh, max_faces, labelled.face_labels),
                             labelled.kinds)
        for label in np.unique(small.face_labels).tolist():
            kind = labelled.kinds.get(label, "unassigned") if label >= 0 else "unassigned"
            name = f"leaf {label}" if kind == "leaf" else kind
            colour = hex_colour(colours[label]) if label in colours else "#bfbfbf"
            sub = small.submesh(label)
            parts.append((name, sub, colour))
            if kind == "leaf" and len(sub.vertices):
                numbers.append((label, _label_anchor(sub)))
    elif run.mesh is not None and not run.mesh.is_empty:
        parts.append(("plant", _decimate(run.mesh, max_faces)[0], hex_colour(PLAIN_RGB)))
    traces = []
    for name, mesh, colour in parts:
        v = np.round(mesh.vertices, 3).astype(np.float32)
        f = mesh.faces.astype(np.int32)
        traces.append(go.Mesh3d(
            x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], color=colour,
            name=name, showlegend=True, flatshading=False, hoverinfo="name",
            lighting=dict(ambient=0.45, diffuse=0.8, specular=0.1, roughness=0.8),
        ))
    if numbers:
        xyz = np.array([p for _, p in numbers])
        traces.append(go.Scatter3d(
            x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="text", name="leaf numbers",
            text=[str(label) for label, _ in numbers], showlegend=True,
            textfont=dict(size=16, color="#000"), hoverinfo="text",
            hovertext=[f"leaf {label}" for label, _ in numbers]))
    return traces


def _mesh_section(run: RunResult, figs: _Figures, max_faces: int) -> str:
    import plotly.graph_objects as go

    traces = _mesh_traces(run, max_faces)
    if not traces:
        return ""
    fig = go.Figure(traces)
    fig.update_layout(
        scene=dict(aspectmode="data", xaxis_title="x (mm)", yaxis_title="y (mm)",
                   zaxis_title="z (mm)", camera=dict(eye=dict(x=1.7, y=1.7, z=1.0))),
        margin=dict(l=0, r=0, t=0, b=0),
        # top left: plotly's toolbar sits top right and used to cover the last entries
        legend=dict(itemsizing="constant", x=0.0, y=1.0, xanchor="left", yanchor="top",
                    bgcolor="rgba(255,255,255,0.75)"),
    )
    mesh = run.labelled.mesh if run.labelled is not None else run.mesh
    note = (f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, "
            f"surface {trust.format_value('surface_mm2', mesh.area())}; the numbers are the "
            "leaf ids of the traits table; drag to rotate, scroll to zoom, click a legend "
            "entry to hide a part.")
    return (f'<section id="plant3d"><h2>3D plant</h2>{figs.html(fig, 620)}'
            f'<p class="note">{_esc(note)}</p></section>')


def _column_text(c: TraitColumn, value: Any) -> str:
    """A value of a traits-table column as the report writes it: fixed decimals, unit apart."""
    if c.is_text or isinstance(value, (str, list, dict)):
        return str(value)
    return trust.format_number(c.display_scale * value, c.decimals)


def _leaf_columns(traits: Traits) -> list[TraitColumn]:
    """The leaf table's number columns: the traits, then the quality figures the measurer set."""
    def said(c: TraitColumn) -> bool:
        return any(math.isfinite(getattr(leaf, c.name)) for leaf in traits.leaves)

    return [c for c in LEAF_COLUMNS if not c.is_text and (c.trait or said(c))]


def _plant_row(key: str, value: Any) -> list[str]:
    c = PLANT_COLUMN.get(key)
    if c is None:  # a value the core's table does not list: its unit from its name
        return [_esc(trust.label_of(key)), _esc(trust.format_value(key, value))]
    text = _column_text(c, value)
    return [_esc(c.title), _esc(f"{text} {c.shown_unit}" if c.shown_unit else text)]


_IN_VERDICT = ("quality_flag", "quality_reasons")  # shown in the verdict, not as traits


def _traits_section(run: RunResult) -> str:
    traits: Traits | None = run.traits
    if traits is None:
        return ""
    colours = label_colours(run.labelled) if run.labelled is not None else {}
    doubts = trust.leaf_doubts(run)
    columns = _leaf_columns(traits)
    rows = []
    for leaf in traits.leaves:
        swatch = (f'<span class="swatch" style="background:{hex_colour(colours[leaf.leaf_id])}">'
                  "</span>" if leaf.leaf_id in colours else "")
        reasons, doubtful = doubts[leaf.leaf_id].reasons, doubts[leaf.leaf_id].doubtful
        mark = ' <span title="read with care: see the reasons">⚠</span>' if doubtful else ""
        cells = [f"{swatch}{leaf.leaf_id}{mark}"]
        cells += [_esc(_column_text(c, getattr(leaf, c.name))) for c in columns]
        cells.append(_esc("; ".join(reasons)))
        rows.append((cells, doubtful))
    header = ["leaf"] + [c.header for c in columns] + ["read with care"]
    if rows:
        head = "".join(f'<th class="{"l" if i == 0 or i == len(header) - 1 else ""}">'
                       f"{_esc(h)}</th>" for i, h in enumerate(header))
        body = "".join(
            f'<tr class="{"warned" if warned else ""}">'
            + "".join(f'<td class="{"l" if i == 0 else "reason" if i == len(cells) - 1 else ""}">'
                      f"{c}</td>" for i, c in enumerate(cells)) + "</tr>"
            for cells, warned in rows)
        leaf_table = f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    else:
        leaf_table = '<p class="note">No leaf was found.</p>'
    plant_rows = [_plant_row(k, v) for k, v in sorted(traits.plant.items())
                  if k != "quality" and k not in _IN_VERDICT and not isinstance(v, (dict, list))]
    plant_table = _table(["plant trait", "value"], plant_rows) if plant_rows else ""
    n_warned = sum(1 for _, w in rows if w)
    note = (f'<p class="note">{n_warned} of {len(rows)} leaves to read with care (⚠, shaded): '
            "low confidence or warned about, the reasons in short here and in full under "
            "Warnings; confidence (0–1) is the measurer's. thick area: the "
            "share of a leaf's area where the reconstructed surface is several times thicker "
            "than the leaf elsewhere (phantom volume the views could not carve, or an organ "
            "fused with the leaf); that leaf's traits carry it.</p>" if rows else "")
    return (f'<section id="traits"><h2>Traits</h2><div class="grid"><div>{leaf_table}{note}'
            f"</div><div>{plant_table}</div></div></section>")


def _warnings_section(run: RunResult) -> str:
    notes = trust.stage_notes(run)
    if not notes:
        return ""
    by_section: dict[str, list[trust.StageNote]] = {}
    for n in notes:
        by_section.setdefault(n.section, []).append(n)
    parts = ['<section id="warnings"><h2>Warnings</h2>']
    for section, items in by_section.items():
        parts.append(f"<h3>{_esc(trust.section_title(section, run))} ({len(items)})</h3><ul>"
                     + "".join(f"<li>{_esc(n.message)}</li>" for n in items) + "</ul>")
    parts.append("</section>")
    return "".join(parts)


def _verdict_section(run: RunResult) -> str:
    """The first block: the plant flag and its reasons, then what to check before using it."""
    v = trust.plant_verdict(run)
    css = {"ok": "flag-ok", "check": "flag-check", "fail": "flag-fail"}.get(v.flag, "flag-na")
    lines = []
    if run.traits is not None:
        doubts = trust.leaf_doubts(run).values()
        assessed = any(getattr(leaf, "quality_flag", "") for leaf in run.traits.leaves)
        said = [f"{sum(d.low_confidence for d in doubts)} low confidence"] if assessed else []
        said.append(f"{sum(d.warned for d in doubts)} warned about by a stage")
        lines.append(f"<b>Leaves</b>: {len(doubts)} measured, "
                     f"{sum(d.doubtful for d in doubts)} to read with care (⚠ in the traits "
                     f"table): {', '.join(said)}")
    if run.calibration is not None:
        level, text = trust.calibration_line(run.calibration.quality)
        lines.append(f'<b>Calibration</b>: <span class="lvl lvl-{_esc(level)}">{_esc(level)}'
                     f"</span> — {_esc(text)}")
    counts = {}
    for n in trust.stage_notes(run):
        counts[n.section] = counts.get(n.section, 0) + 1
    if counts:
        lines.append("<b>Warnings</b>: " + ", ".join(
            f"{_esc(trust.section_title(k, run))} {c}" for k, c in counts.items())
            + ' (<a href="#warnings">list</a>)')
    else:
        lines.append("<b>Warnings</b>: none from any stage")
    skipped = (run.info or {}).get("skipped") or []
    if skipped:
        lines.append(f"<b>Not run</b>: {_esc(', '.join(skipped))}")
    reasons = "".join(f"<li>{_esc(r)}</li>" for r in v.reasons)
    return (f'<section id="verdict"><h2>Can these numbers be trusted? <span class="flag {css}">'
            f"{_esc(v.flag)}</span></h2>"
            + (f"<ul>{reasons}</ul>" if reasons else "")
            + "<ul>" + "".join(f"<li>{line}</li>" for line in lines) + "</ul></section>")


def _calibration_section(run: RunResult, figs: _Figures) -> str:
    """One line (the verdict of ``verdict.calibration_line``), the rest folded away."""
    cal = run.calibration
    if cal is None:
        return ""
    level, text = trust.calibration_line(cal.quality)
    px, k = (lambda v: trust.format_number(v, 2)), (lambda v: trust.format_number(v, 5))
    model_rows = [[_esc(name), px(m.f), px(m.cu), px(m.cv), k(m.d1), k(m.d2),
                   f"{m.width} × {m.height}"] for name, m in sorted(cal.models.items())]
    details = [_table(["camera", "f (px)", "cu (px)", "cv (px)", "d1", "d2", "image (px)"],
                      model_rows),
               f'<p class="note">{len(cal.poses)} calibrated (camera, tilt) poses; tilts '
               f"{_esc(', '.join(f'{k}: {v:g}°' for k, v in sorted(cal.tilts_deg.items())))}; "
               f"turntable angle scale {cal.angle_scale:.6f}"
               f"{'; tilt axis modelled' if cal.tilt_axis is not None else ''}.</p>"]
    if cal.quality:
        plots = quality_plots.quality_figures(cal.quality)
        if plots:
            details.append('<div class="grid">')
            for title, fig in plots:
                details.append(f"<div><h3>{_esc(title)}</h3>{figs.html(fig, 320)}</div>")
            details.append("</div>")
        rows = [[_esc(k), _esc(v)] for k, v in quality_plots.quality_rows(cal.quality)]
        if rows:
            details.append("<details><summary>Calibrator's quality report "
                           f"({len(rows)} items)</summary>"
                           + _table(["item", "value"], rows, 2) + "</details>")
    return (f'<section id="calibration"><h2>Calibration</h2><p><span class="lvl '
            f'lvl-{_esc(level)}">{_esc(level)}</span> — {_esc(text)}</p>'
            f"<details><summary>Camera models, residual plots, the calibrator's report"
            f"</summary>{''.join(details)}</details></section>")


THUMB_WIDTH = 240  # px of a silhouette thumbnail


def _thumbnail_b64(image: np.ndarray, mask: np.ndarray | None, width: int = THUMB_WIDTH) -> str:
    """JPEG (base64) of a BGR image ``width`` px wide, outside of ``mask`` dimmed, outlined.

    The image and the mask are resized to the thumbnail first, so the outline is one
    thumbnail pixel whatever the camera's resolution.
    """
    import cv2

    height = max(1, round(image.shape[0] * width / image.shape[1]))
    interp = cv2.INTER_AREA if image.shape[1] > width else cv2.INTER_LINEAR
    img = cv2.resize(image, (width, height), interpolation=interp)
    if mask is not None:
        m = cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        m = m >= 0.5
        img[~m] = (img[~m] * 0.45).astype(np.uint8)
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(img, contours, -1, (255, 0, 255), 1, lineType=cv2.LINE_AA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    if not ok:
        raise PlantScanError("could not encode a report thumbnail as JPEG")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _decode_reduce(full_width: int, reduce: int) -> int:
    """The largest decode reduction <= ``reduce`` that still gives a thumbnail-wide image."""
    for r in (8, 4, 2):
        if r <= reduce and full_width / r >= THUMB_WIDTH:
            return r
    return 1


def _silhouette_section(run: RunResult, count: int, reduce: int) -> str:
    if run.silhouettes is None or len(run.silhouettes) == 0 or count == 0 or run.scan is None:
        return ""
    items = list(run.silhouettes)
    picks = sorted({round(i) for i in np.linspace(0, len(items) - 1, min(count, len(items)))})
    figures = []
    for i in picks:
        sil = items[i]
        view = sil.view
        h, w = sil.shape
        caption = (f"view {view.index} · {view.camera} · tilt {view.tilt_deg:g}° · "
                   f"{view.angle_deg:g}° · {100 * sil.area / (h * w):.1f}% plant")
        try:
            image = run.scan.read_image(view, reduce=_decode_reduce(w, reduce))
            b64 = _thumbnail_b64(image, sil.mask)  # the full mask, built once per thumbnail
            figures.append(f'<figure><img alt="{_esc(view.file)}" '
                           f'src="data:image/jpeg;base64,{b64}"><figcaption>{_esc(caption)}'
                           "</figcaption></figure>")
        except PlantScanError as exc:  # a missing image must not cost the whole report
            figures.append(f'<figure><p class="bad">{_esc(exc)}</p>'
                           f"<figcaption>{_esc(caption)}</figcaption></figure>")
    return (f'<section id="silhouettes"><h2>Silhouettes</h2><p class="note">{len(picks)} of '
            f"{len(items)} plant views; outside of the silhouette dimmed, outline in magenta."
            f'</p><div class="strip">{"".join(figures)}</div></section>')


def _timings_section(run: RunResult, figs: _Figures) -> str:
    import plotly.graph_objects as go

    timings = {trust.section_title(str(k), run): float(v) for k, v in (run.timings or {}).items()
               if isinstance(v, (int, float))}
    if not timings:
        return ""
    total = sum(timings.values())
    rows = [[_esc(k), f"{v:.2f}", f"{100 * v / total:.0f}%" if total > 0 else "-"]
            for k, v in timings.items()]
    rows.append(["<b>total</b>", f"<b>{total:.2f}</b>", ""])
    fig = go.Figure(go.Bar(x=list(timings.values()), y=list(timings), orientation="h",
                           marker_color="#2f5d3a"))
    fig.update_layout(margin=dict(l=120, r=20, t=10, b=40), yaxis=dict(autorange="reversed"))
    fig.update_xaxes(title_text="seconds")
    height = 80 + 28 * len(timings)
    return (f'<section id="timings"><h2>Timings per stage</h2><div class="grid"><div>'
            f'{_table(["stage", "seconds", "share"], rows)}</div><div>{figs.html(fig, height)}'
            "</div></div></section>")


def _truth_section(run: RunResult, figs: _Figures) -> str:
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    if run.traits is None or run.scan is None:
        return ""
    truth_dir = run.scan.ground_truth_dir
    truth = read_truth_traits(truth_dir)
    if truth is None:
        return ""
    match = match_leaves(run.traits, truth, run.labelled, truth_dir)
    out = ['<section id="truth"><h2>Measured vs. truth</h2>',
           f'<p class="note">{len(match.pairs)} leaves paired ({_esc(match.method)}); '
           f"{match.unmatched_measured} measured and {match.unmatched_truth} truth leaves "
           "unpaired. ε = mean(|truth − measured| / truth), the seed's error measure.</p>"]
    if match.pairs:
        errors = {}
        fig = make_subplots(rows=1, cols=len(TRAIT_NAMES), horizontal_spacing=0.07,
                            subplot_titles=[f"{t} ({_TRAIT_UNITS[t]})" for t in TRAIT_NAMES])
        for c, trait in enumerate(TRAIT_NAMES, start=1):
            t = np.array([p[1].trait(trait) for p in match.pairs])
            m = np.array([p[0].trait(trait) for p in match.pairs])
            errors[trait] = mean_relative_error(t, m)
            lo, hi = float(min(t.min(), m.min())), float(max(t.max(), m.max()))
            pad = 0.05 * (hi - lo or 1.0)
            fig.add_trace(go.Scatter(x=[lo - pad, hi + pad], y=[lo - pad, hi + pad], mode="lines",
                                     line=dict(color="#999", dash="dash"), showlegend=False,
                                     hoverinfo="skip"), row=1, col=c)
            fig.add_trace(go.Scatter(
                x=t, y=m, mode="markers", marker=dict(size=8, color="#2f5d3a"), showlegend=False,
                text=[f"leaf {p[0].leaf_id} ↔ truth {p[1].leaf_id}" for p in match.pairs],
                hovertemplate="%{text}<br>truth %{x:.2f}<br>measured %{y:.2f}<extra></extra>"),
                row=1, col=c)
            fig.update_xaxes(title_text="truth", row=1, col=c)
            fig.update_yaxes(title_text="measured" if c == 1 else None, row=1, col=c)
        fig.update_layout(margin=dict(l=50, r=20, t=40, b=50))
        out.append(figs.html(fig, 340))
        out.append(_table(["trait", "ε (mean relative error)", "pairs"],
                          [[t, f"{100 * e:.1f}%", str(len(match.pairs))]
                           for t, e in errors.items()]))
    plant_rows = []
    for key, value in sorted(truth.plant.items()):
        measured = run.traits.plant.get(key)
        if _is_num(value) and _is_num(measured) and float(value) != 0:
            rel = (float(measured) - float(value)) / abs(float(value))
            name, truth_text = _plant_row(key, value)
            plant_rows.append([name, truth_text, _plant_row(key, measured)[1],
                               f"{100 * rel:+.1f}%"])
    if plant_rows:
        out.append(_table(["plant trait", "truth", "measured", "error"], plant_rows))
    out.append("</section>")
    return "".join(out)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _run_section(run: RunResult) -> str:
    rows = [["scan", _esc(run.scan.root if run.scan is not None else "-")],
            ["run folder", _esc(run.run_dir)], ["report written", _esc(now_iso())]]
    for key, value in (run.info or {}).items():
        if isinstance(value, (str, int, float, bool)) and key not in ("scan", "run_dir"):
            rows.append([_esc(key), _esc(value)])
    overrides = (run.info or {}).get("overrides") or []
    if overrides:
        rows.append(["--set", _esc(" ".join(overrides))])
    exports = (run.info or {}).get("exports") or []
    if exports:
        rows.append(["files", _esc(", ".join(Path(e).name for e in exports))])
    return f'<section id="run"><h2>Run</h2>{_table(["item", "value"], rows, 2)}</section>'


# Plots drawn inside a closed <details> have no width: redraw them when it opens.
_DETAILS_RESIZE = ("<script>document.addEventListener('toggle',function(e){if(e.target.open)"
                   "e.target.querySelectorAll('.js-plotly-plot').forEach(function(p){"
                   "Plotly.Plots.resize(p);});},true);</script>")


def _subtitle(run: RunResult) -> str:
    """Species, scan date, what was captured, and the recipe (with its --set changes)."""
    recipe_name = run.recipe.name if run.recipe is not None else ""
    species = run.recipe.plant.species if run.recipe is not None else ""
    info = run.scan.info if run.scan is not None else {}
    species = info.get("species") or species
    scanned = ""
    if run.scan is not None:
        from plantscan_core.metadata import scan_summary

        scanned = scan_summary(run.scan)["acquired_at"]  # scan.yaml's, else the first image's
    overrides = (run.info or {}).get("overrides") or []
    recipe = f"recipe {recipe_name}" if recipe_name else ""
    if recipe and overrides:
        recipe += f" with --set {' '.join(overrides)}"
    lines = [" · ".join(x for x in (f"species {species}" if species else "",
                                    f"scanned {scanned.replace('T', ' ')}" if scanned else "",
                                    recipe) if x),
             trust.protocol_summary(run)]
    return "".join(f"<p>{_esc(line)}</p>" for line in lines if line)


def render_report(run: RunResult, thumbnails: int = 6, thumbnail_reduce: int = 4,
                  max_faces: int = 150_000) -> str:
    """The whole report as one HTML string (see the module docstring)."""
    from plotly.offline import get_plotlyjs

    figs = _Figures()
    plant_id = plant_id_of(run)
    body = [
        _verdict_section(run),
        _mesh_section(run, figs, max_faces),
        _traits_section(run),
        _warnings_section(run),
        _truth_section(run, figs),
        _calibration_section(run, figs),
        _silhouette_section(run, thumbnails, thumbnail_reduce),
        _timings_section(run, figs),
        _run_section(run),
    ]
    return "".join([
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">",
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>plantscan report: {_esc(plant_id)}</title><style>{_CSS}</style>",
        # plotly.js inline (MIT); its source contains no "</script>" (checked in the tests).
        f'<script type="text/javascript">{get_plotlyjs()}</script></head><body>',
        f"<header><h1>plantscan report: {_esc(plant_id)}</h1>{_subtitle(run)}</header>",
        "<main>", *[b for b in body if b], "</main>", _DETAILS_RESIZE, "</body></html>\n",
    ])


class HtmlReportExporter(Exporter):
    """``report.html``: interactive, self-contained, offline report of one run."""

    name = "html-report"

    class Params(StageParams):
        thumbnails: int = Field(default=6, ge=0, le=72)
        """Number of silhouettes shown over their images (evenly spread over the views)."""
        thumbnail_reduce: Literal[1, 2, 4, 8] = 4
        """Decode images at up to 1/reduce of their size for the thumbnails (fast); less
        reduction when that would be narrower than a thumbnail."""
        max_faces: int = Field(default=150_000, ge=1_000)
        """Face budget of the 3D view (decimated above it; the exported meshes are not)."""

    def export(self, run: RunResult) -> list[Path]:
        text = render_report(run, self.params.thumbnails, self.params.thumbnail_reduce,
                             self.params.max_faces)
        path = Path(run.run_dir) / REPORT_NAME
        atomic_write_text(path, text)
        return [path]


__all__ = ["HtmlReportExporter", "render_report", "REPORT_NAME"]

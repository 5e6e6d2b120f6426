"""The report's trust block, colours and numbers: what a scientist reads first.

Colour distinctness is measured as CIELAB Delta E 1976: about 2.3 is a just
noticeable difference; the fixed Okabe-Ito/Tableau palette's closest pair is
16.2, so 15 is the bar for every pair of labels of one plant.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from plantscan_report import verdict as trust
from plantscan_report.colours import (
    DEBRIS_RGB,
    POT_RGB,
    STEM_RGB,
    UNASSIGNED_RGB,
    _lab,
    face_colours,
    label_colours,
    leaf_palette,
)
from plantscan_report.html_report import render_report
from plantscan_report.meshes import ply_bytes, split_by_face_colour

from plantscan_core.data import LabelledMesh, Mesh

MIN_DELTA_E = 15.0


def _many_leaves(n: int) -> LabelledMesh:
    """``n`` one-triangle leaves (labels 1..n), a stem (0), a pot (n+1), debris (n+2)."""
    k = n + 3
    vertices = np.array([[i, 0.0, 0.0] for i in range(k)] + [[i, 1.0, 0.0] for i in range(k)]
                        + [[i, 0.0, 1.0] for i in range(k)], float)
    faces = np.array([[i, k + i, 2 * k + i] for i in range(k)])
    labels = np.array([0] + list(range(1, n + 1)) + [n + 1, n + 2])
    kinds = {0: "stem", **{i: "leaf" for i in range(1, n + 1)}, n + 1: "pot", n + 2: "debris"}
    return LabelledMesh(Mesh(vertices, faces), labels, kinds)


def test_forty_leaves_get_forty_distinct_colours_unlike_stem_pot_and_debris():
    labelled = _many_leaves(40)
    colours = label_colours(labelled)
    leaves = np.array([colours[i] for i in labelled.leaf_labels])
    assert len({tuple(np.round(c * 255).astype(int)) for c in colours.values()}) == 43
    lab = _lab(leaves)
    d = np.linalg.norm(lab[:, None] - lab[None], axis=2)
    d[np.eye(len(lab), dtype=bool)] = np.inf
    assert d.min() >= MIN_DELTA_E
    others = _lab(np.array([STEM_RGB, POT_RGB, DEBRIS_RGB, UNASSIGNED_RGB]))
    assert np.linalg.norm(lab[:, None] - others[None], axis=2).min() >= MIN_DELTA_E
    # the first twelve leaves keep their colours whatever the plant's leaf count
    np.testing.assert_array_equal(leaf_palette(40)[:12], leaf_palette(12))
    # and the exported PLY carries 43 distinct colours for the 43 labels (was 13 for 18)
    mesh, vc = split_by_face_colour(labelled.mesh, face_colours(labelled))
    data = ply_bytes(mesh, vc)
    body = data.split(b"end_header\n", 1)[1]
    rgb = np.frombuffer(body, dtype=[("xyz", "<f4", (3,)), ("rgb", "u1", (3,))],
                        count=len(mesh.vertices))["rgb"]
    assert len({tuple(c) for c in rgb}) == 43


def test_numbers_never_switch_to_scientific_notation():
    assert trust.format_value("area_mm2", 18240.4) == "18\u2009240 mm²"
    assert trust.format_value("area_mm2", 8110.2) == "8\u2009110 mm²"
    assert trust.format_value("height_mm", 287.05) == "287.1 mm"
    assert trust.format_value("leaf_count", 17.0) == "17"
    assert trust.format_value("thick_share", 0.183) == "18.3 %"
    assert trust.format_value("convex_hull_volume_mm3", 2.4331347e7) == "24\u2009331\u2009347 mm³"
    assert "e+" not in trust.format_number(1.824e4, 1)
    assert trust.format_number(float("nan"), 1) == "—"


def test_calibration_line_levels():
    assert trust.calibration_line({"rms_px": 0.2, "corners": 900})[0] == "ok"
    level, text = trust.calibration_line({"rms_px": 0.2, "flags": ["board covers 40 %"]})
    assert level == "check" and "board covers 40 %" in text
    assert trust.calibration_line({"rms_px": 0.7})[0] == "check"
    assert trust.calibration_line({"rms_px": 1.6})[0] == "fail"
    assert trust.calibration_line({})[0] == "—"


def _verdict_html(html: str) -> str:
    return re.search(r'<section id="verdict">.*?</section>', html, re.S).group(0)


def test_verdict_says_not_assessed_without_a_flag(synthetic_run):
    html = render_report(synthetic_run, thumbnails=0)
    block = _verdict_html(html)
    assert html.index('id="verdict"') < html.index('id="plant3d"')  # first thing on the page
    assert 'class="flag flag-na">not assessed' in block
    assert "2 measured, 1 to read with care (⚠ in the traits table): 1 warned about" in block
    assert "Calibration</b>: <span class=\"lvl lvl-ok\">ok" in block  # RMS 0.21 px, no notes
    # the warned leaf's row is marked, with a short reason
    row = re.search(r'<tr class="warned">(.*?)</tr>', html, re.S).group(1)
    assert ">0 <span" in row and "phantom volume" in row


@pytest.mark.parametrize("flag, reasons", [
    ("check", ["3 of 12 leaves have low confidence", "debris is 20 % of the leaf area"]),
    ("fail", ["no leaf found"]),
    ("ok", []),
])
def test_verdict_shows_the_plant_flag_and_its_reasons(synthetic_run, flag, reasons):
    # as the leaf-geometry measurer writes them into plant_traits.json
    synthetic_run.traits.plant.update(quality_flag=flag, quality_reasons=reasons)
    html = render_report(synthetic_run, thumbnails=0)
    block = _verdict_html(html)
    assert f'class="flag flag-{flag}">{flag}</span>' in block
    for reason in reasons:
        assert f"<li>{reason}</li>" in block
    assert "not assessed" not in block
    plant_table = re.search(r'<section id="traits">.*?</section>', html, re.S).group(0)
    assert "quality flag" not in plant_table  # in the verdict, not among the traits


def test_low_confidence_leaves_are_marked_with_their_reasons(synthetic_run):
    # as leaf-geometry writes them: the traits.csv columns, and a warning that says the same
    leaf = synthetic_run.traits.leaves[1]
    leaf.confidence, leaf.confidence_reasons, leaf.quality_flag = 0.3, "outline;shape", "check"
    synthetic_run.reports["measure"].warn(
        "low-confidence", "leaf 1: confidence 0.30: its perimeter is under 1.8x its length: "
        "...; its area does not fit its length and width", leaf=1)
    synthetic_run.traits.leaves[0].confidence = 0.9
    synthetic_run.traits.leaves[0].quality_flag = "ok"
    html = render_report(synthetic_run, thumbnails=0)
    rows = re.findall(r'<tr class="warned">(.*?)</tr>', html, re.S)
    assert len(rows) == 2  # leaf 0 (warned about, confidence 0.9) and leaf 1 (low confidence)
    assert ">0.90<" in rows[0] and "phantom volume" in rows[0]
    # its two reasons in short, each once (the warning repeating them adds nothing)
    reason = re.findall(r'<td class="reason">(.*?)</td>', rows[1])[0]
    assert reason == "perimeter too short for its length; area does not fit length × width"
    assert ">0.30<" in rows[1]
    assert ("2 to read with care (⚠ in the traits table): 1 low confidence, 1 warned about "
            "by a stage") in _verdict_html(html)


def test_exports_are_named_by_plugin(synthetic_run):
    synthetic_run.timings["export.0"] = 0.3
    synthetic_run.info.setdefault("stages", {})["export.0"] = {"plugin": "ply"}
    html = render_report(synthetic_run, thumbnails=0)
    timings = re.search(r'<section id="timings">.*?</section>', html, re.S).group(0)
    assert "export ply" in timings and "export.0" not in timings


def test_header_gives_the_scan_date_and_the_recipe_as_run(synthetic_run):
    # the scan's own time stamp (scan.yaml), not the run's or the report's
    synthetic_run.scan.info["created"] = "2025-05-04T09:30:00+00:00"
    synthetic_run.info = {"created": "2026-12-01T10:00:00+00:00",
                          "overrides": ["scan.protocol.tilts_deg=[20]",
                                        "segment.params.l_threshold=30"]}
    html = render_report(synthetic_run, thumbnails=0)
    header = re.search(r"<header>.*?</header>", html, re.S).group(0)
    assert "scanned 2025-05-04 09:30:00" in header and "2026-12-01" not in header
    # --set changes the recipe: the header says so, and what was captured is the scan's
    assert ("with --set scan.protocol.tilts_deg=[20] segment.params.l_threshold=30"
            in header)
    assert "8 plant images: 1 camera(s) (cam0) × 1 tilt(s) (0°) × 8 angles" in header
    synthetic_run.info = {}
    plain = re.search(r"<header>.*?</header>", render_report(synthetic_run, thumbnails=0),
                      re.S).group(0)
    assert "--set" not in plain


def test_no_number_on_the_page_is_in_scientific_notation(synthetic_run):
    # The demo's truth table read "1.74e+05" beside "1.7e+05" (total leaf area), and a
    # small lens coefficient would have read "1.2e-05": every table has fixed decimals.
    import json

    truth_file = synthetic_run.scan.ground_truth_dir / "plant_traits.json"
    truth = json.loads(truth_file.read_text())
    truth["total_leaf_area_mm2"] = 174_012.3
    truth_file.write_text(json.dumps(truth))
    synthetic_run.traits.plant["total_leaf_area_mm2"] = 170_003.9
    import dataclasses

    models = synthetic_run.calibration.models
    for name, model in models.items():
        models[name] = dataclasses.replace(model, d2=1.2e-5)
    html = render_report(synthetic_run, thumbnails=0)
    text = re.sub(r"<script.*?</script>|data:[^\"']*", "", html, flags=re.S)
    assert not re.findall(r"\d[eE][+-]\d", text)
    truth_table = re.search(r'<section id="truth">.*?</section>', html, re.S).group(0)
    cells = re.sub(r' class="[^"]*"', "", truth_table)
    assert "<td>total leaf area</td><td>174\u2009012 mm²</td><td>170\u2009004 mm²</td>" in cells
    assert "<td>0.00001</td>" in re.sub(r' class="[^"]*"', "", html)  # d2, 5 decimals


def test_every_measurer_reason_code_has_words():
    # a reason code the leaf-geometry measurer can write (plantscan_leaves/trust.py, the
    # trust model's "model" among them) reaches the report's table in words, not as a code
    from plantscan_leaves.trust import REASON_TEXT

    from plantscan_core.data import LeafTraits

    for code in [*REASON_TEXT, "model"]:
        leaf = LeafTraits(1, 10.0, 2.0, 15.0, 25.0, confidence=0.3, confidence_reasons=code,
                          quality_flag="check")
        words = trust.leaf_reasons(leaf, [])
        assert words and words[0] != code, code

"""The report opened in headless Chromium: it renders, offline, without console errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from plantscan_report.colours import leaf_colour
from plantscan_report.html_report import HtmlReportExporter
from report_chromium import chromium_binary, open_page

pytestmark = pytest.mark.skipif(
    chromium_binary() is None,
    reason="chromium not installed (Debian: apt-get install -y chromium; `make` installs it)")

PROBE = """const box = (sel) => { const r = document.querySelector(sel).getBoundingClientRect();
                          return [r.left, r.top, r.width, r.height]; };
JSON.stringify({
  plots: document.querySelectorAll('.js-plotly-plot').length,
  webgl: document.querySelectorAll('#plant3d canvas').length,
  legend: Array.from(document.querySelectorAll('#plant3d .legendtext')).map(e => e.textContent),
  leafRows: document.querySelectorAll('#traits table')[0].querySelectorAll('tbody tr').length,
  thumbs: Array.from(document.querySelectorAll('#silhouettes img')).filter(
      i => i.complete && i.naturalWidth > 0).length,
  title: document.title,
  verdictFlag: document.querySelector('#verdict .flag').textContent,
  verdictTop: document.querySelector('main section').id,
  warnedRows: Array.from(document.querySelectorAll('#traits tr.warned td:first-child')).map(
      e => e.textContent.trim()),
  numbers: (() => { const d = document.querySelector('#plant3d .js-plotly-plot').data;
                    const t = d.find(t => t.mode === 'text'); return t ? t.text : null; })(),
  legendBox: box('#plant3d .legend'),
  toolbarBox: box('#plant3d .modebar'),
  calibrationFolded: !document.querySelector('#calibration details').open,
  box: (() => { const r = document.querySelector('#plant3d .plot').getBoundingClientRect();
                return [r.left + scrollX, r.top + scrollY, r.width, r.height]; })()
})"""


def _hue_pixels(png: bytes, box: list[float], rgb: np.ndarray) -> int:
    """Pixels inside ``box`` (x, y, w, h) whose hue is that of ``rgb`` and clearly coloured."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    x, y, w, h = (int(round(v)) for v in box)
    hsv = cv2.cvtColor(img[y:y + h, x:x + w], cv2.COLOR_BGR2HSV).astype(int)
    target = cv2.cvtColor(np.uint8([[np.round(rgb[::-1] * 255)]]), cv2.COLOR_BGR2HSV)[0, 0]
    dh = np.abs(hsv[..., 0] - int(target[0]))
    dh = np.minimum(dh, 180 - dh)  # OpenCV hue wraps at 180
    # Shading changes value and a little saturation, not hue: +-6 of 180 and saturated.
    return int(np.count_nonzero((dh <= 6) & (hsv[..., 1] > 80) & (hsv[..., 2] > 60)))


def test_report_renders_in_chromium_without_errors(synthetic_run, tmp_path: Path):
    (path,) = HtmlReportExporter().export(synthetic_run)
    page = open_page(path.as_uri(), tmp_path / "chromium-profile", expression=PROBE)
    assert page.console_errors == []
    # Offline: the only URLs loaded are the file itself and its embedded data: images.
    assert {u.split(":", 1)[0] for u in page.requests} <= {"file", "data"}
    probe = json.loads(page.evaluated)
    # 3D view, truth scatter, 2 calibration plots (folded: drawn when opened), timings
    assert probe["plots"] == 5
    assert probe["webgl"] >= 1  # plotly drew the 3D view in a WebGL canvas
    assert probe["legend"] == ["leaf 0", "leaf 1", "stem", "leaf numbers"]
    assert probe["leafRows"] == 2 and probe["thumbs"] == 6
    # The verdict is the first block; no plant flag in this run: "not assessed".
    assert probe["verdictTop"] == "verdict" and probe["verdictFlag"] == "not assessed"
    assert probe["warnedRows"] == ["0 ⚠"]  # leaf 0 is named by a measure warning
    assert probe["numbers"] == ["0", "1"]  # the 3D view numbers the leaves as the table
    # The legend (top left) and plotly's toolbar (top right) do not overlap.
    lx, ly, lw, lh = probe["legendBox"]
    tx, ty, tw, th = probe["toolbarBox"]
    assert lx + lw <= tx or tx + tw <= lx or ly + lh <= ty or ty + th <= ly
    assert probe["calibrationFolded"]
    assert probe["title"].startswith('plantscan report: <script>alert("x")')  # text, not markup
    # The screenshot's 3D view shows both leaves in their colours: not a blank canvas.  The
    # legend (right 20 % of the view) is left out: its swatches alone have ~130 such pixels;
    # the leaves cover ~4300 and ~570 px (leaf 1 is seen almost edge-on).
    x, y, w, h = probe["box"]
    for rank in (0, 1):
        assert _hue_pixels(page.screenshot_png, [x, y, 0.8 * w, h], leaf_colour(rank)) > 300


def test_the_harness_does_catch_console_errors(tmp_path: Path):
    """Control: a page that throws is reported, so an empty list above means something."""
    page_path = tmp_path / "broken.html"
    page_path.write_text("<html><body><script>console.error('boom');"
                         "undefinedFunction();</script></body></html>")
    page = open_page(page_path.as_uri(), tmp_path / "profile", settle_s=0.5)
    assert any("boom" in e for e in page.console_errors)
    assert any("undefinedFunction" in e for e in page.console_errors)

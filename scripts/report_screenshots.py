"""Screenshots of a run's report.html in headless Chromium, for docs/report.md.

Usage::

    python scripts/report_screenshots.py RUN_DIR NAME [--out docs/img]

writes ``NAME-top.png`` (header and verdict), ``NAME-traits.png`` (the traits
table) and ``NAME-3d.png`` (the 3D view), each clipped from one full-page
screenshot at the box of its section.  Uses the Chromium harness of the report
tests (tests/report/report_chromium.py).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "report"))

from report_chromium import open_page  # noqa: E402

BOXES = """JSON.stringify((() => {
  const box = (sel) => { const e = document.querySelector(sel); if (!e) return null;
    const r = e.getBoundingClientRect(); return [r.left + scrollX, r.top + scrollY, r.width,
    r.height]; };
  const head = box('header'), verdict = box('#verdict');
  return {top: head && verdict ? [0, 0, 1280, verdict[1] + verdict[3] + 8] : head,
          traits: box('#traits'), '3d': box('#plant3d')};
})())"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("name")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    ap.add_argument("--max-height", type=int, default=1100,
                    help="crop a section taller than this (px) to its top")
    args = ap.parse_args(argv)
    import cv2
    import numpy as np

    report = (args.run_dir / "report.html").resolve()
    with tempfile.TemporaryDirectory() as profile:
        page = open_page(report.as_uri(), Path(profile), expression=BOXES, settle_s=6.0,
                         height=1000)
    if page.console_errors:
        print("console errors:", page.console_errors, file=sys.stderr)
    boxes = json.loads(page.evaluated)
    img = cv2.imdecode(np.frombuffer(page.screenshot_png, np.uint8), cv2.IMREAD_COLOR)
    args.out.mkdir(parents=True, exist_ok=True)
    for part, box in boxes.items():
        if box is None:
            continue
        x, y, w, h = (int(round(v)) for v in box)
        h = min(h, args.max_height)
        clip = img[max(y, 0):y + h, max(x, 0):x + w]
        path = args.out / f"{args.name}-{part}.png"
        cv2.imwrite(str(path), clip, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        print(path, clip.shape[1], "x", clip.shape[0])
    return 0


if __name__ == "__main__":
    sys.exit(main())

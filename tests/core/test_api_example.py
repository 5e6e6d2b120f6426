"""docs/api.md runs: its Python blocks, in order, as one script in a fresh folder.

The page is the Python API's worked example; executing it keeps it true
(every block's asserts and prints run against the real pipeline).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.importorskip("pandas")
pytest.importorskip("plantscan_sim.api")
pytestmark = pytest.mark.slow

DOC = Path(__file__).resolve().parents[2] / "docs" / "api.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_api_page_runs_as_a_script(tmp_path, monkeypatch, capsys):
    blocks = python_blocks(DOC.read_text())
    assert len(blocks) >= 5  # scan, process, table, read back, stage by stage
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "api_example"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"{DOC}:block {i + 1}", "exec"), namespace)  # noqa: S102
    out = capsys.readouterr().out
    assert "images" in out and "leaf_id" in out and "faces per leaf" in out
    assert "no segmenter plugin named 'lab-shadw'" in out
    # what the page says it produced is on disk
    assert (tmp_path / "api-example" / "run" / "traits.csv").exists()
    df = namespace["df"]
    assert list(df.columns[:5]) == ["leaf_id", "length_mm", "width_mm", "area_mm2",
                                    "perimeter_mm"]
    assert str(df["leaf_id"].dtype) == "int64"

"""The trust confusion of ``benchmarks/leaf_population.py``: every measured leaf sorted by
what the evaluation says it is, so a flag is judged against the truth, never the code."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import leaf_population as lp  # noqa: E402


def _leaf(measured_id: int, truth_id: int, rel: float) -> dict:
    row = {"measured_id": measured_id, "truth_id": truth_id}
    for n in ("length", "width", "area", "perimeter"):
        row[f"{n}_truth"], row[f"{n}_measured"] = 100.0, 100.0
    row["area_measured"] = 100.0 * (1 + rel)  # one trait off: the worst trait decides
    return row


def test_every_measured_leaf_gets_one_kind_and_merged_wins_over_paired():
    evaluation = {"traits": {
        "per_leaf": [_leaf(1, 0, 0.03), _leaf(2, 1, -0.08), _leaf(3, 2, 0.30),
                     _leaf(4, 3, 0.01)],
        "instances": {"merged_ids": [4], "split_ids": {"2": [3, 5]},
                      "extra_pieces": [{"measured_id": 6}]}}}
    kinds = lp.leaf_kinds(evaluation)
    # 3 is the paired part of the split leaf 2 (judged by its error), 5 its other piece;
    # 4 is paired within 1 % but holds two truth leaves: its traits are two leaves'
    assert kinds == {1: "accurate", 2: "fair", 3: "off", 4: "merged", 5: "split", 6: "extra"}


def test_confusion_table_counts_flagged_bad_leaves_and_flagged_good_ones():
    counts = {("accurate", True): 1, ("accurate", False): 9, ("off", True): 3,
              ("off", False): 1, ("extra", True): 2}
    text = lp.confusion_table(counts)
    assert "| accurate (matched, every trait within 5 %) | 1 | 9 | 10 % |" in text
    # bad = off + extra: 5 of 6 flagged; 1 of the 6 flagged leaves is accurate
    assert "flagged: 5 of 6 (83 %)" in text
    assert "accurate: 1 of 6 (17 %)" in text

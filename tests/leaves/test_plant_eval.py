"""`plantscan evaluate`'s plant-level traits (height, total leaf area, leaf count)."""

from __future__ import annotations

import json

import pytest
from plantscan_leaves.evaluate import plant_errors


def test_plant_errors_compare_each_trait(tmp_path):
    (tmp_path / "m.json").write_text(json.dumps(
        {"height_mm": 289.0, "total_leaf_area_mm2": 990.0, "leaf_count": 12,
         "projected_area_mm2": 5.0}))
    (tmp_path / "t.json").write_text(json.dumps(
        {"height_mm": 300.0, "total_leaf_area_mm2": 1000.0, "leaf_count": 12, "soil_z_mm": 142}))
    out = plant_errors(tmp_path / "m.json", tmp_path / "t.json")
    assert out["height_mm"]["relative_error"] == pytest.approx(-11 / 300)
    assert out["total_leaf_area_mm2"]["relative_error"] == pytest.approx(-0.01)
    assert out["leaf_count"] == {"measured": 12, "truth": 12, "error": 0, "relative_error": 0.0}
    assert set(out) == {"height_mm", "total_leaf_area_mm2", "leaf_count"}  # shared traits only


def test_plant_height_from_the_rim_is_compared_with_the_truth_above_its_rim(tmp_path):
    # The mesher removed the pot: the measured height is above the rim, so the truth's is
    # taken above the truth pot's rim (pot.yaml beside the truth), not from the soil below it.
    (tmp_path / "m.json").write_text(json.dumps({"height_mm": 139.0}))
    (tmp_path / "t.json").write_text(json.dumps(
        {"height_mm": 148.0, "top_z_mm": 290.0, "soil_z_mm": 142.0}))
    (tmp_path / "pot.yaml").write_text("pot: {z_bottom_mm: 30, z_top_mm: 150, r_bottom_mm: 52, "
                                       "r_top_mm: 68, soil_z_mm: 142}\n")
    out = plant_errors(tmp_path / "m.json", tmp_path / "t.json", from_rim=True)
    assert out["height_mm"]["truth"] == pytest.approx(140.0)
    assert out["height_mm"]["relative_error"] == pytest.approx(-1 / 140)
    # without a pot removed the truth stays from the soil
    assert plant_errors(tmp_path / "m.json", tmp_path / "t.json")["height_mm"]["truth"] == 148.0


def test_plant_errors_absent_without_both_files(tmp_path):
    (tmp_path / "t.json").write_text("{}")
    assert plant_errors(tmp_path / "missing.json", tmp_path / "t.json") is None
    (tmp_path / "m.json").write_text('{"height_mm": 1}')
    assert plant_errors(tmp_path / "m.json", tmp_path / "t.json") is None  # nothing to compare

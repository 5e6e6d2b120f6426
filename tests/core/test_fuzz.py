"""Fuzzing every file a user hands plantscan (issue #23), with hypothesis.

The property, for recipes, ``--set``, calibration files, COLMAP text and
``views.jsonl``: either a valid result that holds no NaN or infinity, or a
refusal (exit status 2 / a ``PlantScanError``) whose message names the file,
line or path; never a traceback.  Bounded to ~60 s in all (examples per test
below), so it runs in every CI pass.
"""

from __future__ import annotations

import copy
import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plantscan_core.cli import main
from plantscan_core.data import Calibration, CameraModel, Pose, ViewRecord
from plantscan_core.errors import PlantScanError
from plantscan_core.recipe import read_recipe_file
from plantscan_core.scanfolder import ScanFolder

# capsys is read (and so reset) by every example; derandomize: the same cases in every CI run.
FUZZ = settings(max_examples=100, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

HOSTILE_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                           st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0,
                                            -0.0, 5e-324]))
HOSTILE = st.one_of(
    HOSTILE_FLOATS,
    st.integers(min_value=-(10**20), max_value=10**20),
    st.text(max_size=12),
    st.none(),
    st.booleans(),
    st.lists(HOSTILE_FLOATS, max_size=7),
    st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
    st.sampled_from([".nan", "1e308", "-.inf", "[]", "{}", "~", "!!python/object:os.system",
                     "a" * 300]),
)


def _paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path to a value inside a JSON-like document (dict keys and list indices)."""
    out = [prefix] if prefix else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, prefix + (i,))
    return out


@st.composite
def mutated(draw, doc: Any, max_edits: int = 3) -> Any:
    """``doc`` with up to ``max_edits`` values replaced by hostile ones (or keys added)."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, max_edits))):
        paths = _paths(doc)
        path = draw(st.sampled_from(paths))
        node = doc
        for key in path[:-1]:
            node = node[key]
        if draw(st.booleans()) and isinstance(node, dict):
            node[draw(st.text(min_size=1, max_size=8))] = draw(HOSTILE)
        else:
            node[path[-1]] = draw(HOSTILE)
    return doc


def _finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    if isinstance(value, np.ndarray):
        return bool(np.isfinite(value).all()) if value.dtype.kind == "f" else True
    if hasattr(value, "__dict__"):
        return all(_finite(v) for v in vars(value).values())
    return True


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    status = main(list(argv))
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and "internal error" not in captured.err, captured.err
    assert status in (0, 2), captured.err
    return status, captured.out, captured.err


# --------------------------------------------------------------------------- recipes
PLASTIC_DICOT = read_recipe_file(Path(__file__).resolve().parents[2] / "recipes" /
                                 "plastic-dicot.yaml")


@FUZZ
@given(raw=mutated(PLASTIC_DICOT))
def test_fuzz_recipe_file(capsys, raw):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "r.yaml"
        f.write_text(yaml.safe_dump(raw, allow_unicode=True))
        status, out, err = _run(capsys, "recipe", "check", str(f))
    if status == 0:
        from plantscan_core.recipe import validate_recipe

        assert _finite(validate_recipe(raw).model_dump())
    else:
        # Every error line names a path or the file ("scan.image_size: ...", "/tmp/...: ...").
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert lines and all(": " in ln for ln in lines), err


@FUZZ
@given(data=st.binary(max_size=300))
def test_fuzz_recipe_bytes(capsys, data):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "r.yaml"
        f.write_bytes(b"name: x\n" + data)
        status, _, err = _run(capsys, "recipe", "check", str(f))
    assert status == 2 and str(f) in err  # never a valid recipe: no scan section


OVERRIDE_PATHS = [".".join(str(k) for k in p) for p in _paths(PLASTIC_DICOT)]


@FUZZ
@given(path=st.sampled_from(OVERRIDE_PATHS) | st.text(max_size=15),
       value=st.text(max_size=25) | st.sampled_from([".nan", ".inf", "-.inf", "1e308", "[.nan]",
                                                      "{a: [[[[1]]]]}", "&a [*a]", "!!binary x"]))
def test_fuzz_set_override(capsys, path, value):
    status, _, err = _run(capsys, "recipe", "check", "plastic-dicot", f"--set={path}={value}")
    if status == 2:
        assert all(": " in ln for ln in err.splitlines() if ln.strip()), err


# --------------------------------------------------------------------------- calibration files
CALIBRATION = Calibration(
    {"cam0": CameraModel(f=800.0, cu=319.5, cv=213.0, d1=-0.05, width=640, height=427)},
    {("cam0", 0): Pose(np.eye(3), [0.0, 0.0, 900.0])}, {0: 0.0}).to_dict()


@FUZZ
@given(raw=mutated(CALIBRATION))
def test_fuzz_calibration_file(raw):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "calibration.yaml"
        f.write_text(yaml.safe_dump(raw))
        try:
            cal = Calibration.load(f)
        except PlantScanError as exc:
            assert str(f) in str(exc)
            return
    assert _finite(cal.models) and _finite(cal.poses) and math.isfinite(cal.angle_scale)


# --------------------------------------------------------------------------- COLMAP text
TOKEN = st.one_of(st.sampled_from(["nan", "inf", "-inf", "0", "-1", "1e308", "800", "320.5",
                                   "RADIAL", "PINHOLE", "OPENCV", "SIMPLE_PINHOLE", "a.png", "#"]),
                  st.integers(-5, 2000).map(str), st.floats(-1e3, 1e3).map(repr))
LINE = st.lists(TOKEN, max_size=12).map(" ".join)


@FUZZ
@given(cameras=st.lists(LINE, max_size=4), images=st.lists(LINE, max_size=6))
def test_fuzz_colmap_text(cameras, images):
    from plantscan_hull.colmap import read_cameras, read_images

    with tempfile.TemporaryDirectory() as d:
        cam_file, img_file = Path(d) / "cameras.txt", Path(d) / "images.txt"
        cam_file.write_text("\n".join(cameras) + "\n")
        img_file.write_text("\n".join(images) + "\n")
        for read, f in ((read_cameras, cam_file), (read_images, img_file)):
            try:
                result = read(f)
            except PlantScanError as exc:
                assert str(f) in str(exc)
                continue
            values = result.values() if isinstance(result, dict) else result
            for item in values:
                assert _finite(item)
                if hasattr(item, "q"):
                    assert np.linalg.norm(item.q) > 0


# --------------------------------------------------------------------------- views.jsonl
VIEW = ViewRecord(index=0, role="plant", camera="cam0", tilt_index=0, tilt_deg=0.0,
                  angle_index=0, commanded_angle_deg=0.0, measured_angle_deg=None,
                  file="images/plant/0.png").to_dict()


@FUZZ
@given(lines=st.lists(mutated(VIEW, max_edits=2) | st.just(VIEW), min_size=1, max_size=4),
       tail=st.binary(max_size=40))
def test_fuzz_views_jsonl(lines, tail):
    with tempfile.TemporaryDirectory() as d:
        scan = ScanFolder.create(Path(d) / "s", {"plant_id": "p"})
        text = "".join(json.dumps(v) + "\n" for v in lines)
        (scan.root / "views.jsonl").write_bytes(text.encode() + tail)
        try:
            opened = ScanFolder.open(scan.root)
        except PlantScanError as exc:
            assert "views.jsonl" in str(exc)
            return
    for view in opened.views:
        assert _finite(view.to_dict())


@pytest.mark.parametrize("depth", [31, 33, 5000])
def test_deep_views_line(tmp_path, depth):
    scan = ScanFolder.create(tmp_path / "s", {"plant_id": "p"})
    (scan.root / "views.jsonl").write_text("[" * depth + "]" * depth + "\n")
    with pytest.raises(PlantScanError, match=r"views.jsonl:1: "):
        ScanFolder.open(scan.root)

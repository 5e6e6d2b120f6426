"""Scan folder: atomic append, resume, torn lines, path escapes, named errors."""

from __future__ import annotations

import json

import pytest

from plantscan_core.acquire import acquire, plan
from plantscan_core.data import ViewRecord
from plantscan_core.errors import DataError, ScanFolderError
from plantscan_core.recipe import validate_recipe
from plantscan_core.scanfolder import ScanFolder
from plantscan_core.testing import tiny_recipe


def _view(i: int, file: str) -> ViewRecord:
    return ViewRecord(i, "plant", "cam0", 0, 0.0, i, 10.0 * i, None, file)


def test_failed_capture_leaves_no_line_and_no_file(tmp_path):
    scan = ScanFolder.create(tmp_path / "s", {"plant_id": "p"})
    scan.append_view(_view(0, "images/a.png"), lambda p: p.write_bytes(b"png"))

    def crash(p):
        p.write_bytes(b"half")
        raise OSError("USB unplugged")

    with pytest.raises(OSError):
        scan.append_view(_view(1, "images/b.png"), crash)
    reopened = ScanFolder.open(tmp_path / "s")
    assert [v.file for v in reopened.views] == ["images/a.png"]
    assert sorted(p.name for p in (tmp_path / "s/images").iterdir()) == ["a.png"]


def test_torn_last_line_is_ignored_then_overwritten(tmp_path):
    scan = ScanFolder.create(tmp_path / "s", {})
    scan.append_view(_view(0, "images/a.png"), lambda p: p.write_bytes(b"x"))
    with open(tmp_path / "s/views.jsonl", "ab") as f:
        f.write(b'{"index": 1, "role": "pla')  # crash in the middle of an append
    scan = ScanFolder.open(tmp_path / "s")
    assert len(scan.views) == 1
    scan.append_view(_view(1, "images/b.png"), lambda p: p.write_bytes(b"y"))
    lines = (tmp_path / "s/views.jsonl").read_text().splitlines()
    assert [json.loads(x)["file"] for x in lines] == ["images/a.png", "images/b.png"]


@pytest.mark.parametrize("bad", ["../outside.png", "/etc/passwd", "images/../../x.png"])
def test_paths_escaping_the_folder_are_rejected(tmp_path, bad):
    scan = ScanFolder.create(tmp_path / "s", {})
    line = json.dumps(_view(0, bad).to_dict())
    (tmp_path / "s/views.jsonl").write_text(line + "\n")
    with pytest.raises(ScanFolderError, match="escapes the scan folder"):
        ScanFolder.open(tmp_path / "s")
    with pytest.raises(ScanFolderError, match="escapes"):
        scan.append_view(_view(0, bad), lambda p: p.write_bytes(b"x"))


def test_symlink_escape_is_rejected(tmp_path):
    (tmp_path / "secret.png").write_bytes(b"x")
    scan = ScanFolder.create(tmp_path / "s", {})
    (tmp_path / "s/images/link.png").symlink_to(tmp_path / "secret.png")
    with pytest.raises(ScanFolderError, match="escapes"):
        scan.path_of(_view(0, "images/link.png"))


def test_malformed_line_and_missing_image_are_named(tmp_path):
    ScanFolder.create(tmp_path / "s", {})
    (tmp_path / "s/views.jsonl").write_text('{"index": 0}\n')
    with pytest.raises(ScanFolderError, match=r"views.jsonl:1: malformed"):
        ScanFolder.open(tmp_path / "s")
    (tmp_path / "s/views.jsonl").write_text(json.dumps(_view(0, "images/gone.png").to_dict())
                                            + "\n")
    scan = ScanFolder.open(tmp_path / "s")
    with pytest.raises(DataError, match="gone.png.*missing"):
        scan.read_image(scan.views[0])
    with pytest.raises(ScanFolderError, match="not a plantscan scan folder"):
        ScanFolder.open(tmp_path)


def test_existing_scan_is_not_overwritten(tmp_path):
    ScanFolder.create(tmp_path / "s", {})
    with pytest.raises(ScanFolderError, match="--resume"):
        ScanFolder.create(tmp_path / "s", {})


def test_interrupted_scan_resumes_without_rewriting(tmp_path, tiny_rig_manager):
    raw = tiny_recipe()
    recipe = validate_recipe(raw, tiny_rig_manager.registry)
    total = len(plan(recipe))
    acquire(recipe, tmp_path / "s", tiny_rig_manager, raw_recipe=raw, stop_after=7)
    first = {p: p.stat().st_mtime_ns for p in (tmp_path / "s/images").rglob("*.png")}
    assert len(first) == 7
    scan = acquire(recipe, tmp_path / "s", tiny_rig_manager, raw_recipe=raw, resume=True)
    assert len(scan.views) == total
    assert sorted(v.key for v in scan.views) == sorted(v.key for v in plan(recipe))
    assert [v.index for v in scan.views] == list(range(total))
    for p, mtime in first.items():
        assert p.stat().st_mtime_ns == mtime, f"{p} was rewritten"


def test_resume_with_another_protocol_is_refused(tmp_path, tiny_rig_manager):
    raw = tiny_recipe()
    acquire(validate_recipe(raw, tiny_rig_manager.registry), tmp_path / "s", tiny_rig_manager,
            raw_recipe=raw, stop_after=2)
    other = tiny_recipe(images_per_revolution=8)
    with pytest.raises(ScanFolderError, match="different protocol"):
        acquire(validate_recipe(other, tiny_rig_manager.registry), tmp_path / "s",
                tiny_rig_manager, raw_recipe=other, resume=True)


def test_bad_parameter_fails_before_any_move(tmp_path, tiny_rig_manager):
    from plantscan_core.testing import TinyAxis

    moves = []
    orig = TinyAxis.move_to
    TinyAxis.move_to = lambda self, deg: moves.append(deg)
    try:
        raw = tiny_recipe()
        raw["scan"]["cameras"][1]["params"] = {"noise": "loud"}
        with pytest.raises(Exception, match="noise"):
            recipe = validate_recipe(raw, tiny_rig_manager.registry)
            acquire(recipe, tmp_path / "s", tiny_rig_manager, raw_recipe=raw)
    finally:
        TinyAxis.move_to = orig
    assert moves == []

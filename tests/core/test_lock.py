"""One writer per folder: a second writer is refused; a killed holder's lock is seen as stale."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from plantscan_core.hookspecs import hookimpl
from plantscan_core.lock import LOCK_FILE, FolderBusyError, FolderLock
from plantscan_core.stages import Calibrator

HOLDER = """
import sys, time
from plantscan_core.lock import FolderLock
lock = FolderLock(sys.argv[1], "run folder").acquire()
print("locked", flush=True)
time.sleep(120)
"""


def _start_holder(folder) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_second_writer_is_refused_and_named_then_stale_after_kill_9(tmp_path):
    holder = _start_holder(tmp_path)
    try:
        with pytest.raises(FolderBusyError) as info:
            FolderLock(tmp_path, "run folder").acquire()
        msg = str(info.value)
        assert f"another plantscan is writing this run folder (pid {holder.pid}" in msg
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
    finally:
        if holder.poll() is None:
            holder.kill()
    lock = FolderLock(tmp_path, "run folder").acquire()
    try:
        assert lock.stale is not None and lock.stale["pid"] == holder.pid
        assert "ended without finishing (killed?)" in lock.stale_message()
    finally:
        lock.release()
    # A clean release leaves no record: the next writer finds nothing stale.
    with FolderLock(tmp_path) as again:
        assert again.stale is None


def test_one_process_cannot_take_a_folder_twice(tmp_path):
    """flock is per open file: a second lock in the same process is refused as well."""
    with FolderLock(tmp_path):
        with pytest.raises(FolderBusyError):
            FolderLock(tmp_path).acquire()


def test_a_record_of_a_reused_pid_is_stale(tmp_path):
    """Our own pid with another start time: a previous process whose pid was reused."""
    (tmp_path / LOCK_FILE).write_text(json.dumps({
        "pid": os.getpid(), "host": os.uname().nodename, "start": "1", "since": "then",
        "command": "plantscan process"}))
    with FolderLock(tmp_path) as lock:
        assert lock.stale is not None


def test_kill_9_during_a_scan_leaves_a_stale_lock_that_resume_reports(tmp_path, capsys,
                                                                       tiny_rig_manager):
    """The real scan command: killed mid-scan, ``--resume`` says the last writer was killed."""
    out = tmp_path / "scan"
    code = f"""
import time
from plantscan_core.acquire import acquire
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe
from plantscan_core.testing import tiny_recipe, tiny_rig_plugin
manager = new_manager()
manager.register(tiny_rig_plugin, name="tiny-rig")
raw = tiny_recipe()
acquire(validate_recipe(raw, manager.registry), {str(out)!r}, manager, raw_recipe=raw,
        on_role_start=lambda role: (print("started", flush=True), time.sleep(60)))
"""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "started"
        with pytest.raises(FolderBusyError, match="another plantscan is writing this scan"):
            FolderLock(out, "scan folder").acquire()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    from plantscan_core.acquire import acquire
    from plantscan_core.recipe import validate_recipe
    from plantscan_core.testing import tiny_recipe

    raw = tiny_recipe()
    scan = acquire(validate_recipe(raw, tiny_rig_manager.registry), out, tiny_rig_manager,
                   raw_recipe=raw, resume=True)
    err = capsys.readouterr().err
    assert f"the previous writer (pid {proc.pid} " in err and "(killed?)" in err
    assert len(scan.views) == (2 + 1 + 6) * 2  # calibration, background, plant; 2 cameras


SLOW_PROCESS = """
import sys, time
from plantscan_core.hookspecs import hookimpl
from plantscan_core.pipeline import process
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import load_recipe
from plantscan_core.testing import tiny_rig_plugin
import test_lock

manager = new_manager()
manager.register(tiny_rig_plugin, name="tiny-rig")
manager.register(test_lock, name="slow")
process(sys.argv[1], load_recipe(sys.argv[2], registry=manager.registry), sys.argv[3], manager)
"""


class SlowCalibrator(Calibrator):
    """Holds its run folder for a minute (long enough to be killed mid-run)."""

    name = "tiny-slow"

    def calibrate(self, scan):
        print("calibrating", flush=True)
        time.sleep(60)
        raise AssertionError("should have been killed")


@hookimpl
def plantscan_register_stages(registry):
    registry.add(SlowCalibrator)


def test_two_process_runs_into_one_folder_then_kill_9(tmp_path, tiny_rig_manager, monkeypatch,
                                                     capsys):
    """The second ``plantscan process`` into a busy --out is refused (status 2, holder named);
    after kill -9 of the holder the next run says the lock was stale and runs."""
    from plantscan_core import plugins
    from plantscan_core.cli import main
    from plantscan_core.testing import make_tiny_scan, tiny_recipe

    scan = make_tiny_scan(tmp_path / "scan", tiny_rig_manager)
    raw = tiny_recipe()
    raw["calibrate"] = {"plugin": "tiny-slow"}
    recipe = tmp_path / "slow.yaml"
    recipe.write_text(yaml.safe_dump(raw))
    out = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", SLOW_PROCESS, str(scan.root), str(recipe), str(out)],
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parent,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parent)})
    try:
        assert holder.stdout.readline().strip() == "calibrating"
        tiny_rig_manager.register(sys.modules[__name__], name="slow")
        monkeypatch.setattr(plugins, "_default", tiny_rig_manager)
        raw["calibrate"] = None  # the second run would not even need the slow stage
        quick = tmp_path / "quick.yaml"
        quick.write_text(yaml.safe_dump(raw))
        assert main(["process", str(scan.root), "--recipe", str(quick), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"{out}: another plantscan is writing this run folder (pid {holder.pid}" in err
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
    finally:
        if holder.poll() is None:
            holder.kill()
    assert main(["process", str(scan.root), "--recipe", str(quick), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"the previous writer (pid {holder.pid} " in err and "(killed?)" in err

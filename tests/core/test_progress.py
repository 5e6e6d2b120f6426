"""Progress on every step: a live display in a terminal, plain lines without one, run.log.

The end-to-end tests run ``plantscan process`` on a small virtual scan, once
with stderr a pipe (a log file, CI, a batch worker) and once under a
pseudo-terminal, and check what a user reads: every stage of the run says it
started and finished, the leaf warnings come as one summary line, and run.log
holds them in full.  How often a running step speaks is asserted on the
display itself with a stepped clock, not on wall time (the machine's load
decides that); the silences measured in the runs are printed.
"""

from __future__ import annotations

import io
import os
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from plantscan_core import progress
from plantscan_core.progress import Display

STAGES = ["load plugins", "calibrate", "segment", "reconstruct", "mesh", "segment_mesh", "measure",
          "export csv", "export html-report"]
# Small and quick: exact cameras (calibrator `truth`: the stage still runs), a 64^3 hull.
SETS = ["calibrate.plugin=truth", "calibrate.params={}", "reconstruct.params.resolution=64",
        "export=[{plugin: csv}, {plugin: html-report, params: {thumbnails: 2}}]"]
TOOK = r"(<1 s|\d+ s|\d+:\d\d)"  # how the display writes a duration
ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b[()][0-9A-Za-z]|\r")


# --------------------------------------------------------------------------- the display
def test_plain_display_speaks_while_a_step_runs(monkeypatch):
    out = io.StringIO()
    d = Display("plain", stream=out)
    now = [1000.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    with d.step("segment", estimate_s=20.0) as step:
        step.count(72, "views")
        for _ in range(72):
            now[0] += 0.5  # 36 s in all: the heartbeat must speak every HEARTBEAT_S
            step.advance()
            d.beat()
    d.close()
    lines = out.getvalue().splitlines()
    assert lines[0] == "segment: started, estimated 20 s"
    assert lines[-1] == "segment: done in 36 s"
    beats = [ln for ln in lines if re.match(r"segment: \d+/72 views", ln)]
    assert progress.HEARTBEAT_S == 5.0
    assert len(beats) == 7  # at 5, 10, ..., 35 s: never more than HEARTBEAT_S silent
    assert beats[0] == "segment: 10/72 views, 5 s, ~31 s left"


def test_a_spent_estimate_is_said_not_counted_down_below_zero(monkeypatch):
    # A scan on a busy machine: its first image took longer than the whole estimate.  The
    # line said "0/36 images, 17 s, ~<1 s left" for half a minute; now it says so.
    out = io.StringIO()
    d = Display("plain", stream=out)
    now = [1000.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    with d.step("scan calibration", 36, "images", estimate_s=12.0) as step:
        for _ in range(4):
            now[0] += 5.0
            d.beat()
        step.advance(2)
        now[0] += 5.0
        d.beat()
    d.close()
    lines = out.getvalue().splitlines()
    assert lines[1] == "scan calibration: 0/36 images, 5 s, ~7 s left"
    assert lines[2] == "scan calibration: 0/36 images, 10 s, ~2 s left"
    assert lines[3] == "scan calibration: 0/36 images, 15 s, over the estimate of 12 s"
    assert not any("<1 s left" in ln for ln in lines)
    assert lines[5] == "scan calibration: 2/36 images, 25 s, ~7:05 left"  # from the rate


def test_live_display_updates_its_line_every_beat(monkeypatch):
    # In a terminal the line of a running step changes every second (the display's thread
    # beats each second, rich redraws 5 times a second): never 2 s without a change.
    d = Display("rich", stream=io.StringIO())
    now = [1000.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    with d.step("reconstruct"):
        task = d._rich.tasks[0]
        for seconds in range(1, 4):
            now[0] += 1.0
            d.beat()
            assert task.fields["status"] == f"{seconds} s"
    d.close()


def test_quiet_display_says_warnings_only():
    out = io.StringIO()
    d = Display("quiet", stream=out)
    with d.step("segment", 3) as step:
        step.advance(3)
    d.message("an info line")
    d.message("a warning", 30)
    assert out.getvalue() == "a warning\n"


# --------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def small_scan(tmp_path_factory) -> Path:
    sim = pytest.importorskip("plantscan_sim.api")
    root = tmp_path_factory.mktemp("progress") / "scan"
    sim.make_scan(root, "plastic-dicot", image_size=(320, 213), images_per_revolution=8,
                  roles=("background", "plant"))
    return root


def _command(scan: Path, run: Path, *extra: str) -> list[str]:
    cmd = [sys.executable, "-m", "plantscan_core.cli", "process", str(scan), "--out", str(run),
           *extra]
    for s in SETS:
        cmd += ["--set", s]
    return cmd


def _read_timed(fd: int, proc: subprocess.Popen) -> tuple[str, float]:
    """Everything written to ``fd`` until the process ends, and the longest silence (s)."""
    chunks, last, longest = [], time.monotonic(), 0.0
    while True:
        ready, _, _ = select.select([fd], [], [], 0.2)
        if ready:
            try:
                data = os.read(fd, 65536)
            except OSError:  # the pty's other side closed
                data = b""
            if not data:
                if proc.poll() is not None:
                    break
                continue
            now = time.monotonic()
            longest = max(longest, now - last)
            last = now
            chunks.append(data)
        elif proc.poll() is not None:
            break
    return b"".join(chunks).decode("utf-8", "replace"), longest


@pytest.mark.slow
def test_without_a_terminal_every_stage_has_its_lines(small_scan, tmp_path):
    env = {**os.environ, "COLUMNS": "120"}
    proc = subprocess.Popen(_command(small_scan, tmp_path / "run"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    err, longest = _read_timed(proc.stderr.fileno(), proc)
    out = proc.stdout.read().decode()
    assert proc.wait() == 0, err[-3000:]
    print(f"no terminal: longest silence on stderr {longest:.1f} s")
    lines = err.splitlines()
    for stage in STAGES:
        assert f"{stage}: started" in lines, (stage, err)
        assert any(re.fullmatch(rf"{stage}: done in {TOOK}(; .*)?", ln) for ln in lines), stage
    assert not any("\x1b[" in ln for ln in lines)  # plain text, no terminal codes
    # leaf warnings: one summary line, not one line each; run.log has each in full
    log = (tmp_path / "run" / "run.log").read_text()
    summary = [ln for ln in lines if re.match(r"measure: \d+ warnings? \(lea", ln)]
    warned = len(re.findall(r"WARNING .*leaf \d+:", log))
    if warned:
        assert len(summary) == 1 and not any(re.match(r"leaf \d+:", ln) for ln in lines)
    assert "plantscan.run: process" in log and "done in" in log
    assert "leaves measured" in out
    # a second run from the cache: every stage says "cached", the warnings are not repeated
    again = subprocess.run(_command(small_scan, tmp_path / "run"), capture_output=True,
                           text=True, env=env)
    assert again.returncode == 0
    for stage in STAGES[1:7]:
        assert re.search(rf"^{stage}: done in {TOOK}; cached", again.stderr, re.M), stage
    assert not re.search(r"warnings? \(lea", again.stderr)


@pytest.mark.slow
def test_in_a_terminal_every_stage_is_shown_live(small_scan, tmp_path):
    import pty

    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm-256color", "COLUMNS": "120", "LINES": "40"}
    proc = subprocess.Popen(_command(small_scan, tmp_path / "run"), stdin=slave, stdout=slave,
                            stderr=slave, env=env, close_fds=True)
    os.close(slave)
    try:
        screen, longest = _read_timed(master, proc)
    finally:
        os.close(master)
    assert proc.wait() == 0, screen[-3000:]
    print(f"terminal: longest time without a screen update {longest:.1f} s")
    text = ANSI.sub("", screen)
    for stage in STAGES:
        assert re.search(rf"✓ {re.escape(stage)} {TOOK}", text), (stage, text[-2000:])
    assert "\x1b[" in screen  # a live display (cursor movement, colours), not plain lines
    assert "segment: started" not in text  # the plain lines are for files and pipes


@pytest.mark.slow
def test_a_scan_without_a_terminal_says_each_role_with_its_estimate(tmp_path):
    # The virtual rig, small: 4 board views, 1 background, 8 plant views per camera.
    pytest.importorskip("plantscan_sim.api")
    out = tmp_path / "scan"
    cmd = [sys.executable, "-m", "plantscan_core.cli", "scan", "plastic-dicot", "--out",
           str(out), "--set", "scan.image_size=[320,213]", "--set",
           "scan.images_per_revolution=8", "--set",
           "scan.roles.calibration.images_per_revolution=4"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "COLUMNS": "120"})
    err, longest = _read_timed(proc.stderr.fileno(), proc)
    assert proc.wait() == 0, err[-3000:]
    print(f"scan, no terminal: longest silence on stderr {longest:.1f} s")
    lines = err.splitlines()
    assert "scan set-up: started" in lines
    for role, images in (("calibration", 8), ("background", 2), ("plant", 16)):
        # the timing model's estimate of the virtual camera's render time, then its end
        start = [ln for ln in lines if ln.startswith(f"scan {role}: started")]
        assert len(start) == 1 and re.fullmatch(
            rf"scan {role}: started \({images} images\), estimated {TOOK}",
                                                start[0]), (role, err)
        assert any(re.fullmatch(rf"scan {role}: done in {TOOK}(; .*)?", ln) for ln in lines)
    assert "\x1b[" not in err
    log = (out / "run.log").read_text()  # the scan's own log: what ran, per role, the end
    assert re.search(r"plantscan.scan: scan .* \(recipe plastic-dicot[^)]*\): 26 images to "
                     r"capture, estimated \d+ s", log), log
    assert "plantscan.scan: plant: 16 images" in log
    assert re.search(r"plantscan.scan: done in [\d.]+ s: 26 images in the scan folder", log)

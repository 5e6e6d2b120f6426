"""The ``grbl`` axis against a GRBL emulator: over socket://, a pty, socat, and loop://."""

from __future__ import annotations

import shutil
import subprocess
import threading
import time

import hwfakes
import pytest
from grbl_emulator import GrblMachine, PtyGrbl, TcpGrbl
from hwfakes import RIG, check_scan, fake_recipe
from plantscan_serial import plugin as serial_plugin
from plantscan_serial.grbl import GrblAxis, GrblError, GrblParams

from plantscan_core.acquire import AcquisitionError, acquire
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe


@pytest.fixture
def manager():
    m = new_manager()
    m.register(hwfakes)
    m.register(serial_plugin, name="serial")
    RIG.reset()
    try:
        yield m
    finally:
        m.unregister(hwfakes)


@pytest.fixture
def tcp():
    emu = TcpGrbl()
    try:
        yield emu
    finally:
        emu.close()


def _axis(port, **kw) -> GrblAxis:
    kw = {"poll_interval_s": 0.01, "connect_timeout_s": 2.0, **kw}
    return GrblAxis(GrblParams(port=port, **kw))


def _grbl_recipe(port, n_angles=4, tilts=(0.0, 25.0)):
    raw = fake_recipe(tilts=tilts, n_angles=n_angles)
    raw["scan"]["turntable"] = {"plugin": "grbl", "params": {
        "port": port, "axis": "X", "poll_interval_s": 0.01, "feed_rate": 3000}}
    if len(tilts) > 1:
        raw["scan"]["tilt_arm"] = {"plugin": "grbl", "params": {
            "port": port, "axis": "Y", "poll_interval_s": 0.01, "feed_rate": 600,
            "units_per_degree": 2.0}}
    return raw


def test_move_and_read_back_over_socket(tcp):
    axis = _axis(tcp.url, units_per_degree=4.0)
    axis.open()
    try:
        axis.home()
        measured = axis.move_to(30.0)
        # The emulator reports positions to 0.001 unit = 0.00025 deg here.
        assert measured == pytest.approx(30.0, abs=0.001)
        assert tcp.machine.mpos["X"] == pytest.approx(120.0, abs=1e-6)  # 4 units per degree
        assert axis.position() == pytest.approx(30.0, abs=0.001)
        assert any(line.startswith("G1X120.0000") for line in tcp.machine.lines)
    finally:
        axis.close()


def test_zero_homing_makes_the_current_place_zero(tcp):
    tcp.machine.mpos["X"] = 17.0
    axis = _axis(tcp.url)
    axis.open()
    try:
        axis.home()
        assert axis.position() == pytest.approx(0.0, abs=0.001)
        axis.move_to(10.0)
        assert tcp.machine.mpos["X"] == pytest.approx(27.0, abs=1e-6)
    finally:
        axis.close()


def test_homing_cycle_clears_the_startup_alarm():
    emu = TcpGrbl(GrblMachine(homing_enabled=True, start_in_alarm=True))
    emu.machine.mpos["X"] = 5.0
    axis = _axis(emu.url, homing="cycle")
    try:
        axis.open()
        axis.home()
        assert "$H" in emu.machine.lines
        assert axis.move_to(12.5) == pytest.approx(12.5, abs=0.001)
    finally:
        axis.close()
        emu.close()


def test_errors_are_named():
    emu = TcpGrbl(GrblMachine(start_in_alarm=True))
    axis = _axis(emu.url, unlock_on_alarm=False)
    try:
        with pytest.raises(GrblError, match="Alarm state"):
            axis.open()
        axis.close()
        axis = _axis(emu.url, homing="cycle")  # homing not enabled on this controller
        axis.open()
        with pytest.raises(GrblError, match=r"error:5 \(homing cycle failure"):
            axis.home()
    finally:
        axis.close()
        emu.close()


def test_soft_limit_alarm_is_explained():
    emu = TcpGrbl(GrblMachine(travel=(-10.0, 100.0)))
    axis = _axis(emu.url)
    try:
        axis.open()
        with pytest.raises(GrblError, match=r"ALARM:2 .*soft limit"):
            axis.move_to(200.0)
    finally:
        axis.close()
        emu.close()


def test_loop_url_is_not_mistaken_for_grbl():
    axis = _axis("loop://", connect_timeout_s=0.5)
    with pytest.raises(GrblError, match="no GRBL status answer"):
        axis.open()


def test_stop_halts_a_move_at_once(tcp):
    tcp.machine.speedup = 0.5  # a slow move (36 s), stopped after 0.2 s
    axis = _axis(tcp.url)
    axis.open()
    errors = []

    def run():
        try:
            axis.move_to(90.0)
        except GrblError as exc:
            errors.append(exc)

    t = threading.Thread(target=run)
    t.start()
    time.sleep(0.2)
    axis.stop()
    t.join(timeout=5)
    assert not t.is_alive()
    assert errors and "ALARM:3" in str(errors[0])  # GRBL: reset while in motion
    assert tcp.machine.mpos["X"] < 10.0  # it stopped far from 90
    axis.close()


def test_pty_scan_with_two_axes_on_one_controller(manager, tmp_path):
    emu = PtyGrbl()
    try:
        raw = _grbl_recipe(emu.path)
        recipe = validate_recipe(raw, manager.registry)
        scan = acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
        check_scan(tmp_path / "s", recipe)
        for v in scan.views:  # read back from the controller, 0.001 unit resolution
            assert v.measured_angle_deg == pytest.approx(v.commanded_angle_deg, abs=0.002)
        assert any(line.startswith("G1Y50.0000") for line in emu.machine.lines)  # 25 deg x 2
    finally:
        emu.close()


def test_socket_disconnect_mid_move_then_resume(manager, tmp_path, tcp):
    tcp.machine.disconnect_on_move = 5
    raw = _grbl_recipe(tcp.url)
    recipe = validate_recipe(raw, manager.registry)
    with pytest.raises(AcquisitionError) as err:
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    msg = str(err.value)
    assert "serial link lost during the move" in msg and "--resume" in msg
    assert err.value.captured > 0
    tcp.machine.disconnect_on_move = None
    acquire(recipe, tmp_path / "s", manager, raw_recipe=raw, resume=True)
    check_scan(tmp_path / "s", recipe)


@pytest.fixture
def socat_pty(tmp_path, tcp):
    """A pty at a device path, bridged by socat to the TCP emulator (like a USB-serial adapter)."""
    if shutil.which("socat") is None:
        pytest.skip("socat not installed (apt-get install socat; `make setup` does it)")
    link = tmp_path / "ttyGRBL"

    def start():
        proc = subprocess.Popen(["socat", f"pty,raw,echo=0,link={link}",
                                 f"tcp:127.0.0.1:{tcp.port}"])
        for _ in range(200):
            if link.exists():
                return proc
            time.sleep(0.01)
        proc.kill()
        raise RuntimeError("socat did not create the pty")

    procs = [start()]
    yield link, tcp, procs, start
    for p in procs:
        p.kill()
        p.wait()


def test_socat_pty_disconnect_mid_move_then_resume(manager, tmp_path, socat_pty):
    link, tcp, procs, start = socat_pty
    raw = _grbl_recipe(str(link), tilts=(0.0,), n_angles=6)
    recipe = validate_recipe(raw, manager.registry)
    tcp.machine.speedup = 2.0  # moves of ~0.1 s, so the unplug lands mid-move
    def unplug_when_moving():
        while tcp.machine.moves < 3:
            time.sleep(0.002)
        procs[0].kill()  # the USB-serial adapter disappears

    killer = threading.Thread(target=unplug_when_moving)
    killer.start()
    with pytest.raises(AcquisitionError, match="serial link lost"):
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    killer.join()
    procs.append(start())  # plugged back in
    tcp.machine.speedup = 50.0
    acquire(recipe, tmp_path / "s", manager, raw_recipe=raw, resume=True)
    check_scan(tmp_path / "s", recipe)


@pytest.mark.hardware
def test_real_grbl_controller_moves(request):
    """With a GRBL controller at $PLANTSCAN_GRBL_PORT: a 10 deg move and back."""
    import os

    port = os.environ.get("PLANTSCAN_GRBL_PORT")
    if not request.config.getoption("--hardware", default=False) or not port:
        pytest.skip("set PLANTSCAN_GRBL_PORT and run with --hardware")
    axis = GrblAxis(GrblParams(port=port))
    axis.open()
    try:
        axis.home()
        assert axis.move_to(10.0) == pytest.approx(10.0, abs=0.05)
        assert axis.move_to(0.0) == pytest.approx(0.0, abs=0.05)
    finally:
        axis.close()


def test_backward_moves_end_going_forwards(tcp):
    axis = _axis(tcp.url, approach_deg=1.5)
    axis.open()
    try:
        axis.home()
        axis.move_to(20.0)
        assert axis.move_to(5.0) == pytest.approx(5.0, abs=0.001)
        moves = [line for line in tcp.machine.lines if line.startswith("G1X")]
        assert [m.split("F")[0] for m in moves] == ["G1X20.0000", "G1X3.5000", "G1X5.0000"]
    finally:
        axis.close()


def test_work_offset_is_known_before_any_status_carries_it(tcp):
    """GRBL sends WCO only every few reports: the axis reads G54/G92 with $# on open."""
    tcp.machine.mpos["X"], tcp.machine.wco["X"] = 15.0, 5.0  # set by an earlier session
    axis = _axis(tcp.url, homing="none")
    axis.open()
    try:
        assert axis.position() == pytest.approx(10.0, abs=1e-6)
        assert axis.move_to(12.0) == pytest.approx(12.0, abs=0.001)
        assert tcp.machine.mpos["X"] == pytest.approx(17.0, abs=1e-6)
    finally:
        axis.close()


def test_status_command(tcp):
    import argparse

    parser = argparse.ArgumentParser(prog="plantscan")
    serial_plugin.plantscan_add_commands(subparsers=parser.add_subparsers())
    args = parser.parse_args(["grbl-status", tcp.url])
    tcp.machine.mpos["X"] = 3.0
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert args.func(args) == 0
    out = buf.getvalue()
    assert f"{tcp.url}: Idle; work position X 3, Y 0, Z 0" in out
    assert "$100 = 884.510  (X steps/unit)" in out and "$120 = 30.000" in out

"""The ``phidget`` axis against a simulated stepper at our adapter interface, plus the real
phidget22 library without a device (attach time-out) and, with --hardware, a real one."""

from __future__ import annotations

import os

import hwfakes
import pytest
from fake_stepper import FakeStepperPort
from hwfakes import RIG, check_scan, fake_recipe
from plantscan_phidget import plugin as phidget_plugin
from plantscan_phidget.stepper import (
    PhidgetAxis,
    PhidgetAxisError,
    PhidgetParams,
    move_time_s,
    parse_gear_ratio,
)

from plantscan_core.acquire import AcquisitionError, acquire
from plantscan_core.hookspecs import hookimpl
from plantscan_core.plugins import new_manager
from plantscan_core.recipe import validate_recipe

SEED_RATIO = 99 + 1044 / 2057


class SimPhidgetAxis(PhidgetAxis):
    """The real axis logic on a simulated stepper (detach on the move given in the env)."""

    name = "phidget-sim"

    def make_port(self):
        n = os.environ.get("FAKE_STEPPER_DETACH_ON_MOVE")
        return FakeStepperPort(speedup=200.0, detach_on_move=int(n) if n else None)


class _SimPlugin:
    @staticmethod
    @hookimpl
    def plantscan_register_stages(registry):
        registry.add(SimPhidgetAxis)


@pytest.fixture
def manager():
    m = new_manager()
    m.register(hwfakes)
    m.register(phidget_plugin, name="phidget")
    m.register(_SimPlugin(), name="phidget-sim")
    RIG.reset()
    FakeStepperPort.instances.clear()
    try:
        yield m
    finally:
        m.unregister(hwfakes)


def _axis(**kw) -> SimPhidgetAxis:
    return SimPhidgetAxis(PhidgetParams(settle_s=0.0, **kw))


def test_gear_ratio_forms():
    assert parse_gear_ratio("99 1044/2057") == pytest.approx(SEED_RATIO, rel=1e-15)
    assert parse_gear_ratio("99 1044/2057:1") == pytest.approx(SEED_RATIO, rel=1e-15)
    assert parse_gear_ratio("2057/20") == pytest.approx(102.85)
    assert parse_gear_ratio(100) == 100.0
    with pytest.raises(ValueError, match="mixed fraction"):
        parse_gear_ratio("about 100")


def test_one_revolution_is_the_real_gear_ratio_of_microsteps():
    axis = _axis()
    axis.open()
    axis.home()
    axis.move_to(360.0)
    port = axis.port
    # 200 full steps x 16 microsteps x the real ratio, to the nearest microstep.
    assert port.microsteps == round(200 * 16 * SEED_RATIO)
    # The nominal 0.018 deg/step (ratio 100) would send 320000 microsteps for "360 deg":
    # the plate would overshoot by 1.78 deg every turn (the seed's 1.8 deg drift).
    nominal = 200 * 16 * 100
    assert (nominal - port.microsteps) * 360.0 / port.microsteps == pytest.approx(1.78, abs=0.005)
    assert port.config["velocity"] == 12.0 and port.config["current"] == 1.0
    assert port.engaged
    axis.close()
    assert not port.engaged  # motors released on close


def test_measured_position_is_the_device_read_back():
    axis = _axis(invert=True)
    axis.open()
    axis.home()
    measured = axis.move_to(12.345)
    step = axis.params.deg_per_microstep()
    # Read back from the device: whole microsteps, so within half a microstep of the command.
    assert abs(measured - 12.345) <= step / 2 + 1e-12
    assert axis.port.microsteps < 0  # inverted direction
    assert axis.position() == pytest.approx(measured)
    axis.close()


def test_homing_zero_makes_here_zero():
    axis = _axis()
    axis.open()
    axis.move_to(30.0)
    axis.home()
    assert axis.position() == pytest.approx(0.0, abs=1e-12)
    assert axis.move_to(10.0) == pytest.approx(10.0, abs=axis.params.deg_per_microstep())
    assert axis.port.microsteps == pytest.approx(round(40.0 / axis.params.deg_per_microstep()),
                                                 abs=1)
    axis.close()


def test_move_times_follow_the_trapezoid():
    # 10 deg at 12 deg/s, 24 deg/s^2: 0.5 s ramps + (10 - 6) / 12 s cruise
    assert move_time_s(10.0, 12.0, 24.0) == pytest.approx(1.0 + 4.0 / 12.0)
    # 2 deg never reaches full speed: triangle, 2 * sqrt(2 / 24)
    assert move_time_s(2.0, 12.0, 24.0) == pytest.approx(2 * (2 / 24) ** 0.5)


def test_scan_records_read_back_angles(manager, tmp_path):
    raw = fake_recipe(tilts=(0.0, 30.0), n_angles=5)
    raw["scan"]["turntable"] = {"plugin": "phidget-sim", "params": {"settle_s": 0}}
    raw["scan"]["tilt_arm"] = {"plugin": "phidget-sim", "params": {
        "settle_s": 0, "gear_ratio": 50, "velocity_deg_s": 5}}
    recipe = validate_recipe(raw, manager.registry)
    scan = acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    check_scan(tmp_path / "s", recipe)
    step = PhidgetParams().deg_per_microstep()
    for v in scan.views:
        assert v.measured_angle_deg is not None
        assert abs(v.measured_angle_deg - v.commanded_angle_deg) <= step / 2 + 1e-9
    assert all(not p.engaged for p in FakeStepperPort.instances)


def test_detach_mid_move_then_resume(manager, tmp_path, monkeypatch):
    raw = fake_recipe(n_angles=6)
    raw["scan"]["turntable"] = {"plugin": "phidget-sim", "params": {"settle_s": 0}}
    recipe = validate_recipe(raw, manager.registry)
    monkeypatch.setenv("FAKE_STEPPER_DETACH_ON_MOVE", "4")
    with pytest.raises(AcquisitionError, match="detached during the move") as err:
        acquire(recipe, tmp_path / "s", manager, raw_recipe=raw)
    assert "turntable" in str(err.value) and err.value.captured == 3 * 2
    monkeypatch.delenv("FAKE_STEPPER_DETACH_ON_MOVE")
    acquire(recipe, tmp_path / "s", manager, raw_recipe=raw, resume=True)
    check_scan(tmp_path / "s", recipe)


def test_no_device_gives_an_actionable_error():
    """The real phidget22 library, no device attached: a named time-out, not a hang."""
    axis = PhidgetAxis(PhidgetParams(serial_number=999999, attach_timeout_s=0.3))
    with pytest.raises(PhidgetAxisError) as err:
        axis.open()
    msg = str(err.value)
    assert "serial 999999" in msg and "udev" in msg and "power supply" in msg


def test_bad_gear_ratio_is_a_recipe_error(manager):
    raw = fake_recipe()
    raw["scan"]["turntable"] = {"plugin": "phidget", "params": {"gear_ratio": "a hundred"}}
    from plantscan_core.errors import RecipeError

    with pytest.raises(RecipeError, match="scan.turntable.params.gear_ratio"):
        validate_recipe(raw, manager.registry)


@pytest.mark.hardware
def test_real_phidget_stepper_moves(request):
    """With a Phidget stepper (serial in $PLANTSCAN_PHIDGET_SERIAL): 10 deg and back."""
    serial = os.environ.get("PLANTSCAN_PHIDGET_SERIAL")
    if not request.config.getoption("--hardware", default=False) or not serial:
        pytest.skip("set PLANTSCAN_PHIDGET_SERIAL and run with --hardware")
    axis = PhidgetAxis(PhidgetParams(serial_number=int(serial)))
    axis.open()
    try:
        axis.home()
        assert axis.move_to(10.0) == pytest.approx(10.0, abs=0.01)
        assert axis.move_to(0.0) == pytest.approx(0.0, abs=0.01)
    finally:
        axis.close()


def test_backward_moves_end_going_forwards():
    """approach_deg: every stop is reached going forwards (gear backlash taken up alike)."""
    axis = _axis(approach_deg=2.0)
    axis.open()
    axis.home()
    targets = []
    real = axis.port.set_target
    axis.port.set_target = lambda pos: (targets.append(pos), real(pos))[1]
    axis.move_to(30.0)  # forwards: one leg
    axis.move_to(10.0)  # backwards: past it to 8, then forwards to 10
    assert targets == [30.0, 8.0, 10.0]
    assert axis.position() == pytest.approx(10.0, abs=axis.params.deg_per_microstep())
    axis.close()

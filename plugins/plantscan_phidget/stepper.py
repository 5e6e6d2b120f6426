"""Axis ``phidget``: turntable and tilt-arm stepper motors on Phidget controllers (phidget22).

The seed's rig: bipolar steppers with planetary gearboxes on Phidget stepper
controllers (1063/1067/STC1005).  Positions are in degrees of the *driven*
axis: the rescale factor (degrees per microstep) comes from the real gear
ratio.  A gearbox sold as "100:1" is often 99 1044/2057 : 1; taking the
nominal ratio (0.018 deg/step) overshoots by 1.78 deg per turntable revolution.

The phidget22 calls go through a thin adapter (:class:`StepperPort`), so the
axis logic is tested against a simulated stepper at that interface (no
Phidget simulator exists); :class:`Phidget22Port` is the real one.
"""

from __future__ import annotations

import re
import threading
import time
from fractions import Fraction
from typing import Any, Protocol

from pydantic import Field, field_validator

from plantscan_core.errors import HardwareError, require_module
from plantscan_core.stages import MotionAxis, StageParams
from plantscan_core.timing import move_time_s


def parse_gear_ratio(value: float | int | str) -> float:
    """Gear ratio from a number or a mixed fraction: ``"99 1044/2057"`` -> 99.50753...

    Raises ValueError naming the accepted forms.
    """
    if isinstance(value, (int, float)):
        ratio = float(value)
    else:
        text = str(value).strip().replace(":1", "").strip()
        m = re.fullmatch(r"(?:(\d+(?:\.\d+)?)\s+)?(\d+(?:\.\d+)?)(?:\s*/\s*(\d+(?:\.\d+)?))?", text)
        if not m:
            raise ValueError(f"gear ratio {value!r}: expected a number, a fraction '2057/20' or "
                             "a mixed fraction '99 1044/2057'")
        whole, num, den = m.groups()
        frac = Fraction(num) / Fraction(den) if den else Fraction(num)
        ratio = float((Fraction(whole) if whole else 0) + frac)
    if not ratio > 0:
        raise ValueError(f"gear ratio {value!r} must be > 0")
    return ratio


class PhidgetParams(StageParams):
    """Recipe parameters of a ``phidget`` axis (degrees of the driven axis)."""

    serial_number: int | None = Field(default=None, description="device serial; None = any")
    hub_port: int | None = Field(default=None, description="VINT hub port of the controller")
    channel: int = 0
    is_hub_port_device: bool = False
    gear_ratio: float | str = Field(default="99 1044/2057",
                                    description="motor turns per axis turn ('99 1044/2057')")
    motor_step_deg: float = Field(default=1.8, gt=0.0)
    microsteps: int = Field(default=16, ge=1, description="Phidget position units per full step")
    rescale_factor: float | None = Field(default=None, description="deg per microstep; "
                                         "overrides gear_ratio/motor_step_deg/microsteps")
    invert: bool = False
    velocity_deg_s: float = Field(default=12.0, gt=0.0)
    acceleration_deg_s2: float = Field(default=24.0, gt=0.0)
    current_limit_a: float = Field(default=1.0, gt=0.0)
    holding_current_a: float | None = None
    homing: str = Field(default="zero", pattern="^(zero|none)$")
    settle_s: float = Field(default=0.3, ge=0.0, description="wait after stopping (vibration)")
    approach_deg: float = Field(default=0.0, ge=0.0, description="anti-backlash: reach every "
                                "stop going forwards, overshooting backward moves by this")
    attach_timeout_s: float = Field(default=5.0, gt=0.0)
    move_timeout_s: float | None = Field(default=None, description="default: 2x the profile + 5 s")
    position_tolerance_deg: float = Field(default=0.01, ge=0.0)

    @field_validator("gear_ratio")
    @classmethod
    def _ratio(cls, v):
        parse_gear_ratio(v)
        return v

    def deg_per_microstep(self) -> float:
        if self.rescale_factor is not None:
            return self.rescale_factor
        return self.motor_step_deg / self.microsteps / parse_gear_ratio(self.gear_ratio)


class StepperPort(Protocol):
    """What the axis needs from a Phidget stepper channel (units: degrees after rescale)."""

    def open(self, params: PhidgetParams) -> None: ...
    def configure(self, rescale: float, velocity: float, acceleration: float,
                  current: float, holding: float | None) -> None: ...
    def set_engaged(self, on: bool) -> None: ...
    def set_target(self, position: float) -> None: ...
    def position(self) -> float: ...
    def is_moving(self) -> bool: ...
    def zero_here(self) -> None: ...
    def on_stopped(self, callback) -> None: ...
    def on_detach(self, callback) -> None: ...
    def halt(self) -> None: ...
    def close(self) -> None: ...


class PhidgetAxisError(HardwareError):
    """The Phidget controller is missing, detached, or did not reach its target."""


class Phidget22Port:
    """The real adapter: one phidget22 ``Stepper`` channel."""

    def __init__(self) -> None:
        stepper = require_module("Phidget22.Devices.Stepper", "phidget", "axis plugin phidget")
        self.stepper = stepper.Stepper()
        self.velocity = 0.0

    def open(self, p: PhidgetParams) -> None:
        from Phidget22.PhidgetException import PhidgetException

        s = self.stepper
        if p.serial_number is not None:
            s.setDeviceSerialNumber(p.serial_number)
        if p.hub_port is not None:
            s.setHubPort(p.hub_port)
        s.setIsHubPortDevice(p.is_hub_port_device)
        s.setChannel(p.channel)
        try:
            s.openWaitForAttachment(int(p.attach_timeout_s * 1000))
        except PhidgetException as exc:
            raise PhidgetAxisError(
                f"no Phidget stepper attached ({_where(p)}) within {p.attach_timeout_s:g} s "
                f"({getattr(exc, 'details', exc)}); check the USB cable, the motor power supply, "
                "the udev rules (docs/hardware/phidget.md) and that no other program "
                "(Phidget Control Panel, another scan) has the channel open"
            ) from exc

    def configure(self, rescale, velocity, acceleration, current, holding) -> None:
        from Phidget22.PhidgetException import PhidgetException

        s = self.stepper
        steps = [("rescale_factor", s.setRescaleFactor, rescale),
                 ("current_limit_a", s.setCurrentLimit, current),
                 ("holding_current_a", s.setHoldingCurrentLimit, holding),
                 ("acceleration_deg_s2", s.setAcceleration, acceleration),
                 ("velocity_deg_s", s.setVelocityLimit, velocity)]
        for name, setter, value in steps:
            if value is None:
                continue
            try:
                setter(value)
            except PhidgetException as exc:
                raise PhidgetAxisError(
                    f"Phidget stepper (serial {s.getDeviceSerialNumber()}): params.{name} = "
                    f"{value:g} refused ({getattr(exc, 'details', exc)}); velocity and "
                    "acceleration are in axis degrees, so their limits scale with the gear ratio"
                ) from exc
        self.velocity = velocity

    def set_engaged(self, on: bool) -> None:
        self.stepper.setEngaged(on)

    def set_target(self, position: float) -> None:
        self.stepper.setVelocityLimit(self.velocity)  # undo a previous halt()
        self.stepper.setTargetPosition(position)

    def position(self) -> float:
        return self.stepper.getPosition()

    def is_moving(self) -> bool:
        return self.stepper.getIsMoving()

    def zero_here(self) -> None:
        self.stepper.addPositionOffset(-self.stepper.getPosition())

    def on_stopped(self, callback) -> None:
        self.stepper.setOnStoppedHandler(lambda _ch: callback())

    def on_detach(self, callback) -> None:
        self.stepper.setOnDetachHandler(lambda _ch: callback())

    def halt(self) -> None:
        self.stepper.setVelocityLimit(0.0)  # decelerates to a stop at the set acceleration

    def close(self) -> None:
        self.stepper.close()


def _where(p: PhidgetParams) -> str:
    parts = [f"serial {p.serial_number}" if p.serial_number is not None else "any serial"]
    if p.hub_port is not None:
        parts.append(f"hub port {p.hub_port}")
    parts.append(f"channel {p.channel}")
    return ", ".join(parts)


class PhidgetAxis(MotionAxis):
    """A stepper axis on a Phidget controller (``plugin: phidget``)."""

    name = "phidget"
    Params = PhidgetParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.port: Any = None
        self._stopped = threading.Event()
        self._detached = threading.Event()
        self._sign = -1.0 if self.params.invert else 1.0

    def make_port(self) -> StepperPort:
        """The adapter to the device (tests return a simulated stepper)."""
        return Phidget22Port()

    @property
    def label(self) -> str:
        return f"Phidget stepper ({_where(self.params)})"

    def open(self) -> None:
        p = self.params
        self.port = self.make_port()
        self.port.open(p)
        self.port.on_stopped(self._stopped.set)
        self.port.on_detach(self._detached.set)
        self.port.configure(p.deg_per_microstep(), p.velocity_deg_s, p.acceleration_deg_s2,
                            p.current_limit_a, p.holding_current_a)
        self.port.set_engaged(True)

    def close(self) -> None:
        if self.port is not None:
            try:
                self.port.set_engaged(False)
            finally:
                self.port.close()
                self.port = None

    def home(self) -> None:
        if self.port is None:
            self.open()
        if self.params.homing == "zero":
            self.port.zero_here()

    def move_to(self, deg: float) -> float:
        """Move to ``deg`` (axis degrees); return the position read back from the controller.

        With ``approach_deg`` > 0, a move that would end going backwards first goes
        ``approach_deg`` past the target, so every stop is reached going forwards and the
        gearbox backlash is taken up the same way at every view.
        """
        if self.port is None:
            self.open()
        p = self.params
        here = self._sign * self.port.position()
        if p.approach_deg > 0 and deg < here - 1e-9:
            self._go(deg - p.approach_deg, settle=False)
        return self._go(deg)

    def _go(self, deg: float, settle: bool = True) -> float:
        p = self.params
        target = self._sign * deg
        start = self.port.position()
        self._stopped.clear()
        if self._detached.is_set():
            raise PhidgetAxisError(f"{self.label} is detached; check the USB/VINT cable and "
                                   "the motor power supply, then --resume")
        self.port.set_target(target)
        timeout = p.move_timeout_s or 2.0 * move_time_s(target - start, p.velocity_deg_s,
                                                        p.acceleration_deg_s2) + 5.0
        deadline = time.monotonic() + timeout
        # The stopped event comes from phidget22's thread; poll too, so a lost event or a
        # zero-length move cannot hang the scan.
        while True:
            if self._detached.is_set():
                raise PhidgetAxisError(
                    f"{self.label} detached during the move to {deg:g} deg; check the USB/VINT "
                    "cable and the motor power supply (the axis is re-zeroed on --resume)")
            if self._stopped.wait(0.05) or not self.port.is_moving():
                pos = self.port.position()
                if abs(pos - target) <= max(p.position_tolerance_deg, p.deg_per_microstep()):
                    break
            if time.monotonic() > deadline:
                raise PhidgetAxisError(
                    f"{self.label}: move to {deg:g} deg not finished after {timeout:.1f} s "
                    f"(at {self._sign * self.port.position():g} deg); check the load, the "
                    "current limit and that the motor is not stalled")
        if p.settle_s and settle:
            time.sleep(p.settle_s)
        return self._sign * self.port.position()

    def position(self) -> float | None:
        return None if self.port is None else self._sign * self.port.position()

    def stop(self) -> None:
        """Decelerate to a stop now (Ctrl-C); safe from any thread."""
        if self.port is not None:
            try:
                self.port.halt()
            except Exception:  # noqa: BLE001
                pass

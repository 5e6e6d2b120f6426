"""Axis ``grbl``: a turntable or tilt arm driven by a GRBL-style G-code controller over serial.

GRBL 1.1 (Arduino/CNC shields, most cheap stepper controllers) speaks
line-based G-code answered by ``ok`` / ``error:N``, plus one-byte real-time
commands (``?`` status, ``!`` feed hold, ``0x18`` soft reset).  One
controller often drives both rig axes (turntable on X, tilt arm on Y): the two
``grbl`` axes of a recipe that name the same ``port`` share one connection.

``port`` is a device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``) or any
pyserial URL (``socket://host:port``, ``rfc2217://``, ``loop://``), so the
backend runs against an emulator in tests.

Degrees and controller units: ``units_per_degree`` converts (configure the
controller's steps/mm, ``$100``..., so that its "mm" is whatever is handy,
e.g. 1 mm = 1 deg of turntable, then ``units_per_degree: 1``).
"""

from __future__ import annotations

import logging
import re
import termios
import threading
import time
from typing import Literal

from pydantic import Field

from plantscan_core.errors import HardwareError, require_module
from plantscan_core.stages import MotionAxis, StageParams

log = logging.getLogger(__name__)

# GRBL 1.1 error and alarm codes (grbl/doc/csv/error_codes_en_US.csv, alarm_codes_en_US.csv).
GRBL_ERRORS = {
    1: "G-code words consist of a letter and a value; letter was not found",
    2: "missing the expected G-code word value or numeric value format is not valid",
    3: "'$' system command was not recognized or supported",
    4: "negative value received for an expected positive value",
    5: "homing cycle failure: homing is not enabled via settings ($22)",
    6: "minimum step pulse time must be greater than 3 usec",
    7: "EEPROM read failed, default values used",
    8: "'$' command cannot be used unless GRBL is IDLE",
    9: "G-code commands are locked out during alarm or jog state (home with $H or unlock "
       "with $X)",
    10: "soft limits cannot be enabled without homing also enabled",
    11: "max characters per line exceeded",
    12: "step rate exceeds 30 kHz: lower the feed rate or steps/mm",
    13: "safety door detected as opened and door state initiated",
    14: "build info or startup line exceeded EEPROM line length limit",
    15: "jog target exceeds machine travel",
    16: "jog command has no '=' or contains prohibited G-code",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command found in block",
    21: "more than one G-code command from the same modal group found in block",
    22: "feed rate has not yet been set or is undefined",
    23: "G-code command in block requires an integer value",
    24: "more than one G-code command that requires axis words found in block",
    25: "repeated G-code word found in block",
    26: "no axis words found in a command that requires them",
    27: "line number value is invalid",
    28: "G-code command is missing a required value word",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 only allowed with G0 and G1 motion modes",
    31: "axis words found in block when no command or current modal state uses them",
    32: "G2/G3 arcs require at least one in-plane axis word",
    33: "motion command target is invalid",
    34: "arc radius value is invalid",
    35: "G2/G3 arcs require at least one in-plane offset word",
    36: "unused value words found in block",
    37: "G43.1 dynamic tool length offset is not assigned to configured tool length axis",
    38: "tool number greater than max supported value",
}
GRBL_ALARMS = {
    1: "hard limit triggered: position lost, re-home",
    2: "soft limit: the target is beyond the machine travel",
    3: "reset while in motion: position lost, re-home",
    4: "probe fail",
    5: "probe fail",
    6: "homing fail: the cycle was reset",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: could not clear the limit switch (check pull-off and wiring)",
    9: "homing fail: limit switch not found within the search distance (check the switch, its "
       "wiring and $130-$132)",
}

_STATUS = re.compile(r"<([A-Za-z]+)(?::\d+)?\|(.*)>")


class GrblParams(StageParams):
    """Recipe parameters of a ``grbl`` axis."""

    port: str = Field(description="device path or pyserial URL (socket://host:port, loop://)")
    baudrate: int = 115200
    axis: Literal["X", "Y", "Z", "A", "B", "C"] = "X"
    units_per_degree: float = Field(default=1.0, gt=0.0)
    feed_rate: float = Field(default=1800.0, gt=0.0, description="units/min for G1 moves")
    homing: Literal["cycle", "zero", "none"] = "zero"
    unlock_on_alarm: bool = True
    position_tolerance_deg: float = Field(default=0.05, ge=0.0)
    timeout_s: float = Field(default=120.0, gt=0.0)
    poll_interval_s: float = Field(default=0.05, gt=0.0)
    connect_timeout_s: float = Field(default=5.0, gt=0.0)
    # Timing model only (plantscan scan --dry-run): the controller's $120.. acceleration.
    acceleration_deg_s2: float = Field(default=30.0, gt=0.0)
    settle_s: float = Field(default=0.3, ge=0.0)
    approach_deg: float = Field(default=0.0, ge=0.0, description="anti-backlash: reach every "
                                "stop going forwards, overshooting backward moves by this")

    @property
    def velocity_deg_s(self) -> float:
        return self.feed_rate / 60.0 / self.units_per_degree


class GrblError(HardwareError):
    """The controller refused a command, raised an alarm, or the link failed."""


class GrblConnection:
    """One serial link to one controller, shared by the axes that name its port."""

    _open: dict[str, GrblConnection] = {}
    _registry_lock = threading.Lock()

    def __init__(self, port: str, baudrate: int, connect_timeout_s: float) -> None:
        self.port = port
        self.lock = threading.RLock()
        self.users = 0
        self.wco: dict[str, float] = {}
        self._buf = b""
        # pyserial is the extra plantscan[serial]: imported when a link opens.  A vanished
        # USB-serial adapter surfaces as any of these; pyserial's ``in_waiting`` raises
        # termios.error (not an OSError) when the pty is gone mid-poll.
        serial = require_module("serial", "serial", f"grbl {port}")
        self._link_errors = (serial.SerialException, OSError, termios.error)
        try:
            self.ser = serial.serial_for_url(port, baudrate=baudrate, timeout=0.05,
                                             write_timeout=2.0)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise GrblError(
                f"grbl {port}: cannot open the serial port ({exc}); check the path (ls "
                "/dev/serial/by-id/), that this user is in the 'dialout' group, and that no "
                "other program (a G-code sender, ModemManager) holds it"
            ) from exc
        self._handshake(connect_timeout_s)

    @classmethod
    def acquire(cls, params: GrblParams) -> GrblConnection:
        with cls._registry_lock:
            conn = cls._open.get(params.port)
            if conn is None:
                conn = cls(params.port, params.baudrate, params.connect_timeout_s)
                cls._open[params.port] = conn
            conn.users += 1
            return conn

    def release(self) -> None:
        with self._registry_lock:
            self.users -= 1
            if self.users <= 0:
                self._open.pop(self.port, None)
                try:
                    self.ser.close()
                except Exception:  # noqa: BLE001
                    pass

    def drop(self) -> None:
        """Forget a broken link so the next ``acquire`` reconnects."""
        with self._registry_lock:
            if self._open.get(self.port) is self:
                self._open.pop(self.port, None)
            try:
                self.ser.close()
            except Exception:  # noqa: BLE001
                pass

    # ---------------------------------------------------------------- low level
    def _write(self, data: bytes) -> None:
        try:
            self.ser.write(data)
            self.ser.flush()
        except self._link_errors as exc:
            raise GrblError(f"grbl {self.port}: serial link lost while writing ({exc})") from exc

    def _readline(self, deadline: float) -> str | None:
        """One line without its end, or None at ``deadline``."""
        while True:
            if b"\n" in self._buf:
                line, _, self._buf = self._buf.partition(b"\n")
                return line.decode("ascii", "replace").strip()
            if time.monotonic() > deadline:
                return None
            try:
                chunk = self.ser.read(self.ser.in_waiting or 1)
            except self._link_errors as exc:
                raise GrblError(f"grbl {self.port}: serial link lost ({exc})") from exc
            self._buf += chunk

    def _handshake(self, timeout_s: float) -> None:
        # Wake up the controller (an Arduino resets on open and prints its banner) and
        # ask for a status: anything that answers '<...>' speaks GRBL.
        deadline = time.monotonic() + timeout_s
        self._write(b"\r\n\r\n")
        next_ask = 0.0
        seen: list[str] = []
        while time.monotonic() < deadline:
            if time.monotonic() >= next_ask:
                self._write(b"?")
                next_ask = time.monotonic() + 0.25
            line = self._readline(min(deadline, time.monotonic() + 0.1))
            if line is None or not line:
                continue
            if line.startswith("<"):
                self._buf = b""
                return
            seen.append(line)
        got = "; ".join(seen[:5]) or "nothing"
        raise GrblError(
            f"grbl {self.port}: no GRBL status answer within {timeout_s:g} s (received: {got}); "
            "is this a GRBL controller at the right baud rate?"
        )

    # ---------------------------------------------------------------- protocol
    def command(self, line: str, timeout_s: float = 10.0) -> list[str]:
        """Send one G-code/``$`` line; return the messages before ``ok``; raise on error/alarm."""
        with self.lock:
            self._write(line.encode("ascii") + b"\n")
            deadline = time.monotonic() + timeout_s
            messages: list[str] = []
            while True:
                reply = self._readline(deadline)
                if reply is None:
                    raise GrblError(f"grbl {self.port}: no answer to {line!r} within "
                                    f"{timeout_s:g} s")
                if reply == "ok":
                    return messages
                if reply.startswith("error:"):
                    code = _int(reply[6:])
                    raise GrblError(f"grbl {self.port}: {line!r} refused: error:{code} "
                                    f"({GRBL_ERRORS.get(code, 'unknown error')})")
                if reply.startswith("ALARM:"):
                    code = _int(reply[6:])
                    raise GrblError(f"grbl {self.port}: ALARM:{code} after {line!r} "
                                    f"({GRBL_ALARMS.get(code, 'unknown alarm')})")
                if reply and not reply.startswith("<"):
                    messages.append(reply)

    def status(self, timeout_s: float = 2.0) -> tuple[str, dict[str, float]]:
        """(state, work position per axis letter) from a ``?`` report."""
        with self.lock:
            self._write(b"?")
            deadline = time.monotonic() + timeout_s
            while True:
                reply = self._readline(deadline)
                if reply is None:
                    raise GrblError(f"grbl {self.port}: no status report within {timeout_s:g} s")
                if reply.startswith("ALARM:"):
                    code = _int(reply[6:])
                    raise GrblError(f"grbl {self.port}: ALARM:{code} "
                                    f"({GRBL_ALARMS.get(code, 'unknown alarm')})")
                m = _STATUS.match(reply)
                if m:
                    return m.group(1), self._positions(m.group(2))

    def _positions(self, fields: str) -> dict[str, float]:
        parts = dict(f.split(":", 1) for f in fields.split("|") if ":" in f)
        letters = "XYZABC"
        if "WCO" in parts:  # sent every few reports; remembered in between
            self.wco = dict(zip(letters, map(float, parts["WCO"].split(",")), strict=False))
        if "WPos" in parts:
            return dict(zip(letters, map(float, parts["WPos"].split(",")), strict=False))
        mpos = dict(zip(letters, map(float, parts.get("MPos", "").split(",")), strict=False))
        return {k: v - self.wco.get(k, 0.0) for k, v in mpos.items()}

    def refresh_offsets(self) -> None:
        """Learn the work offset (G54 + G92) with ``$#``: status reports carry ``WCO`` only
        every few reports, and positions must be right from the first one."""
        g54 = g92 = None
        for line in self.command("$#"):
            m = re.match(r"\[(G54|G92):([-\d.,]+)\]", line)
            if m:
                values = dict(zip("XYZABC", map(float, m.group(2).split(",")), strict=False))
                if m.group(1) == "G54":
                    g54 = values
                else:
                    g92 = values
        if g54 is not None:
            self.wco = {k: v + (g92 or {}).get(k, 0.0) for k, v in g54.items()}

    def realtime(self, byte: bytes) -> None:
        """Send a real-time command without waiting (safe from another thread)."""
        try:
            self.ser.write(byte)
            self.ser.flush()
        except Exception:  # noqa: BLE001 - used to stop; a dead link has stopped anyway
            pass


def _int(text: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        return -1


class GrblAxis(MotionAxis):
    """One axis of a GRBL controller, in degrees (``plugin: grbl``)."""

    name = "grbl"
    Params = GrblParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self.conn: GrblConnection | None = None

    @property
    def label(self) -> str:
        return f"grbl axis {self.params.axis} on {self.params.port}"

    def open(self) -> None:
        self.conn = GrblConnection.acquire(self.params)
        state, _ = self.conn.status()
        if state.lower().startswith("alarm"):
            if self.params.homing == "cycle":
                return  # $H clears the alarm
            if not self.params.unlock_on_alarm:
                raise GrblError(f"{self.label}: the controller is in Alarm state; home it ($H) "
                                "or set params.unlock_on_alarm: true")
            self.conn.command("$X")
        self.conn.command("G21 G90 G54")  # units as configured, absolute moves, G54 offsets
        self.conn.refresh_offsets()

    def close(self) -> None:
        if self.conn is not None:
            self.conn.release()
            self.conn = None

    def _link(self) -> GrblConnection:
        if self.conn is None:
            self.open()
        return self.conn

    def home(self) -> None:
        conn = self._link()
        p = self.params
        try:
            if p.homing == "cycle":
                conn.command("$H", timeout_s=p.timeout_s)
                conn.command("G21 G90 G54")
            if p.homing in ("cycle", "zero"):
                conn.command(f"G10 L20 P1 {p.axis}0")  # here is 0 in work coordinates
            conn.refresh_offsets()
        except GrblError as exc:
            self._lost(exc, "homing")

    def move_to(self, deg: float) -> float:
        """Move to ``deg``; return the position read back (``approach_deg``: see PhidgetAxis)."""
        p = self.params
        if p.approach_deg > 0:
            here = self.position()
            if here is not None and deg < here - 1e-9:
                self._go(deg - p.approach_deg)
        return self._go(deg)

    def _go(self, deg: float) -> float:
        conn = self._link()
        p = self.params
        target = deg * p.units_per_degree
        try:
            conn.command(f"G1 {p.axis}{target:.4f} F{p.feed_rate:g}")
            deadline = time.monotonic() + p.timeout_s
            while True:
                state, pos = conn.status()
                if state == "Idle" and abs(pos.get(p.axis, float("nan")) - target) <= (
                        p.position_tolerance_deg * p.units_per_degree):
                    return pos[p.axis] / p.units_per_degree
                if state.startswith("Alarm"):
                    raise GrblError(f"{self.label}: controller went to Alarm during the move")
                if state == "Idle" and not _is_number(pos.get(p.axis)):
                    raise GrblError(f"{self.label}: status reports no {p.axis} position")
                if time.monotonic() > deadline:
                    raise GrblError(f"{self.label}: move to {deg:g} deg not finished after "
                                    f"{p.timeout_s:g} s (state {state}, at "
                                    f"{pos.get(p.axis, float('nan')) / p.units_per_degree:g} "
                                    "deg)")
                time.sleep(p.poll_interval_s)
        except GrblError as exc:
            self._lost(exc, f"the move to {deg:g} deg")

    def _lost(self, exc: GrblError, during: str):
        if "serial link lost" in str(exc) and self.conn is not None:
            self.conn.drop()
            self.conn = None
            raise GrblError(f"{self.label}: serial link lost during {during}; the axis position "
                            "is unknown (it is homed again on --resume). Check the USB cable, "
                            f"power and that nothing else opened the port. ({exc})") from exc
        raise exc

    def position(self) -> float | None:
        _, pos = self._link().status()
        v = pos.get(self.params.axis)
        return None if v is None else v / self.params.units_per_degree

    def stop(self) -> None:
        """Feed hold, then soft reset: motion stops at once (GRBL then needs re-homing)."""
        if self.conn is not None:
            self.conn.realtime(b"!")
            time.sleep(0.05)
            self.conn.realtime(b"\x18")


def _is_number(v) -> bool:
    return isinstance(v, float) and v == v


# --------------------------------------------------------------------------- CLI
GRBL_SETTINGS = {
    20: "soft limits", 21: "hard limits", 22: "homing cycle", 100: "X steps/unit",
    101: "Y steps/unit", 102: "Z steps/unit", 110: "X max rate (units/min)",
    111: "Y max rate (units/min)", 112: "Z max rate (units/min)",
    120: "X acceleration (units/s^2)", 121: "Y acceleration (units/s^2)",
    122: "Z acceleration (units/s^2)", 130: "X max travel", 131: "Y max travel",
    132: "Z max travel",
}


def print_status(port: str, baudrate: int = 115200, out=None) -> int:
    """Print a GRBL controller's state, work position and settings (``plantscan grbl-status``).

    The figures to put in a recipe: ``units_per_degree`` follows from ``$100``...,
    ``feed_rate`` must stay under ``$110``..., ``acceleration_deg_s2`` is ``$120``...
    divided by ``units_per_degree``.
    """
    import sys

    out = out or sys.stdout
    conn = GrblConnection(port, baudrate, 5.0)
    try:
        conn.command("G54")
        conn.refresh_offsets()
        state, pos = conn.status()
        print(f"{port}: {state}; work position "
              + ", ".join(f"{k} {v:g}" for k, v in pos.items()), file=out)
        for line in conn.command("$$"):
            m = re.match(r"\$(\d+)=(\S+)", line)
            if m:
                meaning = GRBL_SETTINGS.get(int(m.group(1)), "")
                print(f"  ${m.group(1)} = {m.group(2)}" + (f"  ({meaning})" if meaning else ""),
                      file=out)
    finally:
        conn.ser.close()
    return 0

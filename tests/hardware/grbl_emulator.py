"""A small GRBL 1.1 emulator for tests, served over TCP (pyserial ``socket://``) or a pty.

It implements what the ``grbl`` axis uses, with GRBL's answers: the banner,
``?`` status reports (``<Idle|MPos:..|FS:..|WCO:..>``), ``!``/``~``/``0x18``
real-time commands, ``$X``, ``$H`` (when homing is enabled), ``$#``, ``G21``,
``G90``, ``G10 L20 P1``, ``G0``/``G1`` absolute moves that take time at the
feed rate, ``error:N`` for what it does not understand and ``ALARM:N`` for
soft-limit and reset-in-motion.  Faults: ``disconnect_on_move=N`` drops the
link while the N-th move runs.
"""

from __future__ import annotations

import os
import re
import socket
import threading
import time

LETTERS = "XYZ"
_WORD = re.compile(r"([A-Z])\s*([-+]?\d*\.?\d+)")


class GrblMachine:
    """Controller state (survives reconnections, like a powered controller)."""

    def __init__(self, *, homing_enabled=False, start_in_alarm=False, travel=(-1e6, 1e6),
                 speedup=20.0, disconnect_on_move: int | None = None):
        self.mpos = dict.fromkeys(LETTERS, 0.0)
        self.wco = dict.fromkeys(LETTERS, 0.0)
        self.target = dict(self.mpos)
        self.start = dict(self.mpos)
        self.t0 = 0.0
        self.duration = 0.0
        self.alarm = start_in_alarm
        self.homing_enabled = homing_enabled
        self.travel = travel
        self.speedup = speedup
        self.hold = False
        self.moves = 0
        self.disconnect_on_move = disconnect_on_move
        self.lines: list[str] = []
        self.lock = threading.Lock()
        self.wco_counter = 3  # the first reports after a (re)connection carry no WCO

    # motion ------------------------------------------------------------------------
    def _update(self) -> None:
        if self.duration <= 0:
            return
        f = min(1.0, (time.monotonic() - self.t0) / self.duration)
        for k in LETTERS:
            self.mpos[k] = self.start[k] + f * (self.target[k] - self.start[k])
        if f >= 1.0:
            self.duration = 0.0

    def moving(self) -> bool:
        self._update()
        return self.duration > 0

    def state(self) -> str:
        if self.alarm:
            return "Alarm"
        if self.hold:
            return "Hold:0"
        return "Run" if self.moving() else "Idle"

    def status(self) -> str:
        # Like GRBL 1.1: WCO only in every 10th report, or in the first one after it changed.
        self._update()
        st = self.state()
        m = ",".join(f"{self.mpos[k]:.3f}" for k in LETTERS)
        report = f"<{st}|MPos:{m}|FS:0,0"
        if self.wco_counter <= 0:
            report += "|WCO:" + ",".join(f"{self.wco[k]:.3f}" for k in LETTERS)
            self.wco_counter = 10
        self.wco_counter -= 1
        return report + ">"

    def start_move(self, target: dict[str, float], feed_per_min: float) -> None:
        self._update()
        self.start = dict(self.mpos)
        self.target = target
        dist = max(abs(target[k] - self.mpos[k]) for k in LETTERS)
        self.duration = dist / (feed_per_min / 60.0) / self.speedup
        self.t0 = time.monotonic()

    # one line of G-code or $ command -> answer lines -----------------------------------
    def line(self, text: str) -> list[str]:
        text = text.strip().upper().replace(" ", "")
        self.lines.append(text)
        if not text:
            return ["ok"]
        if text == "$X":
            self.alarm = False
            return ["[MSG:Caution: Unlocked]", "ok"]
        if text == "$H":
            if not self.homing_enabled:
                return ["error:5"]
            self.alarm = False
            self.start_move(dict.fromkeys(LETTERS, 0.0), 6000.0)
            while self.moving():
                time.sleep(0.005)
            self.wco = dict.fromkeys(LETTERS, 0.0)
            return ["ok"]
        if text == "$#":
            g54 = ",".join(f"{self.wco[k]:.3f}" for k in LETTERS)
            return [f"[G54:{g54}]", "[G55:0.000,0.000,0.000]", "[G28:0.000,0.000,0.000]",
                    "[G30:0.000,0.000,0.000]", "[G92:0.000,0.000,0.000]", "[TLO:0.000]",
                    "[PRB:0.000,0.000,0.000:0]", "ok"]
        if text == "$$":
            return ["$20=0", "$22=" + str(int(self.homing_enabled)), "$100=884.510",
                    "$110=1800.000", "$120=30.000", "ok"]
        if text.startswith("$"):
            return ["error:3"]
        if self.alarm:
            return ["error:9"]
        words = _WORD.findall(text)
        if not words or any(w[0] not in "GXYZFLPN" for w in words):
            return ["error:20"]
        gs = [float(v) for k, v in words if k == "G"]
        axes = {k: float(v) for k, v in words if k in LETTERS}
        if 10 in gs:  # G10 L20 P1 X0: here becomes X0 in work coordinates
            self._update()
            for k, v in axes.items():
                self.wco[k] = self.mpos[k] - v
            self.wco_counter = 0  # reported in the next status
            return ["ok"]
        if any(g in (0, 1) for g in gs) or (axes and not gs):
            feed = next((float(v) for k, v in words if k == "F"), 1800.0)
            target = dict(self.target if self.moving() else self.mpos)
            for k, v in axes.items():
                target[k] = v + self.wco[k]
                if not self.travel[0] <= target[k] <= self.travel[1]:
                    self.alarm = True
                    return ["ALARM:2"]
            self.moves += 1
            self.start_move(target, feed)
            return ["ok"]
        if all(g in (21, 90, 91, 17, 54) for g in gs):
            return ["ok"]
        return ["error:20"]

    def realtime(self, byte: int) -> list[str]:
        if byte == ord("?"):
            return [self.status()]
        if byte == ord("!"):
            self._update()
            self.hold = True
            self.target = dict(self.mpos)
            self.duration = 0.0
            return []
        if byte == ord("~"):
            self.hold = False
            return []
        if byte == 0x18:
            was_moving = self.moving() or self.hold
            self.duration = 0.0
            self.hold = False
            out = []
            if was_moving:
                self.alarm = True
                out.append("ALARM:3")
            return [*out, "", "Grbl 1.1h ['$' for help]"]
        return []


def serve(machine: GrblMachine, read, write, close, stop: threading.Event) -> None:
    """Run one client session over byte-level ``read()``/``write(b)`` callables."""
    write(b"\r\nGrbl 1.1h ['$' for help]\r\n")
    buf = b""
    disconnect_at = None
    while not stop.is_set():
        if disconnect_at is not None and time.monotonic() >= disconnect_at:
            close()
            return
        data = read()
        if data is None:  # link closed by the client
            return
        for b in data:
            with machine.lock:
                if b in (ord("?"), ord("!"), ord("~"), 0x18):
                    out = machine.realtime(b)
                elif b in (10, 13):
                    line, buf = buf.decode("ascii", "replace"), b""
                    out = machine.line(line)  # GRBL answers 'ok' to an empty line too
                    if (machine.disconnect_on_move is not None
                            and machine.moves == machine.disconnect_on_move
                            and disconnect_at is None and machine.moving()):
                        disconnect_at = time.monotonic() + 0.02  # mid-move
                else:
                    buf += bytes([b])
                    out = []
            if out:
                write(("\r\n".join(out) + "\r\n").encode())


class TcpGrbl:
    """The emulator on ``127.0.0.1:port``; clients connect with ``socket://127.0.0.1:port``."""

    def __init__(self, machine: GrblMachine | None = None):
        self.machine = machine or GrblMachine()
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def _accept(self) -> None:
        self.sock.settimeout(0.1)
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, OSError):
                continue
            threading.Thread(target=self._session, args=(conn,), daemon=True).start()

    def _session(self, conn: socket.socket) -> None:
        conn.settimeout(0.02)

        def read():
            try:
                data = conn.recv(256)
            except TimeoutError:
                return b""
            except OSError:
                return None
            return data if data else None

        def write(b):
            try:
                conn.sendall(b)
            except OSError:
                pass

        def close():
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()

        try:
            serve(self.machine, read, write, close, self.stop)
        finally:
            try:
                conn.close()
            except OSError:
                pass

    def close(self) -> None:
        self.stop.set()
        self.sock.close()
        self.thread.join(timeout=2)


class PtyGrbl:
    """The emulator behind a pseudo-terminal made with ``os.openpty`` (no socat needed)."""

    def __init__(self, machine: GrblMachine | None = None):
        import tty

        self.machine = machine or GrblMachine()
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import select

        def read():
            r, _, _ = select.select([self.master], [], [], 0.02)
            if not r:
                return b""
            try:
                return os.read(self.master, 256)
            except OSError:
                return None

        def write(b):
            try:
                os.write(self.master, b)
            except OSError:
                pass

        def close():
            try:
                os.close(self.master)
            except OSError:
                pass

        serve(self.machine, read, write, close, self.stop)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

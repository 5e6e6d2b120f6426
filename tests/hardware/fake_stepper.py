"""A simulated Phidget stepper at our adapter interface (``StepperPort``).

Like the device: positions are whole microsteps (reported times the rescale
factor), moves follow a trapezoidal profile in (scaled) real time, the
stopped event arrives from another thread, and it can detach mid-move.
"""

from __future__ import annotations

import threading
import time

from plantscan_phidget.stepper import PhidgetAxisError, move_time_s


class FakeStepperPort:
    instances: list[FakeStepperPort] = []

    def __init__(self, speedup: float = 50.0, detach_on_move: int | None = None,
                 attached: bool = True):
        self.speedup = speedup
        self.detach_on_move = detach_on_move
        self.attached = attached
        self.config: dict = {}
        self.engaged = False
        self.microsteps = 0  # device position counter
        self.offset = 0.0
        self.moves = 0
        self.halted = False
        self._move = None  # (start, target, t0, duration)
        self._stopped_cb = None
        self._detach_cb = None
        self.lock = threading.Lock()
        FakeStepperPort.instances.append(self)

    def open(self, params) -> None:
        if not self.attached:
            raise PhidgetAxisError("no Phidget stepper attached (simulated)")

    def configure(self, rescale, velocity, acceleration, current, holding) -> None:
        self.config = dict(rescale=rescale, velocity=velocity, acceleration=acceleration,
                           current=current, holding=holding)

    def set_engaged(self, on: bool) -> None:
        self.engaged = on

    def _update(self) -> None:
        if self._move is None:
            return
        start, target, t0, duration = self._move
        f = 1.0 if duration <= 0 else min(1.0, (time.monotonic() - t0) / duration)
        self.microsteps = round(start + f * (target - start))
        if f >= 1.0:
            self._move = None
            if self._stopped_cb is not None:
                threading.Thread(target=self._stopped_cb).start()  # phidget22's event thread

    def set_target(self, position: float) -> None:
        assert self.engaged, "moving a disengaged motor"
        with self.lock:
            self._update()
            self.moves += 1
            rescale = self.config["rescale"]
            target = round((position + self.offset) / rescale)
            dist_deg = (target - self.microsteps) * rescale
            duration = move_time_s(dist_deg, self.config["velocity"],
                                   self.config["acceleration"]) / self.speedup
            self._move = (self.microsteps, target, time.monotonic(), duration)
        if self.detach_on_move == self.moves:
            threading.Timer(duration / 2, self._detach).start()
        threading.Timer(duration + 0.001, self._tick).start()

    def _tick(self) -> None:
        with self.lock:
            if self.attached:
                self._update()

    def _detach(self) -> None:
        with self.lock:
            self.attached = False
            self._move = None
        if self._detach_cb is not None:
            self._detach_cb()

    def position(self) -> float:
        with self.lock:
            self._update()
            return self.microsteps * self.config["rescale"] - self.offset

    def is_moving(self) -> bool:
        with self.lock:
            self._update()
            return self._move is not None

    def zero_here(self) -> None:
        with self.lock:
            self.offset = self.microsteps * self.config["rescale"]

    def on_stopped(self, callback) -> None:
        self._stopped_cb = callback

    def on_detach(self, callback) -> None:
        self._detach_cb = callback

    def halt(self) -> None:
        with self.lock:
            self._update()
            self._move = None
            self.halted = True

    def close(self) -> None:
        self.engaged = False

"""One progress display for every long step, warnings through ``logging``, and ``run.log``.

``Display`` is what the user sees while a command works:

* in a terminal (``rich``): one live line per step with a spinner, a bar and a
  count when the step knows how many items it has, the elapsed time and an
  estimate of the time left (from the rate so far, or the timing model's
  estimate before the first item); log messages print above it;
* without one (a pipe, a log file, a Dask worker, CI): plain lines on stderr,
  one when a step starts and one when it ends, and while it runs a line at
  least every ``HEARTBEAT_S`` seconds (count, elapsed, time left), so no step
  is silent for more than 10 s;
* ``quiet``: only warnings and errors; ``off``: nothing (the caller reports).

``run_logging`` routes every ``logging`` record of a run to ``run.log`` in the
run folder (all of them, INFO and up, each stage's warnings in full) and to
the display (WARNING and up; INFO too with ``-v``).  A warning a stage also
puts in its ``StageReport`` is not printed one by one: after the stage, the
display gets one summary line per stage (``measure: 7 warnings (leaves 5, 6,
9, 10, 11, 16, 17)``) and, with ``-v``, each warning once.  A stage read from
the cache says its warnings again only with ``-v`` (they are in ``run.json``
and the report).  One run at a time per process: the handlers are the
process's (a batch runs one plant per worker process).
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

Mode = Literal["auto", "rich", "plain", "quiet", "off"]
HEARTBEAT_S = 5.0  # plain mode: a line at least this often while a step runs; at 8 s the
# longest silence measured on the shared machine (load 21, no terminal) was 9.7 s: 10 s is the bar
RUN_LOG = "run.log"
LOG = logging.getLogger("plantscan")


def _clock(seconds: float) -> str:
    if seconds < 0.5:
        return "<1 s"
    seconds = int(round(seconds))
    return f"{seconds // 60}:{seconds % 60:02d}" if seconds >= 60 else f"{seconds} s"


@dataclass
class StepProgress:
    """A running step: advance it as items finish; its line shows count, elapsed, time left."""

    name: str
    total: int | None = None
    unit: str = ""
    estimate_s: float | None = None
    done: int = 0
    note: str = ""  # said on the step's "done" line (e.g. "cached, 7 warnings")
    started: float = field(default_factory=lambda: time.monotonic())
    _display: Display | None = None
    _task: Any = None

    def count(self, total: int, unit: str = "") -> None:
        """The step has ``total`` items (``unit``: what they are), none done yet."""
        self.total, self.unit, self.done = int(total), unit or self.unit, 0
        if self._display is not None:
            self._display._advanced(self)

    def advance(self, n: int = 1) -> None:
        self.done += n
        if self._display is not None:
            self._display._advanced(self)

    def left_s(self) -> float | None:
        """Seconds left: from the rate so far, else from the estimate while it lasts; None
        when unknown (nothing done yet and the estimate already spent)."""
        elapsed = time.monotonic() - self.started
        if self.total and self.done:
            return elapsed / self.done * (self.total - self.done)
        if self.estimate_s is not None and elapsed < self.estimate_s:
            return self.estimate_s - elapsed
        return None

    def status(self) -> str:
        parts = []
        if self.total:
            parts.append(f"{self.done}/{self.total}{f' {self.unit}' if self.unit else ''}")
        elapsed = time.monotonic() - self.started
        parts.append(_clock(elapsed))
        left = self.left_s()
        if not self.total or self.done < self.total:
            if left is not None:
                parts.append(f"~{_clock(left)} left")
            elif self.estimate_s:  # a busy machine: say it is over, not "<1 s left"
                parts.append(f"over the estimate of {_clock(self.estimate_s)}")
        return ", ".join(parts)


class Display:
    """The progress display of one command (see the module docstring).

    Parameters
    ----------
    mode : "auto", "rich", "plain", "quiet" or "off"
        "auto": rich when ``stream`` is a terminal, else plain.
    verbose : int
        0 default; 1 (``-v``) also shows INFO messages and every warning.
    stream : file, default sys.stderr
    """

    def __init__(self, mode: Mode = "auto", verbose: int = 0, stream: IO[str] | None = None):
        self.stream = stream if stream is not None else sys.stderr
        if mode == "auto":
            mode = "rich" if getattr(self.stream, "isatty", lambda: False)() else "plain"
        self.mode = mode
        self.verbose = verbose
        self._lock = threading.RLock()
        self._steps: list[StepProgress] = []
        self._rich = None
        self._beat: threading.Thread | None = None
        self._stop = threading.Event()
        self._last_line = time.monotonic()

    # ------------------------------------------------------------------ messages
    def message(self, text: str, level: int = logging.INFO) -> None:
        """A line for the user (above the live steps in a terminal)."""
        if self.mode == "off" or (self.mode == "quiet" and level < logging.WARNING):
            return
        with self._lock:
            if self._rich is not None:
                from rich.markup import escape

                self._rich.console.print(escape(text), highlight=False)
            else:
                print(text, file=self.stream, flush=True)
            self._last_line = time.monotonic()

    @property
    def shows_progress(self) -> bool:
        return self.mode in ("rich", "plain")

    # ------------------------------------------------------------------ steps
    @contextlib.contextmanager
    def step(self, name: str, total: int | None = None, unit: str = "",
             estimate_s: float | None = None) -> Iterator[StepProgress]:
        """Show ``name`` while the block runs; the block advances the returned step (and may
        set its ``note`` for the "done" line)."""
        sp = StepProgress(name, total, unit, estimate_s, _display=self)
        self._start(sp)
        failed = True
        try:
            yield sp
            failed = False
        finally:
            self._finish(sp, failed)

    def _start(self, sp: StepProgress) -> None:
        with self._lock:
            self._steps.append(sp)
            if self.mode == "rich":
                self._ensure_rich()
                sp._task = self._rich.add_task(sp.name, total=sp.total, status=sp.status())
            elif self.mode == "plain":
                extra = f" ({sp.total} {sp.unit})" if sp.total else ""
                est = f", estimated {_clock(sp.estimate_s)}" if sp.estimate_s else ""
                self._plain(f"{sp.name}: started{extra}{est}")
                self._ensure_heartbeat()

    def _finish(self, sp: StepProgress, failed: bool) -> None:
        with self._lock:
            if sp in self._steps:
                self._steps.remove(sp)
            note = sp.note
            took = _clock(time.monotonic() - sp.started)
            if self.mode == "rich" and self._rich is not None:
                self._rich.remove_task(sp._task)
                if not failed:
                    self._rich.console.print(
                        f"[green]✓[/] {sp.name} [dim]{took}{'; ' + note if note else ''}[/]",
                        highlight=False)
                if not self._steps:
                    self._rich.stop()
                    self._rich = None
            elif self.mode == "plain":
                self._plain(f"{sp.name}: {'failed' if failed else 'done'} in {took}"
                            f"{'; ' + note if note and not failed else ''}")

    def _advanced(self, sp: StepProgress) -> None:
        with self._lock:
            if self.mode == "rich" and self._rich is not None and sp._task is not None:
                self._rich.update(sp._task, completed=sp.done, total=sp.total,
                                  status=sp.status())

    def _plain(self, text: str) -> None:
        print(text, file=self.stream, flush=True)
        self._last_line = time.monotonic()

    def _ensure_rich(self) -> None:
        if self._rich is not None:
            return
        from rich.console import Console
        from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn

        self._rich = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                              TextColumn("{task.fields[status]}"),
                              console=Console(file=self.stream), transient=True,
                              refresh_per_second=5)
        self._rich.start()
        self._ensure_heartbeat()  # refreshes the status text (elapsed, time left)

    def _ensure_heartbeat(self) -> None:
        if self._beat is not None and self._beat.is_alive():
            return
        self._stop.clear()
        self._beat = threading.Thread(target=self._heartbeat, name="plantscan-progress",
                                      daemon=True)
        self._beat.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(1.0):
            self.beat()

    def beat(self) -> None:
        """Refresh the running steps' status (rich); in plain mode, a status line when the
        last line is ``HEARTBEAT_S`` old.  The display's thread calls it every second."""
        with self._lock:
            if not self._steps:
                return
            if self.mode == "rich" and self._rich is not None:
                for sp in self._steps:
                    if sp._task is not None:
                        self._rich.update(sp._task, status=sp.status())
            elif self.mode == "plain" and time.monotonic() - self._last_line >= HEARTBEAT_S:
                sp = self._steps[-1]
                self._plain(f"{sp.name}: {sp.status()}")

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            if self._rich is not None:
                self._rich.stop()
                self._rich = None


def display_for(progress: bool | Display | None) -> Display:
    """The display a library call was given: a ``Display``, or True (auto) / False (quiet)."""
    if isinstance(progress, Display):
        return progress
    return Display("auto" if progress else "quiet")


# --------------------------------------------------------------------------- logging
class _ToDisplay(logging.Handler):
    """Log records to the display; while a stage runs, its warnings wait for its summary."""

    def __init__(self, display: Display) -> None:
        super().__init__(logging.INFO)
        self.display = display
        self.held: list[logging.LogRecord] | None = None  # a stage is running
        self.shown: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        if self.held is not None and record.levelno >= logging.WARNING:
            self.held.append(record)
            return
        if record.levelno < logging.WARNING and self.display.verbose < 1:
            return
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            if text in self.shown:
                return  # the same warning once per run
            self.shown.add(text)
        self.display.message(text, record.levelno)


class RunLog:
    """The logging of one run: ``run.log`` and the display (see ``run_logging``)."""

    def __init__(self, display: Display, to_display: _ToDisplay,
                 file_handler: logging.Handler | None) -> None:
        self.display = display
        self._to_display = to_display
        self._file = file_handler
        self._held: list[logging.LogRecord] = []
        self._running = 0  # stages running (two may overlap: calibrate beside segment)
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def stage(self) -> Iterator[None]:
        """Hold the warnings plugins log while a stage runs, for ``summarise``.

        Stages may overlap (``plantscan_core.pipeline``): the records are held while
        any stage runs, and each ``summarise`` takes those its own report names.
        """
        with self._lock:
            if self._running == 0:
                self._to_display.held = []
            self._running += 1
        try:
            yield
        finally:
            with self._lock:
                self._running -= 1
                self._held += self._to_display.held or []
                self._to_display.held = [] if self._running else None

    def _to_file(self, level: int, name: str, text: str) -> None:
        if self._file is not None:
            self._file.handle(logging.LogRecord(name, level, __file__, 0, text, None, None))

    def summarise(self, section: str, title: str, warnings: list[Any], cached: bool) -> str:
        """After a stage: its report's warnings to run.log and one line to the display.

        ``warnings`` are the ``StageWarning``s of the stage's report (``message``,
        ``leaf``).  A warning a plugin logged that is not in its report is shown
        as it is.  Returns a note for the step's "done" line.
        """
        said = {w.message for w in warnings}
        with self._lock:  # this stage's records; the others wait for a stage still running
            held = [r for r in self._held if r.getMessage() in said]
            others = [r for r in self._held if r.getMessage() not in said]
            self._held, others = (others, []) if self._running else ([], others)
        logged = {r.getMessage() for r in held}
        if not cached:
            for w in warnings:  # in full in run.log, once (the plugin may have logged it)
                if w.message not in logged:
                    self._to_file(logging.WARNING, f"plantscan.{section}", w.message)
        for record in others:
            self._to_display.emit(record)
        if not warnings:
            return "cached" if cached else ""
        leaves = sorted({w.leaf for w in warnings if getattr(w, "leaf", None) is not None})
        named = (f" ({'leaf' if len(leaves) == 1 else 'leaves'} {', '.join(map(str, leaves))})"
                 if leaves else "")
        count = f"{len(warnings)} warning{'s' if len(warnings) > 1 else ''}"
        if self.display.verbose >= 1:
            for w in warnings:
                self.display.message(f"{title}: {w.message}", logging.WARNING)
        elif not cached:
            line = f"{title}: {count}{named}"
            self.display.message(f"{line} (-v lists them; so do run.log and the report)",
                                 logging.WARNING)
            self._to_file(logging.INFO, "plantscan.summary", line)
        return f"cached, {count}" if cached else count


@contextlib.contextmanager
def run_logging(folder: Path | None, display: Display) -> Iterator[RunLog]:
    """Route the run's log records to ``folder/run.log`` and to ``display`` (module docstring).

    ``run.log`` is appended to (a re-run adds its lines; a command's error
    traceback goes there too).  Python's own last-resort printing of warnings
    is replaced while the run lasts: nothing reaches stderr but through the
    display.
    """
    root = logging.getLogger()
    to_display = _ToDisplay(display)
    file_handler = None
    if folder is not None:
        Path(folder).mkdir(parents=True, exist_ok=True)
        file_handler = logging.FileHandler(Path(folder) / RUN_LOG, encoding="utf-8")
        file_handler.setLevel(logging.INFO)
        file_handler.setFormatter(logging.Formatter(
            "%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%Y-%m-%dT%H:%M:%S"))
    old_level = root.level
    root.setLevel(min(old_level or logging.WARNING, logging.INFO))
    # third-party chatter at INFO (numba, distributed) stays out of run.log
    quiet = [logging.getLogger(n) for n in ("numba", "distributed", "matplotlib", "PIL")]
    old_quiet = [q.level for q in quiet]
    for q in quiet:
        if q.level == logging.NOTSET:
            q.setLevel(logging.WARNING)
    root.addHandler(to_display)
    if file_handler is not None:
        root.addHandler(file_handler)
    try:
        yield RunLog(display, to_display, file_handler)
    finally:
        root.removeHandler(to_display)
        if file_handler is not None:
            root.removeHandler(file_handler)
            file_handler.close()
        root.setLevel(old_level)
        for q, lvl in zip(quiet, old_quiet):
            q.setLevel(lvl)

"""One writer per scan folder and per run folder.

Two ``plantscan process`` runs into one ``--out`` both finished with status 0,
the last silently overwriting the other's results; two ``plantscan scan``
into one folder would interleave their manifests.  ``FolderLock`` takes an
exclusive ``fcntl.flock`` on ``FOLDER/.plantscan.lock`` for as long as the
command writes there; a second writer is refused with the holder named.

The kernel drops a ``flock`` when its process dies, even by ``kill -9``, so a
lock can never block forever.  The file keeps the holder's pid, host, start
time and command: the next writer that finds a record whose process is gone
says so (``stale``: the previous writer was killed and its results may be
incomplete; the run's cache re-checks every stage anyway).
"""

from __future__ import annotations

import datetime
import errno
import fcntl
import functools
import inspect
import json
import os
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from plantscan_core.errors import PlantScanError

LOCK_FILE = ".plantscan.lock"


class FolderBusyError(PlantScanError):
    """Another plantscan process is writing the folder."""


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux), to tell pid reuse."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _alive(record: dict[str, Any]) -> bool:
    """Whether the process of a lock record still runs (same host, same pid and start)."""
    pid = record.get("pid")
    if not isinstance(pid, int) or record.get("host") != socket.gethostname():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    start = record.get("start")
    return start is None or _process_start(pid) in (None, start)


class FolderLock:
    """An exclusive lock on a folder for one writer; a context manager.

    Parameters
    ----------
    folder : Path, created when missing.
    what : str, what the folder is, for messages ("run folder", "scan folder").
    error : the error class raised when the folder cannot be created or locked.

    Attributes
    ----------
    stale : dict or None
        After ``acquire``: the record of an earlier writer that ended without
        releasing the lock (killed), else None.
    """

    def __init__(self, folder: Path, what: str = "folder",
                 error: type[PlantScanError] = PlantScanError) -> None:
        self.error = error  # raised when the folder cannot be created or locked
        self.folder = Path(folder)
        self.what = what
        self.path = self.folder / LOCK_FILE
        self.stale: dict[str, Any] | None = None
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise self.error(f"{self.folder}: cannot write the {self.what} "
                                 f"({exc.strerror})") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _read_record(fd)
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise self.error(f"{self.path}: cannot lock the {self.what} "
                                     f"({exc.strerror})") from exc
            raise FolderBusyError(
                f"{self.folder}: another plantscan is writing this {self.what} "
                f"({_describe(holder)}); wait for it to finish, or choose another "
                "folder") from None
        previous = _read_record(fd)
        if previous and not _alive(previous):
            self.stale = previous
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "start": _process_start(os.getpid()),
                  "since": datetime.datetime.now().isoformat(timespec="seconds"),
                  "command": " ".join(["plantscan", *sys.argv[1:]])[:500]}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(record).encode(), 0)
        except OSError:
            pass  # the flock is the lock; the record only helps messages
        self._fd = fd
        return self

    def release(self) -> None:
        """Unlock and clear the record (a clean end leaves no stale record)."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, 0)
        except OSError:
            pass
        finally:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def stale_message(self) -> str | None:
        """A warning about a previous writer that was killed, or None."""
        if self.stale is None:
            return None
        return (f"{self.folder}: the previous writer ({_describe(self.stale)}) ended without "
                "finishing (killed?); its lock was stale and is taken over")

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_record(fd: int) -> dict[str, Any]:
    try:
        data = os.pread(fd, 4096, 0)
        record = json.loads(data.decode("utf-8")) if data.strip() else {}
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _describe(record: dict[str, Any]) -> str:
    if not record:
        return "a process that left no record"
    return (f"pid {record.get('pid')} on {record.get('host')} since {record.get('since')}: "
            f"{record.get('command')}")


F = TypeVar("F", bound=Callable[..., Any])


def one_writer(folder_argument: str, what: str) -> Callable[[F], F]:
    """Decorate a function that writes the folder given as ``folder_argument``: it runs
    holding that folder's ``FolderLock`` (a stale record is reported on stderr)."""

    def decorate(fn: F) -> F:
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args: Any, **kwargs: Any) -> Any:
            folder = signature.bind(*args, **kwargs).arguments[folder_argument]
            with FolderLock(Path(folder), what) as lock:
                if lock.stale_message():
                    print(f"plantscan: warning: {lock.stale_message()}", file=sys.stderr)
                return fn(*args, **kwargs)

        return locked  # type: ignore[return-value]

    return decorate

"""A small thread pool for stage work that releases the GIL (OpenCV, numpy, scipy, decoding)."""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

MAX_THREADS = 4
"""Threads per pool at most: the project machine has 2 cores, a lab PC rarely needs more."""


def thread_map(fn: Callable[..., Any], *iterables: Iterable[Any]) -> list[Any]:
    """``list(map(fn, *iterables))`` on one thread per core (at most ``MAX_THREADS``).

    Results keep the items' order; an exception in one item is raised here.
    One item or one core: a plain ``map`` in the calling thread, no pool.
    """
    items = list(zip(*iterables))
    workers = max(1, min(MAX_THREADS, os.cpu_count() or 1, len(items)))
    if workers == 1:
        return [fn(*args) for args in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda args: fn(*args), items))


_cv_lock = threading.Lock()
_cv_users = 0
_cv_before = 0


@contextlib.contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """OpenCV's own thread pool at ``n`` threads for the block (restored after).

    Our pools already run one image per core: OpenCV splitting each call over
    its own threads as well only adds waiting. On the 18 MP paper-360 scan (4.5
    MP masks) ``lab-shadow`` cost 96 ms CPU per view with OpenCV's two threads
    under a 2-thread pool, 73 ms with one (docs/benchmarks/end_to_end.md), the
    same masks and traits (its per-pixel loops split rows; a call that sums in
    parallel, like ``calibrateCamera``, is reproducible only at one thread).

    OpenCV's setting is global and two steps may run at once (calibrate beside
    segment, ``plantscan_core.pipeline``): the setting before the first block is
    restored when the last block still running ends, never while another runs.
    """
    import cv2

    global _cv_users, _cv_before
    with _cv_lock:
        if _cv_users == 0:
            _cv_before = cv2.getNumThreads()
        _cv_users += 1
        cv2.setNumThreads(n)
    try:
        yield
    finally:
        with _cv_lock:
            _cv_users -= 1
            if _cv_users == 0:
                cv2.setNumThreads(_cv_before)


@contextlib.contextmanager
def image_pool(workers: int) -> Iterator[ThreadPoolExecutor]:
    """A ``ThreadPoolExecutor`` of ``workers`` threads, one image each, OpenCV at one thread
    inside it while it runs (:func:`opencv_threads`; a single worker leaves OpenCV as is)."""
    with (opencv_threads(1) if workers > 1 else contextlib.nullcontext(),
          ThreadPoolExecutor(max_workers=workers) as pool):
        yield pool


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_heap_kept = False


def keep_heap_memory() -> bool:
    """Let glibc's malloc keep freed memory for the next array instead of giving it back.

    By default an array of more than 128 kB is mapped fresh and unmapped when freed (the
    limit then rises with what was freed, up to 32 MB): the leaf stages allocate and free
    arrays of tens of MB hundreds of times, and every fresh mapping is zeroed page by page
    by the kernel on first touch.  With the limit at 32 MB (the default's own maximum)
    from the start, 256 MB of headroom at the heap's top and no trimming below 1 GB, the
    same memory is reused: the leaf stages of a 2.7 M-face plant, the first in a process,
    9.4-10.5 -> 8.5-9.6 s (three runs each, alternating), peak memory +90 MB
    (docs/benchmarks/leaf_speed.md, session 26).  Once per process, for the rest of it;
    False where the C library has no ``mallopt`` (not glibc).
    """
    global _heap_kept
    if _heap_kept:
        return True
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _heap_kept = all(mallopt(param, value) == 1 for param, value in (
        (_M_MMAP_THRESHOLD, 32 << 20), (_M_TOP_PAD, 256 << 20), (_M_TRIM_THRESHOLD, 1 << 30)))
    return _heap_kept

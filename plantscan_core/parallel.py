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

"""A small thread pool for stage work that releases the GIL (OpenCV, numpy, scipy, decoding)."""

from __future__ import annotations

import contextlib
import os
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


@contextlib.contextmanager
def opencv_threads(n: int) -> Iterator[None]:
    """OpenCV's own thread pool at ``n`` threads for the block (restored after).

    Our pools already run one image per core: OpenCV splitting each call over
    its own threads as well only adds waiting. On the 18 MP paper-360 scan (4.5
    MP masks) ``lab-shadow`` cost 96 ms CPU per view with OpenCV's two threads
    under a 2-thread pool, 73 ms with one (docs/benchmarks/end_to_end.md), the
    same masks and traits (its per-pixel loops split rows; a call that sums in
    parallel, like ``calibrateCamera``, is reproducible only at one thread).
    """
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


@contextlib.contextmanager
def image_pool(workers: int) -> Iterator[ThreadPoolExecutor]:
    """A ``ThreadPoolExecutor`` of ``workers`` threads, one image each, OpenCV at one thread
    inside it while it runs (:func:`opencv_threads`; a single worker leaves OpenCV as is)."""
    with (opencv_threads(1) if workers > 1 else contextlib.nullcontext(),
          ThreadPoolExecutor(max_workers=workers) as pool):
        yield pool

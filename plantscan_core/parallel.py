"""A small thread pool for stage work that releases the GIL (OpenCV, numpy, scipy, decoding)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
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

"""`thread_map`: the stages' small thread pool."""

from __future__ import annotations

import platform
import sys
import threading

import pytest

from plantscan_core.parallel import thread_map


def test_results_keep_the_items_order_across_threads():
    def slow_square(i, j):
        return i * i + j

    assert thread_map(slow_square, range(50), range(50)) == [i * i + i for i in range(50)]


def test_one_item_runs_in_the_calling_thread_and_errors_reach_the_caller():
    assert thread_map(lambda _: threading.get_ident(), [0]) == [threading.get_ident()]
    with pytest.raises(ValueError, match="view 3"):
        thread_map(lambda i: (_ for _ in ()).throw(ValueError(f"view {i}")) if i == 3 else i,
                   range(6))


def test_opencv_threads_restored_only_when_the_last_overlapping_block_ends():
    """Two steps may hold OpenCV at one thread at once (calibrate beside segment): the first
    to end must not give OpenCV its threads back while the other still runs."""
    import cv2

    from plantscan_core.parallel import opencv_threads

    before = cv2.getNumThreads()
    first, second = opencv_threads(1), opencv_threads(1)
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)  # the blocks end out of order, as threads do
    assert cv2.getNumThreads() == 1
    second.__exit__(None, None, None)
    assert cv2.getNumThreads() == before


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                    reason="mallopt is glibc's")
def test_the_heap_keeps_freed_memory_on_glibc():
    # glibc takes every setting (mallopt returns 1 for each, 0 for one it refuses), once
    # per process
    from plantscan_core import parallel

    assert parallel.keep_heap_memory() is True
    assert parallel.keep_heap_memory() is True  # the second call changes nothing

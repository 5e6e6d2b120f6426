"""`thread_map`: the stages' small thread pool."""

from __future__ import annotations

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

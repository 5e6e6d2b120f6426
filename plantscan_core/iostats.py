"""Work counters (image decodes...), so tests can assert work done instead of times."""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path

_lock = threading.Lock()
decodes: Counter[str] = Counter()


def count_decode(path: Path) -> None:
    with _lock:
        decodes[str(Path(path).resolve())] += 1


def reset() -> None:
    with _lock:
        decodes.clear()

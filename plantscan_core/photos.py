"""The plant photos of a scan, decoded once per run at the run's reduction.

Segmentation reads every plant photo; a step that also needs the photos
(colour, photo-consistency) declares it in the stage table, and the photos
segmentation decoded are then kept for it instead of being decoded again.
Without such a step nothing is kept: 360 photos of 18 MP at 1/2 are 4.8 GB.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np

from plantscan_core.data import ViewRecord
from plantscan_core.errors import DataError
from plantscan_core.scanfolder import ScanFolder


class Photos:
    """The ``plant`` photos of ``scan`` at 1/``reduce`` of their size, with their plates.

    Parameters
    ----------
    scan : ScanFolder
    views : sequence of ViewRecord
        The plant views, in the order of ``image(i)``.
    reduce : int
        Decode at 1/``reduce`` (JPEG DCT scaling; ``ScanFolder.read_image``).
    keep : bool
        Keep every decoded photo for the rest of the run (a later step uses them).

    The background plate of a (camera, tilt) is decoded once and always kept
    (a scan has a few).  Thread-safe: segmentation decodes on a thread pool.
    """

    def __init__(self, scan: ScanFolder, views: Sequence[ViewRecord], reduce: int,
                 keep: bool = False) -> None:
        self.scan = scan
        self.views = list(views)
        self.reduce = int(reduce)
        self.keep = keep
        # The earliest plate of each (camera, tilt) is the one used (a re-shot plate is
        # appended to views.jsonl; the scan protocol writes one).
        self.plates: dict[tuple[str, int], ViewRecord] = {}
        for v in scan.views_by_role("background"):
            self.plates.setdefault((v.camera, v.tilt_index), v)
        self._kept: dict[int, np.ndarray] = {}
        self._plates: dict[tuple[str, int], np.ndarray | None] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.views)

    def image(self, i: int) -> np.ndarray:
        """Photo ``i``: ``(H, W, 3) uint8`` BGR at 1/``reduce``; ``DataError`` naming the file."""
        with self._lock:
            if i in self._kept:
                return self._kept[i]
        image = self.scan.read_image(self.views[i], reduce=self.reduce)
        if self.keep:
            with self._lock:
                self._kept.setdefault(i, image)
        return image

    def plate_view(self, view: ViewRecord) -> ViewRecord | None:
        """The background plate view of ``view``'s camera and tilt, or None."""
        return self.plates.get((view.camera, view.tilt_index))

    def background(self, view: ViewRecord) -> np.ndarray | None:
        """The background plate of ``view`` at 1/``reduce``, or None when the scan has none.

        ``DataError`` naming both files when the plate's size differs from the photo's.
        """
        key = (view.camera, view.tilt_index)
        if key not in self.plates:
            return None
        with self._lock:
            if key not in self._plates:
                self._plates[key] = self.scan.read_image(self.plates[key], reduce=self.reduce)
            return self._plates[key]

    def check_plate(self, view: ViewRecord, image: np.ndarray, plate: np.ndarray | None) -> None:
        """``DataError`` naming both files when ``plate`` is not the size of ``image``."""
        if plate is not None and plate.shape != image.shape:
            raise DataError(
                f"{self.scan.path_of(view)}: image is {image.shape[1]}x{image.shape[0]} but "
                f"its background plate {self.plates[(view.camera, view.tilt_index)].file} is "
                f"{plate.shape[1]}x{plate.shape[0]}")

    def release(self) -> None:
        """Forget the kept photos (the run ends, or no later step needs them)."""
        with self._lock:
            self._kept.clear()

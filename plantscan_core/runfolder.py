"""File formats of the run folder written by ``plantscan process``: masks and PLY meshes.

The layout of a run folder is in docs/formats.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plantscan_core.data import Mesh
from plantscan_core.errors import DataError
from plantscan_core.scanfolder import atomic_write_bytes

CACHE_DIR = "cache"
MASKS_DIR = "masks"


# --------------------------------------------------------------------------- masks
def write_mask(path: Path, mask: np.ndarray) -> None:
    """Store a bool mask as a 1-bit PNG (reads back as 0/255 gray), atomically.

    Bi-level PNG: 5x faster to encode than 8-bit (8 vs 41 ms at 4.5 MP,
    measured) and a third of the size; any PNG reader opens it.
    """
    import cv2

    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255,
                           [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise DataError(f"{path}: could not encode mask")
    atomic_write_bytes(path, buf.tobytes())


def read_mask(path: Path) -> np.ndarray:
    """Read a 0/255 (or 0/1) mask PNG as ``(H, W) bool``; ``DataError`` naming the file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DataError(f"{path}: mask missing or unreadable")
    return img > 0


# --------------------------------------------------------------------------- PLY
def write_ply(path: Path, mesh: Mesh) -> None:
    """Binary little-endian PLY of a mesh (float xyz, mm, turntable frame; int faces)."""
    v = mesh.vertices.astype("<f4")
    f = mesh.faces.astype("<i4")
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment plantscan mesh, units mm, turntable frame",
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(f)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    faces = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    faces["n"] = 3
    faces["idx"] = f
    data = ("\n".join(header) + "\n").encode() + v.tobytes() + faces.tobytes()
    atomic_write_bytes(Path(path), data)

"""Board detection: chessboard through an image pyramid (the seed's method) and ChArUco.

Pixel convention: ``(u, v)`` with the centre of the top-left pixel at
``(0, 0)``.  ``cv2.pyrDown`` puts output pixel ``i`` on input pixel ``2 i``,
so a corner at ``x`` one level up is at ``2 x`` one level down.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

BOARD_KINDS = ("chessboard", "charuco")


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board.

    Attributes
    ----------
    kind : {"chessboard", "charuco"}
    cols, rows : int
        Inner corners along the board's x (row direction) and y.  A ChArUco
        board of ``cols + 1`` x ``rows + 1`` squares has the same inner corners.
    square_mm : float, mm
    marker_mm : float, mm
        ChArUco marker side (ignored for a chessboard).
    dictionary : str
        ChArUco ArUco dictionary name (``DICT_5X5_100``...).
    """

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board kind {self.kind!r}; valid: {', '.join(BOARD_KINDS)}")
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"board needs at least 2x2 inner corners, got {self.cols}x{self.rows}")
        if self.kind == "chessboard" and self.cols == self.rows:
            # A square chessboard has a 90-degree ambiguity in its corner order.
            raise ValueError("a chessboard needs different cols and rows (e.g. 9x6) so that its "
                             "corner order is unambiguous")
        if self.square_mm <= 0:
            raise ValueError(f"square_mm must be > 0, got {self.square_mm}")

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def symmetric(self) -> bool:
        """True when the chessboard looks the same turned by 180 degrees (cols + rows even)."""
        return self.kind == "chessboard" and (self.cols + self.rows) % 2 == 0

    def object_points(self) -> np.ndarray:
        """(cols*rows, 3) float64 corner positions, mm, board frame (z = 0), row-major."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([i.ravel() * self.square_mm, j.ravel() * self.square_mm,
                         np.zeros(self.n_corners)], axis=1).astype(float)

    @property
    def n_markers(self) -> int:
        """ArUco markers on one ChArUco board (the white squares)."""
        return (self.cols + 1) * (self.rows + 1) // 2

    def charuco_board(self, index: int = 0):
        """OpenCV ``CharucoBoard``; board ``index`` uses the next ``n_markers`` marker ids.

        Several ChArUco boards on one turntable are told apart by their ids.
        """
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        ids = np.arange(index * self.n_markers, (index + 1) * self.n_markers, dtype=np.int32)
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), self.square_mm,
                                      self.marker_mm, d, ids)


def to_gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def pyramid(gray: np.ndarray, max_side_px: int) -> list[np.ndarray]:
    """Image pyramid ``[full, 1/2, 1/4, ...]`` halved until the longer side <= max_side_px."""
    levels = [gray]
    while max(levels[-1].shape) > max_side_px:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def _subpix(img: np.ndarray, corners: np.ndarray, spacing_px: float,
            fraction: float = 0.4) -> np.ndarray:
    # A window of ~40 % of a square stays inside the square's X junction (less on ChArUco,
    # whose markers would pull the corner).
    win = int(np.clip(fraction * spacing_px, 2, 15))
    c = corners.reshape(-1, 1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.001)
    cv2.cornerSubPix(img, c, (win, win), (-1, -1), crit)
    return c.reshape(-1, 2).astype(np.float64)


def _spacing(corners: np.ndarray, cols: int) -> float:
    rows = corners.reshape(-1, cols, 2)
    return float(np.median(np.linalg.norm(np.diff(rows, axis=1), axis=-1)))


def track_down(levels: list[np.ndarray], corners_top: np.ndarray, cols: int) -> np.ndarray:
    """Refine corners found at the top level down to full resolution (cornerSubPix per level)."""
    c = corners_top
    for k in range(len(levels) - 1, -1, -1):
        if k != len(levels) - 1:
            c = 2.0 * c
        c = _subpix(levels[k], c, _spacing(c, cols) if cols else 20.0)
    return c


def canonical_chessboard_order(gray: np.ndarray, corners: np.ndarray, cols: int,
                               rows: int) -> np.ndarray:
    """Number the corners the same way in every view (no 180-degree flips).

    For a board with ``cols + rows`` odd, the squares diagonally outside the
    first and the last corner have different colours: corner 0 is put next to
    the dark one.  A symmetric board (sum even) cannot be told from its turned
    self; corner 0 is then put above the last one in the image and the
    solver harmonises the order along each turntable orbit.
    """
    c = corners.reshape(rows, cols, 2)

    def outside(p0, p_row, p_col):
        q = p0 - 0.5 * (p_row - p0) - 0.5 * (p_col - p0)
        x, y = int(round(q[0])), int(round(q[1]))
        h, w = gray.shape
        if not (0 <= x < w and 0 <= y < h):
            return None
        return float(gray[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].mean())

    if (cols + rows) % 2 == 1:
        first = outside(c[0, 0], c[0, 1], c[1, 0])
        last = outside(c[-1, -1], c[-1, -2], c[-2, -1])
        if first is not None and last is not None and first > last:
            return corners[::-1].copy()
        return corners
    if corners[0, 1] > corners[-1, 1]:
        return corners[::-1].copy()
    return corners


def detect_chessboard(image: np.ndarray, cols: int, rows: int, max_side_px: int = 800
                      ) -> np.ndarray | None:
    """The seed's pyramid detection of a chessboard.

    Halve the image down to at most ``max_side_px``, find the chessboard there
    (``findChessboardCorners`` with its fast check, so images without a board
    are rejected quickly), then track each corner down the pyramid with
    ``cornerSubPix`` to full resolution.  When the board is too small to be
    found at the top, the next finer level is tried once.
    ``findChessboardCorners`` slows down steeply with the square size in
    pixels (0.01 s at 600x400 against 1-2 s at 1200x800 for the same view), so
    detection at the coarse level is the main saving.

    Parameters
    ----------
    image : (H, W, 3) uint8 BGR or (H, W) uint8
    cols, rows : int, inner corners

    Returns
    -------
    (cols*rows, 2) float64 array, px, full-resolution, canonical order; or None
    """
    gray = to_gray(image)
    levels = pyramid(gray, max_side_px)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, corners = cv2.findChessboardCorners(levels[-1], (cols, rows), flags=flags)
    if not ok and len(levels) > 1:
        levels = levels[:-1]
        ok, corners = cv2.findChessboardCorners(levels[-1], (cols, rows), flags=flags)
    if not ok:
        return None
    c = track_down(levels, corners.reshape(-1, 2).astype(np.float64), cols)
    return canonical_chessboard_order(gray, c, cols, rows)


def detect_chessboard_plain(image: np.ndarray, cols: int, rows: int) -> np.ndarray | None:
    """Baseline: ``findChessboardCorners`` + ``cornerSubPix`` on the full-resolution image."""
    gray = to_gray(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
    if not ok:
        return None
    c = corners.reshape(-1, 2).astype(np.float64)
    c = _subpix(gray, c, _spacing(c, cols))
    return canonical_chessboard_order(gray, c, cols, rows)


def detect_charuco(image: np.ndarray, spec: BoardSpec, max_side_px: int = 2048,
                   min_corners: int = 6, index: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """ChArUco corners: ids identify each corner, so partial and oblique views are usable.

    Markers are found on a reduced level (long side <= 1.5 * ``max_side_px``),
    corners refined down to full resolution with ``cornerSubPix``.

    Returns
    -------
    (ids (N,) int array, uv (N, 2) float64 px) or None when fewer than
    ``min_corners`` corners were found.  ``ids`` index ``spec.object_points()``.
    """
    gray = to_gray(image)
    levels = pyramid(gray, max_side_px)
    detector = cv2.aruco.CharucoDetector(spec.charuco_board(index))
    corners, ids, _, _ = detector.detectBoard(levels[-1])
    if ids is None or len(ids) < min_corners:
        return None
    ids = ids.ravel().astype(int)
    c = corners.reshape(-1, 2).astype(np.float64)
    scale = 2 ** (len(levels) - 1)
    spacing = spec.square_mm  # unknown in px: estimate from neighbouring ids below
    if len(c) >= 2:
        d = np.linalg.norm(c[:, None] - c[None], axis=-1)
        d[d == 0] = np.inf
        spacing = float(np.median(d.min(axis=1)))
    # detectBoard already refines at its own level; only finer levels need cornerSubPix.
    for k in range(len(levels) - 2, -1, -1):
        c = 2.0 * c
        spacing *= 2.0
        c = _subpix(levels[k], c, spacing, fraction=0.2)
    del scale
    # OpenCV ChArUco corner id = row * (squares_x - 1) + col: the same row-major layout
    # as object_points(); its origin differs by one square, which the board pose absorbs.
    return ids, c

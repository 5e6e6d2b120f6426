"""The `turntable` and `fixed` calibrators and the calibration evaluator."""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from plantscan_calib.detect import BoardSpec, detect_charuco, detect_chessboard
from plantscan_calib.initialise import label_identical_boards
from plantscan_calib.model import CalibrationError, Detection
from plantscan_calib.solver import SolveOptions, solve_turntable
from plantscan_core.data import Calibration, ViewRecord
from plantscan_core.errors import DataError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.parallel import image_pool
from plantscan_core.stages import Calibrator, StageParams

__all__ = ["TurntableCalibrator", "FixedCalibrator", "CalibrationError", "detect_views"]


class TurntableCalibrator(Calibrator):
    """Calibrate a turntable rig from the scan's ``calibration`` views.

    Detects the board in every calibration image (chessboard through an image
    pyramid, or ChArUco), initialises as the seed (mono calibration, plane +
    circle fit of the corner orbits), refines everything jointly with Ceres
    (Cauchy loss, outlier rejection, plain solve) and fits the tilt-arm axis.
    """

    name = "turntable"

    class Params(SolveOptions):
        """The board, its detection and the solver's options (``SolveOptions``)."""

        board: Literal["chessboard", "charuco"] = "chessboard"
        cols: int = Field(9, ge=2, description="inner corners along the board's rows")
        rows: int = Field(6, ge=2, description="inner corners along the board's columns")
        square_mm: float = Field(25.0, gt=0, description="square side, mm (the virtual "
                                 "scanner's board: 25)")
        marker_mm: float = Field(0.0, ge=0, description="ChArUco marker side, mm")
        dictionary: str = "DICT_5X5_100"
        detect_max_side_px: int = Field(800, ge=128,
                                        description="pyramid top size for chessboard detection")
        boards: int = Field(1, ge=1, description="boards on the turntable: ChArUco board k "
                            "uses the k-th block of marker ids; identical chessboards are told "
                            "apart by the turntable angles at which each faces the cameras")
        workers: int = Field(2, ge=1)

    def board_spec(self) -> BoardSpec:
        p = self.params
        try:
            return BoardSpec(p.board, p.cols, p.rows, p.square_mm, p.marker_mm, p.dictionary)
        except ValueError as exc:
            raise CalibrationError(f"calibrate.params: {exc}") from None

    def calibrate(self, scan) -> Calibration:
        views = scan.views_by_role("calibration")
        if not views:
            raise DataError(f"{scan.root}: the scan has no calibration views (role "
                            "'calibration' in views.jsonl)")
        spec = self.board_spec()
        dets, sizes, found = detect_views(scan, views, spec, self.params.detect_max_side_px,
                                          self.params.workers, self.params.boards)
        if spec.kind == "chessboard" and self.params.boards > 1:
            # Identical chessboards: told apart by the turntable angles at which each faces
            # the cameras (ChArUco boards carry their own ids).
            dets = label_identical_boards(dets, self.params.boards)
        _check_detections(views, found, spec, self.params.min_views, scan.root)
        boards = {k: spec.object_points() for k in range(self.params.boards)}
        tilts = {v.tilt_index: v.tilt_deg for v in views}
        solved = solve_turntable(dets, boards, sizes, tilts, self.params,
                                 symmetric_boards=spec.symmetric)
        cal, quality = solved.calibration, solved.quality
        per_ct = Counter((v.camera, v.tilt_index) for v in views)
        cal.quality["board_found"] = {
            f"{c}/t{t}": {"found": found.get((c, t), 0), "views": n}
            for (c, t), n in sorted(per_ct.items())}
        cal.quality["board"] = spec.__dict__ | {}
        self.report.count("views", len(views))
        self.report.count("detections", quality.detections)
        self.report.count("corners", quality.corners)
        if quality.rejected_corners is not None:
            self.report.count("rejected_corners", quality.rejected_corners)
        self.report.note({"rms_px": quality.rms_px, "corner_noise_px": quality.corner_noise_px,
                          "max_px": quality.max_px})
        self.report.warnings += quality.flags
        return cal


def detect_views(scan, views: list[ViewRecord], spec: BoardSpec, max_side_px: int = 800,
                 workers: int = 2, boards: int = 1,
                 ) -> tuple[list[Detection], dict[str, tuple[int, int]],
                            dict[tuple[str, int], int]]:
    """Detect the board in each view (threads: OpenCV releases the GIL).

    Returns the detections, the image size of each camera and the number of
    views with a board per (camera, tilt).  Images of one camera with
    different sizes raise ``DataError`` naming them.
    """
    def one(view: ViewRecord):
        gray = scan.read_image(view, grayscale=True)
        size = (gray.shape[1], gray.shape[0])
        if spec.kind == "chessboard":
            uv = detect_chessboard(gray, spec.cols, spec.rows, max_side_px)
            return view, size, [] if uv is None else [(0, np.arange(spec.n_corners), uv)]
        hits = [(k, detect_charuco(gray, spec, max(2 * max_side_px, 2048), index=k))
                for k in range(boards)]
        return view, size, [(k, *h) for k, h in hits if h is not None]

    with image_pool(workers) as pool:
        results = list(pool.map(one, views))
    sizes: dict[str, tuple[int, int]] = {}
    first: dict[str, ViewRecord] = {}
    dets: list[Detection] = []
    found: dict[tuple[str, int], int] = defaultdict(int)
    for view, size, hit in results:
        if view.camera in sizes and sizes[view.camera] != size:
            raise DataError(
                f"camera {view.camera}: calibration images of different sizes: "
                f"{first[view.camera].file} is {sizes[view.camera][0]}x{sizes[view.camera][1]}, "
                f"{view.file} is {size[0]}x{size[1]}")
        sizes.setdefault(view.camera, size)
        first.setdefault(view.camera, view)
        if not hit:
            continue
        found[(view.camera, view.tilt_index)] += 1
        for board, ids, uv in hit:
            dets.append(Detection(view.camera, view.tilt_index, view.angle_deg, board, ids, uv,
                                  view.index))
    return dets, sizes, dict(found)


def _check_detections(views: list[ViewRecord], found: dict[tuple[str, int], int],
                      spec: BoardSpec, min_views: int, root: Path) -> None:
    """Clear errors for a board never found or too few detections per (camera, tilt)."""
    board = (f"{spec.cols}x{spec.rows}-corner chessboard" if spec.kind == "chessboard"
             else f"{spec.cols + 1}x{spec.rows + 1}-square ChArUco board ({spec.dictionary})")
    if not found:
        raise CalibrationError(
            f"{root}: no {board} found in any of the {len(views)} calibration views (e.g. "
            f"{views[0].file}); check calibrate.params (board, cols, rows) against the photos")
    per_ct = Counter((v.camera, v.tilt_index) for v in views)
    few = [(c, t, found.get((c, t), 0), n) for (c, t), n in sorted(per_ct.items())
           if found.get((c, t), 0) < min_views]
    if few:
        raise CalibrationError(
            f"{root}: too few views with the {board} (need calibrate.params.min_views = "
            f"{min_views} per camera and tilt): " + "; ".join(
                f"camera {c} tilt {t}: found in {k} of {n} views" for c, t, k, n in few))


class FixedCalibrator(Calibrator):
    """Use a calibration computed elsewhere (a plantscan calibration YAML).

    ``path`` is relative to the scan folder unless absolute; the default is
    the scan's own ``calibration.yaml`` (what ``plantscan import`` writes).
    """

    name = "fixed"

    class Params(StageParams):
        path: str = "calibration.yaml"

    def _path(self, scan) -> Path:
        path = Path(self.params.path)
        return path if path.is_absolute() else Path(scan.root) / path

    def input_files(self, scan) -> list[Path]:
        """The calibration file: the run's cache key hashes its content (a re-import with
        another calibration is a new calibration)."""
        return [self._path(scan)]

    def calibrate(self, scan) -> Calibration:
        path = self._path(scan)
        cal = Calibration.load(path)
        views = scan.views
        missing = sorted({v.camera for v in views} - set(cal.models))
        if missing:
            raise DataError(f"{path}: has no camera {', '.join(missing)} used by the scan "
                            f"(it has {', '.join(cal.camera_names)})")
        return cal


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(TurntableCalibrator)
    registry.add(FixedCalibrator)


@hookimpl
def plantscan_evaluate(run_dir: Path, truth_dir: Path) -> dict[str, Any] | None:
    from plantscan_calib.evaluate import evaluate_run

    return evaluate_run(Path(run_dir), Path(truth_dir))

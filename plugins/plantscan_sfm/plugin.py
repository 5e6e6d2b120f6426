"""The ``sfm`` calibrator: calibrate a turntable rig from the plant photos themselves."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from plantscan_core.data import Calibration
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import Calibrator, StageParams
from plantscan_sfm.calibrate import SfmError, SfmSettings, calibrate_scan

__all__ = ["SfmCalibrator", "SfmError"]


class BoardParams(StageParams):
    """The board of the one photo per camera (``plantscan_calib.detect.BoardSpec``)."""

    kind: Literal["chessboard", "charuco"] = "chessboard"
    cols: int = Field(..., ge=2, description="inner corners along the board's rows")
    rows: int = Field(..., ge=2, description="inner corners along the board's columns")
    square_mm: float = Field(..., gt=0)
    marker_mm: float = Field(0.0, ge=0, description="ChArUco marker side, mm")
    dictionary: str = "DICT_5X5_100"


class SfmCalibrator(Calibrator):
    """Structure from motion with the turntable's constraints (pycolmap + pyceres).

    Needs no board: SIFT features of the plant, pot and plate (a printed plate
    makes it dependable) are matched between turntable neighbours, and one
    turntable model (one axis, the commanded angles as priors, one pose per
    camera and tilt, intrinsics per camera) is fitted to them.  The metric
    scale comes from the plate's diameter or a known camera distance.
    """

    name = "sfm"

    class Params(StageParams):
        role: Literal["plant", "calibration", "background"] = Field(
            "plant", description="which photos to calibrate from")
        scale: Literal["plate", "markers", "camera-distance"] = Field(
            "plate", description="where the metric scale comes from")
        marker_mm: float | None = Field(None, gt=0, description="side of the printed ArUco "
                                        "markers, their black border included (scale: markers)")
        markers: Literal["DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_5X5_100",
                         "DICT_5X5_250", "DICT_6X6_250"] | None = Field(
            "DICT_4X4_250", description="ArUco dictionary of the printed markers (their "
            "corners are points every camera identifies; on the plate they turn with it, on "
            "the backdrop they are found fixed); null: no markers")
        refine_dots: bool = Field(True, description="move keypoints on printed dots to the "
                                  "dots' centroids")
        plate_diameter_mm: float | None = Field(None, gt=0, description="turntable plate "
                                                "diameter (scale: plate)")
        camera_distance_mm: float | None = Field(
            None, gt=0, description="distance of the first camera's centre from the axis "
            "(scale: camera-distance)")
        plate_top_mm: float = Field(0.0, description="world height of the plate's top")
        max_features: int = Field(8192, ge=100, description="SIFT features per photo")
        max_image_size: int = Field(3200, ge=200, description="photos are scaled down to this "
                                    "longest side for feature extraction")
        first_octave: int | None = Field(None, ge=-1, le=2, description="SIFT's first octave "
                                         "(-1 upsamples; default: -1 below 0.8 MP, else 0)")
        orbit_neighbours: int = Field(3, ge=1, description="photos of one camera and tilt are "
                                      "matched with this many turntable stops on each side")
        cross_window_deg: float | None = Field(
            None, ge=0, description="photos of different cameras/tilts are matched when their "
            "angles differ by at most this (default: 1.5 turntable steps)")
        exhaustive_below: int = Field(16, ge=0, description="match every pair below this many "
                                      "photos")
        ransac_px: float = Field(2.0, gt=0, description="two-view RANSAC threshold")
        angle_sigma_deg: float | None = Field(
            0.5, gt=0, description="uncertainty of the recorded turntable angles (backlash); "
            "None holds them exact")
        fit_angle_scale: bool = False
        fix_principal_point: bool = Field(
            True, description="hold (cu, cv) at principal_point_px, else at the image centre "
            "(a turntable orbit leaves the principal point loose: 1-sigma 17-38 px on the "
            "virtual paper-72 dicot; freed, it wandered 35-54 px; docs/sfm.md)")
        principal_point_px: dict[str, tuple[float, float]] | None = Field(
            None, description="principal point (cu, cv) per camera, px, from a calibration of "
            "the lens (top-left pixel's centre at 0, 0); held unless fix_principal_point is "
            "false")
        principal_point_prior: float | None = Field(
            0.015, ge=0, description="standard deviation of a prior holding the free "
            "principal point near the image centre, as a fraction of the image width")
        fix_distortion: bool = False
        min_tracks: int = Field(200, ge=10, description="fewer feature tracks: the scene is "
                                "too plain to calibrate from")
        min_view_observations: int = Field(15, ge=1)
        max_rms_px: float = Field(1.5, gt=0)
        max_observations: int = Field(200_000, ge=1000, description="feature tracks drawn "
                                      "at random (seeded) up to this many observations, every "
                                      "marker corner kept (bounds the solve's time)")
        threads: int = Field(2, ge=1)
        focal_px: dict[str, float] | None = Field(
            None, description="focal length per camera, px (lens focal length / pixel "
            "pitch), where the photos do not fix it (a shallow scene)")
        fit_focal: bool = Field(False, description="refine the given focal_px instead of "
                                "holding it")
        weigh_by_kind: bool | None = Field(
            None, description="weigh every observation by the noise of its class (camera x "
            "raw keypoint / refined dot / marker corner / lab marker), measured from the "
            "bundle's own residuals, and solve again; null: when the principal point is "
            "known (principal_point_px, or a board photo of every camera), as measured "
            "best (docs/sfm.md)")
        reject_sigma: float | None = Field(
            None, gt=0, description="after the bundle adjustment, drop each track's "
            "observations farther than this many sigma (its camera's robust residual scale) "
            "from the point the track's other photos give, and solve again (wrong matches of "
            "a repeated print); null: off (docs/sfm.md: it helps with the principal point "
            "given, not with it held)")
        board: BoardParams | None = Field(
            None, description="a calibration board photographed once per camera (photos of "
            "board_role): its corners fix the intrinsics -- the principal point above all -- "
            "jointly with the turntable bundle")
        board_role: Literal["plant", "calibration", "background"] = Field(
            "calibration", description="which photos show the board")
        board_on_turntable: bool = Field(
            False, description="the board stood on the turntable in its photos: one board "
            "pose for every camera, seen at each photo's turntable angle (its squares then "
            "give the scale too: quality.board_views.scale_vs_plate)")
        board_noise: float = Field(1.0, gt=0, description="the board corners' noise relative "
                                   "to a refined dot's")
        prior_poses: str | None = Field(
            None, description="approximate poses (plantscan import poses) relative to the scan "
            "folder; default: the scan's prior_poses.yaml when present")

    def settings(self) -> SfmSettings:
        p = self.params
        return SfmSettings(**{k: getattr(p, k) for k in (
            "role", "max_features", "max_image_size", "first_octave", "orbit_neighbours",
            "cross_window_deg", "exhaustive_below", "ransac_px", "scale", "plate_diameter_mm",
            "camera_distance_mm", "plate_top_mm", "angle_sigma_deg", "fit_angle_scale",
            "fix_principal_point", "fix_distortion", "min_tracks", "min_view_observations",
            "focal_px", "principal_point_px", "fit_focal", "marker_mm", "markers", "refine_dots",
            "principal_point_prior", "max_rms_px", "threads", "max_observations",
            "reject_sigma", "weigh_by_kind", "board_role", "board_noise", "board_on_turntable")},
            board=p.board.model_dump() if p.board is not None else None)

    def input_roles(self, scan) -> list[str]:
        """The photos it calibrates from (and the board's): new ones redo the calibration."""
        roles = [self.params.role]
        if self.params.board is not None and self.params.board_role not in roles:
            roles.append(self.params.board_role)
        return roles

    def input_files(self, scan) -> list[Path]:
        """The approximate poses, when the scan has them."""
        from plantscan_sfm.priors import PRIOR_POSES_FILE

        path = Path(self.params.prior_poses or PRIOR_POSES_FILE)
        path = path if path.is_absolute() else Path(scan.root) / path
        return [path] if path.exists() else []

    def calibrate(self, scan) -> Calibration:
        from plantscan_sfm.priors import PRIOR_POSES_FILE, read_prior_poses

        s = self.settings()
        path = Path(self.params.prior_poses or PRIOR_POSES_FILE)
        if not path.is_absolute():
            path = Path(scan.root) / path
        if path.exists():
            s.prior_poses, s.prior_focal = read_prior_poses(path)
        elif self.params.prior_poses is not None:
            raise SfmError(f"{path}: calibrate.params.prior_poses names no file")
        return calibrate_scan(scan, s)


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(SfmCalibrator)


@hookimpl
def plantscan_add_commands(subparsers) -> None:
    from plantscan_sfm.priors import add_import_command

    add_import_command(subparsers)

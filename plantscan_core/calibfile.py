"""The checks on a calibration file (``plantscan-calibration/1`` YAML) before it is used.

A calibration is read from files a user hands over (``--calibration``, the
``fixed`` calibrator, a COLMAP import), so every number is checked the way a
recipe's are: finite and in range, rotations orthonormal, every pose's camera
defined.  ``Calibration.load`` calls ``check_calibration_dict``; errors name
the file and the key (``calibration.yaml: models.cam0.f: Input should be
greater than 0``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from plantscan_core.bounds import (
    MAX_IMAGE_SIDE_PX,
    AngleDeg,
    CheckedModel,
    FiniteFloat,
    LengthMM,
    TiltDeg,
    error_path,
)
from plantscan_core.errors import DataError

ROTATION_TOLERANCE = 1e-6
"""|R^T R - I| allowed: files carry full float64 (``repr``), so a real rotation is within 1e-12."""


class CameraModelEntry(CheckedModel):
    f: float = Field(gt=0, le=1e7, description="focal length, px")
    cu: float = Field(ge=-1e6, le=1e6)
    cv: float = Field(ge=-1e6, le=1e6)
    d1: float = Field(0.0, ge=-100.0, le=100.0)
    d2: float = Field(0.0, ge=-1e4, le=1e4)
    width: int = Field(0, ge=0, le=MAX_IMAGE_SIDE_PX)
    height: int = Field(0, ge=0, le=MAX_IMAGE_SIDE_PX)
    aspect: float = Field(1.0, gt=0.1, lt=10.0)


def _rotation(r: list[list[float]]) -> list[list[float]]:
    m = np.asarray(r, dtype=float)
    if m.shape != (3, 3):
        raise ValueError(f"R must be 3x3, got {m.shape}")
    err = float(np.abs(m.T @ m - np.eye(3)).max())
    if err > ROTATION_TOLERANCE or np.linalg.det(m) < 0:
        raise ValueError(f"R is not a rotation (|R^T R - I| = {err:.2g}, det = "
                         f"{np.linalg.det(m):.3g})")
    return r


class PoseEntry(CheckedModel):
    camera: str = Field(min_length=1)
    tilt_index: int = Field(ge=0, le=100_000)
    R: list[list[FiniteFloat]]
    t: list[LengthMM] = Field(min_length=3, max_length=3)

    @field_validator("R")
    @classmethod
    def _is_rotation(cls, v: list[list[float]]) -> list[list[float]]:
        return _rotation(v)


class TiltAxisEntry(CheckedModel):
    origin: list[LengthMM] = Field(min_length=3, max_length=3)
    direction: list[FiniteFloat] = Field(min_length=3, max_length=3)
    reference_tilt_index: int = Field(0, ge=0, le=100_000)

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        if not float(np.linalg.norm(v)) > 1e-9:
            raise ValueError("direction must not be the zero vector")
        return v


class CalibrationEntry(CheckedModel):
    format: str = "plantscan-calibration/1"
    units: dict[str, str] = Field(default_factory=dict)
    models: dict[str, CameraModelEntry] = Field(min_length=1)
    poses: list[PoseEntry]
    tilts_deg: dict[int, TiltDeg] = Field(default_factory=dict)
    angle_scale: float = Field(1.0, gt=0.5, lt=2.0, description="real per commanded degree")
    tilt_axis: TiltAxisEntry | None = None
    quality: dict[str, Any] | None = None
    view_angles_deg: dict[int, AngleDeg] = Field(
        default_factory=dict, description="solved turntable angle per view index (sfm)")

    @model_validator(mode="after")
    def _poses_name_models(self) -> CalibrationEntry:
        unknown = sorted({p.camera for p in self.poses} - set(self.models))
        if unknown:
            raise ValueError(f"poses name camera(s) {unknown} that models does not define "
                             f"(it has {sorted(self.models)})")
        keys = [(p.camera, p.tilt_index) for p in self.poses]
        repeated = sorted({k for k in keys if keys.count(k) > 1})
        if repeated:
            raise ValueError(f"poses repeat (camera, tilt_index) {repeated}")
        return self


def check_calibration_dict(raw: Any, source: str) -> None:
    """Raise ``DataError`` listing every problem of a parsed calibration file."""
    if not isinstance(raw, dict):
        raise DataError(f"{source}: not a plantscan calibration (a YAML mapping with models "
                        "and poses)")
    try:
        CalibrationEntry.model_validate(raw)
    except ValidationError as exc:
        lines = [f"{source}: {error_path(e['loc'])}: {e['msg']}" if e["loc"] else
                 f"{source}: {e['msg']}" for e in exc.errors()]
        raise DataError("\n".join(lines)) from None

"""Every number a user gives is finite and in a stated range.

A measuring instrument must never carry a NaN, an infinity or an absurd
magnitude silently into a result.  ``CheckedModel`` is the base of every
pydantic model that reads user numbers (recipes, plugin ``Params``, the
calibration file, manifest lines): NaN and inf are refused
(``allow_inf_nan=False``) and no float may exceed ``MAX_MAGNITUDE`` in size
unless its field states a range of its own.  The annotated types below state
the ranges shared by several files (lengths, angles, tilts, image sides).
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

MAX_MAGNITUDE = 1e15
"""No user number is larger: a product of two stays far from overflow (1e30, float64 holds
1e308), and 1e12 still reads as "instantaneous" (an emulator's acceleration in deg/s²)."""

MAX_LENGTH_MM = 100_000.0
"""A rig, a plant and a camera distance fit in 100 m."""

MAX_ANGLE_DEG = 3600.0
"""Ten turns: any commanded or measured axis angle (a turntable may count past 360)."""

MAX_IMAGE_SIDE_PX = 65_500
"""The JPEG format's limit (65 535), rounded down; PNG decoders refuse larger too."""

FiniteFloat = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
"""A finite float within ``MAX_MAGNITUDE``: the default of every user number."""

LengthMM = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM)]
"""A coordinate or length, mm."""

AngleDeg = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)]
"""An axis angle, deg."""

TiltDeg = Annotated[float, Field(allow_inf_nan=False, ge=-90.0, le=90.0)]
"""A camera-arm tilt, deg: from looking straight up to straight down."""

ImageSidePx = Annotated[int, Field(ge=1, le=MAX_IMAGE_SIDE_PX)]
"""A width or height of an image, px."""


def error_path(parts: tuple[Any, ...]) -> str:
    """A pydantic error location as a recipe path: ``scan.tilts_deg.0``; odd keys quoted."""
    return ".".join(str(p) if str(p).isprintable() and str(p) else repr(p) for p in parts)


def _check_magnitude(value: Any) -> None:
    if isinstance(value, float):
        if abs(value) > MAX_MAGNITUDE:
            raise ValueError(f"{value:g} is out of range (|x| <= {MAX_MAGNITUDE:g} for any "
                             "number without a range of its own)")
    elif isinstance(value, (list, tuple)):
        for item in value:
            _check_magnitude(item)


class CheckedModel(BaseModel):
    """Unknown keys are errors; every float is finite and within ``MAX_MAGNITUDE``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _bounded(cls, value: Any) -> Any:
        _check_magnitude(value)
        return value

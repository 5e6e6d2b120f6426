"""Scan trajectories: the (pan, tilt) stops of the plant views, and their order.

A scan need not be a grid of evenly spaced turntable angles per tilt: the
tilt-axis calibration gives the camera pose for any pair of pan (turntable
angle) and tilt, so the plant views may be any list of stops.  A recipe gives
them as ``scan.trajectory`` (``docs/trajectories.md``)::

    trajectory: {kind: grid, tilts_deg: [0, 20], images_per_revolution: 36}
    trajectory: {kind: per-tilt, rings: [{tilt_deg: 0, stops: 36}, {tilt_deg: 30, stops: 12}]}
    trajectory: {kind: spiral, stops: 50, tilt_range_deg: [-10, 30], turns: 5}
    trajectory: {kind: golden-angle, stops: 50, tilt_range_deg: [-10, 30]}
    trajectory: {kind: views, views: [[0, 0], [45, 10], [90, 30]]}   # [pan, tilt] pairs

Every stop is checked against the rig's limits (``scan.limits``) before any
motor moves, and acquisition visits the stops in the order that the timing
model (``plantscan_core.timing``) says is quickest (``order_stops``).  A stop
is one rig position: every camera takes its image there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import Field, field_validator

from plantscan_core.bounds import CheckedModel, FiniteFloat

GOLDEN_ANGLE_DEG = 180.0 * (3.0 - math.sqrt(5.0))
"""137.508 deg: successive stops of the golden-angle trajectory turn by this."""


@dataclass(frozen=True)
class Stop:
    """One rig position of the plant views.

    Attributes
    ----------
    pan_deg : float, deg
        Commanded turntable angle, in [0, 360).
    tilt_deg : float, deg
        Commanded tilt of the camera arm.
    index : int
        The stop's ``angle_index`` in ``views.jsonl`` (unique among the plant
        stops of its tilt; the position in a revolution for a grid).
    """

    pan_deg: float
    tilt_deg: float
    index: int = 0

    @property
    def position(self) -> tuple[float, float]:
        return (self.pan_deg, self.tilt_deg)


def _pan(deg: float) -> float:
    """``deg`` in [0, 360), rounded to 1e-6 deg (stable names and keys)."""
    p = round(float(deg) % 360.0, 6)
    return 0.0 if p >= 360.0 else p


def _quantised(tilt: float, step: float) -> float:
    return round(round(tilt / step) * step, 6) if step > 0 else round(float(tilt), 6)


# --------------------------------------------------------------------------- generators
class _Trajectory(CheckedModel):
    def stops(self) -> list[Stop]:  # pragma: no cover - abstract
        raise NotImplementedError


class GridTrajectory(_Trajectory):
    """Every tilt times ``images_per_revolution`` evenly spaced turntable angles (as today)."""

    kind: Literal["grid"]
    tilts_deg: list[FiniteFloat] = Field(min_length=1)
    images_per_revolution: int = Field(ge=1, le=3600)
    offset_deg: FiniteFloat = Field(0.0, description="turntable angle of the first stop")

    def stops(self) -> list[Stop]:
        n = self.images_per_revolution
        return [Stop(_pan(self.offset_deg + i * 360.0 / n), float(t), i)
                for t in self.tilts_deg for i in range(n)]


class TiltRing(CheckedModel):
    """One tilt of a ``per-tilt`` trajectory."""

    tilt_deg: FiniteFloat
    stops: int = Field(ge=1, le=3600, description="evenly spaced turntable angles at this tilt")
    offset_deg: FiniteFloat | None = Field(
        None, description="turntable angle of the ring's first stop; default: rings after "
        "the first are turned by half their own step, so their views fall between")


class PerTiltTrajectory(_Trajectory):
    """A ring of evenly spaced stops per tilt, each with its own count (fewer at steep tilts)."""

    kind: Literal["per-tilt"]
    rings: list[TiltRing] = Field(min_length=1)

    def stops(self) -> list[Stop]:
        out: list[Stop] = []
        for r, ring in enumerate(self.rings):
            step = 360.0 / ring.stops
            offset = ring.offset_deg if ring.offset_deg is not None else (0.5 * step if r else 0.0)
            out += [Stop(_pan(offset + i * step), float(ring.tilt_deg), i)
                    for i in range(ring.stops)]
        return out


class _SweepTrajectory(_Trajectory):
    stops_: int = Field(alias="stops", ge=1, le=3600, description="rig positions")
    tilt_range_deg: tuple[FiniteFloat, FiniteFloat] = Field(
        description="lowest and highest tilt of the sweep")
    tilt_step_deg: float = Field(
        5.0, ge=0.0, le=90.0, description="tilts are rounded to multiples of this (each "
        "distinct tilt needs its own background plate per camera); 0: not rounded")

    @field_validator("tilt_range_deg")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError("the lowest tilt comes first: [low, high]")
        return v

    def _tilt(self, fraction: float) -> float:
        lo, hi = self.tilt_range_deg
        return min(hi, max(lo, _quantised(lo + fraction * (hi - lo), self.tilt_step_deg)))


class SpiralTrajectory(_SweepTrajectory):
    """The tilt rises evenly from the lowest to the highest tilt while the plant turns
    ``turns`` times: one continuous sweep of the view sphere's band."""

    kind: Literal["spiral"]
    turns: float = Field(5.0, gt=0.0, le=100.0)

    def stops(self) -> list[Stop]:
        n = self.stops_
        return [Stop(_pan(360.0 * self.turns * i / n), self._tilt(i / max(n - 1, 1)), i)
                for i in range(n)]


class GoldenAngleTrajectory(_SweepTrajectory):
    """Successive stops turn by the golden angle (137.5 deg) and the sine of the tilt
    rises evenly (a Fibonacci lattice): stops spread evenly over the view sphere's band,
    and any first part of the list is spread evenly too."""

    kind: Literal["golden-angle"]

    def stops(self) -> list[Stop]:
        n = self.stops_
        lo, hi = (math.sin(math.radians(t)) for t in self.tilt_range_deg)
        out = []
        for i in range(n):
            s = lo + (hi - lo) * (i + 0.5) / n
            tilt = math.degrees(math.asin(min(1.0, max(-1.0, s))))
            a, b = self.tilt_range_deg
            f = 0.0 if b == a else (tilt - a) / (b - a)
            out.append(Stop(_pan(i * GOLDEN_ANGLE_DEG), self._tilt(f), i))
        return out


class ViewsTrajectory(_Trajectory):
    """An explicit list of ``[pan_deg, tilt_deg]`` stops."""

    kind: Literal["views"]
    views: list[tuple[FiniteFloat, FiniteFloat]] = Field(min_length=1, max_length=100_000)

    def stops(self) -> list[Stop]:
        return [Stop(_pan(p), float(t), i) for i, (p, t) in enumerate(self.views)]


Trajectory = Annotated[
    Union[GridTrajectory, PerTiltTrajectory, SpiralTrajectory, GoldenAngleTrajectory,  # noqa: UP007
          ViewsTrajectory],
    Field(discriminator="kind")]
"""``scan.trajectory``: one of the generators, chosen by ``kind``."""

TRAJECTORY_KINDS = ("grid", "per-tilt", "spiral", "golden-angle", "views")


def duplicate_stops(stops: Sequence[Stop]) -> list[tuple[int, int]]:
    """(earlier, later) positions of stops at the same rig position."""
    seen: dict[tuple[float, float], int] = {}
    out = []
    for i, s in enumerate(stops):
        j = seen.setdefault(s.position, i)
        if j != i:
            out.append((j, i))
    return out


# --------------------------------------------------------------------------- rig limits
class RigLimits(CheckedModel):
    """What the rig can do (``scan.limits``): checked before any motor moves.

    A stop outside the tilt range, or an axis set faster than the rig allows,
    is refused when the recipe is validated, naming the stop or the parameter.
    """

    tilt_deg: tuple[FiniteFloat, FiniteFloat] = Field(
        (-90.0, 90.0), description="travel of the tilt arm, [lowest, highest] deg")
    turntable_velocity_deg_s: float | None = Field(
        None, gt=0.0, le=1e6, description="fastest turntable speed the rig allows")
    turntable_acceleration_deg_s2: float | None = Field(None, gt=0.0, le=1e9)
    tilt_velocity_deg_s: float | None = Field(
        None, gt=0.0, le=1e6, description="fastest tilt-arm speed the rig allows (a heavy "
        "arm with two cameras)")
    tilt_acceleration_deg_s2: float | None = Field(None, gt=0.0, le=1e9)

    @field_validator("tilt_deg")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError("the lowest tilt comes first: [low, high]")
        if v[0] < -90.0 or v[1] > 90.0:
            raise ValueError("the tilt range lies within [-90, 90] deg")
        return v

    def tilt_ok(self, tilt_deg: float) -> bool:
        lo, hi = self.tilt_deg
        return lo - 1e-9 <= tilt_deg <= hi + 1e-9


# --------------------------------------------------------------------------- ordering
@dataclass(frozen=True)
class MotionModel:
    """Seconds between stops with the rig's timing model (``plantscan_core.timing``).

    The tilt arm moves first, then the turntable (as ``acquire`` does); the
    slowest camera download of the previous stop runs during the move, so a
    stop costs ``max(move, download_s) + capture_s``.

    Attributes
    ----------
    turntable, tilt : AxisTiming
    capture_s, download_s : float, s — slowest camera's
    """

    turntable: Any
    tilt: Any
    capture_s: float = 0.0
    download_s: float = 0.0

    def move_s(self, a: tuple[float, float], b: tuple[float, float]) -> float:
        """Seconds of motion from rig position ``a`` to ``b`` ((pan, tilt) deg)."""
        return self.tilt.move_s(b[1] - a[1]) + self.turntable.move_s(b[0] - a[0])

    def stop_s(self, a: tuple[float, float], b: tuple[float, float], first: bool) -> float:
        wait = 0.0 if first else self.download_s
        return max(self.move_s(a, b), wait) + self.capture_s

    def tour_s(self, stops: Sequence[Stop], start: tuple[float, float] = (0.0, 0.0),
               last_download: bool = True) -> float:
        """Seconds to visit ``stops`` in this order from ``start`` and take every image."""
        t, at = 0.0, start
        for i, s in enumerate(stops):
            t += self.stop_s(at, s.position, i == 0)
            at = s.position
        return t + (self.download_s if stops and last_download else 0.0)


def _profile_s(d: np.ndarray, v: float, a: float) -> np.ndarray:
    """``timing.move_time_s`` on an array of distances (deg, >= 0)."""
    if math.isinf(v) or math.isinf(a):
        return np.zeros_like(d)
    ramps = v * v / a
    return np.where(d <= ramps, 2.0 * np.sqrt(d / a), 2.0 * v / a + (d - ramps) / v)


def _axis_s(axis: Any, delta: np.ndarray) -> np.ndarray:
    """``AxisTiming.move_s`` on an array of signed distances (deg)."""
    v, a = float(axis.velocity_deg_s), float(axis.acceleration_deg_s2)
    d = np.abs(delta)
    t = _profile_s(d, v, a)
    if axis.approach_deg > 0:
        back = _profile_s(d + axis.approach_deg, v, a) + _profile_s(
            np.full_like(d, float(axis.approach_deg)), v, a)
        t = np.where(delta < 0, back, t)
    return np.where(delta == 0.0, 0.0, t + float(axis.settle_s))


def _cost_matrix(points: np.ndarray, motion: MotionModel) -> np.ndarray:
    """(n, n) seconds of motion between stops (rows from, columns to)."""
    d_pan = points[None, :, 0] - points[:, None, 0]
    d_tilt = points[None, :, 1] - points[:, None, 1]
    return _axis_s(motion.turntable, d_pan) + _axis_s(motion.tilt, d_tilt)


def _by_tilt(stops: list[Stop], serpentine: bool) -> list[Stop]:
    out: list[Stop] = []
    for k, tilt in enumerate(sorted({s.tilt_deg for s in stops})):
        ring = sorted((s for s in stops if s.tilt_deg == tilt), key=lambda s: s.pan_deg)
        out += ring[::-1] if serpentine and k % 2 else ring
    return out


def _nearest_neighbour(stops: list[Stop], motion: MotionModel,
                       start: tuple[float, float]) -> list[Stop]:
    pts = np.array([s.position for s in stops], float)
    cost = _cost_matrix(pts, motion)
    first = np.array([motion.move_s(start, tuple(p)) for p in pts])
    todo = np.ones(len(stops), bool)
    i = int(np.argmin(first))
    order = [i]
    todo[i] = False
    while todo.any():
        row = np.where(todo, cost[i], np.inf)
        i = int(np.argmin(row))
        order.append(i)
        todo[i] = False
    return [stops[i] for i in order]


ORDER_HEURISTICS = ("as-given", "by-tilt", "by-tilt-serpentine", "nearest-neighbour")
# Nearest neighbour builds an n x n cost matrix from the timing model; beyond this many
# stops it is left out (32 MB of matrix; a 3600-stop grid is ordered by tilt at once).
NEAREST_NEIGHBOUR_MAX_STOPS = 2000


def order_stops(stops: Sequence[Stop], motion: MotionModel,
                start: tuple[float, float] = (0.0, 0.0)) -> tuple[list[Stop], dict[str, float]]:
    """The quickest of a few orders of ``stops`` by the timing model, and every order's time.

    Tried: the order given; by tilt, turntable angle ascending in every ring; by
    tilt, every other ring backwards (no rewind of the turntable between rings);
    nearest neighbour in seconds from ``start`` (up to ``NEAREST_NEIGHBOUR_MAX_STOPS``).
    Tilt moves are slow (a heavy arm) and a rewind of the turntable costs a whole
    revolution, which is what the structured orders avoid; nearest neighbour wins on
    scattered stops (planned views, explicit lists).  Ties keep the earlier order in
    this list, so the result is deterministic.

    Returns
    -------
    order : list of Stop
    seconds : dict heuristic -> seconds of the whole tour (``MotionModel.tour_s``)
    """
    stops = list(stops)
    if len(stops) <= 1:
        return stops, {"as-given": motion.tour_s(stops, start)}
    candidates = {"as-given": stops, "by-tilt": _by_tilt(stops, False),
                  "by-tilt-serpentine": _by_tilt(stops, True)}
    if len(stops) <= NEAREST_NEIGHBOUR_MAX_STOPS:
        candidates["nearest-neighbour"] = _nearest_neighbour(stops, motion, start)
    seconds = {k: motion.tour_s(v, start) for k, v in candidates.items()}
    best = min(candidates, key=lambda k: (seconds[k], ORDER_HEURISTICS.index(k)))
    return candidates[best], seconds


# --------------------------------------------------------------------------- planned views
@dataclass
class PlannedStop:
    """A stop chosen by a view planner, and why.

    Attributes
    ----------
    pan_deg, tilt_deg : float, deg
    gain_mm3 : float, mm³
        Unsure hull volume the planner predicts this stop carves (beyond the stops
        chosen before it in the same round).
    reason : str
        One sentence for a person: what the stop is expected to carve and where.
    index : int
        Its ``angle_index`` once recorded in the scan folder (-1 before).
    """

    pan_deg: float
    tilt_deg: float
    gain_mm3: float = 0.0
    reason: str = ""
    index: int = -1

    @property
    def stop(self) -> Stop:
        return Stop(_pan(self.pan_deg), float(self.tilt_deg), int(self.index))

    def to_dict(self) -> dict[str, Any]:
        return {"pan_deg": float(self.pan_deg), "tilt_deg": float(self.tilt_deg),
                "angle_index": int(self.index), "gain_mm3": float(self.gain_mm3),
                "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlannedStop:
        return cls(float(d["pan_deg"]), float(d["tilt_deg"]), float(d.get("gain_mm3", 0.0)),
                   str(d.get("reason", "")), int(d.get("angle_index", -1)))


@dataclass
class PlannedRound:
    """One round of an adaptive scan as recorded in ``planned_views.jsonl``.

    Attributes
    ----------
    round : int
        1 for the first planned round.
    stops : list of PlannedStop
        With their ``index`` (``angle_index``) set; empty for a closing round.
    planner : str
        The plugin that planned them.
    stop_reason : str or None
        Set on the round that ends the adaptive scan: why (budget spent, gain small).
    figures : dict
        What the planner and the quick processing said (unsure volume, seconds...).
    created : str
        ISO 8601 time stamp.
    """

    round: int
    stops: list[PlannedStop] = field(default_factory=list)
    planner: str = ""
    stop_reason: str | None = None
    figures: dict[str, Any] = field(default_factory=dict)
    created: str = ""

    def to_dict(self) -> dict[str, Any]:
        from plantscan_core.data import plain

        return {"round": int(self.round), "planner": self.planner, "created": self.created,
                "stop_reason": self.stop_reason, "stops": [s.to_dict() for s in self.stops],
                "figures": plain(self.figures)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlannedRound:
        return cls(int(d["round"]), [PlannedStop.from_dict(s) for s in d.get("stops") or []],
                   str(d.get("planner", "")), d.get("stop_reason"),
                   dict(d.get("figures") or {}), str(d.get("created", "")))


@dataclass
class PlanRequest:
    """What the core asks a view planner for.

    Attributes
    ----------
    candidates : list of Stop
        Rig positions the planner may choose from (within the rig's limits, at
        tilts with background plates, not yet captured).
    cameras : list of str
        The cameras that take an image at every stop.
    max_stops : int
        Choose at most this many stops.
    max_seconds : float or None, s
        Capture time budget of the chosen stops (``seconds_of``).
    seconds_of : callable (list of Stop) -> float
        Capture time of a set of stops, ordered, by the rig's timing model.
    final_views : int
        How many plant views the scan will have once the chosen stops are
        taken (the reconstructor's ``k: auto`` depends on it).
    """

    candidates: list[Stop]
    cameras: list[str]
    max_stops: int
    max_seconds: float | None = None
    seconds_of: Callable[[list[Stop]], float] = field(default=lambda stops: 0.0)
    final_views: int = 0


@dataclass
class ViewPlan:
    """A view planner's answer: the stops to take next, in the order they were chosen.

    Attributes
    ----------
    stops : list of PlannedStop
    unsure_volume_mm3 : float, mm³
        Hull volume the planner found unsure (possibly phantom).
    hull_volume_mm3 : float, mm³
    predicted_carve_mm3 : float, mm³
        Unsure volume the chosen stops are predicted to carve (outside in more
        than k views once they are taken).
    capture_s : float, s
        Capture time of the chosen stops by the timing model.
    seconds : float, s
        Planner time (wall).
    figures : dict
        Other figures of the planner.
    """

    stops: list[PlannedStop] = field(default_factory=list)
    unsure_volume_mm3: float = 0.0
    hull_volume_mm3: float = 0.0
    predicted_carve_mm3: float = 0.0
    capture_s: float = 0.0
    seconds: float = 0.0
    figures: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        from plantscan_core.data import plain

        return {"stops": [s.to_dict() for s in self.stops],
                "unsure_volume_mm3": float(self.unsure_volume_mm3),
                "hull_volume_mm3": float(self.hull_volume_mm3),
                "predicted_carve_mm3": float(self.predicted_carve_mm3),
                "capture_s": float(self.capture_s), "seconds": float(self.seconds),
                "figures": plain(self.figures)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewPlan:
        return cls([PlannedStop.from_dict(s) for s in d.get("stops") or []],
                   float(d.get("unsure_volume_mm3", 0.0)), float(d.get("hull_volume_mm3", 0.0)),
                   float(d.get("predicted_carve_mm3", 0.0)), float(d.get("capture_s", 0.0)),
                   float(d.get("seconds", 0.0)), dict(d.get("figures") or {}))

"""How long a scan takes on the rig a recipe describes (``plantscan scan --dry-run``).

The model follows the acquisition orchestrator's timeline (``acquire.py``):
for each stop, the rig moves (tilt arm, then turntable: trapezoidal velocity
profiles from each axis's velocity and acceleration, plus its settle time)
while the cameras download the previous stop's images; then every camera is
triggered at once.  So a stop costs

    max(move + settle, slowest download of the previous stop) + slowest capture

and the last stop of each role adds its downloads (they are committed before
the operator is asked to change the set-up).  For comparison, ``sequential_s``
is the same protocol done one thing after another (move, settle, then each
camera's capture and download in turn), as simple tethering scripts do.

Timing parameters come from each plugin's ``Params``, by name:

* cameras: ``capture_s`` (shutter release to image in the camera) and
  ``download_s`` (to the computer);
* axes: ``velocity_deg_s``, ``acceleration_deg_s2``, ``settle_s`` and optionally
  ``approach_deg`` (backward moves overshoot and come back: anti-backlash).

A camera whose time is not a parameter may say it with a classmethod
``capture_time_s(params, image_size, role) -> float`` (the virtual scanner's
camera: its render time, from the image size).  A plugin with neither counts
as instantaneous and is listed in ``unmodelled``.  Operator time between roles
is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from plantscan_core.recipe import Recipe, StageSpec


def move_time_s(distance_deg: float, velocity_deg_s: float, acceleration_deg_s2: float) -> float:
    """Duration (s) of a trapezoidal velocity profile over ``distance_deg``.

    Accelerates at ``acceleration_deg_s2`` to ``velocity_deg_s``, cruises and
    decelerates; a move too short to reach full speed is a triangle.
    """
    d = abs(distance_deg)
    if d == 0.0:
        return 0.0
    if math.isinf(velocity_deg_s) or math.isinf(acceleration_deg_s2):
        return 0.0
    d_ramps = velocity_deg_s * velocity_deg_s / acceleration_deg_s2
    if d <= d_ramps:
        return 2.0 * math.sqrt(d / acceleration_deg_s2)
    return 2.0 * velocity_deg_s / acceleration_deg_s2 + (d - d_ramps) / velocity_deg_s


@dataclass(frozen=True)
class AxisTiming:
    velocity_deg_s: float = math.inf
    acceleration_deg_s2: float = math.inf
    settle_s: float = 0.0
    approach_deg: float = 0.0  # backward moves overshoot by this, then come back

    def move_s(self, distance_deg: float) -> float:
        if distance_deg == 0.0:
            return 0.0
        t = move_time_s(distance_deg, self.velocity_deg_s, self.acceleration_deg_s2)
        if distance_deg < 0 and self.approach_deg > 0:
            a = self.approach_deg
            t = (move_time_s(abs(distance_deg) + a, self.velocity_deg_s, self.acceleration_deg_s2)
                 + move_time_s(a, self.velocity_deg_s, self.acceleration_deg_s2))
        return t + self.settle_s


@dataclass(frozen=True)
class CameraTiming:
    capture_s: float = 0.0
    download_s: float = 0.0
    by_role: tuple[tuple[str, float], ...] = ()  # capture time of a role, when it differs

    def capture_for(self, role: str) -> float:
        return dict(self.by_role).get(role, self.capture_s)


@dataclass
class RoleTime:
    """Time of one role of the protocol (s)."""

    role: str
    stops: int = 0
    images: int = 0
    move_s: float = 0.0
    capture_s: float = 0.0
    download_wait_s: float = 0.0
    total_s: float = 0.0
    sequential_s: float = 0.0


@dataclass
class ScanTimeEstimate:
    """Estimated duration of a scan, per role, with and without overlap.

    Attributes
    ----------
    roles : list of RoleTime
    total_s : float, s — with this orchestrator (concurrent triggers, downloads during moves)
    sequential_s : float, s — one thing after another
    images : int
    unmodelled : list of str — devices whose plugin has no timing parameters (counted as 0 s)
    """

    roles: list[RoleTime] = field(default_factory=list)
    total_s: float = 0.0
    sequential_s: float = 0.0
    images: int = 0
    unmodelled: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        head = f"{'role':<12}{'stops':>6}{'images':>7}{'moving':>10}{'capture':>10}" \
               f"{'download*':>11}{'total':>10}{'sequential':>12}"
        lines = [head, "-" * len(head)]
        for r in self.roles:
            lines.append(f"{r.role:<12}{r.stops:>6}{r.images:>7}{_fmt(r.move_s):>10}"
                         f"{_fmt(r.capture_s):>10}{_fmt(r.download_wait_s):>11}"
                         f"{_fmt(r.total_s):>10}{_fmt(r.sequential_s):>12}")
        lines.append("-" * len(head))
        lines.append(f"{'scan':<12}{sum(r.stops for r in self.roles):>6}{self.images:>7}"
                     f"{'':>10}{'':>10}{'':>11}{_fmt(self.total_s):>10}"
                     f"{_fmt(self.sequential_s):>12}")
        lines.append("* download time not hidden behind a move. 'sequential' = move, then each "
                     "camera's capture and download in turn.")
        if self.sequential_s > 0:
            saved = 1.0 - self.total_s / self.sequential_s
            lines.append(f"Overlapping downloads with moves and triggering cameras together "
                         f"saves {saved:.0%} ({_fmt(self.sequential_s - self.total_s)}).")
        if self.unmodelled:
            lines.append("No timing parameters (counted as instantaneous): "
                         + ", ".join(self.unmodelled))
        return "\n".join(lines)


def _fmt(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    m, s = divmod(round(seconds), 60)
    if m < 60:
        return f"{m}:{s:02d} min"
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d} h"


def _params(spec: StageSpec, stage: str, registry) -> Any | None:
    if registry is None:
        return None
    try:
        cls = registry.get(stage, spec.plugin).cls
    except Exception:  # noqa: BLE001 - an unknown plugin is reported by recipe validation
        return None
    return cls.Params(**spec.params)


def _axis_timing(spec: StageSpec | None, what: str, registry, unmodelled: list[str]):
    if spec is None:
        return AxisTiming()
    p = _params(spec, "axis", registry)
    v = getattr(p, "velocity_deg_s", None)
    a = getattr(p, "acceleration_deg_s2", None)
    if v is None or a is None:
        unmodelled.append(f"{what} ({spec.plugin})")
        return AxisTiming()
    return AxisTiming(float(v), float(a), float(getattr(p, "settle_s", 0.0) or 0.0),
                      float(getattr(p, "approach_deg", 0.0) or 0.0))


def _camera_timing(spec, registry, unmodelled: list[str],
                   image_size: tuple[int, int] = (0, 0)) -> CameraTiming:
    p = _params(spec, "camera", registry)
    c = getattr(p, "capture_s", None)
    d = getattr(p, "download_s", None)
    if c is None and d is None:
        model = getattr(registry.get("camera", spec.plugin).cls, "capture_time_s", None) \
            if p is not None else None
        if model is not None:
            return CameraTiming(model(p, image_size, "plant"), 0.0, tuple(
                (role, model(p, image_size, role)) for role in ("calibration", "background")))
        unmodelled.append(f"camera {spec.name} ({spec.plugin})")
        return CameraTiming()
    return CameraTiming(float(c or 0.0), float(d or 0.0))


def rig_motion(recipe: Recipe, registry=None):
    """The rig's ``trajectory.MotionModel``: axis timings and the slowest camera's times.

    ``registry`` as in ``estimate_scan_time``; devices without timing parameters
    count as instantaneous.
    """
    from plantscan_core.trajectory import MotionModel

    registry = registry if registry is not None else _default_registry()
    unmodelled: list[str] = []
    cams = [_camera_timing(c, registry, unmodelled) for c in recipe.scan.cameras]
    return MotionModel(_axis_timing(recipe.scan.turntable, "turntable", registry, unmodelled),
                       _axis_timing(recipe.scan.tilt_arm, "tilt_arm", registry, unmodelled),
                       max(c.capture_s for c in cams), max(c.download_s for c in cams))


def _default_registry():
    from plantscan_core.plugins import get_manager

    return get_manager().registry


def estimate_scan_time(recipe: Recipe, registry=None, planned=()) -> ScanTimeEstimate:
    """Estimate how long acquiring ``recipe``'s protocol takes (see the module docstring).

    Parameters
    ----------
    recipe : Recipe
    registry : StageRegistry, optional
        Where the plugins' ``Params`` are looked up; default: every installed plugin.
    planned : sequence of lists of trajectory.Stop
        Rounds of planned plant stops to take after the protocol's (``acquire.plan``).
    """
    from plantscan_core.acquire import plan, stops

    if registry is None:
        registry = _default_registry()
    unmodelled: list[str] = []
    turntable = _axis_timing(recipe.scan.turntable, "turntable", registry, unmodelled)
    tilt_arm = _axis_timing(recipe.scan.tilt_arm, "tilt_arm", registry, unmodelled)
    cams = {c.name: _camera_timing(c, registry, unmodelled, tuple(recipe.scan.image_size))
            for c in recipe.scan.cameras}

    est = ScanTimeEstimate(unmodelled=unmodelled)
    by_role: dict[str, RoleTime] = {}
    angle = 0.0  # after homing
    tilt = 0.0
    prev_download = 0.0  # slowest pending download of the previous stop
    prev_role = None
    for group in stops(plan(recipe, registry, planned)):
        v = group[0]
        row = by_role.setdefault(v.role, RoleTime(v.role))
        if v.role != prev_role and prev_role is not None:
            by_role[prev_role].download_wait_s += prev_download  # committed before the prompt
            by_role[prev_role].total_s += prev_download
            prev_download = 0.0
        prev_role = v.role
        move = 0.0
        if v.tilt_deg != tilt:
            move += tilt_arm.move_s(v.tilt_deg - tilt)
            tilt = v.tilt_deg
        if v.angle_deg != angle:
            move += turntable.move_s(v.angle_deg - angle)
            angle = v.angle_deg
        capture = max(cams[g.camera].capture_for(v.role) for g in group)
        wait = max(0.0, prev_download - move)
        row.stops += 1
        row.images += len(group)
        row.move_s += move
        row.capture_s += capture
        row.download_wait_s += wait
        row.total_s += move + wait + capture
        row.sequential_s += move + sum(cams[g.camera].capture_for(v.role)
                                       + cams[g.camera].download_s for g in group)
        prev_download = max(cams[g.camera].download_s for g in group)
    if prev_role is not None:
        by_role[prev_role].download_wait_s += prev_download
        by_role[prev_role].total_s += prev_download
    est.roles = list(by_role.values())
    est.total_s = sum(r.total_s for r in est.roles)
    est.sequential_s = sum(r.sequential_s for r in est.roles)
    est.images = sum(r.images for r in est.roles)
    return est

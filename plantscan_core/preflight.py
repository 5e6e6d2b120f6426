"""Time and memory estimates checked before any motor moves or any stage starts.

A recipe that asks for more than the machine holds (``scan.image_size:
[100000, 100000]``, ``reconstruct.params.resolution: 1024`` on a small
machine) used to start, create its folders and fail minutes later on an
allocation.  Each stage may say what it will need: a stage class with a
classmethod ``estimate(params, plan: WorkPlan) -> WorkEstimate | None``.
``check`` refuses a plan whose peak exceeds the memory available (with the
estimate and the parameter to change; ``--force`` goes on) and warns above
``WARN_FRACTION`` of it or above ``WARN_SECONDS``.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from plantscan_core.errors import PlantScanError

FORCE_ENV = "PLANTSCAN_FORCE"
"""Set (to 1) by ``--force``: refusals become warnings, here and inside the stages."""

WARN_FRACTION = 0.5
"""Warn when a stage's peak is above this share of the memory available."""

WARN_SECONDS = 120.0
"""Warn when a stage is estimated to take longer than this."""


class ResourceError(PlantScanError):
    """A stage would need more memory than the machine has."""


@dataclass(frozen=True)
class WorkPlan:
    """What processing will be fed, known before it starts.

    Attributes
    ----------
    plant_views : int
        Plant images the segmenter and reconstructor see.
    image_size : (int, int), px
        Width and height of the plant images as decoded (after ``segment.reduce``).
    plant_pixels : int or None
        Pixels of the plant boxes summed over the views, when masks are known;
        None: the whole images (an upper bound).
    workers : int
        Images processed at once.
    capture_size : (int, int) or None, px
        Width and height of the images as captured (acquisition), when known.
    """

    plant_views: int
    image_size: tuple[int, int]
    plant_pixels: int | None = None
    workers: int = 2
    capture_size: tuple[int, int] | None = None


@dataclass(frozen=True)
class WorkEstimate:
    """A stage's estimated peak memory (above what the process held before) and time.

    ``parameter`` is the recipe path a user changes to need less.
    """

    stage: str
    what: str
    peak_bytes: int
    seconds: float | None
    parameter: str

    def describe(self) -> str:
        t = "" if self.seconds is None else f" and ~{_duration(self.seconds)}"
        return f"{self.stage}: {self.what} needs about {_gb(self.peak_bytes)} at its peak{t}"


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def _duration(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min"


def available_memory_bytes() -> int:
    """Memory a new allocation can get without swapping (``MemAvailable``), bytes."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def forced() -> bool:
    return os.environ.get(FORCE_ENV, "") not in ("", "0")


def check(estimates: Iterable[WorkEstimate | None], available: int | None = None,
          force: bool | None = None) -> list[str]:
    """Refuse (``ResourceError``) or warn about estimates; returns the warnings printed."""
    available = available_memory_bytes() if available is None else available
    force = forced() if force is None else force
    warnings, refusals = [], []
    for est in estimates:
        if est is None:
            continue
        if est.peak_bytes > available:
            line = (f"{est.describe()}; {_gb(available)} is available: lower "
                    f"{est.parameter}")
            (warnings if force else refusals).append(line + (" (--force: going on)"
                                                             if force else ""))
        elif est.peak_bytes > WARN_FRACTION * available or (
                est.seconds is not None and est.seconds > WARN_SECONDS):
            warnings.append(f"{est.describe()} ({_gb(available)} available)")
    for w in warnings:
        print(f"plantscan: warning: {w}", file=sys.stderr)
    if refusals:
        raise ResourceError("\n".join(refusals) + "\n(the estimate is conservative; pass "
                            "--force to try anyway)")
    return warnings


def recipe_estimates(recipe, registry, plan: WorkPlan) -> list[WorkEstimate]:
    """The estimates of the scene and every processing stage of ``recipe`` that can give one."""
    from plantscan_core.recipe import PROCESSING_SECTIONS

    out = []
    sections = [("scene", "scene", recipe.scan.scene)] + [
        (section, stage, getattr(recipe, section, None))
        for section, stage in PROCESSING_SECTIONS.items()]
    for _, stage, spec in sections:
        if spec is None:
            continue
        try:
            cls = registry.get(stage, spec.plugin).cls
        except PlantScanError:
            continue  # the recipe check names it
        estimate = getattr(cls, "estimate", None)
        if estimate is None:
            continue
        est = estimate(cls.Params.model_validate(spec.params), plan)
        if est is not None:
            out.append(est)
    return out


def auto_reduce(long_side_px: int, min_long_side_px: int) -> int:
    """``segment.reduce: auto``: the largest of 8, 4, 2 keeping the long side >= the minimum."""
    for r in (8, 4, 2):
        if long_side_px / r >= min_long_side_px:
            return r
    return 1


def recipe_plan(recipe, image_size: tuple[int, int] | None = None, workers: int = 2) -> WorkPlan:
    """The ``WorkPlan`` of a recipe's plant role (``image_size`` as captured, default the
    recipe's), at the size the segmenter decodes (``segment.reduce``)."""
    from plantscan_core.pipeline import AUTO_REDUCE_MIN_LONG_SIDE_PX

    scan = recipe.scan
    w, h = image_size or scan.image_size
    views = len(scan.cameras) * len(scan.role_stops("plant"))
    if scan.adaptive is not None:  # an adaptive scan may grow to its image budget
        views = max(views, scan.adaptive.max_plant_images)
    reduce = recipe.segment.reduce if recipe.segment is not None else 1
    if reduce == "auto":
        reduce = auto_reduce(max(w, h), AUTO_REDUCE_MIN_LONG_SIDE_PX)
    return WorkPlan(plant_views=views, image_size=(-(-w // reduce), -(-h // reduce)),
                    workers=workers, capture_size=(w, h))


def check_recipe(recipe, registry, image_size: tuple[int, int] | None = None) -> list[str]:
    """``check`` of every estimate of the recipe's processing stages."""
    return check(recipe_estimates(recipe, registry, recipe_plan(recipe, image_size)))

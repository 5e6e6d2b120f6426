"""The ``next-best-view`` view planner (``plan: {plugin: next-best-view}``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from plantscan_core.data import Calibration, Silhouettes, Volume
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import StageParams, ViewPlanner
from plantscan_core.trajectory import PlanRequest, ViewPlan
from plantscan_plan.nbv import Planner


class NextBestView(ViewPlanner):
    """Lazy-greedy choice of the stops predicted to carve the most unsure hull volume
    (``plantscan_plan.nbv``; docs/trajectories.md)."""

    name = "next-best-view"

    class Params(StageParams):
        resolution: int = Field(
            128, ge=16, le=1024, description="the hull is pooled to at most this many voxels "
            "along its longest side before planning (a pooled voxel is inside when any of its "
            "voxels is)")
        certain_run_mm: float = Field(
            8.0, gt=0.0, le=1000.0, description="a run of hull along a pixel ray at most this "
            "long holds the object for sure (thicker than a leaf slab and a stem, thinner than "
            "the phantom volume to find)")
        max_targets: int = Field(
            40_000, ge=100, le=10_000_000, description="unsure voxels are pooled 2x, 4x... "
            "until at most this many are projected into every candidate view")
        margin_px: int = Field(1, ge=0, le=10, description="predicted silhouettes are grown "
                               "by this many planning pixels (one planning pixel ~ one voxel)")
        k: Annotated[int, Field(ge=0)] | Literal["recipe"] = Field(
            "recipe", description="a voxel is carved once outside in more than k views; "
            "'recipe': the recipe's reconstruct k at the scan's final number of views")
        pot: Literal["auto", "none"] = Field(
            "auto", description="'auto': the pot fitted from the hull is never a target "
            "(plantscan_hull.pot.fit_pot)")

    def plan(self, volume: Volume, silhouettes: Silhouettes, calibration: Calibration,
             request: PlanRequest) -> ViewPlan:
        p = self.params
        k = self._k(request)
        cylinders = []
        if p.pot == "auto":
            from plantscan_hull.pot import fit_pot

            cylinders = fit_pot(volume)
        planner = Planner(p.certain_run_mm, p.margin_px, p.resolution, p.max_targets)
        plan = planner.plan(volume, silhouettes, calibration, request, k, cylinders)
        self.report.count("candidates", len(request.candidates))
        self.report.count("stops", len(plan.stops))
        self.report.note({"k": k, "unsure_volume_mm3": round(plan.unsure_volume_mm3, 1),
                          "hull_volume_mm3": round(plan.hull_volume_mm3, 1),
                          "predicted_carve_mm3": round(plan.predicted_carve_mm3, 1),
                          "capture_s": round(plan.capture_s, 2),
                          "planner_seconds": round(plan.seconds, 3)})
        if not plan.stops and plan.unsure_volume_mm3 > 0:
            self.report.warn("no-planned-view", f"{plan.unsure_volume_mm3:.0f} mm3 of the hull "
                             "is unsure but no candidate stop within the budgets is predicted "
                             "to carve it")
        return plan

    def _k(self, request: PlanRequest) -> int:
        if self.params.k != "recipe":
            return int(self.params.k)
        recipe = self.context.recipe
        k = (recipe.reconstruct.params.get("k", "auto")
             if recipe is not None and recipe.reconstruct is not None else "auto")
        from plantscan_hull.stages import resolve_k

        return resolve_k(k, max(1, request.final_views))


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(NextBestView)

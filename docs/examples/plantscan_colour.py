"""A new processing stage in one file: the plant's colour, from the photos inside its masks.

Colour (greenness, yellowing) is a trait of its own.  This plugin adds a stage
``colour`` that runs after ``segment``: it reads the plant photos (the very ones
segmentation decoded, not a second decode) inside each view's mask and writes
``colour.json`` into the run folder.

A stage is one base class (its contract), one ``Step`` in the stage table (where
it runs, what it needs, how its result is saved and read back) and one recipe
section::

    colour: {plugin: mean-colour}
"""

from __future__ import annotations

import abc
import json

import numpy as np
from pydantic import Field

from plantscan_core.data import Silhouettes
from plantscan_core.hookspecs import hookimpl
from plantscan_core.photos import Photos
from plantscan_core.scanfolder import atomic_write_text
from plantscan_core.stages import Stage, StageParams
from plantscan_core.steps import Step, StepRun


class ColourMeasurer(Stage):
    """``measure(photos, silhouettes) -> dict``: colour figures of the plant's pixels."""

    stage = "colour_measurer"

    @abc.abstractmethod
    def measure(self, photos: Photos, silhouettes: Silhouettes) -> dict[str, float]:
        """Colour of the plant pixels of every view (``photos.image(i)`` is view ``i``'s)."""


class MeanColour(ColourMeasurer):
    """Mean red, green, blue (0-255) and excess green ``2g - r - b`` of the plant's pixels."""

    name = "mean-colour"

    class Params(StageParams):
        min_plant_px: int = Field(50, ge=1, description="a view with fewer plant pixels is "
                                  "left out (and named in a warning)")

    def measure(self, photos: Photos, silhouettes: Silhouettes) -> dict[str, float]:
        bgr_sum, pixels = np.zeros(3), 0
        for i, sil in enumerate(silhouettes):
            if sil.area < self.params.min_plant_px:
                self.report.warn("few-plant-pixels", f"view {sil.view.index}: {sil.area} "
                                 "plant pixels, left out", view=sil.view.index,
                                 file=sil.view.file)
                continue
            h, w = sil.crop.shape
            inside = photos.image(i)[sil.v0:sil.v0 + h, sil.u0:sil.u0 + w][sil.crop]
            bgr_sum += inside.sum(axis=0)
            pixels += sil.area
        self.report.count("plant_pixels", pixels)
        b, g, r = (float(c) for c in bgr_sum / max(pixels, 1))
        return {"red": r, "green": g, "blue": b, "excess_green": 2 * g - r - b}


def measure_colour(plugin: ColourMeasurer, run: StepRun) -> dict[str, float]:
    colour = plugin.measure(run.context.photos, run.results["silhouettes"])
    atomic_write_text(run.path("colour.json"), json.dumps(colour, indent=2))
    return colour


COLOUR_STEP = Step(
    "colour", ColourMeasurer, "colour", measure_colour,
    load=lambda run: json.loads(run.path("colour.json").read_text()),
    needs=("silhouettes",), files=lambda run: [run.path("colour.json")], photos="segment")


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add_step(COLOUR_STEP, after="segment")
    registry.add(MeanColour)

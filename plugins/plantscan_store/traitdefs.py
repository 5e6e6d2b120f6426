"""The observed variables the store knows: name, level, unit, what it is (MIAPPE trait dictionary).

A trait a run reports that is not listed here is stored all the same, with
the unit its name ends in (``_mm``, ``_mm2``, ``_mm3``; else ``1``) and no
description, and it appears in the ISA-Tab trait dictionary that way.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TraitDefinition:
    name: str
    level: str  # "leaf" or "plant"
    unit: str
    description: str
    method: str = ""


_FLAT = ("flat-leaf measurement of the reconstructed leaf surface (as if dissected onto a "
         "flatbed scanner; docs/leaves.md)")
TRAITS: tuple[TraitDefinition, ...] = (
    TraitDefinition("length_mm", "leaf", "mm", "leaf blade length, base to tip along the "
                    "midrib", _FLAT),
    TraitDefinition("width_mm", "leaf", "mm", "largest blade width across the midrib", _FLAT),
    TraitDefinition("area_mm2", "leaf", "mm2", "one-sided blade area", _FLAT),
    TraitDefinition("perimeter_mm", "leaf", "mm", "blade outline length", _FLAT),
    TraitDefinition("thick_share", "leaf", "1", "share of the leaf's area where the hull is "
                    "over 3x its median thickness (phantom volume or a fused organ): a quality "
                    "figure, not a trait"),
    TraitDefinition("confidence", "leaf", "1", "how far to trust the leaf's measurements "
                    "(0-1), from the measurer"),
    TraitDefinition("height_mm", "plant", "mm", "plant height: vertical extent of the "
                    "reconstructed plant, pot removed",
                    "highest minus lowest point of the plant surface"),
    TraitDefinition("total_leaf_area_mm2", "plant", "mm2", "sum of the one-sided areas of the "
                    "leaves found", _FLAT),
    TraitDefinition("leaf_count", "plant", "1", "number of leaves found"),
    TraitDefinition("convex_hull_volume_mm3", "plant", "mm3", "volume of the convex hull of "
                    "the plant surface"),
    TraitDefinition("projected_area_mm2", "plant", "mm2", "area of the plant seen from "
                    "above (top view)"),
)
BY_NAME = {t.name: t for t in TRAITS}


def definition(name: str, level: str) -> TraitDefinition:
    """The definition of ``name``, or one made from its unit suffix."""
    if name in BY_NAME:
        return BY_NAME[name]
    unit = next((u for suffix, u in (("_mm3", "mm3"), ("_mm2", "mm2"), ("_mm", "mm"),
                                     ("_deg", "deg")) if name.endswith(suffix)), "1")
    return TraitDefinition(name, level, unit, "")

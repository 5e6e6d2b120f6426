"""The observed variables the store knows: name, level, unit, what it is (MIAPPE trait dictionary).

A trait a run reports that is not listed here is stored all the same, with
the unit its name ends in (``_mm``, ``_mm2``, ``_mm3``; else ``1``) and no
description, and it appears in the ISA-Tab trait dictionary that way.
"""

from __future__ import annotations

from dataclasses import dataclass

from plantscan_core.data import LEAF_COLUMNS, PLANT_TRAITS


@dataclass(frozen=True)
class TraitDefinition:
    name: str
    level: str  # "leaf" or "plant"
    unit: str
    description: str
    method: str = ""


# One definition per column of the core's traits tables (plantscan_core.data): a trait added
# there is defined here too.
TRAITS: tuple[TraitDefinition, ...] = tuple(
    TraitDefinition(c.name, c.level, c.unit, c.description, c.method)
    for c in (*LEAF_COLUMNS, *PLANT_TRAITS))
LEAF_NUMBERS = tuple(c.name for c in LEAF_COLUMNS if not c.is_text)
"""The leaf columns that are numbers: one column each in the store's ``leaves`` table."""
BY_NAME = {(t.name, t.level): t for t in TRAITS}  # quality_flag is both a leaf and a plant's


def definition(name: str, level: str) -> TraitDefinition:
    """The definition of ``name``, or one made from its unit suffix."""
    if (name, level) in BY_NAME:
        return BY_NAME[name, level]
    unit = next((u for suffix, u in (("_mm3", "mm3"), ("_mm2", "mm2"), ("_mm", "mm"),
                                     ("_deg", "deg")) if name.endswith(suffix)), "1")
    return TraitDefinition(name, level, unit, "")

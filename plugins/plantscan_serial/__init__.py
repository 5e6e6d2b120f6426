"""plantscan motion axes on serial controllers: GRBL-style G-code stages (``plugin: grbl``)."""

from plantscan_serial.grbl import GrblAxis, GrblError, GrblParams

__all__ = ["GrblAxis", "GrblError", "GrblParams"]

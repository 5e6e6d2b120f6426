"""plantscan motion axes on Phidget stepper controllers (``plugin: phidget``)."""

from plantscan_phidget.stepper import (
    Phidget22Port,
    PhidgetAxis,
    PhidgetAxisError,
    PhidgetParams,
    StepperPort,
    move_time_s,
    parse_gear_ratio,
)

__all__ = ["Phidget22Port", "PhidgetAxis", "PhidgetAxisError", "PhidgetParams", "StepperPort",
           "move_time_s", "parse_gear_ratio"]

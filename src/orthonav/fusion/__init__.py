"""Fusion: the navigation filter (INS + visual fixes + frame-to-frame ground velocity) and the INS
drift model for the simulator."""

from orthonav.fusion.filter import FilterConfig, FixOutcome, NavFilter, NavState, VelocityOutcome
from orthonav.fusion.ins import IMU_PRESETS, ImuErrorModel, ImuErrors, InsSample, InsSimulator

__all__ = [
    "IMU_PRESETS",
    "FilterConfig",
    "FixOutcome",
    "ImuErrorModel",
    "ImuErrors",
    "InsSample",
    "InsSimulator",
    "NavFilter",
    "NavState",
    "VelocityOutcome",
]

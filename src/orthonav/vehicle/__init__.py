"""A simulated vehicle speaking MAVLink as an autopilot does (``orthonav sim-vehicle``), and the
loopback that flies the companion against it in one process, for tests and benchmarks."""

from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

__all__ = ["SimVehicle", "SimVehicleConfig"]

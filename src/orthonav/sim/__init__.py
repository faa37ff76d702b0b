"""Simulation: synthetic terrain, vehicle kinematics and the mission loop driver."""

from orthonav.sim.demo import run_demo
from orthonav.sim.kinematics import Kinematics, Motion
from orthonav.sim.mission import SIMULATED_WORLD, MissionConfig, MissionResult, run_mission
from orthonav.sim.terrain import TerrainConfig, render_terrain, write_terrain_geotiff

__all__ = [
    "SIMULATED_WORLD",
    "Kinematics",
    "MissionConfig",
    "MissionResult",
    "Motion",
    "TerrainConfig",
    "render_terrain",
    "run_demo",
    "run_mission",
    "write_terrain_geotiff",
]

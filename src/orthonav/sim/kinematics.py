"""True horizontal motion of a simulated vehicle, and what its IMU would sense.

Both drivers of the navigation loop fly with it: the mission simulator and the simulated
MAVLink vehicle. The vehicle holds a constant ground speed and turns towards a commanded
heading at a limited rate (a coordinated turn), so the accelerations an INS integrates are
those of a real flight path: none on straight legs, centripetal ones in turns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from orthonav.errors import OrthonavError
from orthonav.geo import destination

SUBSTEP_S = 0.1  # integration step of a turn; a straight leg is one geodesic step


@dataclass(frozen=True)
class Motion:
    """Mean nav-frame acceleration and yaw rate over one step, and the velocity at its end."""

    accel_east_mps2: float
    accel_north_mps2: float
    yaw_rate_dps: float
    vel_east_mps: float
    vel_north_mps: float


@dataclass
class Kinematics:
    """Position, heading and clock of a vehicle flying at ``speed_mps`` over the ground."""

    lat: float
    lon: float
    heading_deg: float
    speed_mps: float
    time_s: float = 0.0
    max_turn_rate_dps: float = 15.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_mps) and self.speed_mps >= 0):
            raise OrthonavError(f"vehicle speed: expected metres per second >= 0, got {self.speed_mps}")
        if not (math.isfinite(self.max_turn_rate_dps) and self.max_turn_rate_dps > 0):
            raise OrthonavError(
                f"vehicle turn rate: expected degrees per second > 0, got {self.max_turn_rate_dps}"
            )

    @property
    def velocity_en_mps(self) -> tuple[float, float]:
        heading = math.radians(self.heading_deg)
        return self.speed_mps * math.sin(heading), self.speed_mps * math.cos(heading)

    def advance(self, dt_s: float, commanded_heading_deg: float) -> Motion:
        """Fly ``dt_s`` seconds, turning towards ``commanded_heading_deg`` as fast as allowed."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise OrthonavError(f"vehicle step: expected seconds > 0, got {dt_s}")
        start_velocity = self.velocity_en_mps
        start_heading = self.heading_deg
        remaining = dt_s
        while remaining > 1e-9:
            step = min(SUBSTEP_S, remaining) if self._turn_left(commanded_heading_deg) else remaining
            self._step(step, commanded_heading_deg)
            remaining -= step
        self.time_s += dt_s
        end_velocity = self.velocity_en_mps
        turned = _wrap180(self.heading_deg - start_heading)
        return Motion(
            (end_velocity[0] - start_velocity[0]) / dt_s,
            (end_velocity[1] - start_velocity[1]) / dt_s,
            turned / dt_s,
            *end_velocity,
        )

    def _turn_left(self, commanded_heading_deg: float) -> float:
        return _wrap180(commanded_heading_deg - self.heading_deg)

    def _step(self, dt_s: float, commanded_heading_deg: float) -> None:
        """Turn for ``dt_s`` then move along the mean heading of the step (midpoint rule)."""
        error = self._turn_left(commanded_heading_deg)
        turn = math.copysign(min(abs(error), self.max_turn_rate_dps * dt_s), error)
        mid_heading = self.heading_deg + turn / 2.0
        self.lat, self.lon = destination(self.lat, self.lon, mid_heading % 360.0, self.speed_mps * dt_s)
        self.heading_deg = (self.heading_deg + turn) % 360.0


def _wrap180(angle_deg: float) -> float:
    return (angle_deg + 180.0) % 360.0 - 180.0

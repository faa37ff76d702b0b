"""Is the autopilot's velocity plausible? The checks its own EKF makes of a sensor, made of it.

Dead reckoning integrates the velocity the autopilot reports, so one wrong velocity moves our
position by its error times the time it lasts, and the filter then gates out the right visual
fixes as outliers. Each new telemetry sample's velocity (LOCAL_POSITION_NED's float one, else
GLOBAL_POSITION_INT's cm/s one) is checked against:

- the vehicle class: a speed beyond what it can fly;
- innovation gating: the change from the last accepted velocity, beyond what the class's
  acceleration allows in the time between them (plus the velocity's own noise);
- the autopilot's position: GLOBAL_POSITION_INT's displacement over the last second is its
  integrated velocity, so the reported velocity must match that mean within what the
  acceleration allows over half the window (plus a margin for the small steps an EKF makes
  when it fuses a position; a larger step, an EKF resetting onto another GPS, starts the window
  again rather than counting as speed);
- each other: LOCAL_POSITION_NED and GLOBAL_POSITION_INT come from the same EKF, so two
  velocities that both pass but disagree leave no way to tell which is right.

A source that fails is not used; if none passes, the sample is **rejected**: the last accepted
velocity is held in its place, with a 1-sigma of a third of the class's acceleration times the
time held (the acceleration bound taken as 3 sigma), which the filter adds to its velocity
uncertainty, so the accuracy it reports grows with what the vehicle could have done meanwhile.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

from orthonav.errors import OrthonavError, require_positive
from orthonav.geo import LocalFrame, distance_m

# MAV_TYPE of the vehicles that fly as planes: fixed wing, flapping wing and the VTOLs (19-25).
PLANE_MAV_TYPES = frozenset({1, 16, *range(19, 26)})
VELOCITY_NOISE_MPS = 1.0  # an EKF's velocity jitter plus GLOBAL_POSITION_INT's cm/s rounding
POSITION_WINDOW_S = 1.0  # the autopilot's displacement over this long gives its mean velocity
POSITION_MARGIN_M = 2.0  # a step of the autopilot's position (a fused GPS) not counted as speed
# A position this far from the local frame's origin starts a new frame: the autopilot's first
# reports may come before its EKF has an origin (ArduPlane's near 0 N 0 E, not exactly there).
REANCHOR_M = 10_000.0
HOLD_SIGMAS = 3.0  # the acceleration bound taken as this many sigma of what a held velocity misses
AUTO = "auto"


@dataclass(frozen=True)
class VehicleLimits:
    """What a vehicle class can do: a velocity beyond it is a fault, not a manoeuvre."""

    name: str
    max_speed_mps: float
    max_accel_mps2: float

    def __post_init__(self) -> None:
        require_positive(f"{self.name} limits", self, ("max_speed_mps", "max_accel_mps2"))


# A copter's horizontal acceleration at a 45 deg lean is 1 g; a plane's in a 60 deg banked turn
# about 1.7 g, and its ground speed includes the wind.
VEHICLE_CLASSES = {
    "copter": VehicleLimits("copter", max_speed_mps=40.0, max_accel_mps2=10.0),
    "plane": VehicleLimits("plane", max_speed_mps=80.0, max_accel_mps2=20.0),
}


@dataclass(frozen=True)
class Plausibility:
    """Which limits apply: a class, or ``auto`` (from the autopilot's HEARTBEAT type), and
    overrides of its speed and acceleration."""

    vehicle: str = AUTO
    max_speed_mps: float | None = None
    max_accel_mps2: float | None = None

    def __post_init__(self) -> None:
        choices = (AUTO, *VEHICLE_CLASSES)
        if self.vehicle not in choices:
            raise OrthonavError(f"vehicle {self.vehicle!r}: expected one of {', '.join(choices)}")
        self.limits(None)  # refuses bad overrides now, not at the first sample

    def limits(self, mav_type: int | None) -> VehicleLimits:
        """The limits for the vehicle; ``mav_type`` (HEARTBEAT's type) decides ``auto``: copter
        limits until a plane is heard."""
        name = self.vehicle
        if name == AUTO:
            name = "plane" if mav_type in PLANE_MAV_TYPES else "copter"
        base = VEHICLE_CLASSES[name]
        return VehicleLimits(
            name,
            base.max_speed_mps if self.max_speed_mps is None else self.max_speed_mps,
            base.max_accel_mps2 if self.max_accel_mps2 is None else self.max_accel_mps2,
        )


class Velocity(NamedTuple):
    """One source's horizontal velocity at its own time (companion UNIX seconds)."""

    source: str
    time_s: float
    east_mps: float
    north_mps: float

    def minus(self, east_mps: float, north_mps: float) -> float:
        return math.hypot(self.east_mps - east_mps, self.north_mps - north_mps)


@dataclass(frozen=True)
class Verdict:
    """The velocity to dead-reckon with, its extra 1-sigma, and what was refused.

    ``rejected`` says why no source was used (the velocity is held; NaN with an infinite sigma
    when none was ever accepted); ``note`` why a source was refused while another one was used.
    """

    east_mps: float
    north_mps: float
    sigma_mps: float = 0.0
    rejected: str | None = None
    note: str | None = None

    @property
    def usable(self) -> bool:
        return math.isfinite(self.sigma_mps)


class _Place(NamedTuple):
    time_s: float
    east_m: float
    north_m: float


class VelocityGuard:
    """Judges each new sample's velocities (see the module docstring); remembers the last
    accepted velocity and the autopilot's recent positions."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything: a new clock (a reboot) or a new start."""
        self._frame: LocalFrame | None = None
        self._places: deque[_Place] = deque()
        self.accepted: Velocity | None = None

    def judge(
        self, limits: VehicleLimits, time_s: float, lat: float, lon: float, candidates: list[Velocity]
    ) -> Verdict:
        """The verdict on the sample at ``time_s`` (the autopilot at ``lat``, ``lon``), sources in
        order of preference."""
        self._remember(time_s, lat, lon, limits)
        refusals = {c.source: self._problem(c, limits) for c in candidates}
        good = [c for c in candidates if refusals[c.source] is None]
        if len(good) == 2 and (mismatch := self._mismatch(*good, limits)) is not None:
            refusals[good[0].source], good = mismatch, []
        refused = "; ".join(f"{source}: {why}" for source, why in refusals.items() if why)
        if good:
            self.accepted = good[0]
            return Verdict(good[0].east_mps, good[0].north_mps, note=refused or None)
        if self.accepted is None:
            return Verdict(math.nan, math.nan, math.inf, rejected=refused)
        held_s = max(0.0, time_s - self.accepted.time_s)
        sigma = limits.max_accel_mps2 / HOLD_SIGMAS * held_s
        return Verdict(self.accepted.east_mps, self.accepted.north_mps, sigma, rejected=refused)

    def _remember(self, time_s: float, lat: float, lon: float, limits: VehicleLimits) -> None:
        """Keep the autopilot's position; after a step of it (or a new frame) the window starts
        again from here, so the step is not taken for speed."""
        if self._frame is None or distance_m(self._frame.lat0, self._frame.lon0, lat, lon) > REANCHOR_M:
            self._frame, self._places = LocalFrame(lat, lon), deque()
        east, north = self._frame.to_enu(lat, lon)
        place = _Place(time_s, float(east), float(north))
        if self._places and self._stepped(self._places[-1], place, limits):
            self._places.clear()
        self._places.append(place)
        while self._places[0].time_s < time_s - POSITION_WINDOW_S:
            self._places.popleft()

    def _stepped(self, last: _Place, place: _Place, limits: VehicleLimits) -> bool:
        """Whether the position moved, since the last sample, further from where the last accepted
        velocity puts it than the class's acceleration allows: the EKF reset its position (a GPS
        switched or re-detected). A velocity fault does not do this: the positions then go on
        following the accepted velocity, and the window refuses the faulty one."""
        if self.accepted is None:
            return False
        dt = max(0.0, place.time_s - last.time_s)
        missed = math.hypot(
            place.east_m - last.east_m - self.accepted.east_mps * dt,
            place.north_m - last.north_m - self.accepted.north_mps * dt,
        )
        return missed > POSITION_MARGIN_M + VELOCITY_NOISE_MPS * dt + limits.max_accel_mps2 * dt**2 / 2

    def _problem(self, velocity: Velocity, limits: VehicleLimits) -> str | None:
        """Why ``velocity`` is not plausible, or None."""
        speed = math.hypot(velocity.east_mps, velocity.north_mps)
        if not math.isfinite(speed):
            return "velocity not finite"
        if speed > limits.max_speed_mps:
            return f"{speed:.1f} m/s, beyond a {limits.name}'s {limits.max_speed_mps:g} m/s"
        return self._jump(velocity, limits) or self._off_track(velocity, limits)

    def _jump(self, velocity: Velocity, limits: VehicleLimits) -> str | None:
        """Innovation gate: the change from the last accepted velocity."""
        if self.accepted is None:
            return None
        dt = abs(velocity.time_s - self.accepted.time_s)
        change = velocity.minus(self.accepted.east_mps, self.accepted.north_mps)
        allowed = VELOCITY_NOISE_MPS + limits.max_accel_mps2 * dt
        if change <= allowed:
            return None
        return f"changed {change:.1f} m/s in {dt:.2f} s (a {limits.name} can {allowed:.1f})"

    def _off_track(self, velocity: Velocity, limits: VehicleLimits) -> str | None:
        """Against the autopilot's mean velocity over the window, from its own positions."""
        first, last = self._places[0], self._places[-1]
        span = last.time_s - first.time_s
        if span < POSITION_WINDOW_S / 2:
            return None
        east, north = (last.east_m - first.east_m) / span, (last.north_m - first.north_m) / span
        off = velocity.minus(east, north)
        allowed = (
            VELOCITY_NOISE_MPS
            + POSITION_MARGIN_M / span
            + limits.max_accel_mps2 * (span / 2 + abs(velocity.time_s - last.time_s))
        )
        if off <= allowed:
            return None
        moved = math.hypot(east, north)
        return f"{off:.1f} m/s off the autopilot's own track ({moved:.1f} m/s over {span:.1f} s)"

    def _mismatch(self, first: Velocity, second: Velocity, limits: VehicleLimits) -> str | None:
        """Two sources that both pass must agree, to within what the time between them allows."""
        differ = first.minus(second.east_mps, second.north_mps)
        allowed = VELOCITY_NOISE_MPS + limits.max_accel_mps2 * abs(first.time_s - second.time_s)
        if differ <= allowed:
            return None
        return f"{differ:.1f} m/s from {second.source}'s velocity: cannot tell which is right"

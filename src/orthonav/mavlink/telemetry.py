"""What the autopilot says about itself: newest telemetry, its age, and its clock.

The companion loop feeds every received message to :meth:`Telemetry.ingest` with the time it
arrived on the companion's UNIX clock (``time.time()``, the clock frame capture times are on).
Telemetry is taken from the autopilot component (component 1 unless named) of one system: the
one named, or the first that sent an autopilot HEARTBEAT.

Autopilot times (``time_boot_ms``) are mapped to UNIX seconds with SYSTEM_TIME (its
``time_unix_usec - time_boot_ms``) when the autopilot knows the UNIX time and it agrees with
the companion's clock; otherwise with the smallest recent ``arrival - time_boot_ms`` (the
least-delayed message), so samples and frames are always compared on one clock. Time jumps
are reported as :class:`TimeEvent`: a reboot (``time_boot_ms`` going backwards: everything
kept from the old boot is dropped), a boot clock leaping ahead of the arrival times, a UNIX
time jump in SYSTEM_TIME, and an autopilot UNIX clock that disagrees with the companion's.

One message stamped far ahead (a corrupt or mis-set ``time_boot_ms``) is not a jump: it is
dropped and held as a suspect; the next message decides. If it continues the leap, the boot
clock did jump; if it continues the old timeline, the leap is reported as ignored. A reboot or
a confirmed jump starts a new :attr:`Telemetry.epoch`: samples of different epochs are on
different clocks, so whoever integrates them must not integrate across the break.

The velocity of each new sample is judged by :class:`~orthonav.mavlink.plausibility.VelocityGuard`
(speed and acceleration for the vehicle class, the autopilot's own track, the two sources
against each other); a rejected one is replaced by the last plausible velocity, held with a
growing uncertainty.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple

from orthonav.fusion import InsSample
from orthonav.mavlink.plausibility import Plausibility, Velocity, VelocityGuard, Verdict

# The autopilot's UNIX time is used only where it agrees with ours this closely: frames are
# stamped by our clock, and a fix fused 0.8 s off its time is 8 m off at 10 m/s (ArduPilot
# SITL's GPS time runs that far behind the wall clock).
UNIX_MATCH_S = 0.1
ATTITUDE_KEEP_S = 10.0  # frames older than this are stale anyway
ATTITUDE_REACH_S = 0.5  # a frame further than this from every sample has no attitude of its time
ATTITUDE_SIGMA_DEG = 0.3  # an autopilot EKF's roll/pitch in steady flight
CAPTURE_TIME_SIGMA_S = 0.02  # a frame's capture time against the autopilot's clock
KEPT = (
    "HEARTBEAT",
    "ATTITUDE",
    "GLOBAL_POSITION_INT",
    "LOCAL_POSITION_NED",
    "VFR_HUD",
    "ALTITUDE",
    "SYSTEM_TIME",
    "GPS_GLOBAL_ORIGIN",
    "GPS_RAW_INT",
    "GPS2_RAW",
)
RECEIVER_MESSAGES = ("GPS_RAW_INT", "GPS2_RAW")  # ArduPilot's first and second GPS, by index
AUTOPILOT_COMPONENT = 1  # MAV_COMP_ID_AUTOPILOT1
AUTOPILOT_INVALID = 8  # MAV_AUTOPILOT_INVALID: a GCS or companion, not a vehicle
AUTOPILOT_ARDUPILOT = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
ARRIVAL_WINDOW = 64  # arrival offsets kept for the least-delay estimate
# Before its EKF has an origin an autopilot reports 0 N 0 E, or (ArduPlane) a point metres from
# it: taken as a position, it would anchor the filter's local frame thousands of km from the flight.
NO_ORIGIN_DEG = 0.01
NEW_AUTOPILOT = "new autopilot"  # the time event of :meth:`Telemetry.restart`: the link's peer changed
RESET_KINDS = ("reboot", "boot time jump", NEW_AUTOPILOT)  # time events that break the boot clock
# GPS_RAW_INT streams at 1-2 Hz in a ground station's default rates: one older than this says
# nothing about the receiver now (its fix may have gone since).
GNSS_MAX_AGE_S = 2.0
GPS_FIX_TYPE_3D = 3  # GPS_FIX_TYPE_3D_FIX; DGPS and RTK fixes are higher
# A 3-D fix whose receiver reports no accuracy (h_acc 0, e.g. an NMEA driver): a consumer
# receiver's in open sky, with room for multipath.
GNSS_UNKNOWN_ACCURACY_M = 10.0


@dataclass(frozen=True)
class TimeEvent:
    """A discontinuity of the autopilot's clocks, at companion time ``time_s``."""

    kind: str  # one of RESET_KINDS | "time leap ignored" | "unix time jump" | "clock mismatch"
    detail: str
    time_s: float

    def __str__(self) -> str:
        return f"{self.kind}: {self.detail}"


class Receiver(NamedTuple):
    """A GPS the autopilot reports: ``index`` 0 for GPS_RAW_INT, 1 for GPS2_RAW (ArduPilot's
    GPS_PRIMARY values), its place and horizontal accuracy (m; None where it reports none)."""

    index: int
    lat: float
    lon: float
    accuracy_m: float | None


class Attitude(NamedTuple):
    """The autopilot's attitude in degrees (heading clockwise from north, in [0, 360))."""

    heading_deg: float
    pitch_deg: float
    roll_deg: float


class BootClock:
    """Autopilot boot time -> companion UNIX time, and the jumps that break the mapping."""

    def __init__(self, tolerance_s: float) -> None:
        self.tolerance_s = tolerance_s
        self._reset()

    def _reset(self) -> None:
        self._arrival_offsets: deque[float] = deque(maxlen=ARRIVAL_WINDOW)
        self._latest: tuple[float, float] | None = None  # (boot_s, arrival_s) of the newest boot time
        self._suspect: tuple[float, float, float] | None = None  # (boot_s, arrival_s, leap_s) held back
        self._unix_offset_s: float | None = None
        self.mismatch_s: float | None = None  # autopilot UNIX clock minus ours (incl. link delay)

    @property
    def source(self) -> str:
        """Which mapping :meth:`to_unix` uses now."""
        if self._use_unix():
            return "SYSTEM_TIME"
        return "arrival time" if self._arrival_offsets else "none"

    def to_unix(self, boot_s: float) -> float | None:
        if self._use_unix():
            return boot_s + self._unix_offset_s
        return boot_s + min(self._arrival_offsets) if self._arrival_offsets else None

    def to_arrival(self, boot_s: float) -> float | None:
        """On our own clock, whatever the autopilot's UNIX time says: the earliest a message
        stamped ``boot_s`` could have arrived (the link's least delay). What a frame stamped by
        our clock must be compared with; the autopilot's UNIX time may be a second off ours."""
        return boot_s + min(self._arrival_offsets) if self._arrival_offsets else None

    def _use_unix(self) -> bool:
        return self._unix_offset_s is not None and (
            self.mismatch_s is None or abs(self.mismatch_s) <= UNIX_MATCH_S
        )

    def observe_boot(self, boot_s: float, arrival_s: float) -> tuple[list[TimeEvent], bool]:
        """A message stamped ``boot_s`` arrived at ``arrival_s``: (time events, keep the message?).

        A reboot resets the mapping at once (distrust is the safe side); a leap ahead is held
        back until the next message confirms or contradicts it (see the module docstring).
        """
        events = self._judge_suspect(boot_s, arrival_s) if self._suspect is not None else []
        if self._latest is not None:
            latest_boot, latest_arrival = self._latest
            leap = (boot_s - latest_boot) - (arrival_s - latest_arrival)
            if boot_s < latest_boot - self.tolerance_s:
                back = f"boot time went back from {latest_boot:.1f} s to {boot_s:.1f} s"
                events.append(TimeEvent("reboot", back, arrival_s))
                self._reset()
            elif leap > self.tolerance_s:
                self._suspect = (boot_s, arrival_s, leap)
                return events, False
        if self._latest is None or boot_s >= self._latest[0]:
            self._latest = (boot_s, arrival_s)
        self._arrival_offsets.append(arrival_s - boot_s)
        return events, True

    def _judge_suspect(self, boot_s: float, arrival_s: float) -> list[TimeEvent]:
        """The held-back leap, confirmed by a message continuing it or else reported as ignored."""
        suspect_boot, suspect_arrival, leap = self._suspect
        self._suspect = None
        if abs((boot_s - suspect_boot) - (arrival_s - suspect_arrival)) <= self.tolerance_s:
            self._reset()  # SYSTEM_TIME's tie of boot to UNIX time is from the old timeline too
            self._latest = (suspect_boot, suspect_arrival)
            return [TimeEvent("boot time jump", f"boot time leapt {leap:.1f} s ahead", arrival_s)]
        ignored = f"one message's boot time leapt {leap:.1f} s ahead of its arrival"
        return [TimeEvent("time leap ignored", ignored, suspect_arrival)]

    def observe_unix(self, unix_s: float, boot_s: float, arrival_s: float) -> list[TimeEvent]:
        """A SYSTEM_TIME (after :meth:`observe_boot` of its boot time); 0 = no UNIX time."""
        if unix_s <= 0:
            return []
        events = []
        offset = unix_s - boot_s
        if self._unix_offset_s is not None and abs(offset - self._unix_offset_s) > self.tolerance_s:
            moved = f"autopilot UNIX time moved {offset - self._unix_offset_s:+.1f} s"
            events.append(TimeEvent("unix time jump", moved, arrival_s))
        self._unix_offset_s = offset
        was_matching = self.mismatch_s is None or abs(self.mismatch_s) <= UNIX_MATCH_S
        self.mismatch_s = offset - min(self._arrival_offsets)
        if was_matching and abs(self.mismatch_s) > UNIX_MATCH_S:
            events.append(
                TimeEvent(
                    "clock mismatch",
                    f"autopilot UNIX clock is {self.mismatch_s:+.2f} s from ours: using arrival times",
                    arrival_s,
                )
            )
        return events


class Telemetry:
    """The newest kept message of each type with its arrival time; samples for the filter."""

    def __init__(
        self,
        max_age_s: float = 1.0,
        time_tolerance_s: float = 2.0,
        system_id: int | None = None,
        component_id: int = AUTOPILOT_COMPONENT,
        plausibility: Plausibility | None = None,
    ) -> None:
        self.max_age_s = max_age_s
        self.system_id = system_id
        self.component_id = component_id
        self.plausibility = plausibility or Plausibility()
        self.clock = BootClock(time_tolerance_s)
        self.epoch = 0  # reboots and boot time jumps so far: samples of one epoch share a clock
        self.problem: str | None = "no telemetry received yet"
        self.velocity: Verdict | None = None  # the newest sample's
        self._guard = VelocityGuard()
        self._judged: tuple[int, int] | None = None  # (epoch, time_boot_ms) of the newest verdict
        self._latest: dict[str, tuple[Any, float]] = {}
        self._events: list[TimeEvent] = []
        self._attitudes: deque[tuple[float, Attitude]] = deque()

    def ingest(self, msg: Any, now_s: float) -> list[TimeEvent]:
        """Keep ``msg`` if it is autopilot telemetry; the time events it revealed (also queued)."""
        kind = msg.get_type()
        if kind not in KEPT or not self._from_vehicle(msg, kind):
            return []
        events, keep = [], True
        if hasattr(msg, "time_boot_ms"):
            events, keep = self.clock.observe_boot(msg.time_boot_ms * 1e-3, now_s)
            if any(e.kind in RESET_KINDS for e in events):
                self._new_epoch()
        if keep:
            if kind == "SYSTEM_TIME":
                unix_s, boot_s = msg.time_unix_usec * 1e-6, msg.time_boot_ms * 1e-3
                events += self.clock.observe_unix(unix_s, boot_s, now_s)
            self._latest[kind] = (msg, now_s)
            if kind == "ATTITUDE":
                self._remember_attitude(msg)
        self._events += events
        return events

    def restart(self, detail: str, now_s: float) -> None:
        """Start over as after a reboot, its clock included: another sender is the autopilot now
        (the link's peer changed), and nothing the one before said describes this one."""
        self.clock = BootClock(self.clock.tolerance_s)
        self._new_epoch()
        self._events.append(TimeEvent(NEW_AUTOPILOT, detail, now_s))

    def _new_epoch(self) -> None:
        self.epoch += 1
        self._latest.clear()  # stamped on the old clock
        self._attitudes.clear()
        self._guard.reset()

    def pop_events(self) -> list[TimeEvent]:
        """Time events since the last call."""
        events, self._events = self._events, []
        return events

    def _from_vehicle(self, msg: Any, kind: str) -> bool:
        if msg.get_srcComponent() != self.component_id:
            return False
        system = msg.get_srcSystem()
        if self.system_id is None and kind == "HEARTBEAT" and msg.autopilot != AUTOPILOT_INVALID:
            self.system_id = system
        return self.system_id is None or system == self.system_id

    def latest(self, kind: str, now_s: float | None = None) -> Any | None:
        """The newest message of ``kind``; None if none, or if older than ``max_age_s`` at ``now_s``."""
        message, _ = self._fresh(kind, now_s)
        return message

    def _fresh(self, kind: str, now_s: float | None) -> tuple[Any | None, str | None]:
        """(message, None), or (None, why not)."""
        if kind not in self._latest:
            return None, f"no {kind} received"
        message, arrival_s = self._latest[kind]
        if now_s is not None and now_s - arrival_s > self.max_age_s:
            return None, f"{kind} is {now_s - arrival_s:.1f} s old (max {self.max_age_s:g} s)"
        return message, None

    def ins_sample(self, now_s: float) -> InsSample | None:
        """The autopilot's INS output at its own time (UNIX s), or None with :attr:`problem` set."""
        position, why = self._fresh("GLOBAL_POSITION_INT", now_s)
        attitude, why_att = self._fresh("ATTITUDE", now_s)
        self.problem = why or why_att
        if position is None or attitude is None:
            return None
        if abs(position.lat) * 1e-7 < NO_ORIGIN_DEG and abs(position.lon) * 1e-7 < NO_ORIGIN_DEG:
            self.problem = "GLOBAL_POSITION_INT has no position (at 0 N 0 E: its EKF has no origin yet)"
            return None
        if not math.isfinite(attitude.yaw):
            self.problem = "ATTITUDE has no heading (yaw not finite)"
            return None
        velocity = self._judge_velocity(position, now_s)
        if not velocity.usable:
            self.problem = f"no plausible velocity yet ({velocity.rejected})"
            return None
        self.problem = None
        return InsSample(
            time_s=self.boot_to_unix(position.time_boot_ms),
            lat=position.lat * 1e-7,
            lon=position.lon * 1e-7,
            vel_east_mps=velocity.east_mps,
            vel_north_mps=velocity.north_mps,
            heading_deg=math.degrees(attitude.yaw) % 360.0,
            alt_agl_m=position.relative_alt * 1e-3,
            velocity_sigma_mps=velocity.sigma_mps,
        )

    def _judge_velocity(self, position: Any, now_s: float) -> Verdict:
        """The verdict on this GLOBAL_POSITION_INT's sample, judged once (later passes reuse it)."""
        key = (self.epoch, position.time_boot_ms)
        if key != self._judged:
            self._judged = key
            time_s = self.boot_to_unix(position.time_boot_ms)
            self.velocity = self._guard.judge(
                self.plausibility.limits(self._mav_type()),
                time_s,
                position.lat * 1e-7,
                position.lon * 1e-7,
                self._velocities(position, time_s, now_s),
            )
        return self.velocity

    def _velocities(self, position: Any, time_s: float, now_s: float) -> list[Velocity]:
        """LOCAL_POSITION_NED's float velocity when fresh, then GLOBAL_POSITION_INT's cm/s."""
        sources = [Velocity("GLOBAL_POSITION_INT", time_s, position.vy * 1e-2, position.vx * 1e-2)]
        local = self.latest("LOCAL_POSITION_NED", now_s)
        if local is not None:
            local_s = self.boot_to_unix(local.time_boot_ms)
            sources.insert(0, Velocity("LOCAL_POSITION_NED", local_s, float(local.vy), float(local.vx)))
        return sources

    def _mav_type(self) -> int | None:
        heartbeat = self.latest("HEARTBEAT")
        return None if heartbeat is None else heartbeat.type

    @property
    def ardupilot(self) -> bool:
        """Whether the vehicle's HEARTBEAT says ArduPilot: the commands only it takes go to it alone."""
        heartbeat = self.latest("HEARTBEAT")
        return heartbeat is not None and heartbeat.autopilot == AUTOPILOT_ARDUPILOT

    def attitude(self, now_s: float | None = None) -> Attitude | None:
        """Heading, pitch and roll (degrees); None when missing (or stale at ``now_s``)."""
        att = self.latest("ATTITUDE", now_s)
        if att is None:
            return None
        return _attitude_deg(att)

    def _remember_attitude(self, att: Any) -> None:
        unix_s = self.clock.to_arrival(att.time_boot_ms * 1e-3)
        if unix_s is None or not all(math.isfinite(v) for v in (att.yaw, att.pitch, att.roll)):
            return
        if self._attitudes and unix_s <= self._attitudes[-1][0]:
            return
        self._attitudes.append((unix_s, _attitude_deg(att)))
        while unix_s - self._attitudes[0][0] > ATTITUDE_KEEP_S:
            self._attitudes.popleft()

    def attitude_at(self, unix_s: float) -> tuple[Attitude, float] | None:
        """The attitude when a frame was captured and how far it may be off (degrees).

        A copter pitches and rolls tens of degrees a second while it manoeuvres, and a camera
        body-fixed to it sees the ground shift by altitude x tan(error): the newest ATTITUDE at
        the time a frame is picked up is the wrong one. ``unix_s`` is on our clock, as the
        samples are (:meth:`BootClock.to_arrival`). Interpolated between the samples around
        ``unix_s`` (held from the newest for at most ``ATTITUDE_REACH_S``); the uncertainty is
        the tilt's rate of change times the capture time's own uncertainty plus the samples'
        spacing. None when no sample lies within reach.
        """
        times = [t for t, _ in self._attitudes]
        if len(times) < 2 or not times[0] <= unix_s <= times[-1] + ATTITUDE_REACH_S:
            return None
        after = min(max(bisect.bisect_left(times, unix_s), 1), len(times) - 1)
        (t0, a0), (t1, a1) = self._attitudes[after - 1], self._attitudes[after]
        span = max(t1 - t0, 1e-3)
        w = min((unix_s - t0) / span, 1.0)
        turn = (a1.heading_deg - a0.heading_deg + 180.0) % 360.0 - 180.0
        attitude = Attitude(
            (a0.heading_deg + w * turn) % 360.0,
            a0.pitch_deg + w * (a1.pitch_deg - a0.pitch_deg),
            a0.roll_deg + w * (a1.roll_deg - a0.roll_deg),
        )
        rate_dps = max(abs(a1.pitch_deg - a0.pitch_deg), abs(a1.roll_deg - a0.roll_deg)) / span
        timing_s = CAPTURE_TIME_SIGMA_S + span + max(unix_s - t1, 0.0)
        return attitude, ATTITUDE_SIGMA_DEG + rate_dps * timing_s

    def alt_msl_m(self, now_s: float | None = None) -> float | None:
        """Altitude above mean sea level (m) from GLOBAL_POSITION_INT."""
        position = self.latest("GLOBAL_POSITION_INT", now_s)
        return None if position is None else position.alt * 1e-3

    def gnss_accuracy_m(self, now_s: float) -> float | None:
        """The horizontal accuracy (m) GPS_RAW_INT reports while it has a 3-D fix or better;
        None without a fresh one or without a fix.

        GPS_RAW_INT describes the autopilot's first receiver (ArduPilot reports a second one in
        GPS2_RAW), so it is orthonav's own input only where GPS_INPUT is that receiver.
        """
        raw = self._receiver("GPS_RAW_INT", now_s)
        if raw is None:
            return None
        accuracy_mm = getattr(raw, "h_acc", 0)
        return accuracy_mm * 1e-3 if accuracy_mm > 0 else GNSS_UNKNOWN_ACCURACY_M

    def receivers(self, now_s: float) -> list[Receiver]:
        """Each GPS the autopilot reports with a fresh 3-D fix."""
        fresh = [(i, self._receiver(kind, now_s)) for i, kind in enumerate(RECEIVER_MESSAGES)]
        return [
            Receiver(i, raw.lat * 1e-7, raw.lon * 1e-7, getattr(raw, "h_acc", 0) * 1e-3 or None)
            for i, raw in fresh
            if raw is not None
        ]

    def _receiver(self, kind: str, now_s: float) -> Any | None:
        """The newest ``kind`` (GPS_RAW_INT or GPS2_RAW) if fresh with a 3-D fix or better."""
        raw = self._latest.get(kind)
        if raw is None or now_s - raw[1] > GNSS_MAX_AGE_S or raw[0].fix_type < GPS_FIX_TYPE_3D:
            return None
        return raw[0]

    def origin(self) -> tuple[float, float] | None:
        """The EKF origin (lat, lon) the autopilot announced, the origin of its local NED frame."""
        origin = self.latest("GPS_GLOBAL_ORIGIN")
        return None if origin is None else (origin.latitude * 1e-7, origin.longitude * 1e-7)

    def boot_to_unix(self, time_boot_ms: int) -> float:
        """An autopilot boot time as companion UNIX seconds (requires one message with a boot time)."""
        unix = self.clock.to_unix(time_boot_ms * 1e-3)
        if unix is None:
            raise ValueError("no autopilot boot time received yet")
        return unix


def _attitude_deg(att: Any) -> Attitude:
    return Attitude(math.degrees(att.yaw) % 360.0, math.degrees(att.pitch), math.degrees(att.roll))

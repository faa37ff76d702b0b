"""``orthonav fly``: the companion-computer loop between camera, map and autopilot.

One thread owns the link: it reads telemetry, dead-reckons, sends heartbeats and the
navigation output at a steady rate. Localization runs in a worker thread on the newest
frame (older ones are dropped and counted), so a slow match never stalls the link. A fused
fix goes out at once; messages are never closer than half the output period (an autopilot's
EKF throttles GPS updates), so a regular message due shortly before an expected fix is held
back for it, by up to one period (see :meth:`Companion._hold_for_fix`).

Dead reckoning integrates the autopilot's velocity (GLOBAL_POSITION_INT / LOCAL_POSITION_NED)
into our own nominal track instead of taking its position: once the autopilot fuses our
GPS_INPUT its position contains our own corrections, and filtering it again would count
them twice; its velocity changes only smoothly when it does. A velocity that is not plausible
for the vehicle (``mavlink.plausibility``) never moves the track: the last plausible one is
held with a growing uncertainty, and the rejection is reported (at most every
``statustext_repeat_s``). Should a fault get through all the same, fixes that agree with each
other but not with the prediction reset the filter (``fusion.filter``).

Nothing is sent unless the filter is initialised, not lost, and its 1-sigma is within
``max_sigma_m``. After the autopilot reboots or its boot clock jumps, the navigation state is
not trusted: the filter's position is widened past "lost" (so fixes far from the stale state
re-initialise it instead of being gated out as outliers, and frames are localized around
the position the autopilot reports on its new clock, as at start, or without a position prior
until it reports one), and nothing is sent until a fix of a frame captured after the break is
accepted. A frame whose attitude is beyond what the localizer takes (+-60 deg) is skipped, not
fatal. A silent link is reopened with an exponential backoff. Every message received and sent,
every fix and every event goes to a JSONL log (UNIX times, frames by capture time) so that
``orthonav replay`` can re-run a flight.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np

from orthonav.atomic import write_json_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError, require_positive
from orthonav.frames import Frame, LiveSource
from orthonav.fusion import FilterConfig, ImuErrorModel, InsSample, NavFilter, NavState
from orthonav.fusion.ground_velocity import (
    FrameVelocity,
    GroundVelocity,
    VelocityError,
    heading_walk_for,
)
from orthonav.geo import LocalFrame, distance_m
from orthonav.mavlink import messages
from orthonav.mavlink.link import Backoff, MavLink, dialect
from orthonav.mavlink.plausibility import Plausibility
from orthonav.mavlink.telemetry import (
    AUTOPILOT_COMPONENT,
    RESET_KINDS,
    Attitude,
    Receiver,
    Telemetry,
    TimeEvent,
)
from orthonav.types import Fix, FixSource, Prior

log = logging.getLogger(__name__)

OUTPUTS = ("gps_input", "vision", "odometry", "global_position_sensor")
ON_SPOOFING = ("warn", "switch-gps", "switch-source")
LOCAL_OUTPUTS = ("vision", "odometry")  # NED metres from the autopilot's EKF origin
# The outputs ArduPilot's EKF3 fuses, which MAV_CMD_EXTERNAL_POSITION_ESTIMATE resets
# (PX4 takes no such command).
POSITION_RESET_OUTPUTS = ("gps_input", "vision", "odometry")
MAV_SEVERITY_WARNING, MAV_SEVERITY_NOTICE = 4, 5
# A stabilised gimbal holds the camera nadir to about a degree. Without it the localizer would
# take the tilt as unknown (10 deg): at 300 m a right fix would claim 53 m and hardly be fused.
GIMBAL_SIGMA_DEG = 1.0
MAX_TILT_DEG = 60.0  # the largest pitch/roll a Prior takes (orthonav.types.Prior)
# A receiver reporting a GPS_INPUT sent lately reports orthonav's own position back: this close
# to it, at its accuracy (a float reported in whole millimetres); messages remembered for that:
# five seconds at the default rate.
OWN_ECHO_M, OWN_ECHO_ACCURACY_M, OWN_ECHO_SENT = 1.0, 0.002, 25
# Before the first visual fix the autopilot's GNSS position seeds the filter at this many times
# its receiver's reported accuracy, never under the floor: the EKF's position lags and smooths
# the receiver's, and the receiver's own figure is optimistic under multipath.
GNSS_SEED_SIGMAS, GNSS_SEED_FLOOR_M = 2.0, 5.0
# After a clock break the position sigma is set this many times the filter's "lost" limit.
RESET_SIGMA_FACTOR = 2.0
RECONNECT_FIRST_S, RECONNECT_MAX_S = 0.5, 4.0  # backoff between reconnects of a silent link
# The autopilot's own position this far from fused fixes (and beyond this many of their sigma),
# for this many in a row, follows another source than orthonav: a spoofed GNSS, say. One wrong
# match, or the autopilot pulled back onto orthonav after a gap, does not last that long.
APART_MIN_M, APART_SIGMAS, APART_RUN = 50.0, 5.0, 5


@dataclass(frozen=True)
class CompanionConfig:
    """How the loop talks, how often, and when it stops trusting itself."""

    output: str = "gps_input"
    rate_hz: float = 5.0
    heartbeat_period_s: float = 1.0
    telemetry_max_age_s: float = 1.0
    frame_timeout_s: float = 5.0
    link_timeout_s: float = 3.0
    max_sigma_m: float = 50.0
    init_sigma_m: float = 100.0
    gnss_seed: bool = True  # before the first visual fix, the autopilot's GNSS position (TelemetryToFilter)
    # When the autopilot stays far from the fused fixes: "warn" (STATUSTEXT), or also "switch-gps":
    # makes orthonav's GPS the primary (ArduPilot, gps_input), or "switch-source": selects EKF3's
    # source set extnav_source_set, the one whose horizontal position is ExternalNav (vision, odometry).
    on_spoofing: str = "warn"
    extnav_source_set: int = 2
    imu: str = "consumer"
    nadir_gimbal: bool = False
    # The autopilot's roll and pitch do not follow the positions sent (a navigation-grade INS;
    # sim-vehicle reports its true attitude): a body camera's correlation fixes are used without
    # GNSS too (Companion._break_attitude_loop).
    independent_attitude: bool = False
    # The ground velocity measured between consecutive frames fused into the filter, and GPS_INPUT's
    # speed accuracy from it (fusion.ground_velocity); needs the level camera of a nadir gimbal.
    frame_velocity: bool = False
    duration_s: float | None = None
    statustext_repeat_s: float = 10.0
    vehicle: str = "auto"  # copter, plane, or auto: from the autopilot's HEARTBEAT type
    max_speed_mps: float | None = None  # None: the vehicle class's
    max_accel_mps2: float | None = None
    # The autopilot's velocity is an estimator's, steered by its aiding (by orthonav's own
    # positions once GNSS is gone): in ArduPilot SITL a hovering copter's drifted about 0.5 m/s
    # within seconds, and a filter trusting it as an IMU claimed 1 m while 10-20 m off.
    velocity_walk_mps_per_sqrt_s: float = 0.5
    # Beyond this since the last fix's frame, our position is the autopilot's own velocity
    # integrated and handed back to it: fused, it closes a loop that amplifies any velocity error
    # (and it tells the autopilot nothing its own dead reckoning does not). Sending nothing lets
    # its EKF dead-reckon on its IMU until fixes return. A ground velocity measured from the
    # frames (frame_velocity) breaks that loop: while one is fresh, positions still go out.
    max_reckoning_s: float = 3.0
    # Frames come faster than their views change: a run of fixes of the same ground shares its
    # error (see FilterConfig.fix_correlation_s), and the autopilot must not be told it is smaller.
    fix_correlation_s: float = 10.0
    # When fixes resume after more than max_reckoning_s without any, nothing was sent meanwhile
    # and the autopilot dead-reckoned: the first fused fix also goes out as
    # MAV_CMD_EXTERNAL_POSITION_ESTIMATE, at most once per this many seconds (None: never).
    position_reset_interval_s: float | None = 10.0

    def __post_init__(self) -> None:
        if self.output not in OUTPUTS:
            raise OrthonavError(f"companion output {self.output!r}: expected one of {', '.join(OUTPUTS)}")
        if self.on_spoofing not in ON_SPOOFING:
            raise OrthonavError(
                f"companion on_spoofing {self.on_spoofing!r}: expected one of {', '.join(ON_SPOOFING)}"
            )
        fits = {"switch-gps": ("gps_input",), "switch-source": LOCAL_OUTPUTS}.get(self.on_spoofing)
        if fits is not None and self.output not in fits:
            raise OrthonavError(
                f"companion on_spoofing {self.on_spoofing!r} does not fit output {self.output!r}: "
                f"it answers for output {' or '.join(fits)}"
            )
        if self.extnav_source_set not in messages.EKF_SOURCE_SETS:
            raise OrthonavError(
                f"companion extnav_source_set {self.extnav_source_set!r}: expected 1, 2 or 3 (EK3_SRCn_*)"
            )
        require_positive(
            "companion",
            self,
            (
                "rate_hz",
                "heartbeat_period_s",
                "telemetry_max_age_s",
                "frame_timeout_s",
                "link_timeout_s",
                "max_sigma_m",
                "init_sigma_m",
                "max_reckoning_s",
            ),
        )
        if self.frame_velocity and not self.nadir_gimbal:
            raise OrthonavError(
                "companion frame_velocity: needs nadir_gimbal (a camera held level: the velocity is "
                "the ground's image shift, which a tilting camera adds its tilt to)"
            )
        interval = self.position_reset_interval_s
        if interval is not None and not (0.0 < interval < math.inf):
            raise OrthonavError(
                f"companion position_reset_interval_s {interval}: expected positive seconds (None: never)"
            )
        ImuErrorModel.preset(self.imu)
        self.plausibility()

    def plausibility(self) -> Plausibility:
        """The bounds a telemetry velocity is judged by."""
        return Plausibility(self.vehicle, self.max_speed_mps, self.max_accel_mps2)


@dataclass
class CompanionStats:
    """Counts for the summary; latencies are frame capture -> first message carrying the fix,
    waits the part of them from the fix's fusion to that message (the output's pacing)."""

    frames: int = 0
    frames_dropped: int = 0
    frames_banked: int = 0  # not localized: pitch or roll beyond MAX_TILT_DEG
    fixes_looped: int = 0  # body camera, no GNSS of the autopilot's own: unpinned fixes not fused
    fixes: int = 0
    fused: int = 0
    sent: int = 0
    position_resets: int = 0
    gps_switches: int = 0  # times orthonav's GPS was made the primary (on_spoofing "switch-gps")
    source_switches: int = 0  # MAV_CMD_SET_EKF_SOURCE_SET sent (on_spoofing "switch-source")
    source_switched: bool = False  # and accepted by the autopilot: never sent again
    withheld: int = 0
    velocities: int = 0  # ground velocities measured between frames
    velocities_fused: int = 0
    events: int = 0
    latencies_s: list[float] = field(default_factory=list)
    waits_s: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        pct = {"median": 50, "p95": 95}
        spreads = {"latency": self.latencies_s, "wait": self.waits_s}
        return {
            **{k: v for k, v in asdict(self).items() if k not in ("latencies_s", "waits_s")},
            **{
                f"{name}_{k}_ms": round(float(np.percentile(values, q)) * 1000.0, 1) if values else None
                for name, values in spreads.items()
                for k, q in pct.items()
            },
        }


class _Pending(NamedTuple):
    """The frame the worker is localizing, its result to come, and when it was handed over."""

    frame: Frame
    future: Future[tuple[Fix, GroundVelocity | None, str]]  # the fix, the velocity or why none
    started_s: float


class FixTimes:
    """How long localizations take (the last ``keep``), to expect the pending frame's fix."""

    def __init__(self, keep: int = 20, needed: int = 3) -> None:
        self._seconds: deque[float] = deque(maxlen=keep)
        self._needed = needed

    def add(self, seconds: float) -> None:
        self._seconds.append(seconds)

    def expected(self, started_s: float) -> float | None:
        """When a localization started at ``started_s`` should end (the median time); None until
        ``needed`` have been timed."""
        if len(self._seconds) < self._needed:
            return None
        return started_s + float(np.median(self._seconds))


class DeadReckoner:
    """Our own nominal track: the autopilot's velocity integrated from a starting point."""

    def __init__(self) -> None:
        self.frame: LocalFrame | None = None
        self.east_m = self.north_m = 0.0
        self.last: InsSample | None = None

    def advance(self, sample: InsSample) -> InsSample:
        """Replace the autopilot's position by ours, moved with the mean of the two velocities.

        A sample older than the last one moves nothing and is not remembered: one bad time
        stamp must not make the next sample integrate its distance from it.
        """
        if self.frame is None:
            self.frame = LocalFrame(sample.lat, sample.lon)
        elif self.last is not None and sample.time_s > self.last.time_s:
            dt = sample.time_s - self.last.time_s
            self.east_m += 0.5 * (sample.vel_east_mps + self.last.vel_east_mps) * dt
            self.north_m += 0.5 * (sample.vel_north_mps + self.last.vel_north_mps) * dt
        if self.last is None or sample.time_s >= self.last.time_s:
            self.last = sample
        lat, lon = self.frame.to_latlon(self.east_m, self.north_m)
        return replace(sample, lat=float(lat), lon=float(lon))

    def restart(self) -> None:
        """A new clock (a reboot): the next sample continues from here, nothing integrated across."""
        self.last = None


class TelemetryToFilter:
    """Telemetry -> our dead-reckoned INS sample -> the filter.

    The step ``fly`` takes on every pass and ``replay`` takes again from the log, so the filter
    is fed identically live and offline. The filter is initialised at the first sample. When
    the telemetry starts a new clock epoch (a reboot, a boot time jump) the dead reckoning
    restarts and the filter's position sigma is widened past "lost": the state is kept as a
    guess but no longer trusted, and the next fixes re-initialise it.
    """

    def __init__(
        self, telemetry: Telemetry, nav: NavFilter, init_sigma_m: float, gnss_seed: bool = True
    ) -> None:
        self.telemetry, self.nav, self.init_sigma_m = telemetry, nav, init_sigma_m
        self.gnss_seed = gnss_seed
        self.reckoner = DeadReckoner()
        self.autopilot: InsSample | None = None  # its newest sample as it reported it
        self.autopilot_epoch = telemetry.epoch  # the clock epoch of that sample
        self.initialised = False
        self.epoch = telemetry.epoch

    def step(self, now: float) -> InsSample | None:
        """Predict to the newest telemetry at ``now``; None without fresh telemetry (see its ``problem``)."""
        sample = self.telemetry.ins_sample(now)
        if sample is None:
            return None
        new_clock = self.telemetry.epoch != self.epoch
        self.epoch = self.telemetry.epoch
        if new_clock:
            self.reckoner.restart()
        self.autopilot, self.autopilot_epoch = sample, self.epoch
        sample = self.reckoner.advance(sample)
        if not self.initialised:
            self.initialised = True
            self.nav.initialise(sample.time_s, sample.lat, sample.lon, self.init_sigma_m)
        elif new_clock:
            self._distrust_position(sample)
            return sample
        if sample.time_s > self.nav.state().time_s:
            self.nav.predict(sample)
            self._seed_from_gnss(now)
        return sample

    def _seed_from_gnss(self, now: float) -> None:
        """Until the first visual fix, the position is the autopilot's own, at its receiver's
        accuracy, while its GNSS reports a 3-D fix.

        Without it the filter's start sigma grows for as long as no frame matches (a plane's
        climb), and a search that wide finds look-alike places: two agreeing wrong fixes would
        start navigation hundreds of metres off, to be handed to the autopilot the moment GNSS
        goes. Nothing is sent before the first visual fix, so the receiver seen is never
        orthonav's own GPS_INPUT. The price: a receiver spoofed before take-off keeps the search
        on the false place, and navigation starts only once it loses its fix (``gnss_seed``
        off for a vehicle that starts under spoofing).
        """
        if not self.gnss_seed or self.autopilot is None or self.nav.state().since_fix_s is not None:
            return
        accuracy_m = self.telemetry.gnss_accuracy_m(now)
        if accuracy_m is None:
            return
        sigma_m = max(GNSS_SEED_FLOOR_M, GNSS_SEED_SIGMAS * accuracy_m)
        self.nav.initialise(self.autopilot.time_s, self.autopilot.lat, self.autopilot.lon, sigma_m)

    def _distrust_position(self, sample: InsSample) -> None:
        """Onto the new clock (the filter restarts its history if it went back), then lost."""
        if sample.time_s != self.nav.state().time_s:
            self.nav.predict(sample)
        state = self.nav.state()
        sigma_m = RESET_SIGMA_FACTOR * self.nav.config.lost_sigma_m
        self.nav.initialise(state.time_s, state.lat, state.lon, sigma_m)
        log.warning(
            "autopilot clock broke: navigation position widened to %.0f m until fixes return", sigma_m
        )


class _Events:
    """Problems and recoveries: logged, written to the JSONL log, and sent as STATUSTEXT."""

    def __init__(self, companion: Companion) -> None:
        self.companion = companion
        self.active: dict[str, float] = {}

    def problem(self, key: str, text: str, now: float) -> None:
        """Report once, then again only every ``statustext_repeat_s`` while it lasts."""
        last = self.active.get(key)
        if last is not None and now - last < self.companion.config.statustext_repeat_s:
            return
        self.active[key] = now
        self._emit(MAV_SEVERITY_WARNING, text, now)

    def resolved(self, key: str, text: str, now: float) -> None:
        if self.active.pop(key, None) is not None:
            self._emit(MAV_SEVERITY_NOTICE, text, now)

    def once(self, severity: int, text: str, now: float) -> None:
        """A one-off event (a reboot): always reported, never held back by the repeat filter."""
        self._emit(severity, text, now)

    def _emit(self, severity: int, text: str, now: float) -> None:
        log.warning("%s", text) if severity <= MAV_SEVERITY_WARNING else log.info("%s", text)
        self.companion.stats.events += 1
        self.companion.record("event", now, {"severity": severity, "text": text})
        self.companion.link.statustext(severity, f"orthonav: {text}")


class Companion:
    """The loop: ``run()`` until the duration ends or Ctrl-C; ``summary()`` afterwards."""

    def __init__(
        self,
        config: CompanionConfig,
        link: MavLink,
        source: LiveSource,
        localizer: FixSource,
        log_path: Path,
        camera: Camera | None = None,
    ) -> None:
        self.config, self.link, self.source, self.localizer = config, link, source, localizer
        self.log_path = log_path
        if config.frame_velocity and camera is None:
            raise OrthonavError("companion frame_velocity: the camera's intrinsics are needed")
        # Used by the localization worker only (one thread): the previous frame's features.
        self._frame_velocity = FrameVelocity(camera) if config.frame_velocity and camera else None
        self.telemetry = _telemetry_for(link, config)
        self.nav = NavFilter(
            FilterConfig.for_imu(
                ImuErrorModel.preset(config.imu),
                velocity_walk_mps_per_sqrt_s=config.velocity_walk_mps_per_sqrt_s,
                heading_walk_deg_per_sqrt_s=heading_walk_for(config.frame_velocity),
                fix_correlation_s=config.fix_correlation_s,
            )
        )
        self.to_filter = TelemetryToFilter(self.telemetry, self.nav, config.init_sigma_m, config.gnss_seed)
        self.stats = CompanionStats()
        self.events = _Events(self)
        self._log: IO[str] | None = None
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="localize")
        self._pending: _Pending | None = None
        self._fix_times = FixTimes()
        self._held_for: float | None = None  # start of the localization a message waited for
        self._unsent: list[tuple[float, float]] = []  # fused fixes not yet sent: (captured, fused)
        self._last_frame_s = time.time()
        self._next_heartbeat = self._next_output = self._last_output = 0.0
        self._reckoning = False  # fresh telemetry at this step's dead reckoning
        self._clock_broke_s: float | None = None  # untrusted since (a reboot) until a fresh fix
        self._last_fused_capture_s: float | None = None
        self._last_reset_s = -float("inf")
        self._apart_run = 0  # fused fixes in a row far from the autopilot's own position
        self._sent_gps: deque[tuple[float, float, float]] = deque(maxlen=OWN_ECHO_SENT)  # lat, lon, m
        self._answered_s = -math.inf  # when the spoofing answer (on_spoofing) was last sent
        self._redial = Backoff(RECONNECT_FIRST_S, RECONNECT_MAX_S)
        self._peer_replaced = 0  # the link's count when telemetry last started over
        self._stopped = False
        self.interrupted = False  # ended by Ctrl-C: the command exits as interrupted, 130

    # --- logging -------------------------------------------------------------------------

    def record(self, kind: str, now: float, data: dict[str, Any]) -> None:
        """One JSONL line, flushed: a crash loses nothing already written."""
        if self._log is not None:
            self._log.write(
                json.dumps({"kind": kind, "time_s": round(now, 6), **data}, default=_jsonable) + "\n"
            )
            self._log.flush()

    # --- the loop ------------------------------------------------------------------------

    def run(self) -> dict:
        """Loop until ``duration_s``, Ctrl-C, SIGTERM or ``stop()``; always closes cleanly."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        started = time.time()
        try:
            with _stopped_by_sigterm(self), open(self.log_path, "a") as self._log:
                self.record("start", started, {"config": asdict(self.config)})
                while not self._stopped:
                    now = time.time()
                    if self.config.duration_s is not None and now - started >= self.config.duration_s:
                        break
                    self.step(now)
                    time.sleep(0.005)
        except KeyboardInterrupt:
            log.info("interrupted: stopping")
            self.interrupted = True
        finally:
            self.close()
        return self.summary()

    def stop(self) -> None:
        self._stopped = True

    def close(self) -> None:
        self._worker.shutdown(wait=True, cancel_futures=True)
        self.source.close()
        self.link.close()
        write_json_atomic(self.log_path.with_name("summary.json"), self.summary())

    def summary(self) -> dict:
        return {**self.stats.summary(), "link": self.link.stats.to_dict(), "output": self.config.output}

    def step(self, now: float) -> None:
        """One pass: link in, dead reckoning, frames, fixes, link out."""
        self._read_link(now)
        self._dead_reckon(now)
        self._collect_fix(now)
        self._watch_fixes(now)
        self._start_localization(now)
        self._heartbeat(now)
        self._send_output(now)

    def _read_link(self, now: float) -> None:
        received = self.link.poll(200)
        if self.link.peer_replaced != self._peer_replaced:
            self._peer_replaced = self.link.peer_replaced
            self.telemetry.restart("another sender is the autopilot now (see the log)", now)
            self._time_events(now)  # logged before the new autopilot's messages: replay restarts there
        for msg in received:
            self.telemetry.ingest(msg, now)
            if msg.get_type() == "COMMAND_ACK":
                self._source_set_ack(msg, now)
            source = {"src_system": msg.get_srcSystem(), "src_component": msg.get_srcComponent()}
            self.record("recv", now, {"type": msg.get_type(), **source, "msg": msg.to_dict()})
        self._time_events(now)
        self._watch_link(now)

    def _time_events(self, now: float) -> None:
        for event in self.telemetry.pop_events():
            self._time_event(event, now)

    def _time_event(self, event: TimeEvent, now: float) -> None:
        """Report a clock event; a reboot or jump also stops trusting the navigation state."""
        text = f"telemetry: {event}"
        if event.kind not in RESET_KINDS:
            self.events.problem(f"time {event.kind}", text, now)
            return
        self.events.once(MAV_SEVERITY_WARNING, text, now)
        if self.to_filter.initialised:
            self._clock_broke_s = now

    def _watch_link(self, now: float) -> None:
        """Reopen a silent link, with exponential backoff; reset it once messages flow again."""
        silent_s = self.link.silent_for(now)
        if silent_s <= self.config.link_timeout_s:
            self._redial.reset()
            self.events.resolved("link", "link back", now)
            return
        self.events.problem("link", f"link silent for {silent_s:.0f} s: reconnecting", now)
        if not self._redial.due(now):
            return
        delay_s = self._redial.attempt(now)
        log.info(
            "MAVLink %s silent for %.0f s: reconnect attempt %d (next in %.1f s if still silent)",
            self.link.url,
            silent_s,
            self._redial.attempts,
            delay_s,
        )
        self.link.reconnect()

    def _dead_reckon(self, now: float) -> None:
        self._reckoning = self.to_filter.step(now) is not None
        if not self._reckoning:
            self.events.problem("telemetry", f"telemetry: {self.telemetry.problem}", now)
            return
        self.events.resolved("telemetry", "telemetry back", now)
        self._judge_velocity(now)

    def _judge_velocity(self, now: float) -> None:
        """Report a rejected telemetry velocity (held meanwhile), or a source refused for another."""
        verdict = self.telemetry.velocity
        if verdict.rejected:
            held = f"holding {verdict.east_mps:.1f} E {verdict.north_mps:.1f} N m/s"
            self.events.problem(
                "velocity",
                f"telemetry velocity rejected ({verdict.rejected}): {held}, +-{verdict.sigma_mps:.1f}",
                now,
            )
            return
        self.events.resolved("velocity", "telemetry velocity plausible again", now)
        if verdict.note:
            self.events.problem("velocity source", f"telemetry velocity source refused ({verdict.note})", now)
        else:
            self.events.resolved("velocity source", "telemetry velocity sources agree again", now)

    def _start_localization(self, now: float) -> None:
        """Hand the newest frame to the worker when it is free; older frames are dropped."""
        frame = self.source.grab(0.0)
        if frame is None:
            if now - self._last_frame_s > self.config.frame_timeout_s:
                self.events.problem("camera", f"camera: no frame for {now - self._last_frame_s:.0f} s", now)
            return
        self._last_frame_s = now
        self.events.resolved("camera", "camera back", now)
        self.stats.frames += 1
        if self._pending is not None:
            self.stats.frames_dropped += 1
            return
        prior = self._prior(now, frame.capture_time_s)
        if prior is None:
            self.stats.frames_dropped += 1
            return
        self._pending = _Pending(frame, self._worker.submit(self._localize, frame, prior), now)

    def _localize(self, frame: Frame, prior: Prior) -> tuple[Fix, GroundVelocity | None, str]:
        """The worker's job: the frame's fix, then its ground velocity since the previous frame."""
        try:
            fix = self.localizer.localize(frame.image, prior)
        except OrthonavError as exc:
            fix = Fix(False, reason=str(exc))
        if self._frame_velocity is None:
            return fix, None, ""
        try:
            heading = prior.heading_deg if prior.heading_deg is not None else math.nan
            alt = prior.alt_agl_m if prior.alt_agl_m is not None else math.nan
            velocity = self._frame_velocity.add(frame.image, frame.capture_time_s, alt, heading)
        except VelocityError as exc:
            return fix, None, str(exc)
        return fix, velocity, "" if velocity is not None else "first frame of a pair"

    def _prior(self, now: float, captured_s: float) -> Prior | None:
        """Altitude, heading and attitude from telemetry (the attitude of the capture time);
        position from the filter while trusted.

        None (no fix this frame) without attitude or altitude, or when the attitude is beyond
        what the localizer takes: a banking aircraft skips frames, it does not stop navigating.
        """
        at_capture = self.telemetry.attitude_at(captured_s)
        if at_capture is None:
            self.events.problem("attitude time", "no ATTITUDE near the frame's capture time: no fix", now)
            return None
        self.events.resolved("attitude time", "ATTITUDE at capture time again", now)
        attitude, attitude_sigma_deg = at_capture
        state = self.nav.state()
        if state.alt_agl_m is None or state.alt_agl_m < 1.0:
            return None
        if not self.config.nadir_gimbal and not _within_tilt(attitude):
            self.stats.frames_banked += 1
            self.events.problem(
                "attitude", f"attitude beyond +-{MAX_TILT_DEG:.0f} deg: no fix this frame", now
            )
            return None
        self.events.resolved("attitude", f"attitude back within +-{MAX_TILT_DEG:.0f} deg", now)
        try:
            return self._prior_from(state, attitude, attitude_sigma_deg)
        except OrthonavError as exc:  # telemetry the localizer cannot take: skip the frame
            self.events.problem("prior", f"no fix this frame: {exc}", now)
            return None

    def _prior_from(self, state: NavState, attitude: Attitude, attitude_sigma_deg: float) -> Prior:
        """The prior itself; no position while the state is lost or distrusted (a wide search)."""
        tilt = {
            "pitch_deg": attitude.pitch_deg,
            "roll_deg": attitude.roll_deg,
            "attitude_sigma_deg": attitude_sigma_deg,
        }
        if self.config.nadir_gimbal:  # level within the gimbal's error, whatever the vehicle does
            tilt = {"pitch_deg": 0.0, "roll_deg": 0.0, "attitude_sigma_deg": GIMBAL_SIGMA_DEG}
        heading = attitude.heading_deg % 360.0
        if self._clock_broke_s is not None:
            return self._prior_after_break(state, heading, tilt)
        if state.status in ("lost", "uninitialised"):
            return Prior(alt_agl_m=state.alt_agl_m, heading_deg=heading, **tilt)
        sigma_m = max(30.0, 1.5 * state.sigma_m)
        return Prior(state.lat, state.lon, state.alt_agl_m, heading, sigma_m=sigma_m, **tilt)

    def _prior_after_break(self, state: NavState, heading: float, tilt: dict[str, float]) -> Prior:
        """After a reboot or a clock jump our own state is stale, but the autopilot's position
        reported on its new clock is as good a seed as its first report was at start (a rebooted
        autopilot reports one only from its own GNSS or origin): the search is centred there at
        the filter's initial sigma. Without a global map index a search with no position (every
        tile's keypoints) may never find a cross-date frame, and navigation would not come back.
        None reported on the new clock yet: no position."""
        reported, to_filter = self.to_filter.autopilot, self.to_filter
        if reported is None or to_filter.autopilot_epoch != self.telemetry.epoch:
            return Prior(alt_agl_m=state.alt_agl_m, heading_deg=heading, **tilt)
        sigma_m = max(30.0, 1.5 * to_filter.init_sigma_m)
        return Prior(reported.lat, reported.lon, state.alt_agl_m, heading, sigma_m=sigma_m, **tilt)

    def _collect_fix(self, now: float) -> None:
        if self._pending is None or not self._pending.future.done():
            return
        frame, future, started = self._pending
        self._pending = None
        self._fix_times.add(now - started)
        fix, velocity, no_velocity = future.result()
        self.stats.fixes += 1
        if self._clock_broke_s is not None and frame.capture_time_s < self._clock_broke_s:
            text = f"fix from {frame.label} not used: captured before the autopilot's clock broke"
            log.info("%s", text)
            self.record("event", now, {"severity": MAV_SEVERITY_NOTICE, "text": text})
            return
        fix = self._break_attitude_loop(fix, now)
        measured = self._fuse_velocity(velocity, no_velocity)
        outcome = self.nav.update(fix, frame.capture_time_s)
        self.record(
            "fix",
            now,
            {
                "frame": frame.label,
                "capture_time_s": frame.capture_time_s,
                "fix": fix.to_dict(),
                "filter": outcome.to_dict(),
                **measured,
            },
        )
        if outcome.accepted:
            self.stats.fused += 1
            if outcome.reset:
                self.events.once(MAV_SEVERITY_WARNING, f"navigation {outcome.reason}", now)
            self._unsent.append((frame.capture_time_s, now))
            self._reset_after_gap(fix, frame.capture_time_s, now)
            self._judge_autopilot(fix, now)
            # The fused fix goes out now, not at the next tick up to 1 / rate_hz later (that wait
            # was most of ORB's capture-to-message latency); never faster than twice the rate.
            self._next_output = min(self._next_output, self._last_output + 0.5 / self.config.rate_hz)
            if self._clock_broke_s is not None:
                self._clock_broke_s = None
                self.events.once(MAV_SEVERITY_NOTICE, "navigation re-established by visual fixes", now)
        elif fix.accepted:
            log.info("fix from %s gated out: %s", frame.label, outcome.reason)

    def _break_attitude_loop(self, fix: Fix, now: float) -> Fix:
        """A body-fixed camera's correlation pose, refused while the autopilot has no GNSS of
        its own.

        Such a pose is placed with the autopilot's tilt and heading (nothing in it measures
        them), and an autopilot aided by nothing but orthonav's positions estimates its tilt from
        them: a bias in the fixes tilts its attitude, which moves the next fixes the same way,
        and the vehicle steers after them. A pose pinned by keypoints measures its own tilt; a
        gimbal's camera does not take the autopilot's.
        """
        config = self.config
        if config.nadir_gimbal or config.independent_attitude or not (fix.accepted and fix.unpinned):
            return fix
        if self._independent_gnss(now):
            self.events.resolved("attitude loop", "correlation fixes used again: the autopilot has GNSS", now)
            return fix
        self.stats.fixes_looped += 1
        reason = (
            "correlation fix of a body-fixed camera not used: without GNSS of its own the autopilot's "
            "tilt, which places it, follows orthonav's positions"
        )
        self.events.problem("attitude loop", reason, now)
        return replace(fix, accepted=False, reason=reason, covariance_enu_m2=None)

    def _independent_gnss(self, now: float) -> bool:
        """Whether the autopilot reports a GNSS fix (GPS_RAW_INT, GPS2_RAW) that is not
        orthonav's own GPS_INPUT reported back."""
        return not all(self._echoes_ours(receiver) for receiver in self.telemetry.receivers(now))

    def _echoes_ours(self, receiver: Receiver) -> bool:
        """A receiver at the place and the accuracy of a GPS_INPUT sent lately: the place alone
        is not enough, as positions seeded from the autopilot's GNSS are its receiver's. One
        reporting no accuracy is taken by its place (were it GNSS, its fixes would be refused,
        not trusted wrongly)."""
        return any(
            distance_m(receiver.lat, receiver.lon, lat, lon) <= OWN_ECHO_M
            and (receiver.accuracy_m is None or abs(receiver.accuracy_m - accuracy) <= OWN_ECHO_ACCURACY_M)
            for lat, lon, accuracy in self._sent_gps
        )

    def _fuse_velocity(self, velocity: GroundVelocity | None, no_velocity: str) -> dict[str, Any]:
        """The frame pair's ground velocity into the filter (before the fix: it is the older);
        what became of it, for the log. A refused or gated-out velocity is never fused."""
        if self._frame_velocity is None:
            return {}
        if velocity is None:
            return {"velocity": {"refused": no_velocity}}
        self.stats.velocities += 1
        outcome = self.nav.update_velocity(velocity)
        self.stats.velocities_fused += outcome.accepted
        return {"velocity": {**velocity.to_dict(), "filter": outcome.to_dict()}}

    def _reset_after_gap(self, fix: Fix, captured_s: float, now: float) -> None:
        """The first fused fix after a span without fixes (longer than ``max_reckoning_s``) puts
        the autopilot's dead-reckoned EKF back on the map at once, rather than when it has
        detected its GPS again; rate-limited. Where measured velocities carried our positions
        through the span, EKF3 was not dead-reckoning and ArduPilot ignores it."""
        last, self._last_fused_capture_s = self._last_fused_capture_s, captured_s
        interval = self.config.position_reset_interval_s
        if (
            interval is None
            or self.config.output not in POSITION_RESET_OUTPUTS
            or self.telemetry.system_id is None
            or not self.telemetry.ardupilot
            or last is None
            or captured_s - last <= self.config.max_reckoning_s
            or now - self._last_reset_s < interval
        ):
            return
        self._last_reset_s = now
        target = (self.telemetry.system_id, self.telemetry.component_id)
        msg = messages.external_position_estimate(fix, captured_s, target=target)
        self.link.send(msg)
        self.stats.position_resets += 1
        text = f"position reset sent after {captured_s - last:.0f} s without a fix (+-{fix.sigma_m:.0f} m)"
        log.info("%s", text)
        self.record("event", now, {"severity": MAV_SEVERITY_NOTICE, "text": text, "msg": msg.to_dict()})

    def _judge_autopilot(self, fix: Fix, now: float) -> None:
        """Warn while the autopilot's own position stays far from the fused fixes: it follows a
        source that orthonav's positions do not move (a spoofed GNSS ahead of orthonav's GPS 2)."""
        autopilot = self.to_filter.autopilot
        if autopilot is None or fix.pose is None or fix.sigma_m is None:
            return
        reach_m = max(APART_MIN_M, APART_SIGMAS * fix.sigma_m)
        apart = float(distance_m(autopilot.lat, autopilot.lon, fix.pose.lat, fix.pose.lon))
        if apart <= reach_m:
            self._apart_run = 0
            self.events.resolved("apart", "the autopilot's position agrees with the visual fixes again", now)
            return
        self._apart_run += 1
        if self._apart_run >= APART_RUN:
            text = (
                f"the autopilot is {apart:.0f} m from {self._apart_run} visual fixes in a row: GNSS spoofed?"
            )
            self.events.problem("apart", text, now)
            if self.config.on_spoofing == "switch-gps" and self._answer_due(now):
                self._switch_to_our_gps(fix.pose.lat, fix.pose.lon, reach_m, now)
            elif (
                self.config.on_spoofing == "switch-source"
                and not self.stats.source_switched
                and self._answer_due(now)
            ):
                self._select_extnav_set(now)

    def _answer_due(self, now: float) -> bool:
        """The answer to spoofing goes to an ArduPilot autopilot, again as often as the warning
        repeats: setting it twice changes nothing, and a lost message is sent again."""
        if (
            not self.telemetry.ardupilot
            or self.telemetry.system_id is None
            or now - self._answered_s < self.config.statustext_repeat_s
        ):
            return False
        self._answered_s = now
        return True

    def _select_extnav_set(self, now: float) -> None:
        """Select EKF3's ExternalNav source set (``--on-spoofing switch-source``): while it runs on
        its GNSS set, orthonav's positions are not fused at all, so no glitch gate or lane switch
        takes the autopilot off a spoofer that passes its checks. Sent until the autopilot accepts
        it, never undone in flight: the receiver is spoofed."""
        target = (self.telemetry.system_id, self.telemetry.component_id)
        source_set = self.config.extnav_source_set
        self.link.send(messages.set_ekf_source_set(target, source_set))
        self.stats.source_switches += 1
        text = f"EKF3 source set {source_set} (ExternalNav, orthonav) requested: MAV_CMD_SET_EKF_SOURCE_SET"
        self.events.once(MAV_SEVERITY_WARNING, text, now)

    def _source_set_ack(self, msg: Any, now: float) -> None:
        """The autopilot's COMMAND_ACK to the source set request: accepted, the switch is done and
        said; refused, it is said, and requested again while the autopilot stays apart."""
        mavlink = dialect()
        if (
            msg.command != mavlink.MAV_CMD_SET_EKF_SOURCE_SET
            or self.stats.source_switches == 0
            or self.stats.source_switched
            or (msg.get_srcSystem(), msg.get_srcComponent())
            != (self.telemetry.system_id, self.telemetry.component_id)
            or msg.target_system not in (0, self.link.source_system)
            or msg.result == mavlink.MAV_RESULT_IN_PROGRESS
        ):
            return
        source_set = self.config.extnav_source_set
        if msg.result == mavlink.MAV_RESULT_ACCEPTED:
            self.stats.source_switched = True
            text = f"EKF3 source set {source_set} (ExternalNav, orthonav) selected: the autopilot accepted"
            self.events.once(MAV_SEVERITY_WARNING, text, now)
            return
        self.events.problem(
            "source set",
            f"the autopilot refused EKF3 source set {source_set} (MAV_RESULT {msg.result}): "
            f"requested again while it stays apart",
            now,
        )

    def _switch_to_our_gps(self, lat: float, lon: float, reach_m: float, now: float) -> None:
        """Make orthonav's GPS the autopilot's primary (``--on-spoofing switch-gps``).

        With two 3-D fixes ArduPilot takes the better one, and a spoofer's fix is as good as it
        claims: no other parameter makes it prefer orthonav. Ours is the one receiver it reports
        (GPS_RAW_INT, GPS2_RAW) near the fixes; where that is not one alone, nothing is changed.
        Repeated while the autopilot stays apart, and never undone in flight: the receiver is
        spoofed.
        """
        near = [
            r.index for r in self.telemetry.receivers(now) if distance_m(r.lat, r.lon, lat, lon) <= reach_m
        ]
        if len(near) != 1:
            self.events.problem(
                "gps switch", "cannot tell which GPS is orthonav's (GPS_RAW_INT, GPS2_RAW): not switched", now
            )
            return
        target = (self.telemetry.system_id, self.telemetry.component_id)
        for name, value in (("GPS_AUTO_SWITCH", 0), ("GPS_PRIMARY", near[0])):
            self.link.send(messages.param_set_int(target, name, value))
        self.stats.gps_switches += 1
        text = f"GPS {near[0] + 1} (orthonav) made primary: GPS_AUTO_SWITCH 0, GPS_PRIMARY {near[0]}"
        self.events.once(MAV_SEVERITY_WARNING, text, now)

    def _watch_fixes(self, now: float) -> None:
        """Tell the ground station when visual fixes stop (dead reckoning) and when they return."""
        state = self.nav.state()
        if state.status == "fixed":
            self.events.resolved("fixes", "visual fixes regained", now)
        elif state.since_fix_s is not None:
            self.events.problem(
                "fixes",
                f"no visual fix for {state.since_fix_s:.0f} s: {state.status}, sigma {state.sigma_m:.0f} m",
                now,
            )

    def _heartbeat(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self.link.heartbeat()
            self._ask_for_origin()
            self._next_heartbeat = now + self.config.heartbeat_period_s

    def _ask_for_origin(self) -> None:
        """The local outputs need the EKF origin, which ArduPilot announces once, when it sets it:
        a companion started (or restarted) later asks for it with each heartbeat until it hears it."""
        if self.config.output not in LOCAL_OUTPUTS or self.telemetry.system_id is None:
            return
        if self.telemetry.origin() is None:
            target = (self.telemetry.system_id, self.telemetry.component_id)
            self.link.send(messages.request_message(target, dialect().MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN))

    def _send_output(self, now: float) -> None:
        """At ``rate_hz``, and as soon as a fix is fused: the filter's state if it is trusted,
        otherwise nothing (and say why)."""
        if now < self._next_output or self._hold_for_fix(now):
            return
        self._last_output = now
        self._next_output = now + 1.0 / self.config.rate_hz
        state = self.nav.state()
        trouble = self._distrust(state)
        if trouble:
            self.stats.withheld += 1
            self.events.problem("output", f"no position sent: {trouble}", now)
            return
        self.events.resolved("output", "sending positions again", now)
        msg = self._message(state)
        self.link.send(msg)
        self.stats.sent += 1
        if msg.get_type() == "GPS_INPUT":
            self._sent_gps.append((msg.lat * 1e-7, msg.lon * 1e-7, msg.horiz_accuracy))
        sent = time.time()
        self.stats.latencies_s += [sent - captured for captured, _ in self._unsent]
        self.stats.waits_s += [sent - fused for _, fused in self._unsent]
        self.record(
            "sent",
            now,
            {
                "type": msg.get_type(),
                "msg": msg.to_dict(),
                "state": state.to_dict(),
                "fix_captures_s": [captured for captured, _ in self._unsent],
            },
        )
        self._unsent = []

    def _hold_for_fix(self, now: float) -> bool:
        """Hold the due message back where the pending frame's fix is expected within half a
        period: sent now, it would make the fix wait out the half-period spacing (a delay added to
        the capture-to-message latency of every frame so caught). The fix, or the message a
        period later, goes out; at most once per localization, so messages stay at most two
        periods apart."""
        if self._pending is None or self._held_for == self._pending.started_s:
            return False
        expected = self._fix_times.expected(self._pending.started_s)
        if expected is None or expected > now + 0.5 / self.config.rate_hz:
            return False
        self._held_for, self._next_output = self._pending.started_s, now + 1.0 / self.config.rate_hz
        return True

    def _distrust(self, state: NavState) -> str:
        """Why the state must not be sent; empty when it may be."""
        if not self._reckoning:
            return f"cannot dead-reckon ({self.telemetry.problem})"
        if self._clock_broke_s is not None:
            return "the autopilot rebooted or its clock jumped: waiting for fresh visual fixes"
        if self.config.output in LOCAL_OUTPUTS and self.telemetry.origin() is None:
            return "the autopilot has announced no EKF origin (GPS_GLOBAL_ORIGIN)"
        return messages.withheld_because(state, self.config.max_sigma_m, self.config.max_reckoning_s)

    def _message(self, state: NavState) -> Any:
        """Stamped with the filter's time, so the autopilot can compensate the lag."""
        if self.config.output == "gps_input":
            return messages.gps_input(state, state.time_s, self.telemetry.alt_msl_m())
        if self.config.output == "global_position_sensor":
            target = (self.telemetry.system_id or 0, self.telemetry.component_id)
            alt_msl_m = self.telemetry.alt_msl_m()
            return messages.global_position_sensor(state, state.time_s, alt_msl_m, target=target)
        builder = messages.vision_position_estimate if self.config.output == "vision" else messages.odometry
        return builder(state, self.telemetry.origin(), state.time_s)


@contextmanager
def _stopped_by_sigterm(companion: Companion) -> Iterator[None]:
    """SIGTERM (systemd's stop, a supervisor, ``kill``) ends the loop as Ctrl-C does: log and
    summary complete. Only the main thread can set a handler; elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, lambda *_: companion.stop())
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _within_tilt(attitude: Attitude) -> bool:
    """Pitch and roll the localizer takes (NaN is not)."""
    return abs(attitude.pitch_deg) < MAX_TILT_DEG and abs(attitude.roll_deg) < MAX_TILT_DEG


def _telemetry_for(link: MavLink, config: CompanionConfig) -> Telemetry:
    """Telemetry from the autopilot the link is pinned to, if it is (else the first one heard)."""
    system, component = link.peers.ids if link.peers is not None else (None, None)
    component = AUTOPILOT_COMPONENT if component is None else component
    return Telemetry(
        max_age_s=config.telemetry_max_age_s,
        system_id=system,
        component_id=component,
        plausibility=config.plausibility(),
    )


def _jsonable(value: Any) -> Any:
    """numpy scalars/arrays and bytes in pymavlink dicts."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes | bytearray):
        return value.decode("latin-1")
    return str(value)

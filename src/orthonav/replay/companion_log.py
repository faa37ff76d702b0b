"""Re-run the navigation filter on a companion log (``fly --log-dir``), to tune it on a real flight.

The log holds every MAVLink message the companion received with its arrival time, every fix
with its frame's capture time, and every state it sent. Read in file order it repeats the live
loop's passes: the messages of one pass (one arrival time) go into a ``Telemetry``, the same
:class:`~orthonav.mavlink.companion.TelemetryToFilter` step dead-reckons and predicts, the
pass's fixes are fused at their capture times, and each ``sent`` record is compared with the
re-run state at that moment. With the log's own settings the re-run reproduces what was sent
(to the log's rounding); with others it shows what they would have sent.

Messages are rebuilt with pymavlink's own classes and codec (packed and decoded again, so
their source system and component are those logged). Lines that cannot be used (malformed
JSON, unknown message types, a truncated last line from a crash mid-write) are skipped,
counted and named by line number.

The reference, where the log has one, is the autopilot's GLOBAL_POSITION_INT while its newest
GPS_RAW_INT reports a 3-D fix or better. With ``--output gps_input`` as the autopilot's only
GPS (``GPS1_TYPE = 14``), GPS_RAW_INT describes our own GPS_INPUT: the summary says so.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import re
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from orthonav.atomic import write_json_atomic, write_text_atomic
from orthonav.errors import OrthonavError, require_positive
from orthonav.fusion import FilterConfig, ImuErrorModel, NavFilter, NavState
from orthonav.fusion.ground_velocity import GroundVelocity, heading_walk_for
from orthonav.geo import LocalFrame, distance_m
from orthonav.mavlink.link import dialect
from orthonav.mavlink.messages import withheld_because
from orthonav.mavlink.plausibility import Plausibility
from orthonav.mavlink.telemetry import AUTOPILOT_COMPONENT, NEW_AUTOPILOT, Telemetry
from orthonav.replay.run import error_stats
from orthonav.types import Fix

log = logging.getLogger(__name__)

KINDS = ("start", "recv", "fix", "sent", "event")
# The companion's event when another sender became the autopilot: its telemetry started over there.
RESTARTED = f"telemetry: {NEW_AUTOPILOT}:"
NAV, SUMMARY, CONFIG, PLOT = "nav.jsonl", "summary.json", "config.json", "replay.png"
NAV_PERIOD_S = 1.0
GNSS_3D_FIX = 3  # GPS_FIX_TYPE_3D_FIX
REFERENCE_MAX_AGE_S = 2.0  # a GPS_RAW_INT older than this says nothing about the GNSS now
REFERENCE_MAX_GAP_S = 2.0  # no reference between two of its points further apart than this
WARNED_LINES = 5  # line numbers named per kind of problem; the rest are counted
STATUSES = ("uninitialised", "dead reckoning", "fixed", "lost")


@dataclass(frozen=True)
class FilterSettings:
    """What decides the re-run: the filter's tuning and the companion's trust limits."""

    imu: str = "consumer"
    gate_probability: float = FilterConfig.gate_probability
    heading_fix_sigma_deg: float | None = FilterConfig.heading_fix_sigma_deg
    history_s: float = FilterConfig.history_s
    # Logs written before the setting existed flew without it.
    velocity_walk_mps_per_sqrt_s: float = 0.0
    frame_velocity: bool = False  # fly --frame-velocity: its heading walk too
    fix_correlation_s: float = 0.0
    init_sigma_m: float = 100.0
    gnss_seed: bool = False  # logs written before the seed existed flew without it
    max_sigma_m: float = 50.0
    max_reckoning_s: float = math.inf  # logs written before the limit existed sent without it
    telemetry_max_age_s: float = 1.0
    vehicle: str = "auto"
    max_speed_mps: float | None = None
    max_accel_mps2: float | None = None

    def __post_init__(self) -> None:
        require_positive("replay settings", self, ("init_sigma_m", "max_sigma_m", "telemetry_max_age_s"))
        self.filter_config()
        self.plausibility()

    def plausibility(self) -> Plausibility:
        return Plausibility(self.vehicle, self.max_speed_mps, self.max_accel_mps2)

    def filter_config(self) -> FilterConfig:
        return FilterConfig.for_imu(
            ImuErrorModel.preset(self.imu),
            gate_probability=self.gate_probability,
            heading_fix_sigma_deg=self.heading_fix_sigma_deg,
            history_s=self.history_s,
            velocity_walk_mps_per_sqrt_s=self.velocity_walk_mps_per_sqrt_s,
            heading_walk_deg_per_sqrt_s=heading_walk_for(self.frame_velocity),
            fix_correlation_s=self.fix_correlation_s,
        )


def settings_from_log(companion_config: dict, overrides: dict[str, Any]) -> FilterSettings:
    """The companion's own settings (its ``start`` record), then ``overrides`` on top."""
    names = {item.name for item in fields(FilterSettings)}
    unknown = set(overrides) - names
    if unknown:
        raise OrthonavError(f"replay settings {sorted(unknown)}: expected some of {sorted(names)}")
    logged = {key: value for key, value in companion_config.items() if key in names}
    try:
        return replace(FilterSettings(**logged), **overrides)
    except TypeError as exc:
        raise OrthonavError(f"companion log start config: {exc}") from None


@dataclass
class CompanionLog:
    """One run of a companion log: its ``start`` config and its records with their line numbers."""

    path: Path
    config: dict
    records: list[tuple[int, dict]]
    run: int
    runs: int
    problems: _Problems


class _Problems:
    """Lines skipped, counted by reason; the first few of each named by line number."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.counts: dict[str, int] = {}

    def skip(self, reason: str, line: int, detail: str = "") -> None:
        count = self.counts[reason] = self.counts.get(reason, 0) + 1
        if count <= WARNED_LINES:
            log.warning(
                "%s: line %d: %s%s: skipped", self.path, line, reason, f" ({detail})" if detail else ""
            )
        elif count == WARNED_LINES + 1:
            log.warning("%s: more lines with %s: counted in the summary, not named", self.path, reason)


def read_companion_log(path: Path, run: int | None = None) -> CompanionLog:
    """Parse a ``companion.jsonl``; ``run`` (1-based) picks one of its appended runs (default: the last)."""
    path = Path(path)
    if not path.is_file():
        raise OrthonavError(
            f"{path}: no such file (expected a companion log, fly --log-dir DIR/companion.jsonl)"
        )
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = text.splitlines()
    if not any(line.strip() for line in lines):
        raise OrthonavError(f"{path}: empty: expected a companion log (JSON lines from fly --log-dir)")
    problems = _Problems(path)
    runs: list[tuple[dict, list[tuple[int, dict]]]] = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        record = _parse(line, number, number == len(lines) and not text.endswith("\n"), problems)
        if record is None:
            continue
        if not runs and record["kind"] != "start":
            raise OrthonavError(
                f"{path}: line {number}: not a companion log: expected it to open with a 'start' record "
                f"(fly --log-dir), got kind {record['kind']!r}"
            )
        if record["kind"] == "start":
            config = record.get("config")
            if not isinstance(config, dict):
                raise OrthonavError(f"{path}: line {number}: 'start' record without its companion config")
            runs.append((config, []))
        else:
            runs[-1][1].append((number, record))
    if not runs:
        raise OrthonavError(
            f"{path}: not a companion log: no line is a JSON object with a 'kind' of {', '.join(KINDS)}"
        )
    return _pick_run(path, runs, run, problems)


def _parse(line: str, number: int, last_unterminated: bool, problems: _Problems) -> dict | None:
    """One line as a record; None (counted) when it cannot be one. A bad first record is an error."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError as exc:
        if last_unterminated:
            problems.skip("truncated last line (the companion stopped mid-write)", number)
            return None
        record, detail = None, str(exc)
    else:
        detail = "no 'kind' or 'time_s'"
    if (
        isinstance(record, dict)
        and record.get("kind") in KINDS
        and isinstance(record.get("time_s"), int | float)
        and math.isfinite(record["time_s"])
    ):
        return record
    if number == 1:
        raise OrthonavError(
            f"{problems.path}: line 1: not a companion log: expected a JSON object with 'kind' "
            f"({', '.join(KINDS)}) and 'time_s' ({detail})"
        )
    problems.skip("malformed line", number, detail)
    return None


def _pick_run(
    path: Path, runs: list[tuple[dict, list[tuple[int, dict]]]], run: int | None, problems: _Problems
) -> CompanionLog:
    if run is not None and not 1 <= run <= len(runs):
        raise OrthonavError(f"--run {run}: {path} holds {len(runs)} run(s): expected 1..{len(runs)}")
    if run is None and len(runs) > 1:
        log.warning(
            "%s holds %d runs (fly appends to its log): replaying the last; --run picks one", path, len(runs)
        )
    index = (run or len(runs)) - 1
    config, records = runs[index]
    if not any(record["kind"] == "recv" for _, record in records):
        raise OrthonavError(f"{path}: run {index + 1} received no telemetry: nothing to dead-reckon with")
    return CompanionLog(path, config, records, index + 1, len(runs), problems)


@dataclass
class ReplayOutcome:
    """What :func:`replay_companion_log` wrote and measured."""

    out_dir: Path
    summary: dict
    nav: list[dict]


@dataclass
class _Run:
    """What the re-run collects as it goes."""

    steps: list[tuple[NavState, bool]] = field(default_factory=list)  # (state, trusted) per new time
    fixes: list[dict] = field(default_factory=list)
    sent: list[dict] = field(default_factory=list)
    reference: list[tuple[float, float, float]] = field(default_factory=list)
    received: int = 0


class _Replayer:
    """The live loop's passes, taken again from the log."""

    def __init__(self, companion_log: CompanionLog, settings: FilterSettings) -> None:
        from orthonav.mavlink.companion import TelemetryToFilter

        self.log, self.settings = companion_log, settings
        self.telemetry = Telemetry(
            max_age_s=settings.telemetry_max_age_s, plausibility=settings.plausibility()
        )
        self.nav = NavFilter(settings.filter_config())
        self.to_filter = TelemetryToFilter(
            self.telemetry, self.nav, settings.init_sigma_m, settings.gnss_seed
        )
        self.mavlink = dialect()
        self.codecs: dict[tuple[int, int], Any] = {}
        self.out = _Run()
        self.reckoning = False
        self.gnss: tuple[int, float] | None = None  # newest GPS_RAW_INT fix type and its arrival

    def run(self) -> _Run:
        pending: float | None = None  # arrival time of the pass whose messages are being read
        for number, record in self.log.records:
            kind, now = record["kind"], float(record["time_s"])
            if kind == "recv":
                if pending is not None and now != pending:
                    self._step(pending)
                pending = now
                self._receive(number, record, now)
            elif kind in ("fix", "sent"):
                pending = None
                self._step(now)
                (self._fix if kind == "fix" else self._sent)(number, record)
            elif kind == "event" and str(record.get("text", "")).startswith(RESTARTED):
                if pending is not None:  # the pass before the change read the autopilot before
                    self._step(pending)
                    pending = None
                self.telemetry.restart(record["text"], now)
        if pending is not None:
            self._step(pending)
        return self.out

    def _step(self, now: float) -> None:
        """The pass's dead reckoning; the state is kept each time the filter moves on."""
        self.reckoning = self.to_filter.step(now) is not None
        state = self.nav.state()
        if self.to_filter.initialised and (not self.out.steps or state.time_s > self.out.steps[-1][0].time_s):
            self.out.steps.append((state, self._trusted(state)))

    def _trusted(self, state: NavState) -> bool:
        """Would the companion send this state (the checks of ``Companion._distrust`` on the filter)?"""
        settings = self.settings
        return self.reckoning and not withheld_because(state, settings.max_sigma_m, settings.max_reckoning_s)

    def _receive(self, number: int, record: dict, now: float) -> None:
        msg = self._rebuild(number, record)
        if msg is None:
            return
        self.out.received += 1
        self.telemetry.ingest(msg, now)
        self._watch_gnss(msg, now)

    def _rebuild(self, number: int, record: dict) -> Any | None:
        """The message as pymavlink decodes it, from its logged dict and source."""
        fields_ = record.get("msg")
        name = fields_.get("mavpackettype") if isinstance(fields_, dict) else None
        cls = getattr(self.mavlink, f"MAVLink_{str(name).lower()}_message", None)
        if name is None or cls is None:
            self.log.problems.skip("unknown message type", number, str(name))
            return None
        source = (int(record.get("src_system", 1)), int(record.get("src_component", AUTOPILOT_COMPONENT)))
        codec = self.codecs.get(source)
        if codec is None:
            codec = self.codecs[source] = self.mavlink.MAVLink(
                None, srcSystem=source[0], srcComponent=source[1]
            )
        try:
            values = {key: _field_value(fields_[key]) for key in cls.fieldnames}
            return codec.decode(bytearray(cls(**values).pack(codec)))
        except Exception as exc:  # pymavlink raises struct.error, TypeError, KeyError, MAVError...
            self.log.problems.skip(f"malformed {name} message", number, f"{type(exc).__name__}: {exc}")
            return None

    def _watch_gnss(self, msg: Any, now: float) -> None:
        """GLOBAL_POSITION_INT is the reference while the newest GPS_RAW_INT has a 3-D fix."""
        kind = msg.get_type()
        if kind == "GPS_RAW_INT" and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            self.gnss = (int(msg.fix_type), now)
        elif kind == "GLOBAL_POSITION_INT" and self.telemetry.latest(kind) is msg and self.gnss is not None:
            fix_type, arrival = self.gnss
            if fix_type >= GNSS_3D_FIX and now - arrival <= REFERENCE_MAX_AGE_S:
                time_s = self.telemetry.boot_to_unix(msg.time_boot_ms)
                self.out.reference.append((time_s, msg.lat * 1e-7, msg.lon * 1e-7))

    def _fix(self, number: int, record: dict) -> None:
        try:
            fix = Fix.from_dict(record.get("fix") or {})
            capture = float(record["capture_time_s"])
        except (OrthonavError, KeyError, TypeError, ValueError) as exc:
            self.log.problems.skip("malformed fix", number, str(exc))
            return
        velocity = record.get("velocity")  # fly --frame-velocity's, fused before the fix as there
        if isinstance(velocity, dict) and "east_mps" in velocity:
            try:
                self.nav.update_velocity(GroundVelocity.from_dict(velocity))
            except OrthonavError as exc:
                self.log.problems.skip("malformed frame velocity", number, str(exc))
        outcome = self.nav.update(fix, capture)
        logged = record.get("filter") or {}
        self.out.fixes.append(
            {
                "capture_time_s": capture,
                "localized": fix.accepted,
                "fused": outcome.accepted,
                "reason": outcome.reason,
                "lat": fix.pose.lat if fix.accepted else None,
                "lon": fix.pose.lon if fix.accepted else None,
                "originally_fused": logged.get("accepted"),
            }
        )

    def _sent(self, number: int, record: dict) -> None:
        logged = record.get("state")
        if not isinstance(logged, dict) or not all(
            isinstance(logged.get(k), int | float) for k in ("lat", "lon")
        ):
            self.log.problems.skip("malformed sent record", number, "no state with lat, lon")
            return
        state = self.nav.state()
        rerun_ok = math.isfinite(state.lat) and math.isfinite(state.lon)
        self.out.sent.append(
            {
                "time_s": float(logged.get("time_s") or record["time_s"]),
                "lat": float(logged["lat"]),
                "lon": float(logged["lon"]),
                "sigma_m": logged.get("sigma_m"),
                "status": logged.get("status"),
                "rerun_offset_m": float(distance_m(state.lat, state.lon, logged["lat"], logged["lon"]))
                if rerun_ok
                else None,
                "rerun_sigma_m": state.sigma_m,
                "rerun_status": state.status,
                "rerun_trusted": self._trusted(state),
            }
        )


def _field_value(value: Any) -> Any:
    """Logged strings back to the bytes pymavlink's constructors take (char fields, raw bytes)."""
    return value.encode("latin-1", errors="replace") if isinstance(value, str) else value


def replay_companion_log(
    companion_log: CompanionLog,
    settings: FilterSettings,
    out_dir: Path,
    overrides: dict[str, Any] | None = None,
) -> ReplayOutcome:
    """Re-run the filter on the log; write config.json, nav.jsonl, summary.json and replay.png."""
    out_dir.mkdir(parents=True, exist_ok=True)
    config = {
        "source": {
            "companion_log": str(companion_log.path),
            "run": companion_log.run,
            "runs": companion_log.runs,
        },
        "companion": companion_log.config,
        "settings": asdict(settings),
        "overrides": overrides or {},
    }
    write_json_atomic(out_dir / CONFIG, config)
    run = _Replayer(companion_log, settings).run()
    if not run.steps:
        raise OrthonavError(
            f"{companion_log.path}: run {companion_log.run}: no usable position telemetry "
            "(GLOBAL_POSITION_INT and ATTITUDE from the autopilot): nothing to dead-reckon"
        )
    if not run.fixes:
        log.warning("%s: the log holds no fix: the re-run is dead reckoning only", companion_log.path)
    reference = _Reference(run.reference)
    nav = _nav_records(run.steps, reference)
    summary = _summary(companion_log, settings, run, reference, nav)
    write_text_atomic(out_dir / NAV, "".join(json.dumps(record) + "\n" for record in nav))
    write_json_atomic(out_dir / SUMMARY, summary)
    from orthonav.viz.replay import plot_companion_replay

    plot_companion_replay(
        nav,
        run.sent,
        _reference_track(run.reference),
        run.fixes,
        out_dir / PLOT,
        _title(companion_log, summary),
    )
    return ReplayOutcome(out_dir, summary, nav)


class _Reference:
    """The GNSS track, interpolated in metres; None where it has no point within the gap."""

    def __init__(self, points: list[tuple[float, float, float]]) -> None:
        points = sorted(points)
        self.times = np.array([p[0] for p in points], float)
        self.frame = LocalFrame(points[0][1], points[0][2]) if points else None
        if self.frame is not None:
            self.east, self.north = self.frame.to_enu([p[1] for p in points], [p[2] for p in points])

    def __bool__(self) -> bool:
        return self.frame is not None

    def errors_m(self, times: list[float], lats: list[float], lons: list[float]) -> list[float | None]:
        """Distance of each position from the reference at its time."""
        if self.frame is None or not times:
            return [None] * len(times)
        t = np.asarray(times, float)
        after = np.clip(np.searchsorted(self.times, t), 1, max(1, len(self.times) - 1))
        covered = (t >= self.times[0]) & (t <= self.times[-1])
        if len(self.times) > 1:
            covered &= self.times[after] - self.times[after - 1] <= REFERENCE_MAX_GAP_S
        east, north = self.frame.to_enu(np.asarray(lats, float), np.asarray(lons, float))
        ref_east = np.interp(t, self.times, self.east)
        ref_north = np.interp(t, self.times, self.north)
        dist = np.hypot(np.atleast_1d(east) - ref_east, np.atleast_1d(north) - ref_north)
        return [
            round(float(d), 3) if ok and math.isfinite(d) else None
            for d, ok in zip(dist, covered, strict=True)
        ]


def _reference_track(points: list[tuple[float, float, float]]) -> list[dict]:
    return [{"time_s": t, "lat": lat, "lon": lon} for t, lat, lon in sorted(points)]


def _nav_records(steps: list[tuple[NavState, bool]], reference: _Reference) -> list[dict]:
    """The re-run state every ``NAV_PERIOD_S`` of filter time, with its error where there is a reference."""
    chosen, next_s = [], -math.inf
    for state, trusted in steps:
        if state.time_s >= next_s:
            chosen.append((state, trusted))
            next_s = state.time_s + NAV_PERIOD_S
    errors = reference.errors_m(
        [s.time_s for s, _ in chosen], [s.lat for s, _ in chosen], [s.lon for s, _ in chosen]
    )
    start = chosen[0][0].time_s
    return [
        {
            "time_s": round(state.time_s, 3),
            "elapsed_s": round(state.time_s - start, 3),
            "lat": round(state.lat, 8),
            "lon": round(state.lon, 8),
            "sigma_m": _rounded(state.sigma_m),
            "status": state.status,
            "since_fix_s": None if state.since_fix_s is None else round(state.since_fix_s, 3),
            "would_send": trusted,
            "gnss_error_m": error,
        }
        for (state, trusted), error in zip(chosen, errors, strict=True)
    ]


def _summary(
    companion_log: CompanionLog, settings: FilterSettings, run: _Run, reference: _Reference, nav: list[dict]
) -> dict:
    steps = run.steps
    durations = dict.fromkeys(STATUSES, 0.0)
    withheld = 0.0
    for (state, trusted), (following, _) in itertools.pairwise(steps):
        durations[state.status] = durations.get(state.status, 0.0) + following.time_s - state.time_s
        withheld += 0.0 if trusted else following.time_s - state.time_s
    rejected = [f for f in run.fixes if not f["fused"]]
    summary = {
        "log": str(companion_log.path),
        "run": companion_log.run,
        "runs": companion_log.runs,
        "skipped_lines": dict(companion_log.problems.counts),
        "messages_replayed": run.received,
        "duration_s": round(steps[-1][0].time_s - steps[0][0].time_s, 3),
        "fixes": {
            "frames": len(run.fixes),
            "localized": sum(f["localized"] for f in run.fixes),
            "fused": len(run.fixes) - len(rejected),
            "rejected": len(rejected),
            "rejected_reasons": _reason_counts(f["reason"] for f in rejected),
            "originally_fused": sum(bool(f["originally_fused"]) for f in run.fixes),
            "verdicts_changed": sum(bool(f["originally_fused"]) != f["fused"] for f in run.fixes),
        },
        "time_s": {
            **{status: round(value, 3) for status, value in durations.items()},
            "not sent (untrusted)": round(withheld, 3),
        },
        "vs_sent": _vs_sent(run.sent),
        "gnss_reference": _gnss_summary(run, reference, nav, companion_log.config),
        "settings": asdict(settings),
    }
    return summary


def _vs_sent(sent: list[dict]) -> dict:
    """How far the re-run is from what the companion sent, at the moments it sent it."""
    offsets = [s["rerun_offset_m"] for s in sent if s["rerun_offset_m"] is not None]
    sigma = [
        abs(s["rerun_sigma_m"] - s["sigma_m"])
        for s in sent
        if s["sigma_m"] is not None and math.isfinite(s["rerun_sigma_m"])
    ]
    return {
        "states": len(sent),
        "would_send": sum(s["rerun_trusted"] for s in sent),
        "position_offset_m": _stats(offsets),
        "sigma_difference_m_max": round(max(sigma), 4) if sigma else None,
        "status_differs": sum(s["status"] != s["rerun_status"] for s in sent),
    }


def _gnss_summary(run: _Run, reference: _Reference, nav: list[dict], companion: dict) -> dict | None:
    if not reference:
        return None
    sent_errors = reference.errors_m(
        [s["time_s"] for s in run.sent], [s["lat"] for s in run.sent], [s["lon"] for s in run.sent]
    )
    for record, error in zip(run.sent, sent_errors, strict=True):
        record["gnss_error_m"] = error
    result = {
        "source": "GLOBAL_POSITION_INT while GPS_RAW_INT reports a 3-D fix",
        "points": len(run.reference),
        "span_s": round(float(reference.times[-1] - reference.times[0]), 3),
        "rerun_error_m": _stats([r["gnss_error_m"] for r in nav if r["gnss_error_m"] is not None]),
        "sent_error_m": _stats([e for e in sent_errors if e is not None]),
    }
    if companion.get("output", "gps_input") == "gps_input":
        result["note"] = (
            "the companion sent GPS_INPUT: where that was the autopilot's only GPS, GPS_RAW_INT is our own "
            "output and this reference is not independent"
        )
    return result


def _reason_counts(reasons: Any) -> dict[str, int]:
    """Rejections by kind: numbers replaced by N ('mahalanobis N > N', 'localizer: only N inliers')."""
    counts: dict[str, int] = {}
    for reason in reasons:
        key = re.sub(r"[-+]?\d+(\.\d+)?", "N", reason)
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda item: -item[1]))


def _stats(values: list[float]) -> dict | None:
    stats = error_stats(values, digits=4)
    return None if stats is None else {"count": len(values), **stats}


def _rounded(value: float) -> float | None:
    return round(float(value), 3) if math.isfinite(value) else None


def _title(companion_log: CompanionLog, summary: dict) -> str:
    fixes = summary["fixes"]
    return (
        f"{companion_log.path.name} run {companion_log.run}: {fixes['fused']} of {fixes['frames']} fixes "
        f"fused (originally {fixes['originally_fused']})"
    )

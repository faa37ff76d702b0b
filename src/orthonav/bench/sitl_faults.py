"""``orthonav bench sitl-faults``: the faults of ``bench faults`` that mean something to a real
autopilot, flown against ArduPilot's firmware (SITL) with ``orthonav bench sitl``'s harness.

- **link loss**: the companion-autopilot link drops both ways (``bench faults``'s relay and its
  ``link-loss`` fault, put between ``fly`` and SITL's SERIAL0), then returns;
- **camera stall**: the camera's frames do not reach the companion (the frame relay and
  ``camera-stall``);
- **autopilot reboot**: the ground station reboots the autopilot (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN)
  on the ground, after the companion has heard it for the whole EKF start, before the mission:
  SITL restarts its own process, and a vehicle in the air does not live through a reboot;
- **steep bank**: ArduPlane loiters tighter than 60 deg of bank allows, with a raised roll limit.

A fault window counts from GNSS loss. ArduCopter bridges about 8 s without a position before its
EKF failsafe whatever the companion does (the SITL page's table), so the copter's link is cut for
less than that; a stalled camera still leaves the companion its dead reckoning of a few seconds.
The copter gets GNSS back at the route's end: its landing is the SITL page's open question, not
the fault's. Each flight is graded as ``bench sitl``'s are, plus: no wrong message from orthonav
at all, navigation back (a fix fused) within ``RESUME_WITHIN_S`` of the fault's end, the flight
completed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench import faults
from orthonav.bench.machine import LoadWatch, machine_line
from orthonav.bench.sitl import (
    SCENARIOS,
    FlightFault,
    GroundStation,
    SitlConfig,
    run_scenario,
    sitl_binaries,
)
from orthonav.errors import OrthonavError
from orthonav.frames import capture_time_from_name
from orthonav.mavlink.link import dialect

RESUME_WITHIN_S = 10.0  # about as long as ArduCopter dead-reckons before its EKF failsafe
STEEP_BANK_DEG = 60.0
EVENT_GRACE_S = 5.0  # the companion reports what a fault left after its own timeouts
AFTER_FAULT_S = 60.0  # the autopilot's error is judged this long after the fault's end
COPTER_ROUTE = (("route_m", ((600.0, 0.0), (600.0, 250.0))), ("descent_mps", 5.0))


@dataclass(frozen=True)
class SitlFault:
    """A fault flight: the SITL scenario it is flown in, what happens and when."""

    name: str
    scenario: str  # a flight of ``bench sitl`` (its SCENARIOS)
    kind: str  # link-loss, camera-stall (``bench faults``'s own), reboot or bank
    description: str
    at_s: float = 25.0  # after GNSS loss
    duration_s: float = 6.0
    config: tuple[tuple[str, Any], ...] = COPTER_ROUTE  # SitlConfig fields this flight changes
    gnss_back: bool = True  # GNSS returns at the route's last waypoint


FAULTS = {
    f.name: f
    for f in (
        SitlFault(
            "copter-link-loss",
            "copter-gnss-off-velocity",
            "link-loss",
            "the companion-autopilot link cut both ways for 6 s on the first leg (ArduPilot drops GPS 2 "
            "after 4 s)",
        ),
        SitlFault(
            "copter-camera-stall",
            "copter-gnss-off-velocity",
            "camera-stall",
            "no frame reaches the companion for 8 s on the first leg",
            duration_s=8.0,
        ),
        SitlFault(
            "copter-autopilot-reboot",
            "copter-gnss-off-velocity",
            "reboot",
            "the autopilot rebooted on the ground with the companion running, then the flight",
            duration_s=0.0,
        ),
        SitlFault(
            "plane-steep-bank",
            "plane-gnss-off",
            "bank",
            "ArduPlane loiters 4 turns of 20 m radius at 25 m/s (ROLL_LIMIT_DEG 75) at the route's end",
            duration_s=0.0,
            config=(
                ("route_m", ((600.0, 0.0),)),
                ("loiter_turns", 4.0),
                # A 20 m circle at 25 m/s takes about 72 deg of bank; ArduPlane's L1 loiter flies
                # wider than asked unless its period is short. The return loiters over home on
                # RTL_RADIUS, gently, so the steep bank ends before the flight does.
                (
                    "extra_params",
                    (
                        ("WP_LOITER_RAD", 20.0),
                        ("AIRSPEED_CRUISE", 25.0),
                        ("NAVL1_PERIOD", 12.0),
                        ("ROLL_LIMIT_DEG", 75.0),
                        ("RTL_RADIUS", 150.0),
                    ),
                ),
            ),
            gnss_back=False,
        ),
    )
}


class _AfterGnssLoss(faults.Clock):
    """``bench faults``'s fault window, counted from GNSS loss rather than the first packet."""

    def start(self) -> None:
        """The relays call this on the autopilot's first packet: the window waits for GNSS loss."""


class _BankWatch(faults.Worker):
    """The vehicle's true bank (SIMSTATE) ten times a second: when it was steeper than
    ``STEEP_BANK_DEG``, and the steepest."""

    def __init__(self, gcs: GroundStation) -> None:
        super().__init__()
        self.gcs = gcs
        self.steep: list[float] = []  # times
        self.max_deg = 0.0

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            state = self.gcs.latest.get("SIMSTATE")
            if state is None:
                continue
            bank = abs(math.degrees(state.roll))
            self.max_deg = max(self.max_deg, bank)
            if bank > STEEP_BANK_DEG:
                self.steep.append(time.time())


class Injector(FlightFault):
    """Puts one :class:`SitlFault` into a ``bench sitl`` flight and grades what it did."""

    def __init__(self, fault: SitlFault, config: SitlConfig) -> None:
        self.fault, self.config = fault, config
        self.clock = _AfterGnssLoss(
            faults.FaultBenchConfig(fault_at_s=fault.at_s, fault_s=max(fault.duration_s, 1))
        )
        self.relay_fault = (faults.SCENARIOS.get(fault.kind) or faults.Fault)(random.Random(0))
        self.bank: _BankWatch | None = None
        self.frame_relay: faults.FrameRelay | None = None

    def links(self, stack: ExitStack, companion_port: int, camera: Path) -> tuple[int, Path]:
        if self.fault.kind == "link-loss":
            relay = stack.enter_context(faults.LinkRelay(companion_port, self.relay_fault, self.clock))
            return relay.vehicle_port, camera
        if self.fault.kind == "camera-stall":
            raw = camera.with_name("camera_raw")
            log = camera.parent / "fly" / "companion.jsonl"
            self.frame_relay = stack.enter_context(
                faults.FrameRelay(raw, camera, self.relay_fault, self.clock, log)
            )
            return companion_port, raw
        return companion_port, camera

    def on_ground(self, gcs: GroundStation, sitl: Any, flight: dict) -> None:
        if self.fault.kind == "bank":
            self.bank = _BankWatch(gcs).__enter__()
        if self.fault.kind != "reboot":
            return
        flight["fault_from"] = time.time()
        gcs.command(dialect().MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
        ready = lambda: any(  # noqa: E731
            "is using GPS" in text for t, text in gcs.track.texts if t > flight["fault_from"]
        )
        gcs.wait_for("EKF using GPS after the reboot", ready, self.config.ekf_ready_timeout_s, sitl)
        flight["fault_to"] = time.time()

    def in_flight(self, gcs: GroundStation, flight: dict) -> None:
        off_at = flight["gnss_off_at"]
        if self.clock.started is None:
            self.clock.started = off_at
            if self.fault.kind in ("link-loss", "camera-stall"):
                flight["fault_from"] = off_at + self.fault.at_s
                flight["fault_to"] = flight["fault_from"] + self.fault.duration_s
        if self.bank is not None and self.bank.steep:
            flight["fault_from"], flight["fault_to"] = self.bank.steep[0], self.bank.steep[-1]
        last_leg = 1 + len(self.config.route_m)  # mission items: home, take-off, the legs
        if (
            self.fault.gnss_back
            and "gnss_back_at" not in flight
            and any(seq == last_leg for _, seq in gcs.track.reached)
        ):
            gcs.set_param("SIM_GPS_DISABLE", 0)
            flight["gnss_back_at"] = time.time()

    def grade(self, row: dict, root: Path, flight: dict) -> dict:
        if self.bank is not None:
            self.bank.__exit__(None, None, None)
        return row | {
            "name": self.fault.name,
            "scenario": self.fault.scenario,
            "fault": self.fault.kind,
            "description": self.fault.description,
            **grade_fault(root, flight, row, self.bank),
        }


def grade_fault(root: Path, flight: dict, row: dict, bank: _BankWatch | None) -> dict:
    """The fault's part of a row: its window (seconds from GNSS loss), the companion's fused
    fixes around it, how soon one came after it, the autopilot's error after it, the verdict."""
    log = faults.read_log(root / "fly" / "companion.jsonl")
    fused = [r["time_s"] for r in log if r["kind"] == "fix" and r["filter"].get("accepted")]
    start, end = flight.get("fault_from"), flight.get("fault_to")
    off_at = flight.get("gnss_off_at")
    out: dict[str, Any] = {"fault_window_s": None, "resumed_s": None, "fixes_in_fault": None}
    if start is not None and end is not None:
        track = json.loads((root / "track.json").read_text())
        # While GNSS is off: a reboot's end is before it, and the copter gets GNSS back.
        since, until = (
            max(end, off_at or math.inf),
            min(end + AFTER_FAULT_S, flight.get("gnss_back_at") or math.inf),
        )
        after = [e[3] for e in track["estimate"] if since <= e[0] < until]
        out |= {
            "fault_window_s": [round(start - (off_at or start), 1), round(end - (off_at or start), 1)],
            "fault_s": round(end - start, 1),
            # From the first frame after the fault: a rebooted copter's camera starts on the climb.
            "resumed_s": faults.first_after(fused, max(end, _first_frame_after(root / "camera", end))),
            "fixes_in_fault": sum(start <= t < end for t in fused),
            "autopilot_error_after_max_m": round(max(after), 1) if after else None,
            "companion_events": [
                r["text"] for r in log if r["kind"] == "event" and start <= r["time_s"] < end + EVENT_GRACE_S
            ],
        }
        if out["resumed_s"] is not None:
            out["resumed_s"] = round(out["resumed_s"], 1)
    if bank is not None:
        out |= {"max_bank_deg": round(bank.max_deg, 1), "steep_bank_s": round(len(bank.steep) * 0.1, 1)}
    messages = row.get("orthonav_messages") or {}
    out["passed"] = bool(
        messages.get("sent")
        and messages.get("wrong") == 0
        and row["completed"]
        and out["resumed_s"] is not None
        and out["resumed_s"] <= RESUME_WITHIN_S
    )
    return out


def _first_frame_after(folder: Path, t: float) -> float:
    """The capture time of the first frame the companion was given at or after ``t`` (``t`` if none)."""
    later = [c for c in map(capture_time_from_name, folder.glob("*.jpg")) if c is not None and c >= t]
    return min(later, default=t)


def fault_config(fault: SitlFault, base: SitlConfig) -> SitlConfig:
    """``base`` with what the fault's flight changes (a shorter route, a tighter loiter)."""
    return dataclasses.replace(base, scenarios=(fault.scenario,), **dict(fault.config))


def run_sitl_fault_benchmark(
    names: tuple[str, ...], sitl_dir: Path, package: Path, frames_from: Path, out: Path, base: SitlConfig
) -> dict:
    """Every fault flight in turn (real time), graded; the JSON rewritten after each and a PNG."""
    unknown = sorted(set(names) - set(FAULTS))
    if unknown or not names:
        raise OrthonavError(
            f"SITL faults {', '.join(unknown) or '(none)'}: expected some of {', '.join(FAULTS)}"
        )
    sitl_dir, package, frames_from, out = (p.resolve() for p in (sitl_dir, package, frames_from, out))
    runs = out.with_suffix("")
    watch = LoadWatch()
    result: dict[str, Any] = {
        "config": asdict(base),
        "faults": {name: asdict(FAULTS[name]) for name in names},
        "sitl": sitl_binaries(sitl_dir),
        "map": str(package),
        "frames_from": str(frames_from),
        "machine": watch.record(),  # brought up to date after each flight
        "rows": [],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in tqdm(names, desc="SITL fault flights", unit="flight"):
        fault = FAULTS[name]
        config = fault_config(fault, base)
        scenario = SCENARIOS[fault.scenario]
        injector = Injector(fault, config)
        row = run_scenario(scenario, config, sitl_dir, package, frames_from, runs / name, injector)
        result["rows"].append(row)
        result["machine"] = watch.record()
        write_json_atomic(out, result)
    from orthonav.viz.sitl import plot_sitl_bench

    plot_sitl_bench(result, runs, out.with_suffix(".png"), machine_line(result["machine"]))
    return result


def summary_line(result: dict) -> str:
    parts = [
        f"{r['name']}: {'passed' if r['passed'] else 'FAILED'} (wrong "
        f"{(r.get('orthonav_messages') or {}).get('wrong')}, resumed {r['resumed_s']} s, "
        f"{'completed' if r['completed'] else 'not completed'})"
        for r in result["rows"]
    ]
    return "bench sitl-faults: " + "; ".join(parts) + f"; {machine_line(result['machine'])}"

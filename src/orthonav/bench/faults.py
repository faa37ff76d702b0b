"""``orthonav bench faults``: the real ``fly`` and ``sim-vehicle`` processes driven through faults.

Each scenario runs the two commands as a user would, over UDP loopback, with this module in
between: a MAVLink relay on the link (drops, corrupts, rewrites or adds packets), a relay on the
camera folder (stalls, delays or reorders frames), a spoofing sender, a reboot (the vehicle
process killed and another started elsewhere) or CPU starvation (the companion stopped and
continued by signals), damaged camera frames, or a damaged map package (``fly`` must then refuse
to start). The fault starts ``fault_at_s`` after the vehicle's first packet and lasts
``fault_s``. The vehicle grades every position it receives against its truth; a position is
**wrong** when it is more than 3 sigma (its own ``horiz_accuracy``) or more than 50 m off, or
when it carries a time outside the true track. The target is no wrong position in any scenario,
none sent to a stranger, and navigation back (positions flowing and a visual fix fused) within
``resume_within_s`` of the fault's end (of the flight's start, for a fault there from it:
``Fault.from_start``). How soon it is back depends on the CPU the processes get, so the result
records the machine's load beside it. A scenario whose fault ``fly`` must refuse at start
(``Fault.refusal``) has nothing to resume: it passes when ``fly`` exits with that refusal, and
the vehicle, flown all the same, got nothing."""

from __future__ import annotations

import itertools
import json
import math
import os
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import AbstractContextManager, ExitStack, contextmanager, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Self

from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch, machine_line
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import capture_time_from_name
from orthonav.geo import GeoRaster, destination
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.mavlink.link import dialect
from orthonav.viz.faults import plot_fault_bench

WRONG_SIGMAS = 3.0
WRONG_M = 50.0
UDP_MAX_BYTES = 65535
# Run as the child's first step, in a fresh interpreter (a hook run between fork and exec in a
# process with threads may deadlock): has the kernel kill the child when the process that started
# it dies (PR_SET_PDEATHSIG, 1 in <linux/prctl.h>), then becomes the command. A benchmark killed
# or crashed (a segfault in OpenCV's warp did so) must not leave SITL or fly running, holding
# their ports and a core each. The signal follows the thread that started the child, which
# outlives it here: `child_process` stops the child before leaving.
DIE_WITH_PARENT = (
    "import ctypes, os, signal, sys\n"
    "ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    os._exit(1)\n"
    "os.execvp(sys.argv[2], sys.argv[2:])\n"
)
BOOT_TIME_TYPES = ("ATTITUDE", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYSTEM_TIME")
VELOCITY_TYPES = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")
INT16_MAX = 32767  # GLOBAL_POSITION_INT's velocities are int16 cm/s
CLI = [sys.executable, "-m", "orthonav.cli.main"]
UNTIL_NEWER_FIXED = math.inf  # a frame delay: held until the companion has localized a later frame
# Events this long after a fault's end (for a reboot, after the new autopilot was first heard,
# which waits for its process to start: seconds, more on a busy machine) are still its trace: the
# companion notices what the fault left (a silent link, a rebooted autopilot) after its timeouts.
EVIDENCE_GRACE_S = 5.0
FRAME_ZEROED_BYTES = 5000  # a corrupt frame's hole: as in a frame with a block lost in transfer
SPOOFER_BOOT_S = 60.0  # the boot time a spoofer claims before it has heard the autopilot's
SKIPPED_FRAME = "skipped until it changes"  # the folder watcher's warning for a frame it refused
REFUSED_EXIT = 2  # the CLI's exit status for an error it explains in one line


@dataclass(frozen=True)
class FaultBenchConfig:
    """The flight and the fault's timing; written beside the numbers."""

    scenarios: tuple[str, ...] = ()
    parallel: int = 3
    fault_at_s: float = 10.0
    fault_s: float = 6.0
    after_s: float = 12.0
    resume_within_s: float = 10.0
    alt_m: float = 1000.0
    speed_mps: float = 20.0
    frame_rate_hz: float = 2.0
    reboot_offset_m: float = 1500.0
    seed: int = 0

    def __post_init__(self) -> None:
        unknown = sorted(set(self.scenarios) - set(SCENARIOS))
        if unknown:
            raise OrthonavError(
                f"fault scenarios {', '.join(unknown)}: expected some of {', '.join(SCENARIOS)}"
            )
        if self.parallel < 1:
            raise OrthonavError(f"fault bench parallel {self.parallel}: expected at least 1")
        if min(self.fault_at_s, self.fault_s, self.after_s, self.resume_within_s) <= 0:
            raise OrthonavError("fault bench: fault_at_s, fault_s, after_s and resume_within_s must be > 0")

    @property
    def flight_s(self) -> float:
        return self.fault_at_s + self.fault_s + self.after_s

    @property
    def names(self) -> tuple[str, ...]:
        return self.scenarios or tuple(SCENARIOS)


# --- the faults --------------------------------------------------------------------------


class Fault:
    """No fault: the reference run. Subclasses change what they must; times are seconds since
    the vehicle's first packet, ``active`` is true inside the fault window."""

    description = "no fault: the reference flight"
    reboots = False  # the vehicle is killed at the fault and another started elsewhere at its end
    refusal: str | None = None  # what ``fly`` must say refusing to start, where it must refuse
    # The fault is there from the flight's start: navigation is judged back from the start, as
    # the fault must not keep it from starting.
    from_start = False

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng

    def workers(self, run: ScenarioRun, relay: LinkRelay, port: int, fly_pid: int) -> list[Worker]:
        """What the fault runs beside the relays while the vehicle flies (a spoofer, a starver)."""
        return []

    def to_companion(self, data: bytes, t: float, active: bool) -> list[bytes]:
        """The datagrams the companion gets for one the vehicle sent."""
        return [data]

    def link_up(self, active: bool) -> bool:
        return True

    def frame_delay_s(self, active: bool) -> float | None:
        """Seconds a frame captured now is held back before the companion sees it; None: lost;
        ``UNTIL_NEWER_FIXED``: until the companion has localized a frame captured after it."""
        return 0.0

    def damage_frame(self, data: bytes, active: bool) -> bytes | None:
        """A frame's file as the companion gets it; None: intact."""
        return None

    def map_package(self, package: Path, root: Path) -> Path:
        """The map package ``fly`` is given."""
        return package


class Garbage(Fault):
    description = "noise datagrams and cut-off MAVLink packets from the autopilot's address"

    def to_companion(self, data: bytes, t: float, active: bool) -> list[bytes]:
        if not active:
            return [data]
        noise = bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 300)))
        return [data, noise, data[: self.rng.randrange(1, len(data))], b"\xfd" + noise[:20]]


class Corrupt(Fault):
    description = "the autopilot's own packets truncated or with flipped bits (a bad radio)"

    def to_companion(self, data: bytes, t: float, active: bool) -> list[bytes]:
        if not active:
            return [data]
        if self.rng.random() < 0.5:
            return [data[: self.rng.randrange(1, len(data))]]
        flipped = bytearray(data)
        flipped[self.rng.randrange(len(data))] ^= 1 << self.rng.randrange(8)
        return [bytes(flipped)]


class LinkLoss(Fault):
    description = "the link drops both ways, then returns"

    def link_up(self, active: bool) -> bool:
        return not active


class _Rewrite(Fault):
    """Rewrites the vehicle's messages in flight (re-packed with the sender's ids and sequence)."""

    persists = False  # the change outlives the fault window (a clock that has stepped)

    def __init__(self, rng: random.Random) -> None:
        super().__init__(rng)
        self.mav = dialect().MAVLink(None)
        self.mav.robust_parsing = True
        self.began = False

    def to_companion(self, data: bytes, t: float, active: bool) -> list[bytes]:
        self.began |= active
        if not (active or (self.persists and self.began)):
            return [data]
        out = []
        for msg in self.mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.rewrite(msg)
            packer = dialect().MAVLink(None, msg.get_srcSystem(), msg.get_srcComponent())
            packer.seq = msg.get_seq()
            out.append(bytes(msg.pack(packer)))
        return out

    def rewrite(self, msg: Any) -> None:
        raise NotImplementedError


class Bank(_Rewrite):
    description = "ATTITUDE reports a 75 deg bank and 65 deg pitch"

    def rewrite(self, msg: Any) -> None:
        if msg.get_type() == "ATTITUDE":
            msg.roll, msg.pitch = math.radians(75.0), math.radians(-65.0)


def _velocity(msg: Any) -> tuple[float, float]:
    """(east, north) m/s of a GLOBAL_POSITION_INT (cm/s) or LOCAL_POSITION_NED (m/s)."""
    scale = 1e-2 if msg.get_type() == "GLOBAL_POSITION_INT" else 1.0
    return msg.vy * scale, msg.vx * scale


def _set_velocity(msg: Any, east_mps: float, north_mps: float) -> None:
    """Write a velocity into either message; GLOBAL_POSITION_INT's saturates at its int16 limit."""
    if msg.get_type() == "GLOBAL_POSITION_INT":
        msg.vy, msg.vx = (max(-INT16_MAX, min(INT16_MAX, round(v * 100))) for v in (east_mps, north_mps))
    else:
        msg.vy, msg.vx = east_mps, north_mps


def _set_speed(msg: Any, speed_mps: float) -> None:
    """The same direction (north when still) at ``speed_mps``."""
    east, north = _velocity(msg)
    norm = math.hypot(east, north)
    east, north = (east / norm, north / norm) if norm > 0 else (0.0, 1.0)
    _set_velocity(msg, east * speed_mps, north * speed_mps)


class VelocityFast(_Rewrite):
    description = "LOCAL_POSITION_NED reports 350 m/s along the track"

    def rewrite(self, msg: Any) -> None:
        if msg.get_type() == "LOCAL_POSITION_NED":
            _set_speed(msg, 350.0)


class VelocityGlitch(_Rewrite):
    description = "one LOCAL_POSITION_NED at 1000 m/s and one GLOBAL_POSITION_INT at its limit (327.67 m/s)"

    def __init__(self, rng: random.Random) -> None:
        super().__init__(rng)
        self.glitched: set[str] = set()

    def rewrite(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind in VELOCITY_TYPES and kind not in self.glitched:
            self.glitched.add(kind)
            _set_speed(msg, 1000.0)


class VelocityBias(_Rewrite):
    description = "both velocities 30 m/s too far north; the positions as flown"

    def rewrite(self, msg: Any) -> None:
        if msg.get_type() in VELOCITY_TYPES:
            east, north = _velocity(msg)
            _set_velocity(msg, east, north + 30.0)


class VelocityNanLocal(_Rewrite):
    description = "LOCAL_POSITION_NED's velocity NaN and GLOBAL_POSITION_INT's 327 m/s"

    def rewrite(self, msg: Any) -> None:
        if msg.get_type() == "LOCAL_POSITION_NED":
            msg.vx = msg.vy = math.nan
        elif msg.get_type() == "GLOBAL_POSITION_INT":
            _set_speed(msg, 327.0)


class TimeJump(_Rewrite):
    """The autopilot's boot clock steps by ``step_ms`` and stays stepped."""

    persists = True
    step_ms = 0

    def rewrite(self, msg: Any) -> None:
        if msg.get_type() in BOOT_TIME_TYPES:
            msg.time_boot_ms = max(0, msg.time_boot_ms + self.step_ms)


class TimeAhead(TimeJump):
    description = "the autopilot's boot clock leaps an hour ahead and stays there"
    step_ms = 3_600_000


class TimeBack(TimeJump):
    description = "the autopilot's boot clock steps 8 s back and stays there"
    step_ms = -8_000


class CameraStall(Fault):
    description = "the camera delivers nothing"

    def frame_delay_s(self, active: bool) -> float | None:
        return None if active else 0.0


class LateFrames(Fault):
    description = "frames reach the companion 2 s after their capture"

    def frame_delay_s(self, active: bool) -> float | None:
        return 2.0 if active else 0.0


class Reordered(Fault):
    """Every other frame held back until the companion has localized a later one. Not for a
    fixed time: the companion localizes only while it is free, and a late frame that arrives
    while it is still busy with the later one is dropped unseen, more often the slower it is."""

    description = "every other frame arrives after the companion has localized the next one"

    def __init__(self, rng: random.Random) -> None:
        super().__init__(rng)
        self.count = 0

    def frame_delay_s(self, active: bool) -> float | None:
        self.count += 1
        return UNTIL_NEWER_FIXED if active and self.count % 2 else 0.0


class Spoof(Fault):
    description = "a stranger sends autopilot telemetry (our autopilot's ids and others) 2 km away"

    def workers(self, run: ScenarioRun, relay: LinkRelay, port: int, fly_pid: int) -> list[Worker]:
        return [Spoofer(port, relay, run.clock, *run.flight.start, speaks=self.speaks(run.clock))]

    def speaks(self, clock: Clock) -> Callable[[], bool]:
        """When the stranger talks: during the fault."""
        return clock.active


class SpoofAfterSilence(LinkLoss, Spoof):
    description = "the link drops both ways; meanwhile a stranger sends autopilot telemetry 2 km away"


class SpoofFirst(Spoof):
    description = "a stranger sends autopilot telemetry 2 km away from before the autopilot's first packet"
    from_start = True

    def speaks(self, clock: Clock) -> Callable[[], bool]:
        end_s = clock.config.fault_at_s + clock.config.fault_s
        return lambda: clock.now() < end_s


class Reboot(Fault):
    description = "the autopilot dies, and reboots 1.5 km from where the companion left it"
    reboots = True


class CorruptFrames(Fault):
    """Two frames in three damaged: a block of the JPEG zeroed in the middle, or its tail cut off."""

    description = "two camera frames in three damaged: 5 kB zeroed in the middle, or cut short"

    def __init__(self, rng: random.Random) -> None:
        super().__init__(rng)
        self.count = 0

    def damage_frame(self, data: bytes, active: bool) -> bytes | None:
        if not active:
            return None
        self.count += 1
        if self.count % 3 == 0:
            return None
        if self.count % 3 == 1:
            hole = min(FRAME_ZEROED_BYTES, len(data) // 4)
            start = (len(data) - hole) // 2
            return data[:start] + bytes(hole) + data[start + hole :]
        return data[: len(data) * 3 // 5]


class DamagedMap(Fault):
    """One bit flipped in a feature chunk of a copy of the map: ``fly`` must refuse to start."""

    description = "one bit flipped in a feature chunk of the map package"
    refusal = "map package damaged"

    def map_package(self, package: Path, root: Path) -> Path:
        copy = root / "map"
        shutil.copytree(package, copy, copy_function=os.link)  # hard links: the original stays intact
        chunk = sorted(copy.rglob("chunk_*.npy"))[0]
        data = bytearray(chunk.read_bytes())
        data[len(data) // 2] ^= 1 << self.rng.randrange(8)
        chunk.unlink()  # break the hard link before writing
        chunk.write_bytes(bytes(data))
        return copy


class Starved(Fault):
    description = "the companion runs 0.1 s in every 1.5 s (stopped and continued by signals)"

    def workers(self, run: ScenarioRun, relay: LinkRelay, port: int, fly_pid: int) -> list[Worker]:
        return [Starver(fly_pid, run.clock)]


SCENARIOS: dict[str, type[Fault]] = {
    "none": Fault,
    "garbage": Garbage,
    "corrupt": Corrupt,
    "spoof": Spoof,
    "spoof-after-silence": SpoofAfterSilence,
    "spoof-first": SpoofFirst,
    "link-loss": LinkLoss,
    "reboot": Reboot,
    "time-ahead": TimeAhead,
    "time-back": TimeBack,
    "bank": Bank,
    "velocity-fast": VelocityFast,
    "velocity-glitch": VelocityGlitch,
    "velocity-bias": VelocityBias,
    "velocity-nan-local": VelocityNanLocal,
    "camera-stall": CameraStall,
    "late-frames": LateFrames,
    "reordered": Reordered,
    "starved": Starved,
    "corrupt-frames": CorruptFrames,
    "damaged-map": DamagedMap,
}


# --- the plumbing between the two processes ------------------------------------------------


class Clock:
    """Seconds since the vehicle's first packet (the flight's start), and the fault window."""

    def __init__(self, config: FaultBenchConfig) -> None:
        self.config = config
        self.started: float | None = None
        self.first_packet = threading.Event()

    def start(self) -> None:
        if self.started is None:
            self.started = time.time()
            self.first_packet.set()

    def now(self) -> float:
        return -math.inf if self.started is None else time.time() - self.started

    def active(self) -> bool:
        t = self.now()
        return self.config.fault_at_s <= t < self.config.fault_at_s + self.config.fault_s


class Worker:
    """A daemon thread running ``_run`` while the ``with`` block lasts; ``_stop`` ends it.
    ``_close`` releases what the worker holds once its thread has ended."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._close()

    def _run(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        """Nothing to release by default."""


class LinkRelay(Worker):
    """UDP between the vehicle (it sends to ``vehicle_port``) and the companion's listening port,
    passing each datagram through the fault. Notes when each vehicle address was first heard
    (a rebooted vehicle sends from a new one)."""

    def __init__(self, companion_port: int, fault: Fault, clock: Clock) -> None:
        super().__init__()
        self.fault, self.clock = fault, clock
        self.vehicle_side = _udp_socket()
        self.companion_side = _udp_socket()
        self.companion = ("127.0.0.1", companion_port)
        self.vehicle: tuple[str, int] | None = None
        self.first_heard: dict[tuple[str, int], float] = {}  # vehicle address -> clock time
        self.latest_boot_ms = 0
        self._parser = dialect().MAVLink(None)
        self._parser.robust_parsing = True

    @property
    def vehicle_port(self) -> int:
        return self.vehicle_side.getsockname()[1]

    def _close(self) -> None:
        self.vehicle_side.close()
        self.companion_side.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.vehicle_side, self.companion_side], [], [], 0.05)
            for sock in ready:
                data, sender = sock.recvfrom(UDP_MAX_BYTES)
                if sock is self.vehicle_side:
                    self._from_vehicle(data, sender)
                elif self.vehicle is not None and self.fault.link_up(self.clock.active()):
                    self.vehicle_side.sendto(data, self.vehicle)

    def _from_vehicle(self, data: bytes, sender: tuple[str, int]) -> None:
        self.clock.start()
        self.vehicle = sender
        self.first_heard.setdefault(sender, self.clock.now())
        self._note_boot_time(data)
        active = self.clock.active()
        if not self.fault.link_up(active):
            return
        for datagram in self.fault.to_companion(data, self.clock.now(), active):
            self.companion_side.sendto(datagram, self.companion)

    def _note_boot_time(self, data: bytes) -> None:
        """The vehicle's clock, for a spoofer that wants to look current."""
        for msg in self._parser.parse_buffer(data) or []:
            if msg.get_type() in BOOT_TIME_TYPES:
                self.latest_boot_ms = msg.time_boot_ms


class FrameRelay(Worker):
    """Moves the vehicle's frames into the folder ``fly`` watches, when the fault lets them; a
    frame held until a later one is localized waits for its fix in the companion's log."""

    def __init__(self, raw: Path, delivered: Path, fault: Fault, clock: Clock, companion_log: Path) -> None:
        super().__init__()
        self.raw, self.delivered, self.fault, self.clock = raw, delivered, fault, clock
        raw.mkdir(parents=True, exist_ok=True)
        delivered.mkdir(parents=True, exist_ok=True)
        self.due: dict[str, float] = {}  # frame name -> when to deliver it, until delivered
        self.lost = 0
        self.damaged = 0
        self.companion_log = companion_log
        self._log_read = 0  # bytes of the log read so far
        self._newest_fixed = -math.inf  # capture time of the newest frame the companion localized

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            now = time.time()
            for entry in os.scandir(self.raw):
                if entry.name.startswith(".") or entry.name in self.due:
                    continue
                active = self.clock.active()
                delay = self.fault.frame_delay_s(active)
                if delay is None:
                    os.unlink(entry.path)
                    self.lost += 1
                else:
                    self._damage(Path(entry.path), active)
                    self.due[entry.name] = now + delay
            if UNTIL_NEWER_FIXED in self.due.values():
                self._read_fixes()
            for name, at in list(self.due.items()):
                if at <= now or (at == UNTIL_NEWER_FIXED and self._captured(name) < self._newest_fixed):
                    os.replace(self.raw / name, self.delivered / name)
                    del self.due[name]

    def _damage(self, frame: Path, active: bool) -> None:
        """Replace the frame by the fault's damaged copy, if it damages it (under a hidden name
        first: the companion must see the damaged frame whole, not one being written)."""
        damaged = self.fault.damage_frame(frame.read_bytes(), active)
        if damaged is not None:
            hidden = frame.with_name(f".{frame.name}")
            hidden.write_bytes(damaged)
            os.replace(hidden, frame)
            self.damaged += 1

    def _captured(self, name: str) -> float:
        """A frame's capture time from its name (one without is never released by a fix)."""
        captured = capture_time_from_name(Path(name))
        return math.inf if captured is None else captured

    def _read_fixes(self) -> None:
        """The fixes the companion has logged since the last call (its last line once complete)."""
        if not self.companion_log.exists():
            return
        with open(self.companion_log, "rb") as log:
            log.seek(self._log_read)
            lines = log.read().split(b"\n")
        for line in lines[:-1]:  # the last is empty, or a line still being written
            self._log_read += len(line) + 1
            if line.startswith(b'{"kind": "fix"'):
                self._newest_fixed = max(self._newest_fixed, json.loads(line)["capture_time_s"])


class Spoofer(Worker):
    """Telemetry from a stranger's address while ``speaks()``: an autopilot heartbeat, a position
    2 km away moving at 30 m/s and a level attitude heading north, as our autopilot (system 1)
    and as system 42, at 10 Hz. Counts the datagrams it is sent back (navigation leaked to it).

    It is as continuous as an autopilot: its sequence numbers step by one, and its boot clock
    runs from ``SPOOFER_BOOT_S`` until it hears the autopilot's, which it then copies to look
    current (a sniffer on the link). Only its attitude and position are its own."""

    def __init__(
        self,
        companion_port: int,
        relay: LinkRelay,
        clock: Clock,
        lat: float,
        lon: float,
        speaks: Callable[[], bool],
    ) -> None:
        super().__init__()
        self.companion = ("127.0.0.1", companion_port)
        self.relay, self.clock, self.speaks = relay, clock, speaks
        self.lat, self.lon = destination(lat, lon, 0.0, 2000.0)
        self.sock = _udp_socket()
        self.received = 0
        self.positions_received = 0
        self.packers = {system: dialect().MAVLink(None, system, 1) for system in (1, 42)}
        self._started = time.monotonic()

    def _close(self) -> None:
        self.sock.close()

    def _run(self) -> None:
        parser = dialect().MAVLink(None)
        while not self._stop.wait(0.1):
            while select.select([self.sock], [], [], 0)[0]:
                data, _ = self.sock.recvfrom(UDP_MAX_BYTES)
                self.received += 1
                kinds = [m.get_type() for m in parser.parse_buffer(data) or []]
                self.positions_received += sum(k == "GPS_INPUT" for k in kinds)
            if self.speaks():
                for packer in self.packers.values():
                    for msg in self._messages():
                        self.sock.sendto(bytes(msg.pack(packer)), self.companion)
                        packer.seq = (packer.seq + 1) % 256  # pack() does not step it; send() would

    def _boot_ms(self) -> int:
        if self.relay.latest_boot_ms:
            return self.relay.latest_boot_ms + 50
        return round((SPOOFER_BOOT_S + time.monotonic() - self._started) * 1000)

    def _messages(self) -> list[Any]:
        m = dialect()
        boot_ms = self._boot_ms()
        return [
            m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3),
            m.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
            m.MAVLink_global_position_int_message(
                boot_ms, round(self.lat * 1e7), round(self.lon * 1e7), 1_100_000, 1_000_000, 3000, 0, 0, 0
            ),
        ]


class Starver(Worker):
    """SIGSTOP/SIGCONT on a process during the fault: it runs ``run_s`` in every ``period_s``."""

    def __init__(self, pid: int, clock: Clock, run_s: float = 0.1, period_s: float = 1.5) -> None:
        super().__init__()
        self.pid, self.clock, self.run_s, self.period_s = pid, clock, run_s, period_s

    def _close(self) -> None:
        self._signal(signal.SIGCONT)  # never leave the companion stopped

    def _run(self) -> None:
        while not self._stop.wait(self.run_s):
            if self.clock.active():
                self._signal(signal.SIGSTOP)
                self._stop.wait(self.period_s - self.run_s)
                self._signal(signal.SIGCONT)

    def _signal(self, sig: int) -> None:
        with suppress(ProcessLookupError):
            os.kill(self.pid, sig)


def _udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock


def free_udp_port() -> int:
    """A UDP port on loopback that no one holds now (the benchmarks' processes bind it next)."""
    with _udp_socket() as sock:
        return sock.getsockname()[1]


# --- one scenario ----------------------------------------------------------------------------


@dataclass
class Flight:
    """Where the vehicle flies (and, after a reboot, where it comes back)."""

    frames_from: Path
    start: tuple[float, float]
    target: tuple[float, float]
    reboot_start: tuple[float, float]


@dataclass
class ScenarioRun:
    """One scenario's processes, folders and what they produced."""

    name: str
    root: Path
    config: FaultBenchConfig
    package: Path
    flight: Flight
    fault: Fault
    clock: Clock
    vehicles: list[Path] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)


def run_scenario(name: str, root: Path, package: Path, flight: Flight, config: FaultBenchConfig) -> dict:
    """Fly one scenario with the real processes; return its graded row."""
    fault = SCENARIOS[name](random.Random(config.seed))
    shutil.rmtree(root, ignore_errors=True)  # the logs are appended to: start from nothing
    root.mkdir(parents=True)
    package = fault.map_package(package, root)
    run = ScenarioRun(name, root, config, package, flight, fault, Clock(config))
    port = free_udp_port()
    with (
        LinkRelay(port, fault, run.clock) as relay,
        FrameRelay(
            root / "camera", root / "frames", fault, run.clock, root / "fly" / "companion.jsonl"
        ) as frames,
        child_process(_fly_command(run, port), root / "fly.out") as fly,
    ):
        _wait_for(root / "fly" / "companion.jsonl", fly, 60.0, refused=fault.refusal is not None)
        extras = fault.workers(run, relay, port, fly.pid)
        with ExitStack() as started:
            for extra in extras:
                started.enter_context(extra)
            _fly_vehicles(run, relay)
        if fly.poll() is None:
            fly.terminate()  # SIGTERM, as a supervisor stops it: the log and summary are complete
        fly.wait(timeout=30)
        run.extra["frames_lost"] = frames.lost
        run.extra["frames_damaged"] = frames.damaged
        run.extra["newest_vehicle_from_s"] = max(relay.first_heard.values(), default=0.0)
        for spoofer in (e for e in extras if isinstance(e, Spoofer)):
            run.extra["leaked_datagrams"] = spoofer.received
            run.extra["leaked_positions"] = spoofer.positions_received
    return grade(run, fly.returncode)


def _fly_vehicles(run: ScenarioRun, relay: LinkRelay) -> None:
    """One vehicle for the whole flight, or (reboot) one killed at the fault and another started
    at its end, elsewhere: the companion still believes the first one's position."""
    config, flight = run.config, run.flight
    if not run.fault.reboots:
        with _vehicle(run, relay, flight.start, config.flight_s, "vehicle") as v:
            _wait_for_start(run, v, "vehicle")
            v.wait(timeout=config.flight_s + 60)
        return
    with _vehicle(run, relay, flight.start, config.flight_s, "vehicle") as first:
        _wait_for_start(run, first, "vehicle")
        time.sleep(max(0.0, config.fault_at_s - run.clock.now()))
        first.kill()
    time.sleep(max(0.0, config.fault_at_s + config.fault_s - run.clock.now()))
    second_s = config.flight_s - run.clock.now()
    with _vehicle(run, relay, flight.reboot_start, second_s, "vehicle-rebooted") as v:
        v.wait(timeout=second_s + 60)


def _vehicle(
    run: ScenarioRun, relay: LinkRelay, start: tuple[float, float], duration_s: float, name: str
) -> AbstractContextManager[subprocess.Popen]:
    """A sim-vehicle process; what it prints goes to ``<name>.out`` beside ``fly.out``."""
    return child_process(_vehicle_command(run, relay, start, duration_s, name), _vehicle_log(run, name))


def _vehicle_log(run: ScenarioRun, name: str) -> Path:
    return run.root / f"{name}.out"


def _wait_for_start(run: ScenarioRun, vehicle: subprocess.Popen, name: str) -> None:
    while not run.clock.first_packet.wait(0.2):
        if vehicle.poll() is not None:
            raise OrthonavError(
                f"sim-vehicle exited with code {vehicle.returncode} before sending anything "
                f"(its output: {_vehicle_log(run, name)})"
            )


def _vehicle_command(
    run: ScenarioRun, relay: LinkRelay, start: tuple[float, float], duration_s: float, name: str
) -> list[str]:
    out = run.root / name
    run.vehicles.append(out)
    return [
        *CLI,
        "sim-vehicle",
        "--frames-from",
        str(run.flight.frames_from),
        "--frames-dir",
        str(run.root / "camera"),
        "--start",
        f"{start[0]},{start[1]}",
        "--target",
        f"{run.flight.target[0]},{run.flight.target[1]}",
        "--altitude",
        str(run.config.alt_m),
        "--speed",
        str(run.config.speed_mps),
        "--frame-rate",
        str(run.config.frame_rate_hz),
        "--seed",
        str(run.config.seed),
        "--connect",
        f"udpout:127.0.0.1:{relay.vehicle_port}",
        "--duration",
        f"{duration_s:.1f}",
        "--out",
        str(out),
    ]


def _fly_command(run: ScenarioRun, port: int) -> list[str]:
    return [
        *CLI,
        "fly",
        "--map",
        str(run.package),
        "--frames",
        str(run.root / "frames"),
        "--connect",
        f"udpin:127.0.0.1:{port}",
        "--log-dir",
        str(run.root / "fly"),
        "--independent-attitude",  # sim-vehicle reports its true attitude
    ]


@contextmanager
def child_process(
    command: list[str], log: Path | None, cwd: Path | None = None, grace_s: float = 0.0
) -> Iterator[subprocess.Popen]:
    """A child process whose output goes to ``log`` (or nowhere), stopped at the end if still
    running: continued first (a stopped process acts on no other signal), given ``grace_s``
    seconds after SIGTERM to end by itself where asked, then killed."""
    with open(log or os.devnull, "w") as out:
        process = subprocess.Popen(_dying_with_parent(command), cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        try:
            yield process
        finally:
            if process.poll() is None:
                _stop(process, grace_s)


def _dying_with_parent(command: list[str]) -> list[str]:
    """``command`` started through DIE_WITH_PARENT on Linux; elsewhere as it is (the context
    manager's own stop is all there is)."""
    if not sys.platform.startswith("linux"):
        return command
    return [sys.executable, "-c", DIE_WITH_PARENT, str(os.getpid()), *command]


def _stop(process: subprocess.Popen, grace_s: float) -> None:
    process.send_signal(signal.SIGCONT)
    if grace_s > 0:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=grace_s)
            return
        except subprocess.TimeoutExpired:
            pass
    process.kill()
    process.wait(timeout=30)


def _wait_for(path: Path, process: subprocess.Popen, timeout_s: float, refused: bool = False) -> None:
    """Until ``path`` exists (the companion has started its loop), or, where ``fly`` must
    refuse to start, until it has exited (graded then)."""
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if process.poll() is not None:
            if refused:
                return
            raise OrthonavError(f"fly exited with code {process.returncode} before starting")
        if time.monotonic() > deadline:
            raise OrthonavError(f"fly did not start within {timeout_s:.0f} s")
        time.sleep(0.1)


# --- grading ---------------------------------------------------------------------------------


def grade(run: ScenarioRun, fly_exit: int | None) -> dict:
    """The scenario's row: positions the vehicle(s) received, the wrong ones, the recovery."""
    config, started = run.config, run.clock.started
    if started is None:
        raise OrthonavError(f"fault scenario {run.name}: the vehicle never sent a packet")
    fault_end = started + config.fault_at_s + config.fault_s
    # A rebooted autopilot is back when it is first heard, however long its process took to start.
    back = max(fault_end, started + run.extra["newest_vehicle_from_s"]) if run.fault.reboots else fault_end
    positions = [p for v in run.vehicles for p in _positions(v / "received.jsonl")]
    wrong = [p for p in positions if _wrong(p)]
    log = read_log(run.root / "fly" / "companion.jsonl")
    fused = [r["capture_time_s"] for r in log if r["kind"] == "fix" and r["filter"].get("accepted")]
    judged_from = started if run.fault.from_start else fault_end
    output_back = first_after([p["received_s"] for p in positions if not _wrong(p)], judged_from)
    fix_back = first_after(fused, judged_from)
    resumed_s = None if output_back is None or fix_back is None else max(output_back, fix_back)
    errors = sorted(p["error_m"] for p in positions if "error_m" in p)
    row = {
        "scenario": run.name,
        "positions": len(positions),
        "wrong": len(wrong),
        "wrong_in_fault": sum(started + config.fault_at_s <= p["received_s"] < fault_end for p in wrong),
        "unverifiable": sum("error_m" not in p for p in positions),
        "leaked": run.extra.get("leaked_positions", 0),
        "max_error_m": round(errors[-1], 1) if errors else None,
        "median_error_m": round(errors[len(errors) // 2], 1) if errors else None,
        "resumed_s": None if resumed_s is None else round(resumed_s, 1),
        "autopilot_back_s": round(back - fault_end, 1) if run.fault.reboots else None,
        "fixes_fused": len(fused),
        "fly_exit": fly_exit,
    }
    row["description"] = run.fault.description
    row["evidence"] = _evidence(run, log, started + config.fault_at_s, back)
    row["passed"] = _passed(row, config, run.fault.refusal)
    row["track"] = [_track_point(p, started) for p in positions]
    return row


def _positions(received: Path) -> list[dict]:
    """GPS_INPUT with a 3-D fix the vehicle logged (a killed vehicle's log may end mid-line)."""
    if not received.exists():
        return []
    rows = []
    for line in received.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return [r for r in rows if r.get("type") == "GPS_INPUT" and r.get("fix_type", 0) >= 3]


def _wrong(position: dict) -> bool:
    """More than 3 sigma or 50 m from the truth, or at a time the truth does not cover."""
    error = position.get("error_m")
    if error is None:
        return True
    return error > WRONG_M or error > WRONG_SIGMAS * position["horiz_accuracy_m"]


def read_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _evidence(run: ScenarioRun, log: list[dict], fault_start: float, fault_end: float) -> dict:
    """What the companion saw of the fault: proof that it was injected, and how it was taken.
    Its events count from the fault's start to ``EVIDENCE_GRACE_S`` after its end."""
    summary_path = run.root / "fly" / "summary.json"
    link = json.loads(summary_path.read_text())["link"] if summary_path.exists() else {}
    said = (run.root / "fly.out").read_text(errors="replace").splitlines()
    fixes = [r for r in log if r["kind"] == "fix"]
    sent = [r["time_s"] for r in log if r["kind"] == "sent"]
    captures = [r["capture_time_s"] for r in fixes]
    return {
        "bad_packets": link.get("bad", 0),
        "ignored_packets": link.get("ignored", 0),
        "events": [
            r["text"]
            for r in log
            if r["kind"] == "event" and fault_start <= r["time_s"] < fault_end + EVIDENCE_GRACE_S
        ],
        "frames_lost": run.extra.get("frames_lost", 0),
        "frames_damaged": run.extra.get("frames_damaged", 0),
        "frames_refused": sum(SKIPPED_FRAME in line for line in said),
        "refusal": next((line for line in said if run.fault.refusal and run.fault.refusal in line), None),
        "oldest_fix_s": round(max((r["time_s"] - r["capture_time_s"] for r in fixes), default=0.0), 2),
        "fixes_out_of_order": sum(b < a for a, b in itertools.pairwise(captures)),
        "longest_silence_s": round(max((b - a for a, b in itertools.pairwise(sent)), default=0.0), 2),
    }


def first_after(times: list[float], end: float) -> float | None:
    """Seconds from ``end`` to the first time at or after it; 0 when it never stopped."""
    later = [t for t in times if t >= end]
    return max(0.0, min(later) - end) if later else None


def _passed(row: dict, config: FaultBenchConfig, refusal: str | None) -> bool:
    """Nothing wrong sent, nothing to the stranger, and navigation back in time; or, where ``fly``
    must refuse to start, that refusal (exit 2 with its message) and nothing sent at all."""
    if row["wrong"] or row["leaked"]:
        return False
    if refusal is not None:
        return (
            row["fly_exit"] == REFUSED_EXIT
            and row["evidence"]["refusal"] is not None
            and not row["positions"]
        )
    return row["resumed_s"] is not None and row["resumed_s"] <= config.resume_within_s


def _track_point(position: dict, started: float) -> list[float | bool | None]:
    """(time since start, error, 3 sigma, wrong) for the plot: the verdict travels with the point,
    so the picture never judges by a rule of its own."""
    error = position.get("error_m")
    return [
        round(position["received_s"] - started, 2),
        None if error is None else round(error, 2),
        round(WRONG_SIGMAS * position["horiz_accuracy_m"], 2),
        _wrong(position),
    ]


# --- the benchmark ---------------------------------------------------------------------------


def default_flight(frames_from: Path, offset_m: float) -> Flight:
    """East across the orthophoto's middle; a reboot comes back ``offset_m`` north."""
    with GeoRaster(frames_from) as raster:
        lat, lon = raster.center_latlon
    start = destination(lat, lon, 270.0, 700.0)
    return Flight(
        frames_from,
        start,
        destination(lat, lon, 90.0, 1000.0),
        destination(*start, 0.0, offset_m),
    )


def ensure_map(orthophoto: Path, out: Path, alt_m: float, hfov_deg: float = 60.0) -> Path:
    """A keypoint map package of ``orthophoto`` for ``fly`` (whose camera is the package's),
    built once and reused."""
    if (out / "manifest.json").exists():
        return out
    camera = Camera.from_hfov(640, 480, hfov_deg)
    build_map(orthophoto, out, camera, TilingConfig(nominal_alt_m=alt_m), progress=False)
    return out


def run_fault_benchmark(
    package: Path | MapPackage, frames_from: Path, out: Path, config: FaultBenchConfig
) -> dict:
    """Every scenario (``config.parallel`` at a time), graded; JSON and PNG written to ``out``."""
    package_dir = package.path if isinstance(package, MapPackage) else package
    flight = default_flight(frames_from, config.reboot_offset_m)
    runs_dir = out.with_suffix("")
    names = config.names
    rows: dict[str, dict] = {}
    watch = LoadWatch()
    with (
        ThreadPoolExecutor(max_workers=config.parallel) as pool,
        tqdm(total=len(names), desc="fault scenarios", unit="scenario") as bar,
    ):
        futures = {
            pool.submit(run_scenario, name, runs_dir / name, package_dir, flight, config): name
            for name in names
        }
        for future in as_completed(futures):
            name = futures[future]
            rows[name] = future.result()
            bar.set_postfix_str(f"{name}: {'pass' if rows[name]['passed'] else 'FAIL'}")
            bar.update()
    ordered = [rows[name] for name in names]
    result = {
        "config": asdict(config),
        "map": str(package_dir),
        "frames_from": str(frames_from),
        "machine": watch.record(),
        "rows": ordered,
        "passed": sum(r["passed"] for r in ordered),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out, result)
    plot_fault_bench(
        ordered,
        config.fault_at_s,
        config.fault_s,
        config.resume_within_s,
        out.with_suffix(".png"),
        machine_line(result["machine"]),
    )
    return result


def summary_line(result: dict) -> str:
    rows = result["rows"]
    wrong = sum(r["wrong"] + r["leaked"] for r in rows)
    return (
        f"{result['passed']} of {len(rows)} fault scenarios passed; "
        f"{wrong} wrong position(s) sent in all, {sum(r['positions'] for r in rows)} graded; "
        f"{machine_line(result['machine'])}"
    )

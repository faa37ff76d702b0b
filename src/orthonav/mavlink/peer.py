"""Who the autopilot is on a listening UDP link, when anyone can send packets with its ids.

MAVLink without signing cannot tell who sent a packet; what an impostor cannot easily copy is
the autopilot's own continuity: one sender address, a sequence number that steps by one per
message, a boot clock (``time_boot_ms``) that runs with ours, and an attitude that changes only
as fast as the airframe turns. :class:`PeerLock` follows every sender claiming autopilot ids as
a *stream* and pins the peer by that continuity:

- at start, no one is the peer (nothing delivered, nothing answered) until an autopilot's stream
  has run unbroken for ``PEER_PROBATION_S``, longer than any other claimant's;
- a live peer is displaced only by a claimant whose stream has run unbroken for longer: one that
  began before the peer's own stream broke (a spoofer that spoke first and then copied the
  autopilot's clock breaks its stream by that jump);
- after the peer falls silent, a new address is believed only with continuity evidence: it began
  after the peer fell silent, its boot clock continues the peer's (a router restarted) or is a
  fresh boot begun after the peer's last message (a reboot), and its first attitude agrees with
  the peer's last. Silence alone never moves the peer; the peer's own address is always heard.

What this cannot defend against, short of MAVLink 2 signing (``MavLink(signing_key=...)``):
a sender that forges the autopilot's source address; a spoofer that speaks before the autopilot
with a stream as continuous as an autopilot's and keeps it so (it is pinned first, and the real
autopilot is then the claimant that is ignored, with a warning; when the spoofer falls silent,
the autopilot that talked beside it is not believed either, as nothing shows which was real);
and one that, after the autopilot falls silent, continues its clock or fakes a fresh boot with a
matching attitude (a sniffer on the same network can). The real autopilot's return at its own
address with its clock continuing takes the peer back, as its stream is the older unbroken one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from orthonav.errors import OrthonavError

log = logging.getLogger(__name__)

MAV_AUTOPILOT_INVALID = 8  # a HEARTBEAT from a GCS or companion computer, not an autopilot
# A peer heard within this is live; beyond it, silent: only continuity evidence moves it then.
PEER_SILENT_S = 2.0
# How long, and over how many messages, a stream must run unbroken before it is believed: long
# enough for its sequence and boot clock to have been checked several times at telemetry rates.
PEER_PROBATION_S = 1.0
PEER_MIN_MESSAGES = 3
# Sequence numbers are judged only between messages this close: after a longer gap any number of
# messages may have been lost (256 wrap the counter).
SEQ_JUDGED_WITHIN_S = 1.0
SEQ_MAX_STEP = 64  # more lost at once than a live link loses between two reads
# A boot clock cannot run ahead of ours (a message cannot arrive before it was sent); it may lag
# by how late we read it (a busy or stopped companion, a burst). The slack is scheduling jitter.
BOOT_AHEAD_SLACK_S = 1.0
BOOT_LATE_S = 5.0
# A fresh boot reads no more than the time since the sender's previous message: a reboot takes
# that long, and at least REBOOT_SILENCE_S. The slack is jitter only: a clock copied from an
# autopilot that booted seconds ago, or one copied without a pause, is not a fresh boot.
FRESH_BOOT_SLACK_S = 0.25
REBOOT_SILENCE_S = 1.0
# Attitude continuity across a new address: what an airframe can turn by between the peer's last
# report and the newcomer's first, plus the noise of two estimators.
ATTITUDE_AGREE_DEG = 20.0
ATTITUDE_TURN_DPS = 5.0
MAX_STREAMS = 16  # claimants followed at once: a flood of addresses cannot grow memory


class PeerFilter:
    """Which ids the autopilot has: named (``system``, ``component``; a system alone admits all
    its components), or else those of the stream :class:`PeerLock` pins (:meth:`pin`)."""

    def __init__(self, system: int | None = None, component: int | None = None) -> None:
        for name, value in (("system", system), ("component", component)):
            if value is not None and not 1 <= value <= 255:
                raise OrthonavError(f"MAVLink target {name} {value}: expected an id in 1..255")
        self.system, self.component = system, component

    def matches(self, system: int, component: int) -> bool:
        """Whether a sender with these ids can be (or is) the autopilot."""
        return self.system in (None, system) and self.component in (None, component)

    def admits(self, msg: Any) -> bool:
        return self.system is not None and self.matches(msg.get_srcSystem(), msg.get_srcComponent())

    def pin(self, system: int, component: int) -> None:
        if self.system is None:
            self.system, self.component = system, component

    @property
    def ids(self) -> tuple[int | None, int | None]:
        return self.system, self.component

    def __str__(self) -> str:
        if self.system is None:
            return "no autopilot confirmed yet"
        return f"system {self.system}" + (
            f" component {self.component}" if self.component is not None else ""
        )


@dataclass
class Stream:
    """One sender (address and ids) as its packets arrive; times on the lock's clock."""

    address: Any
    ids: tuple[int, int]
    first_s: float
    last_s: float = -math.inf
    autopilot: bool = False  # it sent an autopilot HEARTBEAT
    seq: int | None = None
    lead_s: float | None = None  # max(boot time - arrival): its boot clock against ours, least delayed
    boot_heard_s: float = -math.inf  # arrival of its newest boot-stamped message
    first_boot_s: float | None = None  # the boot time of its first boot-stamped message...
    first_boot_at_s: float = math.nan  # ...and when that arrived
    attitude: tuple[float, float, float] | None = None  # roll, pitch, yaw (rad), the newest
    attitude_s: float = -math.inf
    first_attitude: tuple[float, float, float] | None = None
    first_attitude_s: float = math.nan
    unbroken_since_s: float = field(init=False)
    unbroken_messages: int = 0
    broke: str = ""  # why it last broke

    def __post_init__(self) -> None:
        self.unbroken_since_s = self.first_s

    def hear(self, msg: Any, now: float) -> str:
        """Take one message; why it breaks the stream's continuity, or ''."""
        broke = self._sequence(msg.get_seq(), now)
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            broke = self._boot_clock(boot_ms / 1000.0, now) or broke
        if msg.get_type() == "ATTITUDE":
            self.attitude, self.attitude_s = (msg.roll, msg.pitch, msg.yaw), now
            if self.first_attitude is None:
                self.first_attitude, self.first_attitude_s = self.attitude, now
        elif msg.get_type() == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID:
            self.autopilot = True
        self.last_s = now
        if broke:
            self.broke, self.unbroken_since_s, self.unbroken_messages = broke, now, 0
        self.unbroken_messages += 1
        return broke

    def _sequence(self, seq: int, now: float) -> str:
        previous, self.seq = self.seq, seq
        if previous is None or now - self.last_s > SEQ_JUDGED_WITHIN_S:
            return ""
        step = (seq - previous) % 256
        return "" if 0 < step <= SEQ_MAX_STEP else f"sequence {previous} -> {seq}"

    def _boot_clock(self, boot_s: float, now: float) -> str:
        offset = boot_s - now
        if self.lead_s is None:
            self.lead_s, self.first_boot_s, self.first_boot_at_s = offset, boot_s, now
            self.boot_heard_s = now
            return ""
        broke = ""
        if offset > self.lead_s + BOOT_AHEAD_SLACK_S:
            broke = f"boot time leapt {offset - self.lead_s:.1f} s ahead"
        elif offset < self.lead_s - BOOT_LATE_S and not self._fresh_boot(boot_s, now):
            broke = f"boot time stepped {self.lead_s - offset:.1f} s back"
        # A restart of the clock (a break, or a reboot at this address) starts a new baseline.
        restarted = broke or offset < self.lead_s - BOOT_LATE_S
        self.lead_s = offset if restarted else max(self.lead_s, offset)
        self.boot_heard_s = now
        return broke

    def _fresh_boot(self, boot_s: float, now: float) -> bool:
        """A clock begun after this stream's previous boot-stamped message, after a silence a
        reboot takes: it rebooted here."""
        silent_s = now - self.boot_heard_s
        return silent_s >= REBOOT_SILENCE_S and boot_s <= silent_s + FRESH_BOOT_SLACK_S

    def unbroken_s(self, now: float) -> float:
        return now - self.unbroken_since_s

    def proven(self, now: float) -> bool:
        """Unbroken long enough, over enough messages, to be believed."""
        return self.unbroken_s(now) >= PEER_PROBATION_S and self.unbroken_messages >= PEER_MIN_MESSAGES

    def live(self, now: float) -> bool:
        return now - self.last_s < PEER_SILENT_S

    def where(self) -> str:
        host, port = self.address[:2]
        return f"system {self.ids[0]} component {self.ids[1]} at {host}:{port}"


def continues(old: Stream, new: Stream) -> str:
    """Why ``new`` (another address) is ``old`` continued, or '' when nothing shows it is: it
    began after ``old`` fell silent, its boot clock runs on from ``old``'s or began after
    ``old``'s last message, and its first attitude agrees with ``old``'s last."""
    if new.first_s < old.last_s or new.lead_s is None or old.lead_s is None:
        return ""
    if abs(new.lead_s - old.lead_s) <= BOOT_AHEAD_SLACK_S:
        clock = "its boot clock continues the peer's"
    elif (
        new.first_boot_s is not None
        and new.first_boot_s <= new.first_boot_at_s - old.last_s + FRESH_BOOT_SLACK_S
    ):
        clock = f"a fresh boot ({new.first_boot_s:.1f} s) since the peer fell silent"
    else:
        return ""
    if old.attitude is None or new.first_attitude is None:
        return ""
    allowed = ATTITUDE_AGREE_DEG + ATTITUDE_TURN_DPS * max(0.0, new.first_attitude_s - old.attitude_s)
    if _attitude_change_deg(old.attitude, new.first_attitude) > allowed:
        return ""
    return f"{clock} and its attitude agrees"


def _attitude_change_deg(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    """The largest change of roll, pitch or yaw (wrapped), in degrees; NaN counts as any change."""
    changes = [abs(math.remainder(y - x, math.tau)) for x, y in zip(a, b, strict=True)]
    return 180.0 if any(math.isnan(c) for c in changes) else math.degrees(max(changes))


class PeerLock:
    """Which sender of a listening UDP link is the autopilot (see the module docstring).

    :meth:`judge` says for each message: True, the peer's (deliver it, answer its address);
    False, another sender's (ignore it); None, no peer confirmed yet (hold it back).
    """

    def __init__(self, ids: PeerFilter, clock: Callable[[], float]) -> None:
        self.ids, self.clock = ids, clock
        self.streams: dict[tuple[Any, int, int], Stream] = {}
        self.peer: Stream | None = None
        self.replaced = 0  # times the pinned peer gave way to another sender
        self._warned: set[tuple[Any, int, int]] = set()

    @property
    def address(self) -> Any:
        return None if self.peer is None else self.peer.address

    def judge(self, msg: Any, sender: Any) -> bool | None:
        if not self.ids.matches(msg.get_srcSystem(), msg.get_srcComponent()):
            return False  # ids the autopilot cannot have: nothing to follow
        now = self.clock()
        key = (sender, msg.get_srcSystem(), msg.get_srcComponent())
        stream = self.streams.get(key) or self._follow(key, now)
        broke = stream.hear(msg, now)
        if broke and stream is self.peer:
            log.warning("MAVLink peer %s: its stream broke (%s)", stream.where(), broke)
        self._consider(stream, now)
        if self.peer is None:
            return None
        return sender == self.peer.address and self.ids.admits(msg)

    def why_ignored(self, msg: Any, sender: Any) -> str:
        """Why a message :meth:`judge` refused was refused, in words."""
        if self.peer is None or not self.ids.admits(msg):
            return f"not the peer ({self.ids})"
        where = self.peer.where()
        if self.peer.live(self.clock()):
            return f"the peer's ids from another address than the live peer's ({where})"
        return f"the peer's ids from another address, not shown to continue the silent peer ({where})"

    def _follow(self, key: tuple[Any, int, int], now: float) -> Stream:
        if len(self.streams) >= MAX_STREAMS:
            kept = {id(self.peer)}
            oldest = min((s for s in self.streams.values() if id(s) not in kept), key=lambda s: s.last_s)
            del self.streams[(oldest.address, *oldest.ids)]
        stream = self.streams[key] = Stream(key[0], key[1:], now)
        return stream

    def _consider(self, stream: Stream, now: float) -> None:
        """Make ``stream`` the peer if the rules allow (see the module docstring)."""
        peer = self.peer
        if stream is peer or not stream.autopilot or not stream.proven(now):
            return
        if not self.ids.matches(*stream.ids) or (peer is not None and stream.ids != peer.ids):
            return
        if peer is None:
            rivals = [
                s
                for s in self.streams.values()
                if s is not stream and s.autopilot and s.live(now) and self.ids.matches(*s.ids)
            ]
            if all(s.unbroken_since_s > stream.unbroken_since_s for s in rivals):
                self._pin(stream, "the autopilot whose stream has run unbroken longest")
            return
        if peer.live(now):
            if stream.unbroken_since_s < peer.unbroken_since_s:
                self._pin(stream, f"its stream has run unbroken longer; the peer's broke ({peer.broke})")
            else:
                self._warn_once(stream, f"a live peer ({peer.where()}) keeps its place")
            return
        evidence = continues(peer, stream)
        if evidence:
            self._pin(stream, f"the silent peer continued: {evidence}")
        else:
            self._warn_once(stream, f"nothing shows it continues the silent peer ({peer.where()})")

    def _pin(self, stream: Stream, why: str) -> None:
        if self.peer is None:
            log.info("MAVLink peer: %s: %s", stream.where(), why)
        else:
            log.warning("MAVLink peer: %s instead of %s: %s", stream.where(), self.peer.where(), why)
            self.replaced += 1
        self.peer = stream
        self.ids.pin(*stream.ids)

    def _warn_once(self, stream: Stream, why: str) -> None:
        key = (stream.address, *stream.ids)
        if key not in self._warned:
            self._warned.add(key)
            log.warning("MAVLink: %s claims the autopilot's ids, not believed: %s", stream.where(), why)

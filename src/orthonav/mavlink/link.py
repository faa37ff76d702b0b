"""A MAVLink connection that survives bad input: the transport of the companion and the sim vehicle.

pymavlink's ``mavlink_connection`` gives the transport (UDP, TCP, serial); parsing and packing
use one MAVLink 2 codec of the ``ardupilotmega`` dialect (it also reads MAVLink 1 frames), so
the wire format does not depend on pymavlink's process-wide ``MAVLINK20`` switch, and garbage
never raises: bad prefixes, bad CRCs and truncated datagrams are counted in ``stats.bad``.

URLs (pymavlink's conventions, see ``mavutil.mavlink_connection``):

- ``udpin:HOST:PORT`` listens on HOST:PORT and answers its peer at the address it last sent
  from (so it can send nothing before the peer's first packet). A companion's peer is the
  autopilot (:class:`~orthonav.mavlink.peer.PeerFilter`: the system/component named, or those
  of the first autopilot confirmed), pinned by its address and its stream's continuity
  (:class:`~orthonav.mavlink.peer.PeerLock`): packets from anyone else are ignored and counted
  in ``stats.ignored``, so the navigation output does not go to whoever sends a packet to the
  port, and nothing is delivered or answered before an autopilot is confirmed;
- ``udpout:HOST:PORT`` sends to HOST:PORT and receives the answers on its own port;
- ``udp:HOST:PORT`` is pymavlink's legacy spelling of ``udpin``;
- ``tcp:HOST:PORT`` connects, ``tcpin:HOST:PORT`` listens;
- ``serial:DEVICE[:BAUD]``, or a device path such as ``/dev/ttyACM0`` (115200 baud).

Pairing on one machine (both directions tested): the vehicle ``udpout:127.0.0.1:14550``
and the companion ``udpin:0.0.0.0:14550`` (or ``udp:127.0.0.1:14550``), as ArduPilot SITL
and MAVProxy do; or the reverse, vehicle ``udpin:0.0.0.0:14550`` and companion
``udpout:127.0.0.1:14550``, where the vehicle starts streaming once the companion's first
heartbeat arrived. Port 0 (``udpin:127.0.0.1:0``) binds a free port, see :attr:`MavLink.local_port`.

With a ``signing_key`` (MAVLink 2 message signing, the autopilot set with the same key) every
packet sent is signed, and a packet received unsigned, signed with another key, or replayed is
refused and counted in ``stats.unsigned``: the one defence against a sender forging the
autopilot's address or stream.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import logging
import re
import struct
import textwrap
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orthonav.errors import OrthonavError
from orthonav.mavlink.peer import PeerFilter, PeerLock

log = logging.getLogger(__name__)

NETWORK_URL = re.compile(r"(udpin|udpout|udp|tcp|tcpin):[^:/]+:\d+")
COM_PORT = re.compile(r"COM\d+", re.IGNORECASE)
SERIAL_BAUD = 115200
READ_BYTES = 4096
UDP_MAX_BYTES = 65535
STATUSTEXT_LEN = 50  # STATUSTEXT.text is char[50]
STATUSTEXT_MAX_CHUNKS = 4
WARN_EVERY_S = 5.0
ROLES = ("companion", "vehicle")
ARDUCOPTER_GUIDED = 4  # custom_mode of ArduCopter's GUIDED mode
# MAVLink 2 signing: timestamps count 10 us since 2015-01-01; a new signed stream may start at
# most a minute behind our own timestamp (the specification's window against replays).
SIGNING_EPOCH_S = 1420070400
SIGNING_NEW_STREAM_WINDOW = 60 * 100_000
SIGNING_KEY_BYTES = 32


def dialect() -> Any:
    """The MAVLink 2 ``ardupilotmega`` dialect module, imported on first use."""
    try:
        from pymavlink.dialects.v20 import ardupilotmega
    except ImportError:
        raise OrthonavError("MAVLink needs pymavlink: pip install 'orthonav[mavlink]'") from None
    return ardupilotmega


@dataclass
class LinkStats:
    """Counters of one link; ``last_receive_s`` is on the link's clock (None: nothing yet)."""

    received: int = 0
    sent: int = 0
    bad: int = 0
    ignored: int = 0  # good messages from senders that are not the peer (listening UDP)
    unconfirmed: int = 0  # good messages held back while no autopilot is confirmed (listening UDP)
    unsigned: int = 0  # packets refused by signing: unsigned, another key, or replayed
    errors: int = 0
    reconnects: int = 0
    last_receive_s: float | None = None

    def to_dict(self) -> dict:
        return dict(vars(self))


class RateLimitedWarning:
    """Log a warning of one kind at most every ``every_s`` seconds, counting what was held back."""

    def __init__(self, logger: logging.Logger, every_s: float = WARN_EVERY_S) -> None:
        self.logger, self.every_s = logger, every_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def __call__(self, key: str, message: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -float("inf")) < self.every_s:
            self._held[key] = self._held.get(key, 0) + 1
            return
        held = self._held.pop(key, 0)
        self._last[key] = now
        self.logger.warning("%s%s", message, f" ({held} more like it not shown)" if held else "")


class Backoff:
    """When to try again after a failure: ``first_s`` after the first attempt, doubling per
    attempt up to ``max_s``, so a dead peer costs a few attempts a minute, not one per loop pass."""

    def __init__(self, first_s: float = 0.5, max_s: float = 4.0) -> None:
        self.first_s, self.max_s = first_s, max_s
        self.reset()

    def reset(self) -> None:
        """Success: the next failure is retried at once."""
        self.attempts = 0
        self._next_s = -float("inf")

    def due(self, now_s: float) -> bool:
        return now_s >= self._next_s

    def attempt(self, now_s: float) -> float:
        """Count an attempt made at ``now_s``; the delay before the next one."""
        delay = min(self.max_s, self.first_s * 2.0**self.attempts)
        self.attempts += 1
        self._next_s = now_s + delay
        return delay


def check_url(url: str) -> str:
    """``url`` unchanged if it names a MAVLink transport, else an error listing the forms."""
    if (
        NETWORK_URL.fullmatch(url)
        or url.startswith("serial:")
        or url.startswith("/dev/")
        or COM_PORT.match(url)
    ):
        return url
    raise OrthonavError(
        f"MAVLink connection {url!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, udp:HOST:PORT, "
        "tcp:HOST:PORT, tcpin:HOST:PORT, serial:DEVICE[:BAUD] or a serial device path"
    )


def statustext_chunks(text: str) -> list[str]:
    """``text`` as at most 4 STATUSTEXT chunks of <= 50 ASCII characters, split between words.

    MAVLink 2 reassembles chunks sharing an ``id``; ground stations that do not still show
    each chunk as a readable line. Longer text is truncated with '...'.
    """
    ascii_text = " ".join(text.encode("ascii", "replace").decode().split()) or "-"
    chunks = textwrap.wrap(ascii_text, STATUSTEXT_LEN)
    if len(chunks) > STATUSTEXT_MAX_CHUNKS:
        chunks = chunks[:STATUSTEXT_MAX_CHUNKS]
        chunks[-1] = chunks[-1][: STATUSTEXT_LEN - 3] + "..."
    return chunks


class MavLink:
    """One MAVLink endpoint: non-blocking ``poll``, ``send``, heartbeats and status texts.

    ``role`` chooses the heartbeat (and the default component): a companion computer
    (MAV_TYPE_ONBOARD_CONTROLLER, no autopilot, component 191) or a vehicle (quadrotor,
    ArduPilot, component 1). ``clock`` times ``stats.last_receive_s`` and :meth:`silent_for`:
    by default UNIX time, the clock the companion loop and telemetry run on. ``peers`` decides
    whom a listening UDP link answers: by default a companion answers only its autopilot
    (``PeerFilter()``), a vehicle anyone who sends to it. ``signing_key`` (32 bytes, see
    :func:`read_signing_key`) signs what is sent and refuses what is not signed with it.
    """

    def __init__(
        self,
        url: str,
        source_system: int = 1,
        source_component: int | None = None,
        role: str = "companion",
        clock: Callable[[], float] = time.time,
        peers: PeerFilter | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        if role not in ROLES:
            raise OrthonavError(f"MAVLink role {role!r}: expected one of {', '.join(ROLES)}")
        self.url = check_url(url)
        self.role = role
        self.source_system = source_system
        self.source_component = source_component if source_component is not None else _component(role)
        self.clock = clock
        self.peers = peers if peers is not None else (PeerFilter() if role == "companion" else None)
        self._lock = None if self.peers is None else PeerLock(self.peers, clock)
        if signing_key is not None and len(signing_key) != SIGNING_KEY_BYTES:
            raise OrthonavError(
                f"MAVLink signing key: expected {SIGNING_KEY_BYTES} bytes, got {len(signing_key)}"
            )
        self._signing_key = signing_key
        self._signed_streams: dict[tuple[int, int, int], int] = {}  # kept across reopenings
        self.stats = LinkStats()
        self._conn: Any = None
        self._mav: Any = None
        self._datagrams = False
        self._udp_server = False
        self._tcp_client = False
        self._peer_closed = False
        self._down = False  # a reconnect failed: read and send nothing until one succeeds
        self._pending: deque[Any] = deque()
        self._opened_s = clock()
        self._statustext_id = 0
        self._warn = RateLimitedWarning(log)

    # --- connection ----------------------------------------------------------------------
    def open(self) -> MavLink:
        """Open the transport (idempotent); a bad address raises :class:`OrthonavError`."""
        if self._conn is not None:
            return self
        from pymavlink import mavutil

        try:
            self._conn = _connect(mavutil, self.url)
        except Exception as exc:  # pymavlink raises OSError, ValueError, serial errors...
            raise OrthonavError(f"MAVLink connection {self.url}: cannot open ({exc})") from None
        self._datagrams = isinstance(self._conn, mavutil.mavudp)
        self._udp_server = self._datagrams and bool(self._conn.udp_server)
        self._tcp_client = isinstance(self._conn, mavutil.mavtcp)
        self._peer_closed = self._down = False
        self._mav = dialect().MAVLink(self._conn, self.source_system, self.source_component)
        self._mav.robust_parsing = True
        if self._signing_key is not None:
            _setup_signing(self._mav, self._signing_key, self._signed_streams)
        self._conn.mav = self._mav  # pymavlink's own helpers then speak our codec
        if self.stats.reconnects == 0:  # silence counts from the first open: a reopen is no message
            self._opened_s = self.clock()
        self.url = _with_bound_port(self.url, self.local_port)
        return self

    def close(self) -> None:
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.close()
        self._conn = self._mav = None
        self._down = False

    def reconnect(self) -> bool:
        """Close and reopen the transport (e.g. after the link went silent), forgetting partial input.

        False when it cannot be reopened yet (a TCP autopilot still down, a serial port still
        unplugged): counted and logged, never raised mid-flight; :meth:`poll` then reads nothing
        and :meth:`send` drops until a later reconnect succeeds.
        """
        self.close()
        self._pending.clear()
        self.stats.reconnects += 1
        try:
            self.open()
        except OrthonavError as exc:
            self._down = True
            self.stats.errors += 1
            self._warn("reopen", f"{exc}; retrying later")
            return False
        return True

    def __enter__(self) -> MavLink:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def local_port(self) -> int | None:
        """The local UDP/TCP port (useful after binding port 0), None for other transports."""
        sock = getattr(self._conn, "port", None)
        try:
            return int(sock.getsockname()[1])
        except (AttributeError, OSError, TypeError, IndexError):
            return None

    @property
    def peer_replaced(self) -> int:
        """How often the autopilot this link listens to gave way to another sender (listening UDP):
        what was heard before such a change describes another vehicle, or none."""
        return 0 if self._lock is None else self._lock.replaced

    def silent_for(self, now_s: float | None = None) -> float:
        """Seconds since the last good message (or since the link was opened, if none came)."""
        now = self.clock() if now_s is None else now_s
        last = self.stats.last_receive_s
        return now - (self._opened_s if last is None else last)

    # --- receive ---------------------------------------------------------------------------
    def poll(self, max_messages: int = 100) -> list[Any]:
        """Up to ``max_messages`` good messages that have arrived; never blocks, never raises."""
        if not self._usable():
            return []
        messages = [self._pending.popleft() for _ in range(min(max_messages, len(self._pending)))]
        for _ in range(4 * max_messages):  # bounded: a flood of garbage cannot hold the caller
            if len(messages) >= max_messages:
                break
            data, sender = self._read()
            if not data:
                break
            replaced = self.peer_replaced
            admitted = self._admit(self._parse(data), sender)
            if self.peer_replaced != replaced:  # nothing of the autopilot before follows its successor's
                messages.clear()
                self._pending.clear()
            messages.extend(admitted)
        self._pending.extend(messages[max_messages:])
        del messages[max_messages:]
        if messages:
            self.stats.received += len(messages)
            self.stats.last_receive_s = self.clock()
        return messages

    def _read(self) -> tuple[bytes, Any]:
        """(data, sender address): the address only for a listening UDP link."""
        if self._peer_closed:
            return b"", None
        try:
            if self._udp_server:  # from the socket: pymavlink's recv would answer every sender
                data, sender = self._conn.port.recvfrom(UDP_MAX_BYTES)
                return data, sender
            if self._tcp_client:
                return self._read_tcp(), None
            return bytes(self._conn.recv(READ_BYTES) or b""), None
        except (BlockingIOError, ConnectionRefusedError):
            return b"", None
        except Exception as exc:  # a dropped TCP peer, an unplugged serial port
            self.stats.errors += 1
            self._warn("read", f"MAVLink {self.url}: read failed ({type(exc).__name__}: {exc})")
            return b"", None

    def _read_tcp(self) -> bytes:
        """From the socket itself: pymavlink's TCP reader cannot tell a closed peer from no data
        (and prints on every read once the peer is gone)."""
        data = self._conn.port.recv(READ_BYTES)
        if not data:
            self._peer_closed = True
            self.stats.errors += 1
            log.warning("MAVLink %s: the peer closed the connection; reconnect() reopens it", self.url)
        return data

    def _parse(self, data: bytes) -> list[Any]:
        """Good messages in ``data``; bad data is counted and logged, a datagram's tail dropped."""
        good = []
        for msg in self._mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA" and msg.reason == SIGNATURE_REFUSED:
                self.stats.unsigned += 1
                self._warn(
                    "unsigned", f"MAVLink {self.url}: packet refused by signing; {self.stats.unsigned} so far"
                )
            elif msg.get_type() == "BAD_DATA":
                self._bad(f"{msg.reason} ({len(msg.data)} bytes)")
            else:
                good.append(msg)
        # Every UDP datagram holds whole packets: a partial one left over was truncated, and
        # completing it with the next datagram's bytes would corrupt a good packet.
        if self._datagrams and self._mav.buf_len() > 0:
            self._bad(f"truncated packet ({self._mav.buf_len()} bytes)")
            self._reset_parser()
        return good

    def _admit(self, messages: list[Any], sender: Any) -> list[Any]:
        """A listening UDP link keeps the peer's messages (and answers its address), drops others'."""
        if not self._udp_server:
            return messages
        if self._lock is None:
            self._answer(sender, only=False)
            return messages
        kept = []
        for msg in messages:
            replaced = self._lock.replaced
            verdict = self._lock.judge(msg, sender)
            if self._lock.replaced != replaced:
                kept.clear()
            if verdict is None:
                self.stats.unconfirmed += 1
            elif not verdict:
                self._ignore(msg, sender)
            else:
                self._answer(sender, only=True)
                kept.append(msg)
        return kept

    def _answer(self, sender: Any, only: bool) -> None:
        """Send to ``sender`` from now on: only to it (the peer's newest address), or as well."""
        clients = self._conn.clients
        if sender in clients and (not only or len(clients) == 1):
            return
        if only:
            clients.clear()
            self._conn.clients_last_alive.clear()
            log.info("MAVLink %s: answering %s at %s:%s", self.url, self.peers, *sender)
        clients.add(sender)
        self._conn.clients_last_alive[sender] = time.time()

    def _ignore(self, msg: Any, sender: Any) -> None:
        self.stats.ignored += 1
        who = f"system {msg.get_srcSystem()} component {msg.get_srcComponent()} at {sender[0]}:{sender[1]}"
        why = self._lock.why_ignored(msg, sender)
        self._warn(
            "ignored",
            f"MAVLink {self.url}: ignored {msg.get_type()} from {who}: {why}; {self.stats.ignored} so far",
        )

    def _bad(self, what: str) -> None:
        self.stats.bad += 1
        self._warn("bad", f"MAVLink {self.url}: bad input ignored: {what}; {self.stats.bad} so far")

    def _reset_parser(self) -> None:
        mav = self._mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = dialect().HEADER_LEN_V1 + 2

    # --- send ------------------------------------------------------------------------------
    def send(self, msg: Any) -> None:
        """Pack ``msg`` as MAVLink 2 with this link's system/component ids and send it."""
        if not self._usable() or self._peer_closed:
            self.stats.errors += 1
            return
        try:
            self._mav.send(msg)
        except Exception as exc:  # a closed serial port, a TCP peer gone
            self.stats.errors += 1
            self._warn("send", f"MAVLink {self.url}: send failed ({type(exc).__name__}: {exc})")
            return
        self.stats.sent += 1

    def heartbeat(self) -> None:
        """One HEARTBEAT for this link's role; the caller paces them (1 Hz)."""
        self.send(_heartbeat(self.role))

    def statustext(self, severity: int, text: str) -> None:
        """Send ``text`` to the ground station (MAV_SEVERITY_*), in chunks when longer than 50."""
        chunks = statustext_chunks(text)
        msg_id = 0
        if len(chunks) > 1:
            self._statustext_id = self._statustext_id % 65535 + 1
            msg_id = self._statustext_id
        mavlink = dialect()
        for seq, chunk in enumerate(chunks):
            self.send(mavlink.MAVLink_statustext_message(severity, chunk.encode(), msg_id, seq))

    def _usable(self) -> bool:
        """Open: True; down after a failed reconnect: False; never opened or closed: an error."""
        if self._conn is not None:
            return True
        if self._down:
            return False
        raise OrthonavError(f"MAVLink connection {self.url} is not open")


def _component(role: str) -> int:
    mavlink = dialect()
    return mavlink.MAV_COMP_ID_AUTOPILOT1 if role == "vehicle" else mavlink.MAV_COMP_ID_ONBOARD_COMPUTER


def _heartbeat(role: str) -> Any:
    mavlink = dialect()
    if role == "vehicle":
        return mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR,
            mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED,
            ARDUCOPTER_GUIDED,
            mavlink.MAV_STATE_ACTIVE,
            3,
        )
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
    )


def _with_bound_port(url: str, port: int | None) -> str:
    """``udpin:HOST:0`` -> ``udpin:HOST:PORT`` once bound, so a reconnect listens where peers send."""
    prefix, _, rest = url.partition(":")
    host, _, wanted = rest.rpartition(":")
    if prefix in ("udpin", "udp", "tcpin") and wanted == "0" and port:
        return f"{prefix}:{host}:{port}"
    return url


def _connect(mavutil: Any, url: str) -> Any:
    """Open ``url``; TCP tries once (``reconnect`` is the caller's retry)."""
    if url.startswith("serial:"):
        rest = url[len("serial:") :]
        device, sep, baud = rest.rpartition(":")
        if not sep or not baud.isdigit():
            device, baud = rest, ""
        return mavutil.mavlink_connection(device, baud=int(baud or SERIAL_BAUD))
    return mavutil.mavlink_connection(url, baud=SERIAL_BAUD, retries=0)


SIGNATURE_REFUSED = "Invalid signature"  # pymavlink's reason for a packet its signing refused


def read_signing_key(path: Path) -> bytes:
    """The 32-byte MAVLink 2 signing key in ``path``, written as 64 hexadecimal digits (the
    SHA-256 of MAVProxy's or QGroundControl's passphrase: ``printf %s PASSPHRASE | sha256sum``)."""
    try:
        text = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise OrthonavError(f"--signing-key {path}: cannot read it ({exc})") from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != SIGNING_KEY_BYTES:
        raise OrthonavError(
            f"--signing-key {path}: expected {2 * SIGNING_KEY_BYTES} hexadecimal digits on one line"
        )
    return key


def _setup_signing(mav: Any, key: bytes, streams: dict[tuple[int, int, int], int]) -> None:
    """Sign what ``mav`` sends and refuse what it receives unsigned or signed otherwise.

    pymavlink's own check records a stream's timestamp before it checks the signature, so one
    forged packet stamped far ahead would make every genuine one after it look replayed; this
    check verifies the signature first. ``streams`` (the newest timestamp per link and sender)
    outlives a reopened transport, so packets recorded before it cannot be replayed after it.
    """
    signing = mav.signing
    signing.secret_key = key
    signing.sign_outgoing = True
    signing.allow_unsigned_callback = None
    signing.link_id = 0
    now = int((max(time.time(), SIGNING_EPOCH_S) - SIGNING_EPOCH_S) * 100_000)
    signing.timestamp = max(now, max(streams.values(), default=0))
    signing.stream_timestamps = streams
    mav.check_signature = lambda buf, system, component: _signature_ok(mav, buf, system, component)


def _signature_ok(mav: Any, buf: bytearray, system: int, component: int) -> bool:
    """The MAVLink 2 signature check: the key's SHA-256 over the packet, then a timestamp newer
    than the stream's last (a replay is not), or within a minute of ours for a new stream."""
    signing = mav.signing
    digest = hashlib.sha256(signing.secret_key + bytes(buf[:-6])).digest()[:6]
    if not hmac.compare_digest(digest, bytes(buf[-6:])):
        return False
    low, high = struct.unpack("<IH", bytes(buf[-12:-6]))
    timestamp = low + (high << 32)
    stream = (buf[-13], system, component)
    last = signing.stream_timestamps.get(stream)
    if (last is not None and timestamp <= last) or (
        last is None and timestamp + SIGNING_NEW_STREAM_WINDOW < signing.timestamp
    ):
        return False
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True

"""Whom a listening companion believes is its autopilot, and MAVLink 2 signing, over UDP loopback.

Scripted senders with the autopilot's ids (system 1, component 1) send a HEARTBEAT and an ATTITUDE
stamped with their boot clock every 0.1 s of a test clock the companion's link also runs on, so
the timing is exact however busy the machine is. Each ATTITUDE carries its sender's tag in
``rollspeed``, so the test can tell whose messages were delivered.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers_timing import slowdown

pytest.importorskip("pymavlink")

from test_companion_faults import LAT, LON, Autopilot, CompanionThread, StubLocalizer

from orthonav.errors import OrthonavError
from orthonav.geo import destination, distance_m
from orthonav.mavlink.link import MavLink, dialect, read_signing_key
from orthonav.mavlink.peer import PEER_PROBATION_S, PEER_SILENT_S, PeerFilter
from orthonav.mavlink.telemetry import Telemetry
from orthonav.replay import read_companion_log, replay_companion_log, settings_from_log

STEP_S = 0.1
KEY = bytes(range(32))


class Clock:
    """The test's clock: the companion's link reads it, the senders stamp their boot time on it."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Sender:
    """A scripted autopilot from its own address: HEARTBEAT and ATTITUDE (level, ``yaw_deg``)."""

    def __init__(
        self, port: int, clock: Clock, tag: float, boot_s: float, yaw_deg: float = 90.0, **link: Any
    ):
        self.link = MavLink(f"udpout:127.0.0.1:{port}", role="vehicle", **link).open()
        self.clock, self.tag, self.yaw_deg = clock, tag, yaw_deg
        self.boot_at(boot_s)

    def boot_at(self, boot_s: float) -> None:
        """Its boot clock reads ``boot_s`` now (a reboot, or a spoofer copying another's clock)."""
        self._offset_s = boot_s - self.clock.now

    def boot_s(self) -> float:
        return self.clock.now + self._offset_s

    def send(self) -> None:
        self.link.heartbeat()
        yaw = math.radians(self.yaw_deg)
        self.link.send(
            dialect().MAVLink_attitude_message(round(self.boot_s() * 1000), 0.0, 0.0, yaw, self.tag, 0, 0)
        )

    def answered(self) -> bool:
        """Whether the companion's output reached it since the last call."""
        return any(m.get_type() == "HEARTBEAT" for m in self.link.poll())

    def close(self) -> None:
        self.link.close()


class Bench:
    """A listening companion link and the senders around it, on one test clock."""

    def __init__(self, **link: Any) -> None:
        self.clock = Clock()
        self.companion = MavLink("udpin:127.0.0.1:0", clock=self.clock, **link).open()
        self.senders: list[Sender] = []

    def sender(self, tag: float, boot_s: float, yaw_deg: float = 90.0, **link: Any) -> Sender:
        sender = Sender(self.companion.local_port, self.clock, tag, boot_s, yaw_deg, **link)
        self.senders.append(sender)
        return sender

    def run(self, seconds: float, *talking: Sender) -> list[float]:
        """Every ``talking`` sender sends each step; the tags of the ATTITUDEs delivered, in order."""
        delivered = []
        for _ in range(round(seconds / STEP_S)):
            self.clock.now += STEP_S
            for sender in talking:
                sender.send()
            time.sleep(0.003)
            delivered += [m.rollspeed for m in self.companion.poll() if m.get_type() == "ATTITUDE"]
        return delivered

    def answers(self) -> list[float]:
        """The tags of the senders the companion's next message reaches."""
        for sender in self.senders:
            sender.answered()  # forget what came before
        self.companion.heartbeat()
        time.sleep(0.05)
        return [s.tag for s in self.senders if s.answered()]

    def close(self) -> None:
        for sender in self.senders:
            sender.close()
        self.companion.close()


@pytest.fixture
def bench() -> Iterator[Bench]:
    bench = Bench()
    yield bench
    bench.close()


PILOT, SPOOFER = 1.0, 2.0


def test_nothing_is_delivered_or_answered_before_an_autopilot_is_confirmed(bench: Bench) -> None:
    pilot = bench.sender(PILOT, boot_s=100.0)
    early = bench.run(PEER_PROBATION_S - 2 * STEP_S, pilot)
    assert early == [] and bench.answers() == []
    assert set(bench.run(1.0, pilot)) == {PILOT} and bench.answers() == [PILOT]
    assert bench.companion.stats.unconfirmed >= 2 * round(PEER_PROBATION_S / STEP_S) - 4


def test_a_spoofer_after_silence_does_not_capture_the_link_and_the_autopilot_is_heard_again(
    bench: Bench,
) -> None:
    """A sniffer continues the silent autopilot's boot clock and sequence from a new address; its
    attitude is its own. Silence alone does not make it the autopilot."""
    pilot = bench.sender(PILOT, boot_s=100.0)
    assert set(bench.run(2.0, pilot)) == {PILOT}
    spoofer = bench.sender(SPOOFER, boot_s=pilot.boot_s(), yaw_deg=0.0)
    assert bench.run(3 * PEER_SILENT_S, spoofer) == []
    assert bench.answers() == [PILOT]
    assert bench.companion.stats.ignored >= 2 * round(3 * PEER_SILENT_S / STEP_S) - 2
    # The autopilot back at its own address is heard at once, the spoofer still not.
    assert set(bench.run(1.0, pilot, spoofer)) == {PILOT} and bench.answers() == [PILOT]


def test_a_spoofer_faking_a_fresh_boot_with_another_attitude_is_not_believed(bench: Bench) -> None:
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    spoofer = bench.sender(SPOOFER, boot_s=0.5, yaw_deg=0.0)
    assert bench.run(3 * PEER_SILENT_S, spoofer) == [] and bench.answers() == [PILOT]


def test_a_real_reboot_at_a_new_address_is_followed(bench: Bench) -> None:
    """The autopilot falls silent and comes back from another port with a fresh boot clock and
    the attitude it had: it is the autopilot again once its stream has run unbroken a while."""
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    bench.run(3.0)  # rebooting
    rebooted = bench.sender(SPOOFER, boot_s=0.5)
    delivered = bench.run(2 * PEER_PROBATION_S + 1.0, rebooted)
    assert delivered and set(delivered) == {SPOOFER} and bench.answers() == [SPOOFER]
    assert len(delivered) <= round((PEER_PROBATION_S + 1.0) / STEP_S) + 2  # held for its probation


def test_a_new_address_continuing_the_autopilots_clock_and_attitude_is_followed(bench: Bench) -> None:
    """A router restarted: the same autopilot, from another port, its clock running on."""
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    bench.run(PEER_SILENT_S + 0.5)
    moved = bench.sender(SPOOFER, boot_s=pilot.boot_s())
    assert set(bench.run(2 * PEER_PROBATION_S, moved)) == {SPOOFER} and bench.answers() == [SPOOFER]


def test_the_autopilot_back_at_its_address_takes_the_link_back_from_a_faked_reboot(bench: Bench) -> None:
    """A spoofer that fakes a reboot with the right attitude while the autopilot is silent is
    believed (nothing without signing tells them apart), until the autopilot speaks again with
    its clock running on: its unbroken stream is the older, so it was never rebooted."""
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    bench.run(1.0)  # a reboot takes this long: the spoofer's clock must not read more
    spoofer = bench.sender(SPOOFER, boot_s=0.5)
    bench.run(PEER_SILENT_S + 2 * PEER_PROBATION_S, spoofer)
    assert bench.answers() == [SPOOFER]
    back = bench.run(2 * PEER_PROBATION_S, pilot, spoofer)
    assert back[-5:] == [PILOT] * 5 and bench.answers() == [PILOT]


@pytest.mark.parametrize("pilot_boot_s", [0.05, 300.0], ids=["just booted", "long up"])
def test_a_spoofer_first_does_not_capture_the_link_once_the_autopilot_talks(
    bench: Bench, pilot_boot_s: float
) -> None:
    """A spoofer speaks first, on a clock of its own; when the autopilot appears it copies the
    autopilot's clock to look like it, which breaks its own stream (even where the copied clock
    is small, as an autopilot's just booted is: it cannot pass for a reboot of the spoofer's own):
    the autopilot's has then run unbroken longer and is believed."""
    spoofer = bench.sender(SPOOFER, boot_s=60.0, yaw_deg=0.0)
    assert set(bench.run(2.0, spoofer)) == {SPOOFER}  # alone, it is believed: nothing tells
    pilot = bench.sender(PILOT, boot_s=pilot_boot_s)
    bench.run(STEP_S, pilot, spoofer)
    spoofer.boot_at(pilot.boot_s() + 0.05)
    delivered = bench.run(2 * PEER_PROBATION_S + 1.0, pilot, spoofer)
    assert delivered[-10:] == [PILOT] * 10 and bench.answers() == [PILOT]
    # Nothing of the spoofer follows the autopilot's first message: what came before is another's.
    assert SPOOFER not in delivered[delivered.index(PILOT) :]
    assert bench.companion.peer_replaced == 1
    assert bench.run(2.0, pilot, spoofer) == [PILOT] * round(2.0 / STEP_S)


def test_a_spoofer_beside_a_live_autopilot_is_ignored_even_with_a_continuous_stream(bench: Bench) -> None:
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    spoofer = bench.sender(SPOOFER, boot_s=pilot.boot_s())
    assert set(bench.run(4.0, pilot, spoofer)) == {PILOT} and bench.answers() == [PILOT]


def test_the_autopilots_clock_stepping_at_its_own_address_keeps_it_the_peer(bench: Bench) -> None:
    """A reboot or a clock step at the peer's own address is the telemetry's to judge, not an
    impersonation: the peer stays, with no one else talking."""
    pilot = bench.sender(PILOT, boot_s=100.0)
    bench.run(2.0, pilot)
    pilot.boot_at(0.3)
    assert set(bench.run(1.0, pilot)) == {PILOT}
    pilot.boot_at(3600.0)
    assert set(bench.run(1.0, pilot)) == {PILOT} and bench.answers() == [PILOT]


def test_a_named_target_is_the_only_one_followed() -> None:
    bench = Bench(peers=PeerFilter(system=2, component=1))
    try:
        first = bench.sender(PILOT, boot_s=100.0)
        second = bench.sender(SPOOFER, boot_s=50.0, source_system=2)
        assert set(bench.run(2.0, first, second)) == {SPOOFER} and bench.answers() == [SPOOFER]
        assert bench.companion.stats.ignored == 2 * round(2.0 / STEP_S)
    finally:
        bench.close()
    with pytest.raises(OrthonavError, match=r"target system 0: expected an id in 1\.\.255"):
        PeerFilter(system=0)


def test_telemetry_starts_over_when_the_autopilot_changes() -> None:
    """The companion restarts its telemetry when the link's peer changes: nothing the sender
    before said (its attitude, its clock) describes the new one, and a new epoch says so."""
    telemetry, now = Telemetry(), 1000.0
    telemetry.ingest(_decoded(dialect().MAVLink_attitude_message(60_000, 0.0, 0.0, 0.0, 0, 0, 0)), now)
    assert telemetry.attitude(now) is not None
    telemetry.restart("another sender", now)
    assert telemetry.attitude(now) is None and telemetry.epoch == 1
    assert [e.kind for e in telemetry.pop_events()] == ["new autopilot"]
    telemetry.ingest(_decoded(dialect().MAVLink_attitude_message(500, 0.0, 0.0, 1.5, 0, 0, 0)), now + 0.1)
    assert telemetry.pop_events() == [] and telemetry.attitude(now + 0.1) is not None  # a clock of its own


def _decoded(msg: Any) -> Any:
    """``msg`` as it arrives from system 1 component 1."""
    return dialect().MAVLink(None).parse_buffer(msg.pack(dialect().MAVLink(None, 1, 1)))[0]


# --- signing ------------------------------------------------------------------------------------


@pytest.fixture
def signed() -> Iterator[Bench]:
    bench = Bench(signing_key=KEY)
    yield bench
    bench.close()


def test_signed_autopilot_and_companion_talk_both_ways(signed: Bench) -> None:
    pilot = signed.sender(PILOT, boot_s=100.0, signing_key=KEY)
    assert set(signed.run(2.0, pilot)) == {PILOT} and signed.answers() == [PILOT]
    assert signed.companion.stats.unsigned == 0 and signed.companion.stats.bad == 0


@pytest.mark.parametrize("key", [None, bytes(32)], ids=["unsigned", "another key"])
def test_signing_refuses_packets_unsigned_or_signed_with_another_key(
    signed: Bench, key: bytes | None
) -> None:
    pilot = signed.sender(PILOT, boot_s=100.0, signing_key=KEY)
    signed.run(2.0, pilot)
    spoofer = signed.sender(SPOOFER, boot_s=pilot.boot_s(), signing_key=key)
    assert set(signed.run(2.0, pilot, spoofer)) == {PILOT}
    assert signed.companion.stats.unsigned == 2 * round(2.0 / STEP_S)
    assert signed.answers() == [PILOT]


def test_signing_refuses_a_replay_and_a_forgery_stamped_ahead_does_not_block_the_autopilot(
    signed: Bench,
) -> None:
    pilot = signed.sender(PILOT, boot_s=100.0, signing_key=KEY)
    signed.run(2.0, pilot)
    recorded = pilot.link._mav.signing.timestamp
    beat = dialect().MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)
    replayed = _signed_packet(beat, KEY, recorded - 10)
    forged = _signed_packet(beat, bytes(32), recorded + 10**9)  # another key, far in the future
    with MavLink(f"udpout:127.0.0.1:{signed.companion.local_port}", role="vehicle") as raw:
        for packet in (replayed, forged):
            raw._conn.write(packet)
    assert set(signed.run(1.0, pilot)) == {PILOT}
    assert signed.companion.stats.unsigned == 2


def _signed_packet(msg: Any, key: bytes, timestamp: int) -> bytes:
    """``msg`` from system 1 component 1 signed with ``key`` at ``timestamp`` (10 us units)."""
    packer = dialect().MAVLink(None, 1, 1)
    packer.signing.secret_key, packer.signing.sign_outgoing = key, True
    packer.signing.timestamp, packer.signing.link_id = timestamp, 0
    return bytes(msg.pack(packer))


def test_a_signing_key_file_is_64_hex_digits(tmp_path: Path) -> None:
    good = tmp_path / "key"
    good.write_text(KEY.hex() + "\n")
    assert read_signing_key(good) == KEY
    short = tmp_path / "short"
    short.write_text("abcd")
    with pytest.raises(OrthonavError, match=r"--signing-key .*short: expected 64 hexadecimal digits"):
        read_signing_key(short)
    with pytest.raises(OrthonavError, match=r"--signing-key .*missing: cannot read it"):
        read_signing_key(tmp_path / "missing")
    with pytest.raises(OrthonavError, match="MAVLink signing key: expected 32 bytes, got 3"):
        MavLink("udpin:127.0.0.1:0", signing_key=b"abc")


def test_fly_refuses_a_bad_signing_key_file_before_opening_anything(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from orthonav.cli.main import app

    bad = tmp_path / "key.hex"
    bad.write_text("not a key\n")
    args = [
        "fly",
        "--map",
        str(tmp_path / "no map"),
        "--frames",
        str(tmp_path),
        "--connect",
        "udpin:127.0.0.1:0",
    ]
    result = CliRunner().invoke(app, [*args, "--signing-key", str(bad)])
    assert isinstance(result.exception, OrthonavError)
    assert str(result.exception) == f"--signing-key {bad}: expected 64 hexadecimal digits on one line"


# --- the companion behind the link ----------------------------------------------------------------


class Impostor(Autopilot):
    """An autopilot 2 km north on a boot clock of its own, until it copies ``model``'s (a sniffer)."""

    def __init__(self, port: int) -> None:
        super().__init__(port)
        self._boot0_s = 60.0
        self.model: Autopilot | None = None

    def boot_ms(self) -> int:
        return super().boot_ms() if self.model is None else self.model.boot_ms() + 50

    def position(self) -> tuple[float, float]:
        return destination(LAT, LON, 0.0, 2000.0)

    def talk(self) -> None:
        self.link.heartbeat()
        self.send_telemetry()


def test_a_spoofer_that_spoke_first_leaves_nothing_behind_and_replay_follows_the_change(
    tmp_path: Path,
) -> None:
    """The impostor is alone at first and is believed; once the autopilot talks and the impostor
    copies its clock, the autopilot takes the link, the companion's telemetry starts over (nothing
    of the impostor's position, velocity or clock stays), and a replay of the log does the same."""
    localizer = StubLocalizer(lambda: (LAT, LON))
    with CompanionThread(localizer, tmp_path) as run:
        impostor = Impostor(run.port)
        impostor.fly(2.0)
        pilot = Autopilot(run.port)
        impostor.model = pilot
        pilot.fly(3.0 * slowdown(), also=impostor.talk)
        pilot.fly(2.0 * slowdown())
    assert run.error is None, f"the companion stopped: {run.error!r}"
    assert any(text.startswith("telemetry: new autopilot") for text in run.events())
    positions = [m for m in pilot.received if m.get_type() == "GPS_INPUT"]
    assert len(positions) >= 3
    assert max(distance_m(m.lat * 1e-7, m.lon * 1e-7, LAT, LON) for m in positions) < 50.0
    log = read_companion_log(run.log_path)
    summary = replay_companion_log(log, settings_from_log(log.config, {}), tmp_path / "replay", {}).summary
    assert summary["vs_sent"]["position_offset_m"]["max"] < 0.05

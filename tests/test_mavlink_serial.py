"""The serial link (``--connect /dev/ttyACM0``) on a pseudo-terminal pair: the companion opens the
pty's device as a serial port, the test plays the autopilot on the other end.

pyserial comes with the ``mavlink`` extra: without it pymavlink cannot open any serial port, so
this test fails (it does not skip) where the extra was installed without it.
"""

from __future__ import annotations

import os
import re
import select
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from orthonav.mavlink.link import MavLink, dialect


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(the autopilot's end as a file descriptor, the device path the companion opens)."""
    autopilot, device = os.openpty()
    try:
        yield autopilot, os.ttyname(device)
    finally:
        os.close(autopilot)
        os.close(device)


def read_messages(fd: int, timeout_s: float = 2.0) -> list[Any]:
    """What the companion wrote to its serial port, decoded, once something arrived."""
    parser = dialect().MAVLink(None)
    parser.robust_parsing = True
    got: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while not got and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            got += parser.parse_buffer(os.read(fd, 4096)) or []
    return got


@pytest.mark.parametrize("form", ["serial:{device}:57600", "{device}"], ids=["serial-url", "device-path"])
def test_a_serial_url_opens_and_talks_both_ways_over_a_pty(pty_pair: tuple[int, str], form: str) -> None:
    autopilot, device = pty_pair
    mavlink = dialect()
    beat = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
    )
    with MavLink(form.format(device=device)) as companion:
        os.write(autopilot, beat.pack(mavlink.MAVLink(None, 1, 1)))
        got: list[Any] = []
        deadline = time.monotonic() + 2.0
        while not got and time.monotonic() < deadline:
            got = [m for m in companion.poll() if m.get_type() == "HEARTBEAT"]
            time.sleep(0.01)
        assert got and (got[0].get_srcSystem(), got[0].autopilot) == (1, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        companion.heartbeat()
        back = [m for m in read_messages(autopilot) if m.get_type() == "HEARTBEAT"]
        assert back and back[0].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        assert companion.stats.received >= 1 and companion.stats.sent == 1


def test_the_mavlink_extra_declares_pyserial() -> None:
    """What a fresh ``pip install 'orthonav[mavlink]'`` gets: the test above passes wherever
    pyserial came by another way, so the declaration itself is checked."""
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    extra = pyproject["project"]["optional-dependencies"]["mavlink"]
    names = {re.match(r"[A-Za-z0-9._-]+", requirement).group(0).lower() for requirement in extra}
    assert {"pymavlink", "pyserial"} <= names, extra

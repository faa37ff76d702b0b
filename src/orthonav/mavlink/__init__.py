"""MAVLink side of orthonav: the link, telemetry, outgoing navigation messages, the companion
loop, a simulated vehicle, and flight-log readers. pymavlink is imported only when used."""

from orthonav.mavlink import messages
from orthonav.mavlink.link import LinkStats, MavLink
from orthonav.mavlink.logs import FlightLog, LoggedPoses, read_flight_log
from orthonav.mavlink.telemetry import Attitude, Telemetry, TimeEvent

__all__ = [
    "Attitude",
    "FlightLog",
    "LinkStats",
    "LoggedPoses",
    "MavLink",
    "Telemetry",
    "TimeEvent",
    "messages",
    "read_flight_log",
]

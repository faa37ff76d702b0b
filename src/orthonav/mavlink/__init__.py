"""MAVLink side of orthonav: the link, the autopilot's peer and telemetry, outgoing navigation
messages and the companion loop. pymavlink is imported only when used."""

from orthonav.mavlink import messages
from orthonav.mavlink.link import LinkStats, MavLink
from orthonav.mavlink.telemetry import Attitude, Telemetry, TimeEvent

__all__ = ["Attitude", "LinkStats", "MavLink", "Telemetry", "TimeEvent", "messages"]

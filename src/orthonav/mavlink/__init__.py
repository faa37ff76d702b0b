"""MAVLink side of orthonav: flight log readers (pymavlink, imported only when a log is read)."""

from orthonav.mavlink.logs import FlightLog, LoggedPoses, read_flight_log

__all__ = ["FlightLog", "LoggedPoses", "read_flight_log"]

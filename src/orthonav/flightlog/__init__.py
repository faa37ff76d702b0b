"""What a past flight recorded: the autopilot's logs (``.tlog``, ``.bin``) and geotagged photos,
read as poses over time for replays, odometry and benchmarks. pymavlink is imported only to read
autopilot logs."""

from orthonav.flightlog.autopilot import FlightLog, LoggedPoses, read_flight_log
from orthonav.flightlog.photos import Photo, PhotoFlight, read_photo, read_photos

__all__ = ["FlightLog", "LoggedPoses", "Photo", "PhotoFlight", "read_flight_log", "read_photo", "read_photos"]

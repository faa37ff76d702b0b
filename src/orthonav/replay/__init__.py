"""Flight-log replay: recorded frames localized against a map, scored against the recorded GNSS."""

from orthonav.replay.inputs import ReplayInput, flight_input, photo_input
from orthonav.replay.run import (
    ReplayConfig,
    ReplayResult,
    camera_for_photos,
    replay_flight,
    replay_photos,
    run_replay,
    summarize,
)

__all__ = [
    "ReplayConfig",
    "ReplayInput",
    "ReplayResult",
    "camera_for_photos",
    "flight_input",
    "photo_input",
    "replay_flight",
    "replay_photos",
    "run_replay",
    "summarize",
]

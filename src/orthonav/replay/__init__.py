"""Flight-log replay: recorded frames localized against a map, scored against the recorded GNSS;
and a companion log's filter re-run with other settings."""

from orthonav.replay.companion_log import (
    FilterSettings,
    read_companion_log,
    replay_companion_log,
    settings_from_log,
)
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
    "FilterSettings",
    "ReplayConfig",
    "ReplayInput",
    "ReplayResult",
    "camera_for_photos",
    "flight_input",
    "photo_input",
    "read_companion_log",
    "replay_companion_log",
    "replay_flight",
    "replay_photos",
    "run_replay",
    "settings_from_log",
    "summarize",
]

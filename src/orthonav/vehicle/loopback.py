"""The whole companion loop on one machine: a simulated vehicle and the companion over UDP.

The vehicle runs in a thread and writes its frames into a folder the companion watches; the
companion listens on a free loopback port. Used by the benchmark (end-to-end latency) and by
anyone who wants to try ``fly`` without an autopilot.
"""

from __future__ import annotations

import threading
from pathlib import Path

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import open_live_source
from orthonav.geo import GeoRaster
from orthonav.mavlink.companion import Companion, CompanionConfig
from orthonav.mavlink.link import MavLink
from orthonav.types import FixSource
from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

VEHICLE_EXTRA_S = 2.0  # the vehicle outlives the companion, so its last messages are graded


def fly_loopback(
    fix_source: FixSource,
    frames_from: GeoRaster,
    camera: Camera,
    vehicle_config: SimVehicleConfig,
    companion_config: CompanionConfig,
    out_dir: Path,
) -> tuple[dict, dict]:
    """Run both for ``companion_config.duration_s``; return (vehicle summary, companion summary)."""
    if companion_config.duration_s is None:
        raise OrthonavError("loopback flight: give the companion a duration_s")
    frames_dir = out_dir / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    companion_link = MavLink("udpin:127.0.0.1:0", role="companion").open()
    vehicle_link = MavLink(f"udpout:127.0.0.1:{companion_link.local_port}", role="vehicle")
    vehicle = SimVehicle(vehicle_config, vehicle_link, frames_from, camera, frames_dir, out_dir / "vehicle")
    result: dict = {}
    duration = companion_config.duration_s + VEHICLE_EXTRA_S
    thread = threading.Thread(target=lambda: result.update(vehicle.run(duration)), daemon=True)
    thread.start()
    try:
        companion = Companion(
            companion_config,
            companion_link,
            open_live_source(str(frames_dir)),
            fix_source,
            out_dir / "companion" / "companion.jsonl",
            camera,
        ).run()
    except BaseException:
        vehicle.stop()
        raise
    finally:
        thread.join(timeout=duration + 30.0)
    return result, companion

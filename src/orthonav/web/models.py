"""Request bodies of the JSON API; their constraints are the API's first line of validation
and appear in its OpenAPI schema. Ranges here only keep requests sane; the mission's own
``MissionConfig`` checks still apply (and their errors reach the user as they are)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

from orthonav.sim import MissionConfig
from orthonav.web.store import NAME_PATTERN

# 1-64 letters, digits, '_', '-' or '.': one path component, never a path.
Name = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]


class LatLon(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # true is not a number

    lat: float = Field(ge=-90.0, le=90.0, description="WGS84 latitude (deg)")
    lon: float = Field(ge=-180.0, le=180.0, description="WGS84 longitude (deg)")


class MissionRequest(BaseModel):
    """A simulated mission over one map (see ``orthonav simulate``)."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,  # "speed_mps": true is refused, not read as 1 m/s
        json_schema_extra={
            "examples": [
                {
                    "map": "naip2020",
                    "start": {"lat": 47.0204, "lon": -99.1640},
                    "target": {"lat": 47.0204, "lon": -99.1417},
                    "alt_agl_m": 1000,
                }
            ]
        },
    )

    map: Name
    start: LatLon = Field(description="Centre of the start zone")
    target: LatLon
    fix_source: Literal["cascade", "map", "correlation", "ins"] = Field(
        "cascade",
        description="cascade: correlation, keypoints and a verified decision; map: keypoints with the "
        "map's backend; correlation: dense; ins: INS alone",
    )
    frames_from: Name | None = Field(
        None, description="Uploaded orthophoto to render frames from (default: the map's)"
    )
    speed_mps: float = Field(20.0, gt=0, le=100)
    alt_agl_m: float | None = Field(None, gt=0, le=10000, description="Default: the map's nominal altitude")
    step_s: float = Field(5.0, gt=0, le=60, description="Time between frames")
    max_time_s: float = Field(1200.0, gt=0, le=7200)
    arrival_radius_m: float = Field(60.0, gt=0, le=10000)
    start_zone_m: float = Field(100.0, gt=0, le=10000)
    imu: str = Field("consumer", description="perfect, tactical or consumer")
    gnss_loss_s: float = Field(0.0, ge=0, le=7200, description="0: GNSS lost from the start")
    seed: int = Field(0, ge=0, le=2**31 - 1)

    def to_config(self) -> MissionConfig:
        """The mission itself; raises ``OrthonavError`` for combinations it refuses."""
        return MissionConfig(
            self.start.lat,
            self.start.lon,
            self.target.lat,
            self.target.lon,
            speed_mps=self.speed_mps,
            step_s=self.step_s,
            max_time_s=self.max_time_s,
            arrival_radius_m=self.arrival_radius_m,
            alt_agl_m=self.alt_agl_m,
            start_zone_m=self.start_zone_m,
            imu=self.imu,
            gnss_loss_s=self.gnss_loss_s,
            seed=self.seed,
            visual_fixes=self.fix_source != "ins",
            save_frames=True,  # the page shows each frame
        )


class BuildRequest(BaseModel):
    """A map package from an uploaded orthophoto (see ``orthonav map build``)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    name: Name
    orthophoto: Name
    altitude_m: float = Field(300.0, gt=0, le=10000, description="Nominal flight altitude above ground")
    hfov_deg: float = Field(60.0, gt=1, lt=170)
    width: int = Field(640, ge=64, le=8192)
    height: int = Field(480, ge=64, le=8192)
    features: str = Field("orb", description="Feature backend (GET /api/options)")
    max_keypoints: int = Field(1024, ge=64, le=16384)

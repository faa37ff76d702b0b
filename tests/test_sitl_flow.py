"""The optical-flow landing aid's SITL scenarios: what they set, and when the flow takes over."""

from __future__ import annotations

import math
from types import SimpleNamespace

from orthonav.bench.sitl import (
    FLOW_LIDAR_RANGE_M,
    FLOW_PARAMS,
    FLOW_SWITCH_M,
    SCENARIOS,
    SitlConfig,
    parm_text,
    select_flow,
    vehicle_params,
)
from orthonav.mavlink.link import dialect

FLOW_SCENARIOS = ("copter-gnss-off-flow", "copter-gnss-off-flow-alone")


def test_the_flow_twins_are_the_gnss_off_twins_with_the_sensors_and_source_set_2() -> None:
    config = SitlConfig(hfov_deg=90.0)
    for flow, plain in zip(FLOW_SCENARIOS, ("copter-gnss-off", "copter-gnss-off-alone"), strict=True):
        params = vehicle_params(config, SCENARIOS[flow])
        assert params == vehicle_params(config, SCENARIOS[plain]) | FLOW_PARAMS, flow
        # Set 2: position from GPS (orthonav's GPS 2 where it flies), velocity from the flow, and
        # nothing fuses the flow's velocity while set 1 is active.
        assert (params["EK3_SRC2_POSXY"], params["EK3_SRC2_VELXY"], params["EK3_SRC_OPTIONS"]) == (3, 5, 0)
        assert params.get("EK3_SRC1_VELXY", 3) != 5, flow
        assert f"RNGFND1_MAX_CM {FLOW_LIDAR_RANGE_M * 100:.15g}\n" in parm_text(params)
    assert vehicle_params(config, SCENARIOS[FLOW_SCENARIOS[0]])["GPS2_TYPE"] == 14
    assert vehicle_params(config, SCENARIOS[FLOW_SCENARIOS[1]])["GPS2_TYPE"] == 0
    for name, scenario in SCENARIOS.items():
        if not scenario.flow:
            assert not {"FLOW_TYPE", "RNGFND1_TYPE"} & vehicle_params(config, scenario).keys(), name
    # The frame-velocity flight differs from its twin in orthonav only, not in the autopilot.
    twin = vehicle_params(config, SCENARIOS["copter-gnss-off-flow"])
    assert vehicle_params(config, SCENARIOS["copter-gnss-off-flow-velocity"]) == twin
    for twin_name in ("copter-gnss-off", "plane-gnss-off"):
        with_velocity = SCENARIOS[twin_name.replace("-gnss-off", "-gnss-off-velocity")]
        assert with_velocity.frame_velocity and not SCENARIOS[twin_name].frame_velocity
        assert vehicle_params(config, with_velocity) == vehicle_params(config, SCENARIOS[twin_name])


def test_the_lidar_reaches_the_ground_where_the_flow_takes_over_at_a_descents_tilt() -> None:
    for tilt_deg in (0.0, 10.0, 20.0):
        assert FLOW_SWITCH_M / math.cos(math.radians(tilt_deg)) < FLOW_LIDAR_RANGE_M, tilt_deg


class _Station:
    """What select_flow reads and sends: the autopilot's height and its commands."""

    def __init__(self) -> None:
        self.latest: dict = {}
        self.commands: list[tuple[int, tuple[float, ...]]] = []

    def command(self, command: int, *params: float) -> None:
        self.commands.append((command, params))


def test_source_set_2_is_selected_once_below_the_switch_height_and_only_with_the_aid() -> None:
    for scenario, heights, expected in (
        (SCENARIOS["copter-gnss-off-flow"], (300.0, FLOW_SWITCH_M + 1, FLOW_SWITCH_M - 1, 40.0, 2.0), 1),
        (SCENARIOS["copter-gnss-off-flow-alone"], (300.0, 250.0), 0),
        (SCENARIOS["copter-gnss-off"], (300.0, 60.0, 2.0), 0),
    ):
        station, flight = _Station(), {}
        for height in heights:
            station.latest["GLOBAL_POSITION_INT"] = SimpleNamespace(relative_alt=height * 1000)
            select_flow(station, scenario, flight)  # type: ignore[arg-type]
        assert len(station.commands) == expected, scenario.name
        assert all(c == (dialect().MAV_CMD_SET_EKF_SOURCE_SET, (2,)) for c in station.commands)
        assert ("flow_from" in flight) == bool(expected)

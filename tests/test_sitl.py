"""orthonav in the loop with ArduPilot's real firmware (SITL, EKF3): GNSS cut at altitude, orthonav's
GPS_INPUT as GPS 2. One short flight (take off, GNSS off, hold over home); the mission with a route
and its twin without orthonav are ``orthonav bench sitl``."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from orthonav.bench.faults import ensure_map
from orthonav.bench.sitl import (
    DEFAULT_SCENARIOS,
    SCENARIOS,
    TROUBLE,
    FlightFault,
    SitlConfig,
    Track,
    _fly_mission,
    _orthonav,
    binary,
    extra_param,
    fly_command,
    gnss_denial,
    mission_items,
    parm_text,
    return_error,
    run_scenario,
    spoof_verdict,
    targets_apply,
    tilt_errors,
    vehicle_params,
)
from orthonav.errors import OrthonavError
from orthonav.geo import distance_m
from orthonav.mavlink.companion import CompanionConfig

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
SITL_DIR = SHARED / "ardupilot"
NAIP = SHARED / "data" / "naip"


def test_a_missing_sitl_binary_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(
        OrthonavError, match=r"arducopter: no ArduPilot SITL binary for the copter \(pass --sitl-dir"
    ):
        binary(tmp_path, "copter")


def test_orthonav_is_gps2_only_where_it_flies() -> None:
    """The twin is the autopilot alone (no GPS 2, every arming check); with orthonav, GPS 2 is
    MAVLink and only the GPS-lock check is cleared (orthonav has no fix on the ground)."""
    config = SitlConfig()
    with_us = vehicle_params(config, SCENARIOS["copter-gnss-off"])
    alone = vehicle_params(config, SCENARIOS["copter-gnss-off-alone"])
    assert (with_us["GPS1_TYPE"], with_us["GPS2_TYPE"], alone["GPS2_TYPE"]) == (1, 14, 0)
    assert alone["ARMING_CHECK"] == 1 and int(with_us["ARMING_CHECK"]) & 8 == 0
    assert int(with_us["ARMING_CHECK"]) & 2 and int(with_us["ARMING_CHECK"]) & 16  # baro, INS kept


def test_an_experiments_parameters_go_over_the_scenarios_and_a_bad_one_is_named() -> None:
    assert extra_param("EK3_POSNE_M_NSE=25") == ("EK3_POSNE_M_NSE", 25.0)
    assert extra_param(" EK3_ACC_P_NSE = 1.0 ") == ("EK3_ACC_P_NSE", 1.0)
    extra = (extra_param("EK3_ACC_P_NSE=1"), extra_param("GPS2_DELAY_MS=120"))
    config = SitlConfig(hfov_deg=90.0, extra_params=extra)
    for name in ("copter-gnss-off-flow", "copter-gnss-off-extnav", "plane-gnss-off"):
        params = vehicle_params(config, SCENARIOS[name])
        assert (params["EK3_ACC_P_NSE"], params["GPS2_DELAY_MS"]) == (1.0, 120.0), name
        plain = vehicle_params(SitlConfig(hfov_deg=90.0), SCENARIOS[name])
        assert {k: v for k, v in params.items() if k not in dict(extra)} == {
            k: v for k, v in plain.items() if k not in dict(extra)
        }, name
    for bad, field in (
        ("EK3_POSNE_M_NSE", "NAME=VALUE"),
        ("ek3_posne_m_nse=25", "NAME=VALUE"),
        ("=25", "NAME=VALUE"),
        ("EK3_POSNE_M_NSE_TOO_LONG=1", "NAME=VALUE"),
        ("EK3_POSNE_M_NSE=", "EK3_POSNE_M_NSE"),
        ("EK3_POSNE_M_NSE=five", "EK3_POSNE_M_NSE"),
        ("EK3_POSNE_M_NSE=nan", "EK3_POSNE_M_NSE"),
        ("EK3_POSNE_M_NSE=inf", "EK3_POSNE_M_NSE"),
    ):
        with pytest.raises(OrthonavError, match=field):
            extra_param(bad)


def test_bench_sitl_names_a_bad_parameter_before_it_builds_or_flies_anything(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from orthonav.cli.main import app

    out = tmp_path / "bench_sitl.json"
    result = CliRunner().invoke(app, ["bench", "sitl", "--param", "EK3_POSNE_M_NSE=five", "--out", str(out)])
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    assert "EK3_POSNE_M_NSE" in str(result.exception)
    assert list(tmp_path.iterdir()) == []


def test_the_parameter_file_says_every_value_exactly() -> None:
    """What SITL loads is what was meant: a bitmask written to six digits loses its low bits
    (ARMING_CHECK's barometer check, or sets the visual-odometry check it clears)."""
    config = SitlConfig()
    for scenario in SCENARIOS.values():
        params = vehicle_params(config, scenario)
        loaded = {
            name: float(value) for name, value in (line.split() for line in parm_text(params).splitlines())
        }
        assert loaded == params, scenario.name
    extnav = vehicle_params(config, SCENARIOS["copter-gnss-off-extnav"])
    assert (extnav["VISO_TYPE"], extnav["EK3_SRC2_POSXY"], extnav["GPS2_TYPE"]) == (1, 6, 0)
    assert int(extnav["ARMING_CHECK"]) & (1 << 18) == 0 and int(extnav["ARMING_CHECK"]) & 8


def test_both_externalnav_flights_set_what_a_user_sets_and_send_their_own_message(tmp_path: Path) -> None:
    """VISION_POSITION_ESTIMATE and ODOMETRY fly on the same ExternalNav set-up: no velocity from
    it (ODOMETRY's is the autopilot's own), and EKF3's floor for the stale GPS accuracy it weighs
    ExternalNav by raised above a receiver's, within EK3_POSNE_M_NSE's range; the GPS flights keep
    ArduPilot's default (GPS 2 reports its own accuracy)."""
    config = SitlConfig()
    extnav = {
        name: vehicle_params(config, SCENARIOS[name])
        for name in ("copter-gnss-off-extnav", "copter-gnss-off-odometry")
    }
    vision, odometry = extnav.values()
    assert vision == odometry
    assert (odometry["VISO_TYPE"], odometry["EK3_SRC2_POSXY"], odometry["EK3_SRC2_VELXY"]) == (1, 6, 0)
    assert 1.0 < odometry["EK3_POSNE_M_NSE"] <= 10.0
    for name in ("copter-gnss-off", "copter-gnss-spoofed", "plane-gnss-off"):
        assert "EK3_POSNE_M_NSE" not in vehicle_params(config, SCENARIOS[name]), name
    for name in extnav:
        command = fly_command(tmp_path, tmp_path, 14550, tmp_path, SCENARIOS[name])
        assert command[command.index("--output") + 1] == SCENARIOS[name].output
    assert {SCENARIOS[name].output for name in extnav} == {"vision", "odometry"}


def test_a_body_camera_flies_without_a_gimbal_and_only_its_fused_twin_lifts_the_attitude_rule(
    tmp_path: Path,
) -> None:
    """fly's flags as a user would pass them: the body camera without --nadir-gimbal, and the
    experiment that fuses its correlation fixes without GNSS says --independent-attitude."""
    flags = {
        name: fly_command(tmp_path, tmp_path, 14550, tmp_path, scenario)
        for name, scenario in SCENARIOS.items()
    }
    for name in (
        "copter-gnss-off-body-camera",
        "plane-gnss-off-body-camera",
        "plane-gnss-off-body-camera-fused",
    ):
        assert "--nadir-gimbal" not in flags[name], name
    lifted = {name for name, command in flags.items() if "--independent-attitude" in command}
    assert lifted == {"plane-gnss-off-body-camera-fused"}


def test_every_scenarios_answer_to_spoofing_fits_its_output(tmp_path: Path) -> None:
    """fly refuses an answer that does not fit its output: every scenario's would start; the
    ExternalNav spoof flight is set up as the ExternalNav one, its answer selecting set 2."""
    for scenario in SCENARIOS.values():
        command = fly_command(tmp_path, tmp_path, 14550, tmp_path, scenario)
        answer = command[command.index("--on-spoofing") + 1]
        CompanionConfig(output=command[command.index("--output") + 1], on_spoofing=answer)
    switch = SCENARIOS["copter-gnss-spoofed-extnav-switch"]
    assert (switch.output, switch.on_spoofing, switch.gnss) == ("vision", "switch-source", "spoofed")
    config = SitlConfig()
    params = vehicle_params(config, switch)
    assert (
        params == vehicle_params(config, SCENARIOS["copter-gnss-off-extnav"])
        and params["EK3_SRC2_POSXY"] == 6
    )


@pytest.mark.parametrize("name", ["copter-gnss-off-extnav", "copter-gnss-spoofed-extnav-switch"])
def test_the_ground_station_selects_externalnav_when_it_takes_gnss_away_not_when_spoofed(name: str) -> None:
    """It knows when GPS 1 goes; a spoofer it does not see, so there the switch is fly's alone."""
    commands: list[tuple] = []
    gcs = SimpleNamespace(
        track=Track(disarmed_at=1.0),
        latest={},
        wait_for=lambda *a: None,
        upload_mission=lambda items: None,
        set_mode=lambda mode: None,
        arm=lambda: None,
        set_param=lambda name, value: None,
        command=lambda *a: commands.append(a),
    )
    flight: dict = {}
    _fly_mission(
        gcs,
        SimpleNamespace(poll=lambda: None),
        SCENARIOS[name],
        SitlConfig(),
        (47.0, -99.0),
        flight,
        FlightFault(),
    )
    selects = [c for c in commands if c[0] == 42007]
    assert selects == ([(42007, 2)] if SCENARIOS[name].gnss == "off" else []) and "ended_at" in flight


def test_the_autopilots_trouble_is_told_from_its_routine() -> None:
    """ArduCopter's own words (a drag-fusion flight's log): its estimate's trouble and failsafes
    are kept, mission progress and start-up chatter are not."""
    trouble = [
        "GPS Glitch or Compass error",
        "Dead Reckoning started",
        "Dead Reckoning timeout",
        "EKF variance",
        "EKF Failsafe: changed to LAND Mode",
        "EKF3 lane switch 1",
    ]
    routine = ["Reached command #3", "Mission: 5 RTL", "EKF3 IMU1 is using GPS", "GPS 2: detected MAV"]
    assert [text for text in trouble + routine if TROUBLE.search(text)] == trouble


def test_a_flight_says_when_its_answer_to_spoofing_went_out_and_was_accepted(tmp_path: Path) -> None:
    """Timed from the spoof by fly's own events; absent ones (no answer, or no spoof) are None."""
    track = Track(truth=[(100.0, 47.0, -99.0), (200.0, 47.0, -99.0)])
    records = [
        {"kind": "sent", "time_s": t, "state": {"time_s": t, "lat": 47.0, "lon": -99.0, "sigma_m": 5.0}}
        for t in (110.0, 150.0)
    ] + [
        {"kind": "event", "time_s": 132.0, "text": "the autopilot is 425 m from 5 visual fixes in a row"},
        {"kind": "event", "time_s": 133.0, "text": "EKF3 source set 2 (ExternalNav, orthonav) requested: x"},
        {"kind": "event", "time_s": 133.4, "text": "EKF3 source set 2 (ExternalNav, orthonav) selected: y"},
    ]
    log = tmp_path / "companion.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    row = _orthonav(log, track, 120.0)
    assert (row["answer_sent_after_s"], row["answer_accepted_after_s"]) == (13.0, 13.4)
    unanswered = _orthonav(log, track, None)
    assert (unanswered["answer_sent_after_s"], unanswered["answer_accepted_after_s"]) == (None, None)


def test_the_spoofer_moves_gps1_by_the_configured_distance_and_orthonav_stays_gps2() -> None:
    """SIM_GPS_GLITCH is in degrees: the offsets put GPS 1 where the spoofer is meant to, and the
    spoofed flight is set up as the jammed one (orthonav GPS 2, a 50 ms delay for its state)."""
    config, home = SitlConfig(spoof_m=(300.0, -200.0)), (47.0204, -99.1548)
    glitch = gnss_denial(SCENARIOS["copter-gnss-spoofed"], config, home)
    moved = distance_m(*home, home[0] + glitch["SIM_GPS_GLITCH_X"], home[1] + glitch["SIM_GPS_GLITCH_Y"])
    assert abs(float(moved) - np.hypot(300.0, 200.0)) < 0.5
    assert glitch["SIM_GPS_GLITCH_X"] < 0 < glitch["SIM_GPS_GLITCH_Y"]  # south, east
    assert gnss_denial(SCENARIOS["copter-gnss-off"], config, home) == {"SIM_GPS_DISABLE": 1}
    params = vehicle_params(config, SCENARIOS["copter-gnss-spoofed"])
    assert (params["GPS2_TYPE"], params["GPS2_DELAY_MS"], params["GPS_AUTO_SWITCH"]) == (14, 50, 1)


def test_the_spoof_verdict_tells_whom_the_autopilot_followed() -> None:
    """An estimate on the spoofed track counts as following the spoofer, one on the truth not."""
    home, config = (47.0204, -99.1548), SitlConfig(spoof_m=(300.0, 300.0))
    glitch = gnss_denial(SCENARIOS["copter-gnss-spoofed"], config, home)
    times = np.arange(0.0, 20.0, 0.5)
    track = Track(truth=[(t, home[0] + 1e-5 * t, home[1]) for t in times])
    on_truth = np.array([(t, home[0] + 1e-5 * t, home[1], 0.0) for t in times])
    on_spoofer = on_truth.copy()
    on_spoofer[:, 1] += glitch["SIM_GPS_GLITCH_X"]
    on_spoofer[:, 2] += glitch["SIM_GPS_GLITCH_Y"]
    on_spoofer[:, 3] = distance_m(on_truth[:, 1], on_truth[:, 2], on_spoofer[:, 1], on_spoofer[:, 2])
    believed = spoof_verdict(on_spoofer, track, glitch)
    assert believed["followed_spoofer_share"] == 1.0 and believed["spoofer_distance_p50_m"] < 1.0
    assert abs(believed["spoof_m"] - np.hypot(300.0, 300.0)) < 1.0
    honest = spoof_verdict(on_truth, track, glitch)
    assert honest["followed_spoofer_share"] == 0.0 and honest["spoofer_distance_p50_m"] > 400.0


def test_a_flight_says_whether_localization_kept_up_with_the_camera(tmp_path: Path) -> None:
    """From fly's summary: behind real time where over a tenth of the frames were dropped or the
    p95 latency exceeds a frame period (0.5 s at 2 frames a second); absent without a summary."""
    from orthonav.bench.sitl import localization_pace

    config, summary = SitlConfig(), tmp_path / "summary.json"
    assert localization_pace(summary, config) is None
    cases = ((800, 27, 458.4, False), (800, 120, 300.0, True), (800, 10, 650.0, True), (800, 0, None, False))
    for frames, dropped, p95, behind in cases:
        summary.write_text(json.dumps({"frames": frames, "frames_dropped": dropped, "latency_p95_ms": p95}))
        pace = localization_pace(summary, config)
        assert pace is not None and pace["behind_real_time"] is behind, (frames, dropped, p95)
        assert (pace["frames"], pace["frames_dropped"], pace["latency_p95_ms"]) == (frames, dropped, p95)


def test_the_plane_loiters_at_the_routes_end_and_returns_at_cruise_height() -> None:
    """ArduPlane's mission: a take-off with a minimum pitch, the route, loiter turns at its end,
    RTL; its parameters return at cruise height without landing and carry no copter settings."""
    from orthonav.mavlink.link import dialect

    mav, config = dialect(), SitlConfig()
    plane = mission_items(config, (47.0, -99.0), "plane")
    commands = [item.command for item in plane]
    assert commands == [
        mav.MAV_CMD_NAV_WAYPOINT,
        mav.MAV_CMD_NAV_TAKEOFF,
        mav.MAV_CMD_NAV_WAYPOINT,
        mav.MAV_CMD_NAV_WAYPOINT,
        mav.MAV_CMD_NAV_LOITER_TURNS,
        mav.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    ]
    assert plane[1].param1 > 0 and plane[4].param1 == config.loiter_turns
    copter = mission_items(config, (47.0, -99.0))
    assert mav.MAV_CMD_NAV_LOITER_TURNS not in [item.command for item in copter] and copter[1].param1 == 0
    params = vehicle_params(config, SCENARIOS["plane-gnss-off"])
    assert (params["RTL_ALTITUDE"], params["RTL_AUTOLAND"], params["GPS2_TYPE"]) == (config.alt_m, 0, 14)
    assert not [k for k in params if k.startswith(("WPNAV_", "AUTO_OPTIONS", "RTL_ALT_"))]


def test_the_copter_targets_judge_only_a_copter_that_lost_gnss_for_good() -> None:
    """A fault flight that gives GNSS back lands on it, a plane does not land, a spoofed GPS 1 is
    another question: none of them can meet or miss the copter targets."""
    assert targets_apply(SCENARIOS["copter-gnss-off-velocity"], {"gnss_off_at": 10.0})
    assert targets_apply(SCENARIOS["copter-gnss-off-alone"], {"gnss_off_at": 10.0})
    assert not targets_apply(
        SCENARIOS["copter-gnss-off-velocity"], {"gnss_off_at": 10.0, "gnss_back_at": 99.0}
    )
    assert not targets_apply(SCENARIOS["plane-gnss-off"], {"gnss_off_at": 10.0})
    assert not targets_apply(SCENARIOS["copter-gnss-spoofed"], {"gnss_off_at": 10.0})


def test_the_autopilots_tilt_error_is_graded_with_gnss_and_without() -> None:
    """The larger of roll's and pitch's error against SIMSTATE per ATTITUDE from arming, split
    at the GNSS loss (and its return): what a body-fixed camera's fixes are placed with."""
    track = Track(armed_at=1.0)
    track.true_attitude.append((0.0, 0.0, 0.0, 0.0))
    track.attitude.append((0.5, 70.0, 0.0, 0.0))  # on the ground, tilt not aligned yet: not graded
    for step in range(200):
        t = 0.1 * step
        track.true_attitude.append((t, 10.0 * np.sin(t), 5.0, 90.0))
        roll_off, pitch_off = (0.2, -0.1) if t < 5.0 or t >= 15.0 else (0.5, -2.0)
        if step % 2:  # ATTITUDE at half SIMSTATE's rate, between its samples
            later = t + 0.05
            track.attitude.append((later, 10.0 * np.sin(later) + roll_off, 5.0 + pitch_off, 91.0))
    graded = tilt_errors(track, 5.0, 15.0)
    assert graded["gnss"]["max"] == pytest.approx(0.2, abs=0.02)  # the truth interpolated
    assert graded["gnss_off"]["p50"] == pytest.approx(2.0, abs=0.01)
    assert tilt_errors(Track(), 5.0, 15.0) is None
    assert tilt_errors(replace(track, armed_at=None), 5.0, 15.0) is None
    assert tilt_errors(track, None, 20.0)["gnss_off"] is None


def test_a_plane_returned_where_its_loiter_over_home_is_centred() -> None:
    """A plane does not land: where it ended is the centre of its loiter over home (a circle of
    150 m radius 20 m north of home gives 20 m, the leg home before it left out), and nothing
    before it has loitered there for half of plane_home_s."""
    home, config = (47.0204, -99.1548), SitlConfig(plane_home_s=60.0)
    times = np.arange(0.0, 200.0, 0.1)
    angle = 2 * np.pi * times / 43.0
    north, east = 20.0 + 150.0 * np.cos(angle), 150.0 * np.sin(angle)
    homing = times < 110.0  # from RTL at 100 s: flying home from 600 m north at 22 m/s
    north[homing], east[homing] = 170.0 + 22.0 * (110.0 - times[homing]), 0.0
    lat, lon = home[0] + north / 111_320.0, home[1] + east / (111_320.0 * np.cos(np.radians(home[0])))
    track = Track(truth=list(zip(times, lat, lon, strict=True)), modes=[(0.0, 10), (100.0, 11)])
    plane = SCENARIOS["plane-gnss-off"]
    assert abs(return_error(plane, config, track, home, 200.0) - 20.0) < 1.0
    assert return_error(plane, config, track, home, 130.0) is None  # 20 s over home, not 30
    assert return_error(plane, config, Track(truth=track.truth, modes=[(0.0, 10)]), home, 200.0) is None


@pytest.fixture(scope="module")
def hover_flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict, Path]:
    """Take off to 200 m, cut GPS 1 (SIM_GPS_DISABLE), hold over home for 40 s with orthonav as
    GPS 2 (2018 map, 2020 frames, a nadir gimbal, fly's defaults for it: the default flight's
    scenario): the graded row, the ground station's track and the companion's log."""
    if not (SITL_DIR / "arducopter").is_file():
        pytest.skip(f"no ArduPilot SITL binary in {SITL_DIR}")
    if not NAIP.is_dir():
        pytest.skip(f"no NAIP orthophotos in {NAIP}")
    root = tmp_path_factory.mktemp("sitl")
    scenario = SCENARIOS[DEFAULT_SCENARIOS[0]]
    config = SitlConfig(
        scenarios=(scenario.name,), alt_m=200.0, route_m=((0.0, 0.0),), hold_s=60.0, timeout_s=40.0
    )
    package = ensure_map(sorted(NAIP.glob("*2018*.tif"))[0], root / "map", config.alt_m)
    frames_from = sorted(NAIP.glob("*2020*.tif"))[0]
    row = run_scenario(scenario, config, SITL_DIR, package, frames_from, root / "flight")
    track = json.loads((root / "flight" / "track.json").read_text())
    return row, track, root / "flight" / "fly" / "companion.jsonl"


def test_ekf3_fuses_orthonavs_gps_input_once_gnss_is_off(hover_flight: tuple[dict, dict, Path]) -> None:
    """ArduPilot's own estimate follows what orthonav sends: with GPS 1 gone, GLOBAL_POSITION_INT
    stays within a few metres of orthonav's GPS_INPUT (the positions EKF3 fuses), and orthonav
    keeps ArduPilot's GPS rate (5 Hz, no gap near the 4 s that drop a GPS)."""
    row, track, _ = hover_flight
    assert track["gnss_off_at"] is not None and row["gnss_off_s"] >= 35.0
    sent = row["orthonav_messages"]
    assert sent["sent"] >= 100 and sent["rate_hz"] >= 4.5 and sent["gap_max_s"] < 1.0
    t, lat, lon = np.asarray(sent["track"], float).T
    estimate = np.asarray([e for e in track["estimate"] if e[0] >= track["gnss_off_at"] + 5.0], float)
    apart = distance_m(
        np.interp(estimate[:, 0], t, lat), np.interp(estimate[:, 0], t, lon), *estimate[:, 1:3].T
    )
    assert np.median(apart) <= 5.0, np.percentile(apart, [50, 95, 100])


def test_nothing_wrong_reaches_ekf3_with_gnss_off_and_it_takes_no_failsafe(
    hover_flight: tuple[dict, dict, Path],
) -> None:
    """Once GNSS is off no GPS_INPUT is more than 3 sigma or 50 m off SITL's truth, EKF3 stays
    within 15 m of it and takes no failsafe: the companion's filter does not trust the
    autopilot's velocity (which orthonav itself now steers) as if it were an IMU's."""
    row, _, _ = hover_flight
    assert row["orthonav_messages"]["wrong_gnss_off"] == 0
    assert not any("failsafe" in text.lower() for text in row["failsafes"]), row["failsafes"]
    assert row["horizontal_error_max_m"] is not None and row["horizontal_error_max_m"] <= 15.0


def test_the_velocity_measured_between_frames_goes_to_ekf3_at_its_accuracy(
    hover_flight: tuple[dict, dict, Path],
) -> None:
    """With a gimbal camera fly measures the ground velocity between its frames by default, fuses
    it, and GPS_INPUT claims the filter's velocity sigma (EKF3 takes it as a GPS's) instead of "no
    velocity"; EKF3's position stays with what is sent (the test above)."""
    _, track, log = hover_flight
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert records[0]["config"]["frame_velocity"] is True
    # Over the hover, not the climb: low down the rendered ground is too smooth for a velocity.
    fixes = [r for r in records if r["kind"] == "fix" and r["capture_time_s"] > track["gnss_off_at"]]
    fused = [r for r in fixes if r.get("velocity", {}).get("filter", {}).get("accepted")]
    assert len(fused) >= 0.3 * len(fixes) > 0, f"{len(fused)} of {len(fixes)} frame velocities fused"
    sent = [
        r["msg"]["speed_accuracy"]
        for r in records
        if r["kind"] == "sent" and r["type"] == "GPS_INPUT" and r["state"]["time_s"] > track["gnss_off_at"]
    ]
    assert sent and np.median(sent) < 1.0, np.percentile(sent, [5, 50, 95])

"""SLAM simulated over the real NAIP orthophoto: rendered rig and two-UAV frames, real VO, iSAM2."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from orthonav.features import create_backend
from orthonav.slam.association import AssociationConfig, make_view, match_views

pytest.importorskip("gtsam", reason="the 'slam' extra (gtsam) is not installed")

from orthonav.slam.simulate import (
    SETUPS,
    SlamSimConfig,
    _odometry,
    default_rig,
    make_world,
    run_setup,
    spotting_summary,
)
from orthonav.slam.spotting import Detection

CONFIG = SlamSimConfig(keyframes=7)


@pytest.fixture(scope="module")
def world(naip_raster, camera):
    return make_world(naip_raster, default_rig(camera), CONFIG, uavs=2, seed=0)


def _setup(label: str):
    return next(s for s in SETUPS if s.label == label)


def test_real_odometry_on_rendered_frames_follows_the_circle(world) -> None:
    assert not world.vo_failures
    step = CONFIG.speed_mps * CONFIG.keyframe_s
    for motion in world.motions[0][1:]:
        assert motion.method == "homography"
        assert motion.forward_m == pytest.approx(step, abs=5.0)


def test_rig_and_two_uavs_build_one_map_and_improve_on_odometry_alone(world) -> None:
    vo = run_setup(world, _setup("VO only, no fixes")).metrics()
    rig = run_setup(world, _setup("rig, no fixes"))
    # UAV 2 missed in one spotter frame: that keyframe has no baseline and no stereo pair.
    missed = [*world.spotted]
    missed[3] = dataclasses.replace(missed[3], detection=Detection(None, "not detected: test"))
    two = run_setup(dataclasses.replace(world, spotted=missed), _setup("2 UAVs, no fixes"))
    for run in (rig, two):
        m = run.metrics()
        assert m["landmarks"] > 300 and run.wrong_tracks <= 0.02 * m["landmarks"]
        # Without fixes the error is held by the launch point (5 m) and compass (1 deg) alone.
        assert m["ate_m"] < 30.0 and m["landmark_m"] < m["ate_m"] + 15.0
    assert rig.metrics()["rpe_m"] < vo["rpe_m"]  # the obliques' landmarks tie the steps together
    assert two.metrics()["ate_m"] < vo["ate_m"]  # two launch points and the baseline hold the heading
    # Landmarks from the obliques and from the other UAV are in the same map as the nadir ones.
    assert rig.counts["observations"] > run_setup(world, _setup("1 camera, no fixes")).counts["observations"]
    assert two.counts["baselines"] == CONFIG.keyframes - 1  # UAV 2 detected at every other keyframe
    s = two.stereo
    assert s is not None and 3 <= s["frames"] <= CONFIG.keyframes - 1
    assert 3 not in [p["keyframe"] for p in s["pairs"]]
    # The measured variable baseline beats assuming the planned, fixed one.
    assert s["distance_error_m"]["best measured baseline"] < 30.0
    assert s["distance_error_m"]["best measured baseline"] < s["distance_error_m"]["fixed baseline"]
    assert s["size_error_pct"]["best measured baseline"] < 5.0


def test_failed_odometry_coasts_on_the_last_motion(world) -> None:
    views = [list(v) for v in world.gray[0][:3]]
    views[2] = [np.full_like(img, 128) for img in views[2]]  # a blank frame: no texture at all
    failures: list[str] = []
    motions = _odometry(world.rig, views, world.baro[0][:3], 0, "orb", failures, CONFIG)
    assert len(failures) == 1 and "keyframe 2" in failures[0]
    assert motions[2].method == "coasting" and motions[2].forward_m == motions[1].forward_m
    assert np.sqrt(motions[2].covariance[1, 1]) > 50.0  # wide: landmarks and fixes decide


def test_frames_with_too_little_overlap_are_not_matched(world) -> None:
    rig, cfg = world.rig, AssociationConfig()
    backend = create_backend("orb", max_keypoints=800)
    nadir = rig.cameras[0]
    views = []
    for k in (0, CONFIG.keyframes - 1):  # 960 m apart along the circle: about 10 % shared ground
        e, n, alt, yaw = world.truth[0][k]
        views.append(
            make_view(world.gray[0][k][0], nadir, nadir.camera_pose(e, n, alt, yaw), 0, k, 0, backend, cfg)
        )
    result = match_views(views[1], views[0], 0, backend, cfg)
    assert (len(result.pairs) == 0 and "homography" in result.reason) or "matches" in result.reason


def test_the_baseline_comes_from_uav2_detected_in_the_rendered_spotter_frames(world) -> None:
    summary = spotting_summary(world.spotted, CONFIG)
    assert summary["detected"] == CONFIG.keyframes and summary["false_detections"] == 0
    assert 20 < summary["span_px_median"] < 60  # 4 m at 320-450 m through a 10 deg lens
    assert summary["range_error_median_pct"] < 3.0
    missed = dataclasses.replace(world.spotted[0], detection=Detection(None, "not detected: test"))
    assert missed.baseline(CONFIG) is None and missed.range_error_m(CONFIG) is None


def test_slam_command_writes_a_flight_and_refuses_a_bad_rig(naip2020_tif, tmp_path) -> None:
    from typer.testing import CliRunner

    from orthonav.cli.main import app
    from orthonav.errors import OrthonavError

    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"cameras": [{"name": "nadir", "width": 640, "height": 480, "hfov_deg": 60}]}))
    out = tmp_path / "run"
    args = ["slam", "--map", str(naip2020_tif), "--out", str(out), "--keyframes", "5", "--fix-every", "2"]
    result = CliRunner().invoke(app, [*args, "--rig", str(rig), "--uavs", "2"])
    assert result.exit_code == 0, result.output
    lines = (out / "trajectory.jsonl").read_text().splitlines()
    assert len(lines) == 10 and {json.loads(line)["uav"] for line in lines} == {1, 2}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"]["ate_m"] < 20.0 and summary["metrics"]["landmarks"] > 100
    assert summary["spotting"]["detected"] == 5 and summary["counts"]["fixes_tried"] == 4
    assert len((out / "landmarks.csv").read_text().splitlines()) == summary["metrics"]["landmarks"] + 1
    assert (out / "slam.png").stat().st_size > 10_000
    rig.write_text(json.dumps({"cameras": [{"name": "down", "width": 640, "height": 480, "hfov_deg": 60}]}))
    bad = CliRunner().invoke(app, [*args, "--rig", str(rig)])
    assert isinstance(bad.exception, OrthonavError) and "named 'nadir'" in str(bad.exception)
    rig.write_text('{"cameras": [{"name": "nadir", "width": 640}')
    bad = CliRunner().invoke(app, [*args, "--rig", str(rig)])
    assert isinstance(bad.exception, OrthonavError)
    assert "not valid JSON (rig file expected" in str(bad.exception)

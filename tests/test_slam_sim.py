"""SLAM simulated over the real NAIP orthophoto: rendered rig and two-UAV frames, real VO, iSAM2."""

from __future__ import annotations

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
)

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
    two = run_setup(world, _setup("2 UAVs, no fixes"))
    for run in (rig, two):
        m = run.metrics()
        assert m["landmarks"] > 300 and run.wrong_tracks <= 0.02 * m["landmarks"]
        # Without fixes the error is held by the launch point (5 m) and compass (1 deg) alone.
        assert m["ate_m"] < 30.0 and m["landmark_m"] < m["ate_m"] + 15.0
    assert rig.metrics()["rpe_m"] < vo["rpe_m"]  # the obliques' landmarks tie the steps together
    assert two.metrics()["ate_m"] < vo["ate_m"]  # two launch points and the baseline hold the heading
    # Landmarks from the obliques and from the other UAV are in the same map as the nadir ones.
    assert rig.counts["observations"] > run_setup(world, _setup("1 camera, no fixes")).counts["observations"]
    assert two.counts["baselines"] == CONFIG.keyframes  # UAV 2 seen by UAV 1's spotter every keyframe
    s = two.stereo
    assert s is not None and s["frames"] >= 3
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

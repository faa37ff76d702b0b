"""Multi-camera / multi-UAV SLAM simulated over a real orthophoto.

What is simulated: the ground is flat, at the orthophoto; the vehicles fly level circles at
constant altitude (UAV 1 outside, UAV 2 inside at a varying offset and lower); frames are
rendered per camera and per vehicle from the orthophoto with the known rig extrinsics and a
photometric change; the AHRS (roll/pitch) and barometer are the truth plus Gaussian noise;
UAV 1's gimballed narrow camera is pointed at UAV 2 by a tracker (the true direction plus a
pointing error), its frame is rendered, UAV 2 is drawn into it (:mod:`orthonav.slam.spotting`)
and a strong photometric change (blur, noise, colour) is applied after.

What is measured: visual odometry by :func:`orthonav.odometry.estimate_motion` on the rendered
nadir frames (when it fails, the step falls back to a constant-velocity guess with a wide
covariance); landmarks from features matched between rendered frames; map fixes by a real fix
source (keypoint localizer or dense correlation) on the rendered nadir frames, searched
around the graph's own estimate within its uncertainty; the baseline from UAV 2 as detected in
the spotter frame (centre and span of its ring), and the false detections of the same detector
on the same frame rendered without UAV 2.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from orthonav.camera import Camera, pixel_to_ground, rotation_enu_from_camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, create_backend
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame
from orthonav.odometry import Motion, OdometryError, estimate_motion
from orthonav.slam import spotting, stereo
from orthonav.slam.association import (
    AssociationConfig,
    PairResult,
    Tracks,
    View,
    make_view,
    match_views,
    overlap_fraction,
)
from orthonav.slam.graph import GraphConfig, SlamGraph, body_pose, odometry_step, yaw_deg_of
from orthonav.slam.metrics import ate_m, landmark_errors_m, rpe_m
from orthonav.slam.rig import Rig, RigCamera, enu_r_body
from orthonav.slam.spotting import Detection
from orthonav.types import FixSource, Prior

log = logging.getLogger(__name__)

NADIR = "nadir"
WRONG_TRACK_M = 15.0  # a track whose observations' true ground points spread wider is a mismatch


def default_rig(camera: Camera, oblique_deg: float = 25.0) -> Rig:
    """A nadir camera and two obliques looking forward and back."""
    return Rig(
        (
            RigCamera.from_angles(NADIR, camera),
            RigCamera.from_angles("forward", camera, pitch_deg=oblique_deg),
            RigCamera.from_angles("rear", camera, pitch_deg=-oblique_deg),
        )
    )


@dataclass(frozen=True)
class SlamSimConfig:
    """The flight, the sensors and the processing; written beside the results."""

    keyframes: int = 24
    keyframe_s: float = 8.0
    speed_mps: float = 20.0
    alt_m: float = 1000.0
    second_alt_m: float = 800.0
    radius_m: float = 900.0
    offset_m: tuple[float, float] = (250.0, 400.0)  # UAV 2 inside UAV 1's circle, min..max
    fix_every: int = 4
    photometric: float = 0.4
    ahrs_sigma_deg: float = 0.3
    baro_sigma_m: float = 2.0
    start_sigma_m: float = 5.0
    uav_span_m: float = 4.0  # known size of the other (helicopter-type) UAV
    spotter_hfov_deg: float = 10.0
    spotter_photometric: float = 1.0  # haze, blur and noise of a long telephoto view
    tracking_sigma_deg: float = 1.0  # how far off the tracker points the gimbal
    sighting_sigma_px: float = 0.5  # of the detected centre and of each end of the span
    features: str = "orb"
    max_keypoints: int = 800
    fix_sigma_floor_m: float = 50.0
    association: AssociationConfig = field(default_factory=AssociationConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)

    def __post_init__(self) -> None:
        if self.keyframes < 3 or self.fix_every < 1:
            raise OrthonavError(f"slam simulation: expected keyframes >= 3 and fix_every >= 1, got {self}")
        lo, hi = self.offset_m
        if not 0 < lo <= hi < self.radius_m:
            raise OrthonavError(
                f"slam simulation offset_m: expected 0 < min <= max < radius, got {self.offset_m}"
            )

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Setup:
    """One configuration compared: which rig cameras, how many UAVs, map fixes or not."""

    name: str
    cameras: tuple[str, ...]
    uavs: int
    fixes: bool

    @property
    def label(self) -> str:
        return f"{self.name}, {'map fixes' if self.fixes else 'no fixes'}"


SETUPS = tuple(
    Setup(name, cams, uavs, fixes)
    for fixes in (False, True)
    for name, cams, uavs in (
        ("VO only", (), 1),
        ("1 camera", (NADIR,), 1),
        ("rig", (NADIR, "forward", "rear"), 1),
        ("2 UAVs", (NADIR,), 2),
    )
)
"""The compared setups; "VO only" chains the odometry (and fixes) with no landmark."""


@dataclass
class World:
    """Everything rendered and sensed once per seed, shared by every setup."""

    config: SlamSimConfig
    rig: Rig
    frame: LocalFrame
    truth: list[np.ndarray]  # per UAV (K, 4): east, north, alt, yaw_deg
    gray: list[list[list[np.ndarray]]]  # [uav][keyframe][rig camera]
    nadir_bgr: list[list[np.ndarray]]
    ahrs: list[np.ndarray]  # per UAV (K, 2): pitch, roll measured
    baro: list[np.ndarray]  # per UAV (K,)
    motions: list[list[Motion | None]]  # per UAV, [k] from k-1 to k (None at 0)
    vo_failures: list[str]
    start: list[np.ndarray]  # per UAV: the known launch pose (east, north, alt, yaw) with its error
    seed: int
    spotted: list[Spotting] = field(default_factory=list)  # per keyframe, with two UAVs


@dataclass(frozen=True)
class Spotting:
    """UAV 2 in UAV 1's spotter frame at one keyframe: what the detector said, and the truth."""

    spotter: RigCamera  # the gimbal's pointing, read from its encoders
    detection: Detection
    true_span_px: float
    true_range_m: float
    false_detection: bool  # the detector found a UAV in the same frame rendered without one

    def baseline(self, config: SlamSimConfig) -> stereo.Baseline | None:
        """The baseline from the detection, or None when UAV 2 was not detected."""
        if not self.detection.found:
            return None
        return stereo.baseline_from_sighting(
            self.spotter, self.detection.sighting, config.uav_span_m, config.sighting_sigma_px
        )

    def range_error_m(self, config: SlamSimConfig) -> float | None:
        baseline = self.baseline(config)
        return None if baseline is None else baseline.range_m - self.true_range_m


def circle_truth(config: SlamSimConfig, uav: int, start_angle: float, phase: float) -> np.ndarray:
    """(K, 4) true east, north, alt, yaw: counter-clockwise circles round the frame origin."""
    t = np.arange(config.keyframes) * config.keyframe_s
    omega = config.speed_mps / config.radius_m
    theta = start_angle + omega * t
    radius = np.full_like(t, config.radius_m)
    alt = config.alt_m
    if uav == 1:
        lo, hi = config.offset_m
        period = config.keyframes * config.keyframe_s / 1.5
        radius = radius - (lo + (hi - lo) * 0.5 * (1 + np.sin(2 * math.pi * t / period + phase)))
        alt = config.second_alt_m
    yaw = np.degrees(-theta) % 360.0  # heading of the tangent, counter-clockwise
    return np.column_stack([radius * np.cos(theta), radius * np.sin(theta), np.full_like(t, alt), yaw])


def make_world(
    raster: GeoRaster,
    rig: Rig,
    config: SlamSimConfig,
    uavs: int,
    seed: int,
    vo_backend: FeatureBackend | str = "orb",
) -> World:
    """Fly the circles, render every camera of every UAV, sense, and run visual odometry."""
    rng = np.random.default_rng(seed)
    lat0, lon0 = raster.pixel_to_latlon(raster.width / 2.0, raster.height / 2.0)
    frame = LocalFrame(float(lat0), float(lon0))
    start_angle, phase = float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0, 2 * math.pi))
    truth = [circle_truth(config, u, start_angle, phase) for u in range(uavs)]
    gray, bgr, ahrs, baro, motions, failures, starts = [], [], [], [], [], [], []
    for u in range(uavs):
        views, nadirs = [], []
        for e, n, alt, yaw in truth[u]:
            photometric = Photometric.random(rng, config.photometric)
            per_camera = []
            for cam in rig.cameras:
                pose = cam.camera_pose(e, n, alt, yaw)
                lat, lon = frame.to_latlon(pose.east_m, pose.north_m)
                image = render_frame(
                    raster,
                    cam.camera,
                    TruePose(
                        float(lat), float(lon), pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg
                    ),
                    photometric,
                    rng,
                )
                if cam.name == NADIR:
                    nadirs.append(image)
                per_camera.append(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
            views.append(per_camera)
        gray.append(views)
        bgr.append(nadirs)
        ahrs.append(rng.normal(0.0, config.ahrs_sigma_deg, (config.keyframes, 2)))
        baro.append(truth[u][:, 2] + rng.normal(0.0, config.baro_sigma_m, config.keyframes))
        start = truth[u][0].copy()
        start[:2] += rng.normal(0.0, config.start_sigma_m, 2)
        start[3] += rng.normal(0.0, config.graph.start_yaw_sigma_deg)
        starts.append(start)
        motions.append(_odometry(rig, views, baro[u], u, vo_backend, failures, config))
    spotted = []
    if uavs == 2:
        spotter_camera = _spotter_camera(config)
        spotted = [
            spot_other_uav(raster, frame, spotter_camera, truth[0][k], truth[1][k], config, rng)
            for k in range(config.keyframes)
        ]
    return World(config, rig, frame, truth, gray, bgr, ahrs, baro, motions, failures, starts, seed, spotted)


def spot_other_uav(
    raster: GeoRaster,
    frame: LocalFrame,
    camera: Camera,
    spotter_state: np.ndarray,
    other_state: np.ndarray,
    config: SlamSimConfig,
    rng: np.random.Generator,
) -> Spotting:
    """Point the gimbal at the other UAV (with a tracking error), render the frame, draw the UAV
    into it, blur and add noise, and detect it; the same frame without the UAV counts false
    detections. States are (east, north, alt, yaw_deg) in level flight."""
    e, n, alt, yaw = (float(v) for v in spotter_state)
    other = np.asarray(other_state[:3], float)
    d_body = enu_r_body(yaw).T @ (other - [e, n, alt])
    aim_yaw = math.degrees(math.atan2(d_body[1], d_body[0])) + rng.normal(0.0, config.tracking_sigma_deg)
    tilt = math.degrees(math.acos(d_body[2] / np.linalg.norm(d_body)))
    spotter = RigCamera.from_angles(
        "spotter", camera, yaw_deg=aim_yaw, pitch_deg=tilt + rng.normal(0.0, config.tracking_sigma_deg)
    )
    pose = spotter.camera_pose(e, n, alt, yaw)
    lat, lon = frame.to_latlon(pose.east_m, pose.north_m)
    ground = render_frame(
        raster, camera, TruePose(float(lat), float(lon), alt, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    )
    photometric = Photometric.random(rng, config.spotter_photometric)
    seen = photometric.apply(
        spotting.composite_uav(ground, camera, pose, other, float(other_state[3]), config.uav_span_m), rng
    )
    _, depth = spotting.project_points(camera, pose, other[None])
    return Spotting(
        spotter,
        spotting.detect_uav(seen),
        float(math.sqrt(camera.fx * camera.fy) * config.uav_span_m / depth[0]),
        float(np.linalg.norm(d_body)),
        spotting.detect_uav(photometric.apply(ground, rng)).found,
    )


def spotting_sweep(
    raster: GeoRaster, config: SlamSimConfig, ranges_m: tuple[float, ...], per_range: int, seed: int
) -> list[dict]:
    """Detection rate, range error and false detections against the distance between the UAVs:
    UAV 1 at random places over the map, UAV 2 at the given range, 20-60 deg below, any bearing."""
    rng = np.random.default_rng([seed, 11])
    lat0, lon0 = raster.pixel_to_latlon(raster.width / 2.0, raster.height / 2.0)
    frame = LocalFrame(float(lat0), float(lon0))
    camera = _spotter_camera(config)
    rows = []
    for range_m in ranges_m:
        spotted = []
        for _ in range(per_range):
            e, n = rng.uniform(-1000.0, 1000.0, 2)
            yaw, bearing = rng.uniform(0.0, 360.0, 2)
            depression = math.radians(rng.uniform(20.0, 60.0))
            d_body = range_m * np.array(
                [
                    math.cos(depression) * math.cos(math.radians(bearing)),
                    math.cos(depression) * math.sin(math.radians(bearing)),
                    math.sin(depression),
                ]
            )
            other = np.array([e, n, config.alt_m]) + enu_r_body(yaw) @ d_body
            state = np.array([e, n, config.alt_m, yaw])
            spotted.append(spot_other_uav(raster, frame, camera, state, np.append(other, yaw), config, rng))
        rows.append({"range_m": range_m, **spotting_summary(spotted, config)})
    return rows


def spotting_summary(spotted: list[Spotting], config: SlamSimConfig) -> dict:
    """Detection rate, range error against the truth, and false detections on frames without UAV 2."""
    errors = [e for e in (s.range_error_m(config) for s in spotted) if e is not None]
    relative = [abs(s.range_error_m(config)) / s.true_range_m for s in spotted if s.detection.found]
    return {
        "frames": len(spotted),
        "detected": sum(s.detection.found for s in spotted),
        "range_error_median_m": round(float(np.median(np.abs(errors))), 2) if errors else None,
        "range_bias_m": round(float(np.mean(errors)), 2) if errors else None,
        "range_error_median_pct": round(100 * float(np.median(relative)), 2) if relative else None,
        "span_px_median": round(float(np.median([s.true_span_px for s in spotted])), 1) if spotted else None,
        "false_detections": sum(s.false_detection for s in spotted),
        "misses": sorted({s.detection.reason for s in spotted if not s.detection.found}),
    }


def _odometry(
    rig: Rig,
    views: list,
    baro: np.ndarray,
    uav: int,
    backend: FeatureBackend | str,
    failures: list[str],
    config: SlamSimConfig,
) -> list[Motion | None]:
    """Real VO between consecutive nadir frames; a failed step repeats the last motion, widened."""
    nadir = rig.names.index(NADIR)
    camera = rig.cameras[nadir].camera
    out: list[Motion | None] = [None]
    for k in range(1, len(views)):
        try:
            out.append(
                estimate_motion(views[k - 1][nadir], views[k][nadir], camera, float(baro[k - 1]), backend)
            )
        except OdometryError as exc:
            failures.append(f"uav {uav + 1} keyframe {k}: {exc}")
            out.append(coasting_motion(out[-1], config))
    return out


def coasting_motion(last: Motion | None, config: SlamSimConfig) -> Motion:
    """Graceful degradation when VO fails: the last motion (or the nominal speed straight on),
    with a covariance wide enough that landmarks and fixes decide instead."""
    step = config.speed_mps * config.keyframe_s
    forward, right, dyaw = (last.forward_m, last.right_m, last.dyaw_deg) if last else (step, 0.0, 0.0)
    cov = np.diag([(0.5 * step) ** 2, (0.5 * step) ** 2, 10.0**2])
    return Motion(right, forward, dyaw, cov, inliers=0, inlier_ratio=0.0, method="coasting", degenerate=True)


@dataclass
class SlamRun:
    """One setup on one world: the estimates against the truth and what went into them."""

    setup: Setup
    estimate: list[np.ndarray]  # per UAV (K, 4)
    truth: list[np.ndarray]
    landmarks_est: np.ndarray  # (L, 3)
    landmarks_true: np.ndarray
    wrong_tracks: int
    counts: dict
    stereo: dict | None
    seconds: float

    def metrics(self) -> dict:
        errors = landmark_errors_m(self.landmarks_est, self.landmarks_true)
        everyone = np.concatenate(self.estimate), np.concatenate(self.truth)
        return {
            "ate_m": round(ate_m(self.estimate[0], self.truth[0]), 2),
            "ate_all_m": round(ate_m(*everyone), 2),
            "rpe_m": round(
                float(np.mean([rpe_m(e, t) for e, t in zip(self.estimate, self.truth, strict=True)])), 2
            ),
            "landmark_m": round(float(np.median(errors)), 2) if len(errors) else None,
            "landmarks": len(errors),
        }


def run_setup(
    world: World, setup: Setup, fix_source: FixSource | None = None, backend: FeatureBackend | None = None
) -> SlamRun:
    """The SLAM loop over the world's keyframes: odometry, fixes, baseline, landmarks, iSAM2."""
    started = time.perf_counter()
    config = world.config
    if setup.uavs > len(world.truth):
        raise OrthonavError(
            f"setup {setup.name!r}: needs {setup.uavs} UAVs, the world has {len(world.truth)}"
        )
    rig = world.rig.subset(list(setup.cameras or (NADIR,)))
    cam_index = [world.rig.names.index(n) for n in rig.names]
    backend = backend or create_backend(config.features, max_keypoints=config.max_keypoints)
    graph = SlamGraph([rig] * setup.uavs, config.graph)
    views: list[View] = []
    tracks = Tracks()
    counts = {
        "fixes_tried": 0,
        "fixes_used": 0,
        "pairs_matched": 0,
        "pairs_refused": 0,
        "sightings": 0,
        "vo_failures": len(world.vo_failures),
    }
    stereo_pairs: list[tuple[int, stereo.StereoPair, stereo.StereoPair]] = []
    for k in range(config.keyframes):
        for u in range(setup.uavs):
            _add_pose(graph, world, u, k)
            if setup.fixes and fix_source is not None and k % config.fix_every == 0 and k > 0:
                counts["fixes_tried"] += 1
                counts["fixes_used"] += _add_fix(graph, world, fix_source, u, k)
        baseline = _add_sighting(graph, world, k) if setup.uavs == 2 else None
        counts["sightings"] += baseline is not None
        new = []
        for u in range(setup.uavs if setup.cameras else 0):
            pose = graph.pose(u, k)
            e, n, alt = pose.translation()
            yaw = yaw_deg_of(pose)
            for c, rig_cam in enumerate(rig.cameras):
                cam_pose = rig_cam.camera_pose(e, n, alt, yaw)
                views.append(
                    make_view(
                        world.gray[u][k][cam_index[c]],
                        rig_cam,
                        cam_pose,
                        u,
                        k,
                        c,
                        backend,
                        config.association,
                    )
                )
                new.append(len(views) - 1)
        touched: set[int] = set()
        for v in new:
            for result in _match_candidates(views, v, backend, config.association):
                counts["pairs_matched" if len(result.pairs) else "pairs_refused"] += 1
                for a, b in result.pairs:
                    track = tracks.link(views, (v, int(a)), (result.other, int(b)))
                    if track is not None:
                        touched.add(track)
        _add_landmarks(graph, views, tracks, touched)
        graph.update()
        if baseline is not None:
            pair = _stereo_pair(world, graph, views, new, backend, k, baseline)
            if pair is not None:
                stereo_pairs.append(pair)
    estimate = [
        np.array(
            [[*graph.pose(u, k).translation(), yaw_deg_of(graph.pose(u, k))] for k in range(config.keyframes)]
        )
        for u in range(setup.uavs)
    ]
    lm_est, lm_true, wrong = _landmark_truth(world, rig, cam_index, graph, views, tracks)
    counts.update(graph.counts)
    return SlamRun(
        setup,
        estimate,
        world.truth[: setup.uavs],
        lm_est,
        lm_true,
        wrong,
        counts,
        _stereo_summary(world, stereo_pairs),
        time.perf_counter() - started,
    )


def _add_pose(graph: SlamGraph, world: World, u: int, k: int) -> None:
    pitch, roll = world.ahrs[u][k]
    if k == 0:
        e, n, _, yaw = world.start[u]
        start = body_pose(e, n, world.baro[u][0], yaw, pitch, roll)
        graph.add_pose(u, 0, start)
        graph.add_start_prior(u, 0, start)
    else:
        motion = world.motions[u][k]
        prev = graph.pose(u, k - 1)
        climb = float(world.baro[u][k] - world.baro[u][k - 1])
        guess = prev.compose(odometry_step(motion, climb))
        e, n, _ = guess.translation()
        graph.add_pose(u, k, body_pose(e, n, world.baro[u][k], yaw_deg_of(guess), pitch, roll))
        graph.add_odometry(u, k - 1, k, motion, climb)
    graph.add_attitude(u, k, pitch, roll)
    graph.add_altitude(u, k, float(world.baro[u][k]))


def _add_fix(graph: SlamGraph, world: World, fix_source: FixSource, u: int, k: int) -> int:
    """Localize the nadir frame around the graph's estimate; an accepted fix becomes a factor."""
    pose = graph.pose(u, k)
    e, n, _ = pose.translation()
    lat, lon = world.frame.to_latlon(e, n)
    sigma = max(world.config.fix_sigma_floor_m, 2.0 * graph.position_sigma_m(u, k - 1))
    pitch, roll = world.ahrs[u][k]
    prior = Prior(
        float(lat),
        float(lon),
        float(world.baro[u][k]),
        yaw_deg_of(pose),
        float(pitch),
        float(roll),
        sigma_m=sigma,
        heading_sigma_deg=3.0,
        attitude_sigma_deg=world.config.ahrs_sigma_deg,
    )
    fix = fix_source.localize(world.nadir_bgr[u][k], prior)
    if not fix.accepted:
        return 0
    fe, fn = world.frame.to_enu(fix.pose.lat, fix.pose.lon)
    graph.add_fix(u, k, float(fe), float(fn), fix.covariance_enu_m2, float(world.baro[u][k]))
    return 1


def _spotter_camera(config: SlamSimConfig) -> Camera:
    return Camera.from_hfov(640, 480, config.spotter_hfov_deg)


def _add_sighting(graph: SlamGraph, world: World, k: int) -> stereo.Baseline | None:
    """UAV 2 as detected in UAV 1's spotter frame: a bearing-range factor between the two poses."""
    baseline = world.spotted[k].baseline(world.config)
    if baseline is not None:
        graph.add_baseline(
            0,
            1,
            k,
            baseline.bearing_body,
            baseline.range_m,
            baseline.bearing_sigma_rad,
            baseline.range_sigma_m,
        )
    return baseline


def _match_candidates(
    views: list[View], v: int, backend: FeatureBackend, config: AssociationConfig
) -> list[PairResult]:
    """Earlier views whose predicted footprints overlap the new one enough, best first."""
    new = views[v]
    scored = []
    for i in range(v):
        overlap = overlap_fraction(new.footprint_en, views[i].footprint_en)
        if overlap >= config.min_overlap:
            scored.append((overlap, i))
    scored.sort(reverse=True)
    return [match_views(new, views[i], i, backend, config) for _, i in scored[: config.max_candidates]]


def _add_landmarks(graph: SlamGraph, views: list[View], tracks: Tracks, touched: set[int]) -> None:
    """Tracks seen from two places become landmarks; their new observations become factors."""
    for track in sorted(touched):
        members = tracks.members.get(track)
        if members is None:  # merged away
            continue
        if track not in tracks.in_graph:
            if len(tracks.places(views, track)) < 2:
                continue
            ground = np.mean([views[vi].ground_en[kp] for vi, kp in members], axis=0)
            graph.add_landmark(track, np.array([ground[0], ground[1], 0.0]))
            tracks.in_graph.add(track)
        for vi, kp in members:
            if (vi, kp) in tracks.added:
                continue
            view = views[vi]
            graph.add_observation(view.uav, view.keyframe, view.camera, track, view.features.keypoints[kp])
            tracks.added.add((vi, kp))


def _landmark_truth(
    world: World, rig: Rig, cam_index: list[int], graph: SlamGraph, views: list[View], tracks: Tracks
) -> tuple[np.ndarray, np.ndarray, int]:
    """Each landmark's estimate and true ground point (the median of its observations' true
    ground points, from the true camera poses); tracks spread over WRONG_TRACK_M are mismatches."""
    est, true, wrong = [], [], 0
    for track in sorted(tracks.in_graph):
        points = []
        for vi, kp in tracks.members[track]:
            view = views[vi]
            e, n, alt, yaw = world.truth[view.uav][view.keyframe]
            cam = rig.cameras[view.camera]
            ground = pixel_to_ground(cam.camera, cam.camera_pose(e, n, alt, yaw), view.features.keypoints[kp])
            points.append(ground[0])
        points = np.array(points)
        centre = np.median(points, axis=0)
        if np.max(np.linalg.norm(points - centre, axis=1)) > WRONG_TRACK_M:
            wrong += 1
        est.append(graph.landmark(track))
        true.append([centre[0], centre[1], 0.0])
    return np.array(est).reshape(-1, 3), np.array(true).reshape(-1, 3), wrong


# --- two-UAV stereo: distance and size of objects -----------------------------------------


def _stereo_pair(
    world: World,
    graph: SlamGraph,
    views: list[View],
    new: list[int],
    backend: FeatureBackend,
    k: int,
    baseline: stereo.Baseline,
) -> tuple[int, stereo.StereoPair, stereo.StereoPair] | None:
    """Simultaneous nadir frames of both UAVs as a stereo pair: with the measured baseline and with
    the planned (fixed) formation baseline. None when they overlap too little or do not match."""
    config = world.config
    a, b = (next(v for v in new if views[v].uav == u and views[v].camera == 0) for u in (0, 1))
    pose_a, pose_b = graph.pose(0, k), graph.pose(1, k)
    cam = world.rig.cameras[0]
    poses = [cam.camera_pose(*p.translation(), yaw_deg_of(p)) for p in (pose_a, pose_b)]
    try:
        stereo.check_overlap(cam.camera, poses[0], cam.camera, poses[1])
    except OrthonavError:
        return None
    result = match_views(views[a], views[b], b, backend, config.association)
    if len(result.pairs) == 0:
        return None
    rotations = [rotation_enu_from_camera(p.yaw_deg, p.pitch_deg, p.roll_deg) for p in poses]
    r_enu_body = pose_a.rotation().matrix()
    px_a = views[a].features.keypoints[result.pairs[:, 0]]
    px_b = views[b].features.keypoints[result.pairs[:, 1]]
    measured = r_enu_body @ baseline.vector_body_m
    planned_body = np.array([0.0, -float(np.mean(config.offset_m)), config.alt_m - config.second_alt_m])
    common = (cam.camera, cam.camera, rotations[0], rotations[1])
    return (
        k,
        stereo.StereoPair(*common, measured, baseline.range_sigma_m, px_a, px_b),
        stereo.StereoPair(*common, r_enu_body @ planned_body, baseline.range_sigma_m, px_a, px_b),
    )


def _stereo_summary(
    world: World, pairs: list[tuple[int, stereo.StereoPair, stereo.StereoPair]]
) -> dict | None:
    """Distance and size errors: the best measured baseline, every measured one, the fixed one."""
    if not pairs:
        return None
    cam = world.rig.cameras[0]
    rng = np.random.default_rng(world.seed)

    def errors(k: int, pair: stereo.StereoPair) -> tuple[np.ndarray, np.ndarray]:
        e, n, alt, yaw = world.truth[0][k]
        cam_pose = cam.camera_pose(e, n, alt, yaw)
        ground = pixel_to_ground(cam.camera, cam_pose, pair.pixels_a)
        true = np.column_stack([ground, np.zeros(len(ground))]) - [
            cam_pose.east_m,
            cam_pose.north_m,
            cam_pose.alt_agl_m,
        ]
        points = stereo.triangulate(pair)
        index = rng.integers(0, len(points), (min(200, len(points) ** 2), 2))
        index = index[index[:, 0] != index[:, 1]]
        true_sizes = stereo.sizes_m(true, index)
        keep = true_sizes > 30.0  # objects of at least 30 m (6 NAIP pixels)
        size_err = np.abs(stereo.sizes_m(points, index)[keep] / true_sizes[keep] - 1.0)
        return np.abs(np.linalg.norm(points, axis=1) - np.linalg.norm(true, axis=1)), size_err

    predicted = [stereo.triangulate_with_error(p)[1] for _, p, _ in pairs]
    best = int(np.argmin(predicted))
    every = [errors(k, p) for k, p, _ in pairs]
    fixed = [errors(k, p) for k, _, p in pairs]
    dist_best, size_best = every[best]
    realized = [float(np.median(d)) for d, _ in every]
    return {
        "frames": len(pairs),
        "best_keyframe": pairs[best][0],
        "best_baseline_m": round(float(np.linalg.norm(pairs[best][1].baseline_enu_m)), 1),
        "predicted_distance_error_m": round(predicted[best], 2),
        # How good the choice was in fact: its rank among the pairs (1 = the truly best) and the
        # rank correlation of predicted and actual errors over the flight.
        "best_rank": int(np.sum(np.array(realized) < realized[best])) + 1,
        "rank_correlation": _rank_correlation(predicted, realized),
        "pairs": [
            {
                "keyframe": k,
                "baseline_m": round(float(np.linalg.norm(p.baseline_enu_m)), 1),
                "predicted_m": round(e, 2),
                "distance_error_m": round(r, 2),
            }
            for (k, p, _), e, r in zip(pairs, predicted, realized, strict=True)
        ],
        "distance_error_m": {
            "best measured baseline": round(float(np.median(dist_best)), 2),
            "every measured baseline": round(float(np.median(np.concatenate([d for d, _ in every]))), 2),
            "fixed baseline": round(float(np.median(np.concatenate([d for d, _ in fixed]))), 2),
        },
        "size_error_pct": {
            "best measured baseline": round(100 * float(np.median(size_best)), 2),
            "every measured baseline": round(
                100 * float(np.median(np.concatenate([s for _, s in every]))), 2
            ),
            "fixed baseline": round(100 * float(np.median(np.concatenate([s for _, s in fixed]))), 2),
        },
    }


def _rank_correlation(a: list[float], b: list[float]) -> float | None:
    """Spearman's rank correlation (no ties expected in continuous errors)."""
    if len(a) < 3:
        return None
    ranks = [np.argsort(np.argsort(np.asarray(x, float))) for x in (a, b)]
    return round(float(np.corrcoef(*ranks)[0, 1]), 2)

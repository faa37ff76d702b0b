"""Visual odometry over a sequence: chained poses, keyframes, a local map of triangulated
landmarks, and the comparison of each step with the photos' GNSS and gimbal yaw.

Local frame of a run: metres from the first frame's camera, x along its image right, y along
its image up (forward), z up; yaw clockwise from that first image-up direction.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend
from orthonav.flightlog.photos import Photo, PhotoFlight
from orthonav.geo import azimuth_deg, distance_m
from orthonav.odometry.keymap import KeyObjectMapBuilder
from orthonav.odometry.motion import FramePair, Motion, MotionConfig, OdometryError, track


@dataclass(frozen=True)
class Pose2D:
    """A camera in the run's local frame (see the module docstring)."""

    x_m: float
    y_m: float
    yaw_deg: float

    def then(self, motion: Motion) -> Pose2D:
        """This pose followed by ``motion`` (given in this pose's image axes)."""
        yaw = math.radians(self.yaw_deg)
        # Image right of a camera turned clockwise by yaw is (cos, -sin); image up is (sin, cos).
        dx = motion.right_m * math.cos(yaw) + motion.forward_m * math.sin(yaw)
        dy = -motion.right_m * math.sin(yaw) + motion.forward_m * math.cos(yaw)
        return Pose2D(self.x_m + dx, self.y_m + dy, _wrap_deg(self.yaw_deg + motion.dyaw_deg))


@dataclass(frozen=True)
class KeyframePolicy:
    """A new keyframe when the view has moved on: little overlap left, a turn, or few inliers."""

    min_overlap: float = 0.7
    max_dyaw_deg: float = 20.0
    min_inliers: int = 60

    def is_keyframe(self, since_keyframe: Motion) -> bool:
        return (
            since_keyframe.overlap < self.min_overlap
            or abs(since_keyframe.dyaw_deg) > self.max_dyaw_deg
            or since_keyframe.inliers < self.min_inliers
        )


@dataclass
class LocalMap:
    """Triangulated 3D landmarks of the last ``max_keyframes`` keyframes, with descriptors.

    Points are in the run's local frame; z is the height above the ground plane (the
    altitude minus the depth), so tree tops and roofs stand out from the ground.
    """

    max_keyframes: int = 5
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    descriptors: list[np.ndarray] = field(default_factory=list)
    keyframe_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.points)

    def add(
        self,
        keyframe_id: int,
        pose: Pose2D,
        alt_agl_m: float,
        motion: Motion,
        pair: FramePair,
        inliers: np.ndarray,
    ) -> int:
        """Triangulate the inliers of a keyframe-to-keyframe ``pair``; returns how many were kept."""
        xyz_cam = triangulate(pair, inliers, motion)
        depth = xyz_cam[:, 2]
        keep = np.isfinite(depth) & (depth > 0.2 * alt_agl_m) & (depth < 3.0 * alt_agl_m)
        xyz_cam = xyz_cam[keep]
        yaw = math.radians(pose.yaw_deg)
        # Camera axes (x right, y down, z down) -> local frame (x, y forward, z up).
        right, forward = xyz_cam[:, 0], -xyz_cam[:, 1]
        world = np.column_stack(
            [
                pose.x_m + right * math.cos(yaw) + forward * math.sin(yaw),
                pose.y_m - right * math.sin(yaw) + forward * math.cos(yaw),
                alt_agl_m - xyz_cam[:, 2],
            ]
        )
        desc = pair.previous.descriptors[pair.pairs[np.flatnonzero(inliers)[keep], 0]]
        self.points = np.vstack([self.points, world])
        self.descriptors.extend(desc)
        self.keyframe_ids = np.concatenate([self.keyframe_ids, np.full(len(world), keyframe_id)])
        self._prune(keyframe_id)
        return len(world)

    def _prune(self, newest: int) -> None:
        keep = self.keyframe_ids > newest - self.max_keyframes
        self.points, self.keyframe_ids = self.points[keep], self.keyframe_ids[keep]
        self.descriptors = [d for d, k in zip(self.descriptors, keep, strict=True) if k]


def triangulate(pair: FramePair, inliers: np.ndarray, motion: Motion) -> np.ndarray:
    """(N, 3) inlier points in the previous camera's frame (metres), from the metric ``motion``.

    The camera is taken as nadir in both frames, turned by ``dyaw`` about its optical axis.
    """
    k = pair.camera.K
    a = math.radians(motion.dyaw_deg)
    # Rotation taking previous-camera vectors into the current camera (a turn about z).
    rot = np.array([[math.cos(a), math.sin(a), 0.0], [-math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([motion.right_m, -motion.forward_m, -motion.climb_m])
    p1 = k @ np.hstack([np.eye(3), np.zeros((3, 1))])
    p2 = k @ np.hstack([rot, (-rot @ centre)[:, None]])
    idx = np.flatnonzero(inliers)
    homog = cv2.triangulatePoints(p1, p2, pair.previous_px[idx].T, pair.current_px[idx].T)
    return (homog[:3] / homog[3]).T


@dataclass(frozen=True)
class Truth:
    """A step's reference from GNSS (pyproj geodesics) and the previous photo's heading."""

    right_m: float
    forward_m: float
    dyaw_deg: float
    distance_m: float
    course_deg: float  # GNSS azimuth of travel


def truth_between(previous: Photo, current: Photo) -> Truth:
    """GNSS displacement in the previous image's axes (its heading = image up), heading change."""
    if previous.heading_deg is None or current.heading_deg is None:
        raise OrthonavError(f"{previous.path.name}/{current.path.name}: no gimbal or flight yaw in XMP")
    dist = float(distance_m(previous.lat, previous.lon, current.lat, current.lon))
    course = float(azimuth_deg(previous.lat, previous.lon, current.lat, current.lon))
    rel = math.radians(course - previous.heading_deg)
    return Truth(
        dist * math.sin(rel),
        dist * math.cos(rel),
        _wrap_deg(current.heading_deg - previous.heading_deg),
        dist,
        course,
    )


@dataclass
class Step:
    """One frame of a photo run: the motion from the previous frame (or why there is none)."""

    index: int
    name: str
    motion: Motion | None
    reason: str
    pose: Pose2D | None
    truth: Truth | None
    keyframe: bool = False
    landmarks: int = 0
    elapsed_s: float = 0.0

    def errors(self) -> dict:
        """Errors against GNSS/gimbal; ``heading_offset_deg``: where the image top really pointed
        (GNSS course minus the VO direction of travel) minus the photo's recorded heading."""
        if self.motion is None or self.truth is None:
            return {}
        m, t = self.motion, self.truth
        out = {
            "displacement_error_m": math.hypot(m.right_m - t.right_m, m.forward_m - t.forward_m),
            "distance_error_m": m.distance_m - t.distance_m,
            "dyaw_error_deg": _wrap_deg(m.dyaw_deg - t.dyaw_deg),
        }
        if t.distance_m > 2.0 and m.distance_m > 0.5 * t.distance_m:
            travel = math.degrees(math.atan2(m.right_m, m.forward_m))
            course_in_image = math.degrees(math.atan2(t.right_m, t.forward_m))
            out["heading_offset_deg"] = _wrap_deg(course_in_image - travel)
        return out

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "name": self.name,
            "ok": self.motion is not None,
            "reason": self.reason,
            "motion": self.motion.to_dict() if self.motion else None,
            "pose": None if self.pose is None else vars(self.pose),
            "truth": None if self.truth is None else vars(self.truth),
            "keyframe": self.keyframe,
            "landmarks": self.landmarks,
            "elapsed_s": self.elapsed_s,
            **self.errors(),
        }


def run_photos(
    flight: PhotoFlight,
    backend: str | FeatureBackend = "orb",
    method: str = "homography",
    config: MotionConfig | None = None,
    policy: KeyframePolicy | None = None,
    local_map: LocalMap | None = None,
    key_objects: KeyObjectMapBuilder | None = None,
) -> Iterator[Step]:
    """VO over consecutive photos; a failed step keeps the last pose and restarts from the frame.

    Yields one :class:`Step` per photo (the first has no motion). Photos without a relative
    altitude (no DJI XMP) use the last known one, or fail with a clear reason. With
    ``key_objects``, every photo's key objects and each step's landmarks go into that builder
    (``key_objects.build(keyframes)`` then makes the map).
    """
    import time

    policy = policy or KeyframePolicy()
    local_map = local_map if local_map is not None else LocalMap()
    camera = _flight_camera(flight)
    photos = flight.photos
    pose, previous, keyframe = Pose2D(0.0, 0.0, 0.0), _load(photos[0], camera), 0
    key_image, key_pose = previous, pose
    alt = photos[0].rel_alt_m
    segment = 0
    _observe(key_objects, 0, photos[0], previous, pose, alt, segment)
    yield Step(0, photos[0].path.name, None, "first frame", pose, None, keyframe=True)
    for i in range(1, len(photos)):
        start = time.perf_counter()
        current = _load(photos[i], camera)
        alt = photos[i - 1].rel_alt_m or alt
        step = Step(i, photos[i].path.name, None, "", None, _truth_or_none(photos[i - 1], photos[i]))
        if alt is None:
            step.reason = f"{photos[i - 1].path.name}: no RelativeAltitude in XMP: the scale is unknown"
        else:
            try:
                motion, pair, inliers = track(previous, current, camera, alt, backend, method, config)
            except OdometryError as exc:
                step.reason = str(exc)
            else:
                if key_objects is not None:
                    name = backend if isinstance(backend, str) else backend.name
                    landmarks = triangulate(pair, inliers, motion)
                    key_objects.add_landmarks(i - 1, name, pair, inliers, landmarks)
                step.motion, pose = motion, pose.then(motion)
                step.pose = pose
                step.keyframe, step.landmarks = _keyframe(
                    (key_image, key_pose, keyframe),
                    current,
                    camera,
                    alt,
                    backend,
                    method,
                    config,
                    policy,
                    local_map,
                    i,
                )
                if step.keyframe:
                    key_image, key_pose, keyframe = current, pose, i
        if step.motion is None:  # lost: the next step starts from this frame
            key_image, key_pose, keyframe = current, pose, i
            segment += 1
        _observe(key_objects, i, photos[i], current, pose, photos[i].rel_alt_m or alt, segment)
        step.elapsed_s = time.perf_counter() - start
        previous = current
        yield step


def _keyframe(
    key: tuple[np.ndarray, Pose2D, int],
    current: np.ndarray,
    camera: Camera,
    alt: float,
    backend: str | FeatureBackend,
    method: str,
    config: MotionConfig | None,
    policy: KeyframePolicy,
    local_map: LocalMap,
    index: int,
) -> tuple[bool, int]:
    """Whether ``current`` becomes a keyframe; if so its landmarks go into the local map."""
    key_image, key_pose, keyframe = key
    try:
        since, pair, inliers = track(key_image, current, camera, alt, backend, method, config)
    except OdometryError:
        return True, 0
    if not policy.is_keyframe(since) and index - keyframe < 10:
        return False, 0
    return True, local_map.add(index, key_pose, alt, since, pair, inliers)


def _observe(
    builder: KeyObjectMapBuilder | None,
    index: int,
    photo: Photo,
    image: np.ndarray,
    pose: Pose2D,
    alt: float | None,
    segment: int,
) -> None:
    if builder is not None and alt is not None:
        where = np.array([pose.x_m, pose.y_m, alt, pose.yaw_deg])
        builder.observe(index, photo.path.name, image, where, segment)


def _truth_or_none(previous: Photo, current: Photo) -> Truth | None:
    try:
        return truth_between(previous, current)
    except OrthonavError:
        return None


def _flight_camera(flight: PhotoFlight) -> Camera:
    if len(flight) < 2:
        raise OrthonavError(f"{flight.source}: visual odometry needs at least 2 photos, got {len(flight)}")
    camera = flight.camera
    if camera is None:
        raise OrthonavError(
            f"{flight.source}: the photos do not share one camera with known intrinsics "
            "(EXIF FocalLength and FocalPlaneXResolution or FocalLengthIn35mmFilm)"
        )
    return camera


def _load(photo: Photo, camera: Camera) -> np.ndarray:
    image = cv2.imread(str(photo.path), cv2.IMREAD_COLOR)
    if image is None:
        raise OrthonavError(f"{photo.path}: cannot be decoded as an image")
    if image.shape[:2] != (camera.height, camera.width):
        raise OrthonavError(
            f"{photo.path}: {image.shape[1]}x{image.shape[0]} px, the other photos are "
            f"{camera.width}x{camera.height}"
        )
    return image


def _wrap_deg(angle: float) -> float:
    return (angle + 180.0) % 360.0 - 180.0

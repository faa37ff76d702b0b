"""Landmarks across frames, cameras and vehicles: ground-rectified features, verified matches, tracks.

Each frame is warped to a north-up view of the ground at one common resolution, using its
camera's predicted pose (the current estimate, the rig's extrinsics and the AHRS attitude),
so a nadir frame, an oblique frame and the other UAV's frame of the same ground look alike
to the feature matcher. Keypoints are found there and mapped back to the frame's own pixels
(what the projection factors measure). A new frame is matched against the earlier frames
whose predicted footprints overlap it; a pair is kept only when a homography (the ground is
a plane) explains enough matches. Verified matches join keypoints into tracks; a track
becomes a landmark once vehicles at two different places have seen it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from orthonav.camera import CameraPose, apply_homography, footprint_enu, ground_to_image_homography
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet
from orthonav.slam.rig import RigCamera

MAX_RECTIFIED_PX = 1400


@dataclass(frozen=True)
class AssociationConfig:
    """How frames are matched and when a pair counts as overlapping."""

    rectified_gsd_m: float = 2.5
    min_overlap: float = 0.25
    max_candidates: int = 8
    min_inliers: int = 15
    min_inlier_ratio: float = 0.25
    homography_threshold_px: float = 2.0
    max_observations_per_view: int = 150

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class View:
    """One frame of one camera of one vehicle at one keyframe, with its features."""

    uav: int
    keyframe: int
    camera: int
    features: FeatureSet  # keypoints in the frame's camera-model pixels (centre of pixel 0: 0.5)
    ground_en: np.ndarray  # (N, 2) the keypoints on the ground from the predicted pose (ENU m)
    footprint_en: np.ndarray  # (4, 2) predicted ground footprint
    track: np.ndarray = field(default=None)  # (N,) track id per keypoint, -1 none

    def __post_init__(self) -> None:
        if self.track is None:
            self.track = np.full(len(self.features), -1, np.int64)

    @property
    def place(self) -> tuple[int, int]:
        return self.uav, self.keyframe


def make_view(
    gray: np.ndarray,
    rig_camera: RigCamera,
    camera_pose: CameraPose,
    uav: int,
    keyframe: int,
    camera_index: int,
    backend: FeatureBackend,
    config: AssociationConfig,
) -> View:
    """Rectify ``gray`` to a north-up ground view, extract features there, keep them in frame pixels."""
    cam = rig_camera.camera
    if gray.ndim != 2 or gray.shape != (cam.height, cam.width):
        raise OrthonavError(
            f"view of camera {rig_camera.name!r}: expected a {cam.width}x{cam.height} grayscale frame, "
            f"got shape {gray.shape}"
        )
    footprint = footprint_enu(cam, camera_pose)
    gsd = config.rectified_gsd_m
    east0, north0 = footprint[:, 0].min(), footprint[:, 1].max()
    size = np.ceil((footprint.max(axis=0) - footprint.min(axis=0)) / gsd).astype(int)
    if np.any(size > MAX_RECTIFIED_PX):  # a far-reaching oblique view: coarser, not huge
        gsd *= float(size.max()) / MAX_RECTIFIED_PX
        size = np.ceil((footprint.max(axis=0) - footprint.min(axis=0)) / gsd).astype(int)
    ground_to_rect = np.array([[1 / gsd, 0, -east0 / gsd], [0, -1 / gsd, north0 / gsd], [0, 0, 1]])
    frame_to_rect = ground_to_rect @ np.linalg.inv(ground_to_image_homography(cam, camera_pose))
    width, height = int(size[0]) + 1, int(size[1]) + 1
    # Frame pixel index i is the camera model's i + 0.5 (pixel centres); the rectified view's
    # index is its own coordinate.
    index_to_rect = frame_to_rect @ np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    rect = cv2.warpPerspective(gray, index_to_rect, (width, height), flags=cv2.INTER_AREA)
    valid = cv2.warpPerspective(
        np.full_like(gray, 255), index_to_rect, (width, height), flags=cv2.INTER_NEAREST
    )
    valid = cv2.erode(valid, np.ones((15, 15), np.uint8))
    feats = backend.extract(rect, valid)
    if len(feats):
        frame_px = apply_homography(np.linalg.inv(frame_to_rect), feats.keypoints)
        inside = np.flatnonzero(
            (frame_px[:, 0] >= 0)
            & (frame_px[:, 0] < cam.width)
            & (frame_px[:, 1] >= 0)
            & (frame_px[:, 1] < cam.height)
        )
        ground = apply_homography(np.linalg.inv(ground_to_rect), feats.keypoints[inside])
        feats = FeatureSet(
            frame_px[inside], feats.descriptors[inside], feats.scores[inside], (cam.width, cam.height)
        )
    else:
        ground = np.zeros((0, 2))
    return View(uav, keyframe, camera_index, feats, ground, footprint)


def overlap_fraction(a: np.ndarray, b: np.ndarray) -> float:
    """Shared ground area of two convex footprints over the smaller one's area."""
    pa, pb = a.astype(np.float32), b.astype(np.float32)
    area, _ = cv2.intersectConvexConvex(pa, pb)
    smaller = min(cv2.contourArea(pa), cv2.contourArea(pb))
    return float(area / smaller) if smaller > 0 else 0.0


@dataclass
class PairResult:
    """The verified matches of a new view against an earlier one, or why there are none."""

    other: int
    pairs: np.ndarray  # (M, 2) keypoint indices (new view, other view)
    reason: str = ""


def match_views(
    new: View, old: View, other_index: int, backend: FeatureBackend, config: AssociationConfig
) -> PairResult:
    """Descriptor matches checked by a ground homography; refused pairs say why."""
    if len(new.features) < config.min_inliers or len(old.features) < config.min_inliers:
        return PairResult(other_index, np.zeros((0, 2), np.int64), "too few features")
    matches = backend.match(new.features, old.features)
    if len(matches) < config.min_inliers:
        return PairResult(other_index, np.zeros((0, 2), np.int64), f"only {len(matches)} matches")
    pairs = matches.pairs
    src = new.ground_en[pairs[:, 0]] / config.rectified_gsd_m
    dst = old.ground_en[pairs[:, 1]] / config.rectified_gsd_m
    h, mask = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, config.homography_threshold_px, maxIters=2000)
    inliers = int(mask.sum()) if h is not None else 0
    if inliers < config.min_inliers or inliers < config.min_inlier_ratio * len(pairs):
        return PairResult(
            other_index,
            np.zeros((0, 2), np.int64),
            f"{inliers} of {len(pairs)} matches fit one ground homography",
        )
    return PairResult(other_index, pairs[mask.ravel().astype(bool)])


class Tracks:
    """Keypoints of different views joined by verified matches; one track = one ground point.

    A track never holds two keypoints of the same view. ``in_graph`` marks the tracks that are
    landmarks already, and ``added`` the observations their factors carry.
    """

    def __init__(self) -> None:
        self.members: dict[int, list[tuple[int, int]]] = {}  # track -> [(view index, keypoint)]
        self.in_graph: set[int] = set()
        self.added: set[tuple[int, int]] = set()
        self._next = 0

    def link(self, views: list[View], a: tuple[int, int], b: tuple[int, int]) -> int | None:
        """Join keypoint ``a`` (view, kp) with ``b``; returns the track they now share, if any."""
        ta, tb = views[a[0]].track[a[1]], views[b[0]].track[b[1]]
        if ta < 0 and tb < 0:
            track = self._new()
            self._add(views, track, a)
            self._add(views, track, b)
            return track
        if ta >= 0 and tb >= 0:
            return ta if ta == tb else self._merge(views, int(ta), int(tb))
        track, loose = (int(ta), b) if ta >= 0 else (int(tb), a)
        if any(v == loose[0] for v, _ in self.members[track]):
            return None  # the track already has a keypoint of that view
        self._add(views, track, loose)
        return track

    def places(self, views: list[View], track: int) -> set[tuple[int, int]]:
        return {views[v].place for v, _ in self.members[track]}

    def _new(self) -> int:
        self._next += 1
        self.members[self._next - 1] = []
        return self._next - 1

    def _add(self, views: list[View], track: int, member: tuple[int, int]) -> None:
        self.members[track].append(member)
        views[member[0]].track[member[1]] = track

    def _merge(self, views: list[View], ta: int, tb: int) -> int | None:
        """Two tracks meet: merge when their views do not clash and at most one is a landmark."""
        if ta in self.in_graph and tb in self.in_graph:
            return None
        if {v for v, _ in self.members[ta]} & {v for v, _ in self.members[tb]}:
            return None
        keep, gone = (tb, ta) if ta not in self.in_graph and tb in self.in_graph else (ta, tb)
        for member in self.members.pop(gone):
            self._add(views, keep, member)
        return keep

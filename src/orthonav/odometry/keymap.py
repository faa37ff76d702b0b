"""The key-object map filled by a VO run: each keyframe is a trajectory key point ``l``;
its viewpoints ``r`` are the keyframe and its neighbouring photos tracked with it; each
viewpoint's cloud holds the key objects it sees inside the keyframe's ground footprint:

- triangulated landmarks (detector F = the feature backend, H its descriptor), from the
  viewpoint and the next photo;
- low-level points (gradient, extremum; H the relative descriptor ``D_RI``) and line segments
  (H the line descriptor, both endpoints kept), placed in 3D on the ground plane at the
  viewpoint's altitude (a nadir camera);
- colour regions (H a one-hot class and the area in m^2), each point, line and landmark linked
  to the region it lies in.

The base viewpoint ``r_B`` of each key point is the one with the most key objects over all
directions, and every cloud of the key point is moved into ``r_B``'s frame. Frames of one photo
are computed once and reused by every key point that sees them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from matplotlib.path import Path as Polygon

from orthonav.camera import Camera, image_corners
from orthonav.keyobjects import (
    CLASSES,
    KeyObjectCloud,
    KeyObjectMap,
    LineConfig,
    LowLevelConfig,
    RegionConfig,
    classify,
    detect_lines,
    detect_low_level,
    line_descriptors,
    region_map,
    relative_descriptors,
    relative_pose,
)
from orthonav.keyobjects.model import place
from orthonav.odometry.motion import FramePair


@dataclass(frozen=True)
class KeyObjectConfig:
    direction: str = "nadir"  # the camera's name; a multi-camera rig adds one per camera
    max_side_px: int = 1280
    low_level: LowLevelConfig = field(
        default_factory=lambda: LowLevelConfig(max_gradient_points=500, max_extrema=800)
    )
    lines: LineConfig = field(default_factory=LineConfig)
    regions: RegionConfig = field(default_factory=lambda: RegionConfig(min_area_px=400))
    neighbours: int = 1  # viewpoints: the keyframe and this many photos either side


@dataclass
class _Frame:
    """One photo's key objects in its own viewpoint frame, and its pose in the run frame."""

    name: str
    pose: np.ndarray  # x, y, z (altitude), yaw_deg
    segment: int  # photos of one segment are chained by VO; across segments poses are unrelated
    footprint: np.ndarray  # (4, 2) ground corners in the viewpoint frame
    cloud: KeyObjectCloud
    region_ids: np.ndarray  # (H, W) index of the region object (= cloud index) per pixel, -1 none
    camera: Camera


@dataclass
class KeyObjectMapBuilder:
    """Collects per-photo key objects during a VO run, then builds the :class:`KeyObjectMap`."""

    camera: Camera
    config: KeyObjectConfig = field(default_factory=KeyObjectConfig)
    frames: dict[int, _Frame] = field(default_factory=dict)

    def observe(self, index: int, name: str, image: np.ndarray, pose: np.ndarray, segment: int) -> None:
        """Key objects of photo ``index`` (BGR, full size) at ``pose`` (x, y, altitude, yaw_deg)."""
        scale = min(1.0, self.config.max_side_px / max(self.camera.width, self.camera.height))
        work = self.camera.scaled(scale) if scale < 1.0 else self.camera
        bgr = cv2.resize(image, (work.width, work.height), interpolation=cv2.INTER_AREA)
        cloud, ids = frame_objects(bgr, work, float(pose[2]), self.config)
        footprint = _ground(work, image_corners(work), float(pose[2]))[:, :2]
        self.frames[index] = _Frame(name, np.asarray(pose, float), segment, footprint, cloud, ids, work)

    def add_landmarks(
        self, index: int, detector: str, pair: FramePair, inliers: np.ndarray, cam: np.ndarray
    ) -> None:
        """Landmarks of photo ``index`` and the next one (``cam``: the inliers triangulated in
        ``index``'s camera frame, x right, y down, z along the axis), added to ``index``'s cloud."""
        frame = self.frames.get(index)
        if frame is None or not len(cam):
            return
        alt = float(frame.pose[2])
        keep = np.isfinite(cam[:, 2]) & (cam[:, 2] > 0.2 * alt) & (cam[:, 2] < 3.0 * alt)
        rows = np.flatnonzero(inliers)[keep]
        xyz = np.column_stack([cam[keep, 0], -cam[keep, 1], -cam[keep, 2]])
        px = pair.previous.keypoints[pair.pairs[rows, 0]]
        added = KeyObjectCloud(
            xyz,
            [detector] * len(xyz),
            list(pair.previous.descriptors[pair.pairs[rows, 0]]),
            _region_at(frame.region_ids, px),
        )
        frame.cloud = _concat(frame.cloud, added)

    def build(self, keyframes: list[int]) -> KeyObjectMap:
        """The map over ``keyframes`` (photo indices): viewpoints, base choice, clouds moved."""
        model = KeyObjectMap()
        for key in keyframes:
            if key not in self.frames:
                continue
            home = self.frames[key]
            views = {}
            for r in range(key - self.config.neighbours, key + self.config.neighbours + 1):
                frame = self.frames.get(r)
                if frame is None or frame.segment != home.segment:
                    continue
                pose = relative_pose(frame.pose, home.pose)  # viewpoint r in the keyframe's frame
                area = Polygon(home.footprint)
                inside = area.contains_points(place(frame.cloud.xyz, pose)[:, :2])
                views[r] = (pose, frame.cloud.subset(inside | _is_region(frame.cloud)))
            for r, (_, cloud) in views.items():
                model.add(key, self.config.direction, r, cloud)
            base = model.base_viewpoint(key)
            base_pose = views[base][0]
            for r, (pose, cloud) in views.items():
                in_base = relative_pose(pose, base_pose)
                model.add(key, self.config.direction, r, cloud.moved(in_base))
                model.poses[(key, r)] = in_base
            model.origins[key] = _compose(home.pose, base_pose)
            model.names[key] = home.name
        return model


def frame_objects(
    bgr: np.ndarray, camera: Camera, alt_m: float, config: KeyObjectConfig
) -> tuple[KeyObjectCloud, np.ndarray]:
    """Regions, low-level points and line segments of one image (at ``camera``'s size) in its
    viewpoint frame, on the ground plane ``alt_m`` below; and the region index image."""
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    found, ids = region_map(classify(bgr, config.regions), config.regions)
    gsd2 = (alt_m / math.sqrt(camera.fx * camera.fy)) ** 2
    region_xy = np.array([[r.x, r.y] for r in found]).reshape(-1, 2)
    region_h = [
        np.concatenate([np.eye(len(CLASSES))[CLASSES.index(r.label)], [r.area_px * gsd2]]) for r in found
    ]
    region_xyz = _ground(camera, region_xy, alt_m)
    parts = [KeyObjectCloud(region_xyz, ["region"] * len(found), region_h, np.arange(len(found)))]
    low = detect_low_level(gray, config.low_level)
    n = config.low_level.neighbours
    if len(low.gradient) > n:
        for name, pts in (("gradient", low.gradient), ("extremum", low.extremal)):
            if len(pts):
                desc = relative_descriptors(pts, low.gradient, n)  # extrema relative to gradient points
                xyz, region = _ground(camera, pts, alt_m), _region_at(ids, pts)
                parts.append(KeyObjectCloud(xyz, [name] * len(pts), list(desc), region))
    segments = detect_lines(gray, config.lines)
    if len(segments) > config.lines.neighbours:
        ends = _ground(camera, segments.reshape(-1, 2), alt_m).reshape(-1, 2, 3)
        mid = (segments[:, :2] + segments[:, 2:]) / 2
        parts.append(
            KeyObjectCloud(
                ends.mean(axis=1),
                ["line"] * len(segments),
                list(line_descriptors(segments, config.lines)),
                _region_at(ids, mid),
                ends,
            )
        )
    cloud = parts[0]
    for part in parts[1:]:
        cloud = _concat(cloud, part)
    return cloud, ids


def _ground(camera: Camera, px: np.ndarray, alt_m: float) -> np.ndarray:
    """Pixels -> points on the ground plane ``alt_m`` below a nadir camera (viewpoint frame)."""
    if not len(px):
        return np.zeros((0, 3))
    ideal = camera.undistort_points(px)
    x = (ideal[:, 0] - camera.cx) / camera.fx * alt_m
    y = (ideal[:, 1] - camera.cy) / camera.fy * alt_m
    return np.column_stack([x, -y, np.full(len(x), -alt_m)])


def _region_at(ids: np.ndarray, px: np.ndarray) -> np.ndarray:
    h, w = ids.shape
    col = np.clip(np.round(px[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.round(px[:, 1]).astype(int), 0, h - 1)
    return ids[row, col].astype(np.int64)


def _is_region(cloud: KeyObjectCloud) -> np.ndarray:
    return np.array([f == "region" for f in cloud.detectors], bool)


def _concat(first: KeyObjectCloud, second: KeyObjectCloud) -> KeyObjectCloud:
    """``second`` appended to ``first``; region links of both keep pointing at ``first``'s regions."""
    return KeyObjectCloud(
        np.vstack([first.xyz, second.xyz]),
        first.detectors + second.detectors,
        first.descriptors + second.descriptors,
        np.concatenate([first.region, second.region]),
        np.concatenate([first.ends, second.ends]),
    )


def _compose(pose: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """The pose at ``relative`` in the frame of ``pose``, in ``pose``'s own parent frame."""
    xyz = place(relative[None, :3], pose)[0]
    return np.array([*xyz, (float(pose[3]) + float(relative[3]) + 180.0) % 360.0 - 180.0])

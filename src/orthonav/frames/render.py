"""Synthesize camera frames from an orthophoto at a given pose, with photometric change.

The frame is what the camera model sees of a flat ground textured by the orthophoto:
frame pixels -> ground ENU (inverse ground homography) -> WGS84 -> orthophoto pixels, all
through the geo module, then one resampling. The orthophoto window is read at about the
frame's ground resolution first (area averaging), so distant high-resolution maps do not alias.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, apply_homography, footprint_enu, pixel_to_ground
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, LocalFrame


@dataclass(frozen=True)
class Photometric:
    """A camera/light/season change: out = gain * ((in/255)^gamma * contrast + brightness)."""

    brightness: float = 0.0
    contrast: float = 1.0
    gamma: float = 1.0
    colour_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    blur_sigma_px: float = 0.0
    noise_sigma: float = 0.0

    @classmethod
    def random(cls, rng: np.random.Generator, strength: float = 1.0) -> Photometric:
        """A random change; ``strength`` 1 is a strong but realistic difference."""
        s = float(strength)
        return cls(
            brightness=float(rng.uniform(-0.12, 0.12) * s),
            contrast=float(1.0 + rng.uniform(-0.3, 0.3) * s),
            gamma=float(np.exp(rng.uniform(-0.3, 0.3) * s)),
            colour_gain=tuple(float(g) for g in 1.0 + rng.uniform(-0.1, 0.1, 3) * s),
            blur_sigma_px=float(rng.uniform(0.0, 1.2) * s),
            noise_sigma=float(rng.uniform(0.0, 0.03) * s),
        )

    def apply(self, bgr: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        img = bgr.astype(np.float32) / 255.0
        img = np.power(img, self.gamma) * self.contrast + self.brightness
        img *= np.array(self.colour_gain[::-1], np.float32)
        if self.blur_sigma_px > 0.05:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma_px)
        if self.noise_sigma > 0:
            img += rng.normal(0.0, self.noise_sigma, img.shape).astype(np.float32)
        return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TruePose:
    """Where the simulated vehicle really is."""

    lat: float
    lon: float
    alt_agl_m: float
    yaw_deg: float
    pitch_deg: float = 0.0
    roll_deg: float = 0.0


def render_frame(
    raster: GeoRaster,
    camera: Camera,
    pose: TruePose,
    photometric: Photometric | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """(H, W, 3) BGR uint8 frame seen by ``camera`` at ``pose`` over ``raster``.

    Raises where the horizon is in view (see `sees_only_ground`): beyond it the ground mapping
    turns over, which would draw ground in the sky or, with a window that large, crash OpenCV's
    warp."""
    enu = LocalFrame(pose.lat, pose.lon)
    cam_pose = _camera_pose(pose)
    footprint_enu(camera, cam_pose)  # raises with the horizon in view

    def frame_to_latlon(pts_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ground = pixel_to_ground(camera, cam_pose, pts_px)
        return enu.to_latlon(ground[:, 0], ground[:, 1])

    gsd_m = camera.nadir_gsd_m(pose.alt_agl_m)
    if camera.distortion and any(camera.distortion):
        rgb, h_frame_to_window = raster.read_view_window(frame_to_latlon, camera.width, camera.height, gsd_m)
        frame = _render_distorted(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), camera, h_frame_to_window)
    else:
        rgb = raster.read_view(frame_to_latlon, camera.width, camera.height, gsd_m)
        frame = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if photometric is not None:
        frame = photometric.apply(frame, rng or np.random.default_rng(0))
    return frame


def sees_only_ground(camera: Camera, pose: TruePose) -> bool:
    """Whether every corner of the frame looks at the ground, so `render_frame` can draw it: a
    camera banked or pitched past the horizon sees sky."""
    try:
        footprint_enu(camera, _camera_pose(pose))
    except OrthonavError:
        return False
    return True


def _camera_pose(pose: TruePose) -> CameraPose:
    """The camera's pose in the local frame centred under it."""
    return CameraPose(0.0, 0.0, pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)


def _render_distorted(bgr: np.ndarray, camera: Camera, h_frame_to_window: np.ndarray) -> np.ndarray:
    """Each distorted output pixel looks up its ideal pinhole position, then the window."""
    ideal = _ideal_pixels(camera)
    window = apply_homography(h_frame_to_window, ideal).astype(np.float32)
    mx = window[:, 0].reshape(camera.height, camera.width)
    my = window[:, 1].reshape(camera.height, camera.width)
    return cv2.remap(bgr, mx, my, cv2.INTER_LINEAR, borderValue=0)


@functools.lru_cache(maxsize=4)
def _ideal_pixels(camera: Camera) -> np.ndarray:
    """(H * W, 2) ideal pinhole positions of every pixel centre, row by row (float32, read-only):
    the same for every rendering with one camera, and most of one's cost (the cascade renders a
    real photo's camera two or three times a frame). Float32 (1e-4 px at 1600 px,
    what the remap samples with anyway) and 4 cameras at most: 15 MB for a 1600 x 1200 one."""
    u, v = np.meshgrid(
        np.arange(camera.width, dtype=np.float64) + 0.5, np.arange(camera.height, dtype=np.float64) + 0.5
    )
    ideal = camera.undistort_points(np.column_stack([u.ravel(), v.ravel()])).astype(np.float32)
    ideal.setflags(write=False)
    return ideal

"""Frame-to-frame motion of a downward camera, in metres, from two overlapping frames.

Frames and conventions (those of :mod:`orthonav.camera.pose`)
- Pixels: x right, y down; the image top is the heading. A nadir image seen on screen is a
  view from above, so a clockwise turn of the heading is a clockwise turn on screen.
- :class:`Motion` gives the current camera centre in the PREVIOUS frame's axes: ``right_m``
  along its image x, ``forward_m`` along its image up (-y), and ``dyaw_deg`` the heading
  change, clockwise positive.

Two geometric models, chosen by ``method``:
- ``homography`` (default): matches are assumed on the ground plane; the homography is
  decomposed with the intrinsics (``R + t n^T / d``) and ``d``, the plane's distance from the
  previous camera, is the altitude above ground. Hovering and pure rotation are not
  degenerate for it (t = 0 is a valid answer).
- ``essential``: the essential matrix makes no planar assumption (trees, buildings); its
  translation has no scale, which comes from the median depth of the triangulated inliers set
  to the altitude. Without parallax (hovering, pure rotation) the translation direction is
  undefined: the homography answer is returned instead, marked ``method="homography"`` and
  ``degenerate=True``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np

from orthonav.camera import Camera, apply_homography, image_corners
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, backend_class, create_backend

METHODS = ("homography", "essential")


class OdometryError(OrthonavError):
    """Two frames give no trustworthy motion: too little overlap, too few inliers, degenerate."""


@dataclass(frozen=True)
class Motion:
    """The current camera's displacement and heading change relative to the previous frame.

    ``covariance`` is 3x3 over (right_m, forward_m, dyaw_deg), in m^2, m deg and deg^2: the
    inliers' residual spread propagated through a rigid ground-plane fit, plus the altitude's
    scale uncertainty along the displacement.
    """

    right_m: float
    forward_m: float
    dyaw_deg: float
    covariance: np.ndarray
    inliers: int
    inlier_ratio: float
    climb_m: float = 0.0  # height gained (m), from the same decomposition
    overlap: float = 1.0  # fraction of the current frame seen in the previous one
    rmse_px: float = 0.0  # inliers' transfer error at the working resolution
    method: str = "homography"
    degenerate: bool = False  # True when the essential model had no parallax (see module doc)
    matches: int = 0

    @property
    def distance_m(self) -> float:
        return math.hypot(self.right_m, self.forward_m)

    def to_dict(self) -> dict:
        return {
            "right_m": self.right_m,
            "forward_m": self.forward_m,
            "dyaw_deg": self.dyaw_deg,
            "climb_m": self.climb_m,
            "covariance": np.asarray(self.covariance).tolist(),
            "inliers": self.inliers,
            "inlier_ratio": self.inlier_ratio,
            "matches": self.matches,
            "overlap": self.overlap,
            "rmse_px": self.rmse_px,
            "method": self.method,
            "degenerate": self.degenerate,
        }


@dataclass(frozen=True)
class MotionConfig:
    """Thresholds of :func:`estimate_motion`; pixel values are at the working resolution."""

    max_side_px: int = 1280  # frames are shrunk to this longest side before extraction
    max_keypoints: int = 3000
    ransac_px: float = 3.0
    min_inliers: int = 20
    min_inlier_ratio: float = 0.15
    min_overlap: float = 0.10
    min_spread: float = 0.02  # inliers' convex hull over the frame area
    min_parallax_px: float = 2.0  # essential model: median parallax below this = no baseline
    alt_sigma_frac: float = 0.03  # 1-sigma of the altitude as a fraction (scale of the motion)
    extra: dict = field(default_factory=dict)  # backend options beyond max_keypoints


@dataclass(frozen=True)
class FramePair:
    """Matched, undistorted keypoints of two frames at the working resolution."""

    camera: Camera  # the camera scaled to the working resolution
    previous_px: np.ndarray  # (M, 2)
    current_px: np.ndarray  # (M, 2)
    previous: FeatureSet
    current: FeatureSet
    pairs: np.ndarray  # (M, 2) indices into previous, current


def estimate_motion(
    previous: np.ndarray,
    current: np.ndarray,
    camera: Camera,
    alt_agl_m: float,
    backend: str | FeatureBackend = "orb",
    method: str = "homography",
    config: MotionConfig | None = None,
) -> Motion:
    """Motion of the camera from ``previous`` to ``current`` (H, W[, 3]) uint8 frames.

    ``alt_agl_m`` is the previous frame's height above the ground plane (it sets the scale);
    ``backend`` a feature backend or its registry name. Raises :class:`OdometryError` naming
    the reason when the frames overlap too little, give too few inliers or degenerate geometry.
    """
    return track(previous, current, camera, alt_agl_m, backend, method, config)[0]


def track(
    previous: np.ndarray,
    current: np.ndarray,
    camera: Camera,
    alt_agl_m: float,
    backend: str | FeatureBackend = "orb",
    method: str = "homography",
    config: MotionConfig | None = None,
) -> tuple[Motion, FramePair, np.ndarray]:
    """:func:`estimate_motion` with its matches and inlier mask (for keyframes and landmarks)."""
    config = config or MotionConfig()
    if method not in METHODS:
        raise OrthonavError(f"odometry method: expected one of {', '.join(METHODS)}, got {method!r}")
    if not (math.isfinite(alt_agl_m) and alt_agl_m > 0):
        raise OdometryError(f"alt_agl_m: expected a positive height above ground in metres, got {alt_agl_m}")
    pair = match_frames(previous, current, camera, _backend(backend, config), config)
    if method == "homography":
        motion, _, inliers = _homography_motion(pair, alt_agl_m, config)
        return motion, pair, inliers
    try:
        homography, rotation, inliers = _homography_motion(pair, alt_agl_m, config)
    except OdometryError:
        homography = None  # no dominant plane (trees, buildings): the essential model's case
    else:
        # Parallax left once the rotation is undone: without it the translation direction is noise.
        if _parallax_px(pair, rotation, inliers) < config.min_parallax_px:
            return replace(homography, degenerate=True), pair, inliers
    return _essential_motion(pair, alt_agl_m, config, homography)


def match_frames(
    previous: np.ndarray, current: np.ndarray, camera: Camera, backend: FeatureBackend, config: MotionConfig
) -> FramePair:
    """Both frames shrunk to the working size, features extracted and matched (ratio test)."""
    prev_gray, cur_gray = _gray(previous, camera, "previous"), _gray(current, camera, "current")
    scale = min(1.0, config.max_side_px / max(camera.width, camera.height))
    work = camera.scaled(scale) if scale < 1.0 else camera
    if scale < 1.0:
        size = (work.width, work.height)
        prev_gray = cv2.resize(prev_gray, size, interpolation=cv2.INTER_AREA)
        cur_gray = cv2.resize(cur_gray, size, interpolation=cv2.INTER_AREA)
    prev_set, cur_set = backend.extract(prev_gray), backend.extract(cur_gray)
    matches = backend.match(prev_set, cur_set)
    if len(matches) < config.min_inliers:
        raise OdometryError(
            f"too few feature matches: {len(matches)} (need {config.min_inliers}; keypoints "
            f"{len(prev_set)} and {len(cur_set)}): the frames overlap too little or show no texture"
        )
    p = work.undistort_points(prev_set.keypoints[matches.pairs[:, 0]])
    q = work.undistort_points(cur_set.keypoints[matches.pairs[:, 1]])
    return FramePair(work, p, q, prev_set, cur_set, matches.pairs)


@lru_cache(maxsize=8)
def _cached_backend(name: str, max_keypoints: int, extra: tuple) -> FeatureBackend:
    defaults = backend_class(name).default_conf
    # Odometry wants every good match, not the localizer's few hundred best.
    sizes = {key: max_keypoints for key in ("max_keypoints", "max_matches") if key in defaults}
    conf = {**sizes, **dict(extra)}
    return create_backend(name, **conf)


def _backend(backend: str | FeatureBackend, config: MotionConfig) -> FeatureBackend:
    if isinstance(backend, FeatureBackend):
        return backend
    return _cached_backend(backend, config.max_keypoints, tuple(sorted(config.extra.items())))


def _gray(image: np.ndarray, camera: Camera, which: str) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise OrthonavError(
            f"{which} frame: expected an (H, W) or (H, W, 3) uint8 image, got {image.shape} {image.dtype}"
        )
    if image.shape[:2] != (camera.height, camera.width):
        raise OrthonavError(
            f"{which} frame: {image.shape[1]}x{image.shape[0]} px does not match the camera's "
            f"{camera.width}x{camera.height}"
        )
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def _homography_motion(
    pair: FramePair, alt_agl_m: float, config: MotionConfig
) -> tuple[Motion, np.ndarray, np.ndarray]:
    """The plane-induced motion, its rotation and the inlier mask."""
    h, mask = cv2.findHomography(pair.previous_px, pair.current_px, cv2.USAC_MAGSAC, config.ransac_px)
    inliers = mask.ravel().astype(bool) if mask is not None else np.zeros(len(pair.previous_px), bool)
    _check_inliers(int(inliers.sum()), len(inliers), config)
    if h is None or np.linalg.det(h[:2, :2]) <= 0:
        raise OdometryError("degenerate geometry: the homography between the frames mirrors or collapses")
    _check_spread(pair.previous_px[inliers], pair.camera, config)
    overlap = _overlap(h, pair.camera)
    if overlap < config.min_overlap:
        raise OdometryError(
            f"too little overlap: {overlap:.0%} of the current frame is in the previous one "
            f"(need {config.min_overlap:.0%})"
        )
    rotation, t_over_d = _decompose(h, pair.camera)
    centre = -rotation.T @ t_over_d * alt_agl_m  # current camera centre in the previous camera frame
    residual = pair.current_px[inliers] - apply_homography(h, pair.previous_px[inliers])
    rmse_px = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    motion = _motion(pair, inliers, rotation, centre, alt_agl_m, rmse_px, overlap, "homography", config)
    return motion, rotation, inliers


def _parallax_px(pair: FramePair, rotation: np.ndarray, inliers: np.ndarray) -> float:
    """Median image motion of the inliers once the camera rotation is undone (the baseline's)."""
    k = pair.camera.K
    p, q = pair.previous_px[inliers], pair.current_px[inliers]
    rotated = apply_homography(k @ rotation @ np.linalg.inv(k), p)
    return float(np.median(np.linalg.norm(q - rotated, axis=1)))


def _decompose(h: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(R, t/d) of ``H = K (R + t n^T / d) K^-1`` whose plane normal is nearest the optical axis."""
    count, rotations, translations, normals = cv2.decomposeHomographyMat(h, camera.K)
    best = max(range(count), key=lambda i: float(normals[i][2, 0]))
    return np.asarray(rotations[best]), np.asarray(translations[best]).ravel()


def _essential_motion(
    pair: FramePair, alt_agl_m: float, config: MotionConfig, fallback: Motion | None
) -> tuple[Motion, FramePair, np.ndarray]:
    k = pair.camera.K
    e, mask = cv2.findEssentialMat(
        pair.previous_px, pair.current_px, k, cv2.USAC_MAGSAC, 0.999, config.ransac_px
    )
    if e is None or e.shape[0] % 3 or e.shape[1] != 3:
        raise OdometryError("degenerate geometry: no essential matrix fits the matches")
    e = e[:3]  # the first of several solutions
    inliers = mask.ravel().astype(bool)
    _check_inliers(int(inliers.sum()), len(inliers), config)
    p, q = pair.previous_px[inliers], pair.current_px[inliers]
    _, rotation, t, pose_mask, points = cv2.recoverPose(e, p, q, k, distanceThresh=1e4)
    if _parallax_px(pair, rotation, inliers) < config.min_parallax_px:
        if fallback is None:
            raise OdometryError(
                "degenerate geometry: no baseline (hovering or pure rotation) and no ground plane"
            )
        return replace(fallback, degenerate=True), pair, inliers  # a planar scene read as a rotation
    good = pose_mask.ravel() > 0
    xyz = points[:3, good] / points[3, good]
    depth = xyz[2][np.isfinite(xyz[2]) & (xyz[2] > 0)]
    if len(depth) < config.min_inliers:
        raise OdometryError(
            f"degenerate geometry: only {len(depth)} inliers triangulate in front of both cameras"
        )
    # Unit baseline: depths are in baselines; the ground (median depth) is alt_agl_m away.
    centre = -rotation.T @ t.ravel() * (alt_agl_m / float(np.median(depth)))
    epipolar = _sampson_px(e, p, q, k)
    full = np.zeros(len(pair.previous_px), bool)
    full[np.flatnonzero(inliers)] = True
    overlap = fallback.overlap if fallback is not None else math.nan
    motion = _motion(pair, full, rotation, centre, alt_agl_m, epipolar, overlap, "essential", config)
    return motion, pair, full


def _sampson_px(e: np.ndarray, p: np.ndarray, q: np.ndarray, k: np.ndarray) -> float:
    """RMS Sampson distance of the inliers, in pixels."""
    f = np.linalg.inv(k).T @ e @ np.linalg.inv(k)
    ph, qh = np.column_stack([p, np.ones(len(p))]), np.column_stack([q, np.ones(len(q))])
    fp, ftq = ph @ f.T, qh @ f
    num = np.sum(qh * fp, axis=1) ** 2
    den = fp[:, 0] ** 2 + fp[:, 1] ** 2 + ftq[:, 0] ** 2 + ftq[:, 1] ** 2
    return float(np.sqrt(np.mean(num / np.maximum(den, 1e-12))))


def _motion(
    pair: FramePair,
    inliers: np.ndarray,
    rotation: np.ndarray,
    centre: np.ndarray,
    alt_agl_m: float,
    rmse_px: float,
    overlap: float,
    method: str,
    config: MotionConfig,
) -> Motion:
    # Camera 2's image-up axis (-y) in camera 1's axes, as a clockwise angle from camera 1's up.
    up = -rotation[1, :]
    dyaw_deg = math.degrees(math.atan2(up[0], -up[1]))
    right_m, forward_m = float(centre[0]), float(-centre[1])
    covariance = _covariance(pair, inliers, alt_agl_m, rmse_px, (right_m, forward_m), config)
    n_in = int(inliers.sum())
    return Motion(
        right_m,
        forward_m,
        dyaw_deg,
        covariance,
        n_in,
        n_in / len(inliers),
        climb_m=float(-centre[2]),
        overlap=overlap,
        rmse_px=rmse_px,
        method=method,
        matches=len(inliers),
    )


def _covariance(
    pair: FramePair,
    inliers: np.ndarray,
    alt_agl_m: float,
    rmse_px: float,
    displacement_m: tuple[float, float],
    config: MotionConfig,
) -> np.ndarray:
    """Rigid ground-plane fit (tx, ty, yaw) to the inliers with their residual spread, in metres."""
    cam = pair.camera
    gsd_m = alt_agl_m / math.sqrt(cam.fx * cam.fy)
    ground = (pair.previous_px[inliers] - [cam.cx, cam.cy]) * gsd_m
    n = len(ground)
    jac = np.zeros((2 * n, 3))
    jac[0::2, 0], jac[1::2, 1] = 1.0, 1.0
    jac[0::2, 2], jac[1::2, 2] = -ground[:, 1], ground[:, 0]
    sigma_m = max(rmse_px, 0.5) * gsd_m / math.sqrt(2.0)  # per axis, floored at half a pixel
    cov = sigma_m**2 * np.linalg.inv(jac.T @ jac)
    to_deg = np.diag([1.0, 1.0, math.degrees(1.0)])
    cov = to_deg @ cov @ to_deg
    d = np.asarray(displacement_m)
    cov[:2, :2] += np.outer(d, d) * config.alt_sigma_frac**2
    return cov


def _check_inliers(n_inliers: int, n_matches: int, config: MotionConfig) -> None:
    ratio = n_inliers / max(n_matches, 1)
    if n_inliers < config.min_inliers or ratio < config.min_inlier_ratio:
        raise OdometryError(
            f"too few inliers: {n_inliers} of {n_matches} matches ({ratio:.0%}; need "
            f"{config.min_inliers} and {config.min_inlier_ratio:.0%}): too little overlap or a changed scene"
        )


def _check_spread(points_px: np.ndarray, camera: Camera, config: MotionConfig) -> None:
    hull = cv2.convexHull(points_px.astype(np.float32))
    spread = float(cv2.contourArea(hull)) / (camera.width * camera.height)
    if spread < config.min_spread:
        raise OdometryError(
            f"degenerate geometry: the inliers cover {spread:.1%} of the frame "
            f"(need {config.min_spread:.0%}); they are bunched or on a line"
        )


def _overlap(h: np.ndarray, camera: Camera) -> float:
    """Fraction of the current frame whose ground the previous frame also saw."""
    corners = image_corners(camera).astype(np.float32)
    back = apply_homography(np.linalg.inv(h), corners).astype(np.float32)
    if cv2.contourArea(back) <= 0 or not cv2.isContourConvex(back):
        return 0.0
    area, _ = cv2.intersectConvexConvex(corners, back)
    return float(area) / float(cv2.contourArea(back))

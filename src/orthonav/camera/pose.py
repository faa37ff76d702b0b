"""Camera attitude, ground footprint and the ground-plane homography, both directions.

Frames and conventions
- World: local ENU metres (x east, y north, z up); the ground is the plane z = 0.
- Body: forward-right-down; yaw (heading) clockwise from north, pitch nose-up positive,
  roll right-wing-down positive (aerospace Z-Y-X order).
- Camera: OpenCV (x right, y down, z along the optical axis), mounted looking straight
  down with the image top towards the nose, so at zero roll/pitch the image top points
  along the heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from orthonav.camera.model import Camera
from orthonav.errors import OrthonavError

# Columns: the camera's x (right), y (image down), z (optical axis) axes in the body frame.
BODY_FROM_CAMERA = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
# NED -> ENU axis swap.
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class CameraPose:
    """Where the camera is in a local ENU frame and how it is turned."""

    east_m: float
    north_m: float
    alt_agl_m: float
    yaw_deg: float
    pitch_deg: float = 0.0
    roll_deg: float = 0.0

    @property
    def tilt_deg(self) -> float:
        """Angle between the optical axis and the vertical."""
        r = rotation_enu_from_camera(self.yaw_deg, self.pitch_deg, self.roll_deg)
        return math.degrees(math.acos(np.clip(-r[2, 2], -1.0, 1.0)))


def ned_from_body(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rotation of a body (FRD) with Z-Y-X Euler angles in radians into NED."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def rotation_enu_from_camera(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """3x3 rotation taking camera-frame vectors to ENU."""
    rb = ned_from_body(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
    return ENU_FROM_NED @ rb @ BODY_FROM_CAMERA


def ground_to_image_homography(camera: Camera, pose: CameraPose) -> np.ndarray:
    """3x3 H with [u, v, 1] ~ H [east_m, north_m, 1] for ground points (ideal pinhole pixels)."""
    r_cw = rotation_enu_from_camera(pose.yaw_deg, pose.pitch_deg, pose.roll_deg).T
    centre = np.array([pose.east_m, pose.north_m, pose.alt_agl_m])
    t = -r_cw @ centre
    h = camera.K @ np.column_stack([r_cw[:, 0], r_cw[:, 1], t])
    return h / h[2, 2]


def apply_homography(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (N, 2) points."""
    pts = np.asarray(pts, float).reshape(-1, 2)
    homog = np.column_stack([pts, np.ones(len(pts))]) @ h.T
    return homog[:, :2] / homog[:, 2:3]


def pixel_to_ground(camera: Camera, pose: CameraPose, pts_px: np.ndarray) -> np.ndarray:
    """(N, 2) ideal pinhole pixels -> (N, 2) ground ENU points seen there from ``pose``."""
    return apply_homography(np.linalg.inv(ground_to_image_homography(camera, pose)), pts_px)


def image_corners(camera: Camera) -> np.ndarray:
    """(4, 2) image corners: top-left, top-right, bottom-right, bottom-left."""
    w, h = camera.width, camera.height
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], float)


def footprint_enu(camera: Camera, pose: CameraPose) -> np.ndarray:
    """(4, 2) ground ENU corners seen by the image corners (TL, TR, BR, BL).

    Raises when a corner ray does not hit the ground (the horizon is in view).
    """
    r = rotation_enu_from_camera(pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    corners = image_corners(camera)
    rays_cam = np.column_stack(
        [(corners[:, 0] - camera.cx) / camera.fx, (corners[:, 1] - camera.cy) / camera.fy, np.ones(4)]
    )
    rays = rays_cam @ r.T
    if np.any(rays[:, 2] >= -1e-6):
        raise OrthonavError(
            f"camera attitude pitch {pose.pitch_deg:.1f}, roll {pose.roll_deg:.1f} deg puts the "
            "horizon in view: no ground footprint"
        )
    scale = -pose.alt_agl_m / rays[:, 2]
    return np.column_stack([pose.east_m + rays[:, 0] * scale, pose.north_m + rays[:, 1] * scale])


def pose_from_homography(camera: Camera, h_img_to_ground: np.ndarray) -> CameraPose:
    """Recover the full camera pose from an image -> ground-plane (ENU metres) homography.

    The ground -> image homography is K [r1 r2 t] up to scale (Zhang's planar decomposition);
    r3 = r1 x r2 and the nearest rotation comes from an SVD.
    """
    h = np.linalg.inv(h_img_to_ground)
    m = np.linalg.inv(camera.K) @ h
    scale = 2.0 / (np.linalg.norm(m[:, 0]) + np.linalg.norm(m[:, 1]))
    for sign in (1.0, -1.0):
        r1, r2, t = sign * scale * m[:, 0], sign * scale * m[:, 1], sign * scale * m[:, 2]
        u, _, vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
        r_cw = u @ vt
        if np.linalg.det(r_cw) < 0:
            continue
        centre = -r_cw.T @ t
        if centre[2] > 0:
            return _pose_from_rotation(r_cw.T, centre)
    raise OrthonavError("homography does not correspond to a camera above the ground plane")


def planar_pose_candidates(camera: Camera, frame_px: np.ndarray, ground_en: np.ndarray) -> list[CameraPose]:
    """Both poses a plane seen through a lens admits (OpenCV's IPPE), camera above the ground.

    A nearly flat scene seen through a narrow lens fits two poses about equally well: the frame
    centre in place, the camera tilted to either side of it. A refinement finds whichever its
    start is nearer to; seeding it from both makes the rival found on every machine, not by how
    the rounding of one CPU tips a single start.
    """
    ground = np.column_stack([np.asarray(ground_en, float)[:, :2], np.zeros(len(ground_en))])
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            ground, np.asarray(frame_px, float), camera.K, None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error:
        return []  # degenerate points (collinear, too few): no candidates, the other starts remain
    poses = []
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        r_cam_from_enu = cv2.Rodrigues(rvec)[0]
        centre = -r_cam_from_enu.T @ np.ravel(tvec)
        if centre[2] > 0:
            poses.append(_pose_from_rotation(r_cam_from_enu.T, centre))
    return poses


def _pose_from_rotation(r_enu_from_cam: np.ndarray, centre: np.ndarray) -> CameraPose:
    rb = ENU_FROM_NED.T @ r_enu_from_cam @ BODY_FROM_CAMERA.T
    pitch = math.asin(float(np.clip(-rb[2, 0], -1.0, 1.0)))
    roll = math.atan2(rb[2, 1], rb[2, 2])
    yaw = math.atan2(rb[1, 0], rb[0, 0])
    return CameraPose(
        east_m=float(centre[0]),
        north_m=float(centre[1]),
        alt_agl_m=float(centre[2]),
        yaw_deg=math.degrees(yaw) % 360.0,
        pitch_deg=math.degrees(pitch),
        roll_deg=math.degrees(roll),
    )


def project_ground(camera: Camera, pose: CameraPose, ground_en: np.ndarray) -> np.ndarray:
    """(N, 2) ground ENU points -> (N, 2) ideal pinhole pixels."""
    return apply_homography(ground_to_image_homography(camera, pose), ground_en)


def project_points(camera: Camera, pose: CameraPose, points: np.ndarray) -> np.ndarray:
    """(N, 3) ENU points (or (N, 2) on the plane z = 0) -> (N, 2) ideal pinhole pixels.

    ``pose.alt_agl_m`` is then the camera's height in the points' vertical datum.
    """
    pts = np.asarray(points, float)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    r_cw = rotation_enu_from_camera(pose.yaw_deg, pose.pitch_deg, pose.roll_deg).T
    cam = (pts - np.array([pose.east_m, pose.north_m, pose.alt_agl_m])) @ r_cw.T
    z = cam[:, 2]
    return np.column_stack([camera.fx * cam[:, 0] / z + camera.cx, camera.fy * cam[:, 1] / z + camera.cy])


def _project_many(camera: Camera, poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 6) poses (east, north, height, yaw, pitch, roll) and (N, 3) points -> (K, N, 2) ideal
    pixels: :func:`project_points` for many poses in one pass, as a refinement's finite
    differences need (one call per pose costs more in its overhead than in its arithmetic)."""
    body = Rotation.from_euler("ZYX", poses[:, 3:6], degrees=True).as_matrix()
    r_wc = ENU_FROM_NED @ body @ BODY_FROM_CAMERA  # (K, 3, 3): camera -> ENU
    # One product of the points with every rotation, less each camera centre's (rotated).
    turned = (points @ r_wc.transpose(1, 0, 2).reshape(3, -1)).reshape(len(points), -1, 3)
    cam = turned.transpose(1, 0, 2) - (poses[:, None, :3] @ r_wc)
    return np.array([camera.fx, camera.fy]) * cam[..., :2] / cam[..., 2:] + np.array([camera.cx, camera.cy])


@dataclass(frozen=True)
class AttitudePrior:
    """Pitch and roll from the autopilot with their 1-sigma (deg): a soft prior of the refinement."""

    pitch_deg: float
    roll_deg: float
    sigma_deg: float


_POSE_FIELDS = ("east_m", "north_m", "alt_agl_m", "yaw_deg", "pitch_deg", "roll_deg")
# Finite-difference steps of the Jacobian (m, m, m, deg, deg, deg).
_POSE_STEPS = np.array([1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5])
# Pixel residuals beyond this many sigmas count less (soft L1): relief off the model, moving objects.
ROBUST_SCALE = 2.0


def refine_pose(
    camera: Camera,
    frame_px: np.ndarray,
    ground: np.ndarray,
    initial: CameraPose,
    fix_attitude: bool = False,
    attitude_prior: AttitudePrior | None = None,
    robust: bool = False,
    effective_points: int | None = None,
    iterations: int = 20,
) -> tuple[CameraPose, np.ndarray, float]:
    """Levenberg-Marquardt pose from pixel <-> ground correspondences, ground as (N, 2) on a
    plane or (N, 3) on terrain.

    Solves east, north, height and yaw, and pitch and roll unless ``fix_attitude`` (kept at
    ``initial``'s). An ``attitude_prior`` adds pitch and roll residuals weighted by its sigma
    against the pixels' own noise (estimated from the residuals as it goes), so the image and
    the autopilot share the attitude by their precision. ``robust`` re-weights points beyond
    ``ROBUST_SCALE`` sigmas (soft L1). ``effective_points``: real pixel errors are correlated
    (lens, map seams, relief off the model), so N points carry the information of at most this
    many independent ones; their weight, and so the covariance and the share of a prior, follow
    from that. Returns the pose, the parameter covariance (m and deg, in
    the order east, north, height, yaw[, pitch, roll]) and the residual RMS per point in pixels.
    """
    names = list(_POSE_FIELDS[:4] if fix_attitude else _POSE_FIELDS)
    base = {k: getattr(initial, k) for k in _POSE_FIELDS}
    fixed = np.array([base[k] for k in _POSE_FIELDS], float)
    frame_px = np.asarray(frame_px, float)
    points = np.asarray(ground, float)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    prior = None if fix_attitude else attitude_prior
    steps = _POSE_STEPS[: len(names)]
    # Correlated errors: the points count as at most ``effective_points`` independent ones.
    dilution = math.sqrt(max(1.0, len(frame_px) / effective_points)) if effective_points else 1.0

    def pose_of(p: np.ndarray) -> CameraPose:
        return CameraPose(**{**base, **dict(zip(names, p, strict=True))})

    def residuals_many(ps: np.ndarray) -> np.ndarray:
        """(K, params) -> (K, 2N) pixel residuals, each row one parameter vector's."""
        poses = np.repeat(fixed[None, :], len(ps), axis=0)
        poses[:, : len(names)] = ps
        return (_project_many(camera, poses, points) - frame_px).reshape(len(ps), -1)

    def pixel_residuals(p: np.ndarray) -> np.ndarray:
        return residuals_many(p[None, :])[0]

    def weights(r_px: np.ndarray, sigma_px: float) -> np.ndarray:
        """Whitening of the pixel rows, down-weighting outliers when robust."""
        w = _soft_l1_weights(r_px / sigma_px) if robust else np.ones(len(r_px))
        return w / (sigma_px * dilution)

    def prior_rows(p: np.ndarray) -> np.ndarray:
        if prior is None:
            return np.zeros(0)
        return (p[4:6] - [prior.pitch_deg, prior.roll_deg]) / prior.sigma_deg

    def whitened(p: np.ndarray, r_px: np.ndarray, sigma_px: float) -> np.ndarray:
        """Whitened residuals of ``p`` (its pixel residuals ``r_px``): pixel rows, then the
        attitude prior's."""
        return np.concatenate([r_px * weights(r_px, sigma_px), prior_rows(p)])

    def system(p: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals and their Jacobian (finite differences of the pixel rows)."""
        stepped = residuals_many(np.vstack([p, p + np.diag(steps)]))
        r = stepped[0]
        jac = ((stepped[1:] - r) / steps[:, None]).T
        w = weights(r, sigma_px)
        prior_jac = (
            np.eye(len(names))[4:6] / prior.sigma_deg if prior is not None else np.zeros((0, len(names)))
        )
        return np.concatenate([r * w, prior_rows(p)]), np.vstack([jac * w[:, None], prior_jac])

    params = np.array([base[k] for k in names], float)
    dof = max(1, frame_px.size - len(names))
    sigma_px = _noise(pixel_residuals(params), dof)
    damping = 1e-3
    for _ in range(iterations):
        r, jac = system(params, sigma_px)
        normal, grad = jac.T @ jac, jac.T @ r
        delta = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), -grad)
        candidate = params + delta
        r_px = pixel_residuals(candidate)
        r_new = whitened(candidate, r_px, sigma_px)
        if r_new @ r_new <= r @ r:
            params, damping = candidate, damping * 0.3
            sigma_px = _noise(r_px, dof)
        else:
            damping *= 10.0
        if np.all(np.abs(delta) < steps):
            break
    _, jac = system(params, sigma_px)
    cov = np.linalg.pinv(jac.T @ jac)
    r_px = pixel_residuals(params)
    return pose_of(params), 0.5 * (cov + cov.T), float(np.sqrt(r_px @ r_px / len(frame_px)))


def _noise(residuals_px: np.ndarray, dof: int) -> float:
    """Per-coordinate pixel noise estimated from the residuals (never zero)."""
    return max(float(np.sqrt(residuals_px @ residuals_px / dof)), 1e-6)


def _soft_l1_weights(z: np.ndarray) -> np.ndarray:
    """Square roots of the soft-L1 IRLS weights: 1 near zero, ~sqrt(c/|z|) far out."""
    c = ROBUST_SCALE
    return (1.0 + (z / c) ** 2) ** -0.25

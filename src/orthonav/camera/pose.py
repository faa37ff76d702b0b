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

import numpy as np

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


def refine_pose(
    camera: Camera,
    frame_px: np.ndarray,
    ground_en: np.ndarray,
    initial: CameraPose,
    fix_attitude: bool = False,
    iterations: int = 10,
) -> tuple[CameraPose, np.ndarray, float]:
    """Gauss-Newton refinement of a pose from pixel <-> ground correspondences.

    Minimises reprojection error in pixels over (east, north, alt, yaw) and, unless
    ``fix_attitude`` (roll/pitch known from the autopilot's AHRS), pitch and roll too.
    Returns the pose, the parameter covariance sigma^2 (J^T J)^-1 (metres and degrees, in
    the order east, north, alt, yaw[, pitch, roll]) and the residual RMS in pixels.
    """
    names = ["east_m", "north_m", "alt_agl_m", "yaw_deg"] + (
        [] if fix_attitude else ["pitch_deg", "roll_deg"]
    )
    base = {
        k: getattr(initial, k) for k in ("east_m", "north_m", "alt_agl_m", "yaw_deg", "pitch_deg", "roll_deg")
    }
    params = np.array([base[k] for k in names], float)
    steps = np.array([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4][: len(names)])

    def residuals(p: np.ndarray) -> np.ndarray:
        pose = CameraPose(**{**base, **dict(zip(names, p, strict=True))})
        return (project_ground(camera, pose, ground_en) - frame_px).ravel()

    def jacobian(p: np.ndarray, r0: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [(residuals(p + e) - r0) / s for e, s in zip(np.diag(steps), steps, strict=True)]
        )

    r = residuals(params)
    for _ in range(iterations):
        jac = jacobian(params, r)
        delta, *_ = np.linalg.lstsq(jac, -r, rcond=None)
        candidate = params + delta
        r_new = residuals(candidate)
        if r_new @ r_new <= r @ r:
            params, r = candidate, r_new
        if np.all(np.abs(delta) < steps):
            break
    jac = jacobian(params, r)
    dof = max(1, len(r) - len(names))
    cov = (r @ r / dof) * np.linalg.pinv(jac.T @ jac)
    pose = CameraPose(**{**base, **dict(zip(names, params, strict=True))})
    return pose, cov, float(np.sqrt(r @ r / (len(r) / 2)))

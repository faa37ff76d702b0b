"""A rig of D cameras fixed to one vehicle: intrinsics plus known extrinsics, validated.

Frames (the camera package's conventions): body forward-right-down (FRD); camera OpenCV
(x right, y down, z along the optical axis). A camera's *mount* is the rotation from the
camera to the body, given either as angles or as a matrix:

- ``yaw_deg, pitch_deg, roll_deg``: the body attitude that would point a nadir camera the
  same way (pitch +25 looks 25 deg forward, roll +25 looks 25 deg to the left, yaw turns the
  image about the optical axis);
- ``rotation``: the 3x3 matrix body_R_camera (columns: the camera's x, y, z axes in FRD),
  checked to be a proper rotation.

``lever_arm_m`` is the camera centre in the body frame (forward, right, down metres).

Rig JSON: ``{"cameras": [{"name": "nadir", "width": 640, "height": 480, "hfov_deg": 60,
"pitch_deg": 0}, {"name": "forward", ..., "pitch_deg": 25}]}`` (camera fields as in the
camera JSON).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from orthonav.camera import BODY_FROM_CAMERA, ENU_FROM_NED, Camera, CameraPose, footprint_enu, ned_from_body
from orthonav.errors import OrthonavError, read_json_file

ORTHONORMAL_TOLERANCE = 1e-6
MAX_LEVER_ARM_M = 20.0


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig: its name, intrinsics and body_R_camera / lever arm (FRD, metres)."""

    name: str
    camera: Camera
    body_r_camera: np.ndarray
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_angles(
        cls,
        name: str,
        camera: Camera,
        yaw_deg: float = 0.0,
        pitch_deg: float = 0.0,
        roll_deg: float = 0.0,
        lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> RigCamera:
        mount = ned_from_body(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
        return cls(name, camera, mount @ BODY_FROM_CAMERA, tuple(float(v) for v in lever_arm_m))

    @property
    def tilt_deg(self) -> float:
        """Angle between the optical axis and the body's down axis."""
        return math.degrees(math.acos(float(np.clip(self.body_r_camera[2, 2], -1.0, 1.0))))

    def camera_attitude_deg(
        self, yaw_deg: float, pitch_deg: float, roll_deg: float
    ) -> tuple[float, float, float]:
        """(yaw, pitch, roll) that :func:`orthonav.camera.rotation_enu_from_camera` takes to turn
        this camera as it sits on a body with the given attitude (what ``render_frame`` needs)."""
        body = ned_from_body(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
        r = body @ self.body_r_camera @ BODY_FROM_CAMERA.T
        pitch = math.asin(float(np.clip(-r[2, 0], -1.0, 1.0)))
        return (
            math.degrees(math.atan2(r[1, 0], r[0, 0])) % 360.0,
            math.degrees(pitch),
            math.degrees(math.atan2(r[2, 1], r[2, 2])),
        )

    def camera_pose(
        self,
        east_m: float,
        north_m: float,
        alt_m: float,
        yaw_deg: float,
        pitch_deg: float = 0.0,
        roll_deg: float = 0.0,
    ) -> CameraPose:
        """This camera's ENU pose on a body at (east, north, alt) with the given attitude."""
        r_enu_body = enu_r_body(yaw_deg, pitch_deg, roll_deg)
        offset = r_enu_body @ np.asarray(self.lever_arm_m)
        yaw, pitch, roll = self.camera_attitude_deg(yaw_deg, pitch_deg, roll_deg)
        return CameraPose(east_m + offset[0], north_m + offset[1], alt_m + offset[2], yaw, pitch, roll)


def enu_r_body(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """3x3 rotation taking body (FRD) vectors to ENU: the rotation of a vehicle's pose."""
    return ENU_FROM_NED @ ned_from_body(
        math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg)
    )


@dataclass(frozen=True)
class Rig:
    """D cameras on one vehicle, checked on construction (see :func:`validate_rig`)."""

    cameras: tuple[RigCamera, ...]
    ground: bool = field(default=True)

    def __post_init__(self) -> None:
        validate_rig(self.cameras, self.ground)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def subset(self, names: list[str]) -> Rig:
        """The rig with only the named cameras, in that order."""
        by_name = {c.name: c for c in self.cameras}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise OrthonavError(f"rig: no camera named {missing}; the rig has {self.names}")
        return Rig(tuple(by_name[n] for n in names), self.ground)

    @classmethod
    def from_dict(cls, data: dict, source: str = "rig") -> Rig:
        entries = data.get("cameras") if isinstance(data, dict) else None
        if not isinstance(entries, list) or not entries:
            raise OrthonavError(f"{source}: expected {{'cameras': [ ... ]}} with at least one camera")
        return cls(tuple(_camera_from_dict(e, f"{source} cameras[{i}]") for i, e in enumerate(entries)))

    @classmethod
    def from_json(cls, path: str | Path) -> Rig:
        return cls.from_dict(read_json_file(Path(path), "rig file"), str(path))


def _camera_from_dict(entry: object, source: str) -> RigCamera:
    if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) or not entry["name"]:
        raise OrthonavError(f"{source}: expected an object with a non-empty 'name' and camera fields")
    camera = Camera.from_dict(entry, source)
    lever = entry.get("lever_arm_m", (0.0, 0.0, 0.0))
    try:
        lever = tuple(float(v) for v in lever)
    except (TypeError, ValueError):
        raise OrthonavError(f"{source} lever_arm_m: expected 3 numbers (forward, right, down m)") from None
    if "rotation" in entry:
        try:
            rotation = np.array(entry["rotation"], dtype=float)
        except (TypeError, ValueError):
            raise OrthonavError(f"{source} rotation: expected a 3x3 matrix of numbers") from None
        return RigCamera(entry["name"], camera, rotation, lever)
    try:
        angles = {k: float(entry.get(k, 0.0)) for k in ("yaw_deg", "pitch_deg", "roll_deg")}
    except (TypeError, ValueError):
        raise OrthonavError(f"{source}: yaw_deg, pitch_deg, roll_deg must be numbers") from None
    return RigCamera.from_angles(entry["name"], camera, lever_arm_m=lever, **angles)


def validate_rig(cameras: tuple[RigCamera, ...], ground: bool = True) -> None:
    """Refuse a rig whose extrinsics cannot be right, naming the camera and the fault.

    Checks: at least one camera; unique names; body_R_camera a finite 3x3 proper rotation
    (orthonormal, determinant +1, not a reflection); a finite lever arm under 20 m; and for a
    ground-mapping rig (``ground``) every camera's whole field of view below the horizon in
    level flight, or it would put sky into the map.
    """
    if not cameras:
        raise OrthonavError("rig: expected at least one camera")
    names = [c.name for c in cameras]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise OrthonavError(f"rig: duplicate camera name(s) {duplicates}; each camera needs its own name")
    for cam in cameras:
        _check_rotation(cam)
        lever = np.asarray(cam.lever_arm_m, float)
        if lever.shape != (3,) or not np.all(np.isfinite(lever)) or np.linalg.norm(lever) > MAX_LEVER_ARM_M:
            raise OrthonavError(
                f"rig camera {cam.name!r} lever_arm_m: expected 3 finite numbers within "
                f"{MAX_LEVER_ARM_M:g} m of the body origin, got {cam.lever_arm_m}"
            )
        if ground:
            _check_below_horizon(cam)


def _check_rotation(cam: RigCamera) -> None:
    r = np.asarray(cam.body_r_camera, float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise OrthonavError(
            f"rig camera {cam.name!r} rotation: expected a finite 3x3 matrix, got shape {r.shape}"
        )
    error = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if error > ORTHONORMAL_TOLERANCE:
        raise OrthonavError(
            f"rig camera {cam.name!r} rotation: not orthonormal (max |R^T R - I| = {error:.2g}); "
            "expected body_R_camera, a rotation matrix"
        )
    if np.linalg.det(r) < 0:
        raise OrthonavError(
            f"rig camera {cam.name!r} rotation: determinant -1 is a reflection, not a rotation "
            "(a swapped or negated axis?)"
        )


def _check_below_horizon(cam: RigCamera) -> None:
    yaw, pitch, roll = cam.camera_attitude_deg(0.0, 0.0, 0.0)
    try:
        footprint_enu(cam.camera, CameraPose(0.0, 0.0, 100.0, yaw, pitch, roll))
    except OrthonavError:
        raise OrthonavError(
            f"rig camera {cam.name!r}: part of its field of view is above the horizon in level flight "
            f"(tilt {cam.tilt_deg:.1f} deg from nadir, vertical FOV {cam.camera.vfov_deg:.1f} deg); "
            "a ground-mapping rig needs every camera to see only ground"
        ) from None

"""Pinhole camera intrinsics with optional Brown-Conrady distortion, and its JSON format.

Camera JSON: ``{"width": 640, "height": 480, "hfov_deg": 60}`` or with ``fx, fy, cx, cy``
instead of ``hfov_deg``; optional distortion ``k1, k2, p1, p2, k3`` (OpenCV's model).
Pixel coordinates are x right, y down, origin at the top-left corner of the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from orthonav.errors import OrthonavError, read_json_file

DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
# One distortion term alone may move the image corner by at most twice its distance from the
# centre. A real lens distorts its corners by tens of percent at most (figures in formats.md),
# and the terms of a calibration fit that partly cancel stay well within this; beyond it lies a
# typo, a value in other units, or a failed calibration (1e30 makes every undistorted point NaN).
# Bounding the term, not the coefficient, holds for narrow and wide lenses alike: k3 multiplies
# the sixth power of the corner's normalised radius.
MAX_DISTORTION_TERM = 2.0
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class Camera:
    """Intrinsics of a frame camera (pixels); distortion as OpenCV's (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        # A tuple whatever sequence was given: a camera is a value (hashable, cached per camera).
        object.__setattr__(self, "distortion", tuple(self.distortion))
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or not 8 <= value <= 100_000:
                raise OrthonavError(f"camera {name}: expected an integer 8..100000 px, got {value!r}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise OrthonavError(f"camera {name}: expected a positive focal length in px, got {value}")
        if not (math.isfinite(self.cx) and 0 <= self.cx <= self.width):
            raise OrthonavError(f"camera cx: expected 0..{self.width} px, got {self.cx}")
        if not (math.isfinite(self.cy) and 0 <= self.cy <= self.height):
            raise OrthonavError(f"camera cy: expected 0..{self.height} px, got {self.cy}")
        if len(self.distortion) not in (0, 5) or not all(map(math.isfinite, self.distortion)):
            raise OrthonavError(
                f"camera distortion: expected 5 finite numbers {DISTORTION_KEYS}, got {self.distortion}"
            )
        self._check_distortion_bounds()
        fov = self.hfov_deg
        if not 1.0 <= fov <= 170.0:
            raise OrthonavError(
                f"camera: horizontal field of view {fov:.1f} deg is impossible "
                "for a frame camera (expected 1..170)"
            )

    def _check_distortion_bounds(self) -> None:
        """Each coefficient within :data:`MAX_DISTORTION_TERM` at this camera's image corner."""
        r = math.hypot(
            max(self.cx, self.width - self.cx) / self.fx, max(self.cy, self.height - self.cy) / self.fy
        )
        # How far each term moves the corner, relative to its radius, per unit coefficient: k_n r^2n;
        # a tangential one (2 p1 x y + p2 (r^2 + 2 x^2)) at most 3 p r.
        scales = {"k1": r**2, "k2": r**4, "p1": 3 * r, "p2": 3 * r, "k3": r**6}
        for name, value in zip(DISTORTION_KEYS, self.distortion, strict=False):
            limit = MAX_DISTORTION_TERM / scales[name]
            if abs(value) > limit:
                raise OrthonavError(
                    f"camera {name}: expected |{name}| <= {limit:.3g} for this camera, got {value:g} (a "
                    f"term that alone moves the image corner by over {MAX_DISTORTION_TERM:g} times its "
                    "distance from the centre is no real lens)"
                )

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> Camera:
        """Square pixels, principal point at the image centre."""
        if not (math.isfinite(hfov_deg) and 1.0 <= hfov_deg <= 170.0):
            raise OrthonavError(f"camera hfov_deg: expected 1..170 degrees, got {hfov_deg}")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(int(width), int(height), f, f, width / 2.0, height / 2.0)

    @classmethod
    def from_dict(cls, data: dict, source: str = "camera") -> Camera:
        """Full intrinsics (fx, fy, cx, cy) when given, else square pixels from ``hfov_deg``; both
        given must agree (within 0.5 deg), since one silently winning hides a wrong file."""
        missing = [k for k in ("width", "height") if k not in data]
        if missing or not ("hfov_deg" in data or "fx" in data):
            what = repr(missing[0]) if missing else "'hfov_deg' or 'fx'"
            raise OrthonavError(
                f"{source}: missing field {what}; expected width, height and either "
                "hfov_deg or fx, fy, cx, cy (optional k1, k2, p1, p2, k3)"
            )
        try:
            width, height = _integer(data, "width"), _integer(data, "height")
            dist = tuple(_number(data, k) for k in DISTORTION_KEYS) if "k1" in data else ()
            if "fx" not in data:
                cam = cls.from_hfov(width, height, _number(data, "hfov_deg"))
                return cls(width, height, cam.fx, cam.fy, cam.cx, cam.cy, dist)
            fx, fy, cx, cy = (_number(data, k) for k in ("fx", "fy", "cx", "cy"))
            cam = cls(width, height, fx, fy, cx, cy, dist)
            if "hfov_deg" in data and abs(_number(data, "hfov_deg") - cam.hfov_deg) > 0.5:
                raise OrthonavError(
                    f"hfov_deg {data['hfov_deg']:g} disagrees with fx {fx:g} px at width {width} px "
                    f"({cam.hfov_deg:.2f} deg); give one of them, or both consistent"
                )
        except KeyError as exc:
            raise OrthonavError(
                f"{source}: missing field {exc.args[0]!r}; with fx give fy, cx and cy too"
            ) from None
        except OrthonavError as exc:
            raise OrthonavError(f"{source}: {exc}") from None
        return cam

    @classmethod
    def from_json(cls, path: str | Path) -> Camera:
        path = Path(path)
        data = read_json_file(path, "camera file")
        if not isinstance(data, dict):
            raise OrthonavError(f"{path}: expected a JSON object with width, height, hfov_deg|fx..")
        return cls.from_dict(data, source=str(path))

    def to_dict(self) -> dict:
        out = {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
        }
        out.update(dict(zip(DISTORTION_KEYS, self.distortion, strict=False)))
        return out

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], float)

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2 * math.atan2(self.width / 2.0, self.fx))

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2 * math.atan2(self.height / 2.0, self.fy))

    def nadir_footprint_m(self, alt_agl_m: float) -> tuple[float, float]:
        """Ground width and height (m) seen straight down from ``alt_agl_m``: 2 h tan(fov/2)."""
        return alt_agl_m * self.width / self.fx, alt_agl_m * self.height / self.fy

    def nadir_gsd_m(self, alt_agl_m: float) -> float:
        """Ground size of one pixel at the image centre, looking straight down."""
        return alt_agl_m / math.sqrt(self.fx * self.fy)

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (distortion stays in normalised units)."""
        w, h = max(8, round(self.width * factor)), max(8, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.distortion)

    def undistort_points(self, pts_px: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) ideal pinhole pixels (identity without distortion)."""
        pts = np.asarray(pts_px, np.float64).reshape(-1, 2)
        if not self.distortion or not any(self.distortion):
            return pts
        src, dist = pts.reshape(-1, 1, 2), np.array(self.distortion)
        # Iterate to convergence: OpenCV's default 5 iterations leave ~0.1 px at strong distortion.
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
            out = cv2.undistortPointsIter(src, self.K, dist, np.eye(3), self.K, _UNDISTORT_CRITERIA)
        else:  # OpenCV 5: the criteria are an argument of undistortPoints
            out = cv2.undistortPoints(src, self.K, dist, P=self.K, criteria=_UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)


def _number(data: dict, key: str) -> float:
    """A finite real number (not a bool or a string), or an error naming the field."""
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise OrthonavError(f"{key}: expected a finite number, got {value!r}")
    return float(value)


def _integer(data: dict, key: str) -> int:
    """A whole number of pixels (640 or 640.0, not 640.5), or an error naming the field."""
    value = _number(data, key)
    if not value.is_integer():
        raise OrthonavError(f"{key}: expected a whole number of pixels, got {data[key]!r}")
    return int(value)

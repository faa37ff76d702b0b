"""INS drift model: what a horizontal strapdown INS makes of the true motion.

The simulator needs dead reckoning that drifts the way a real one does once GNSS is gone:
the IMU senses the true acceleration in its own (body) axes, corrupted by turn-on bias,
bias random walk, white noise and scale-factor error; the INS rotates that back with its own,
drifting, gyro-integrated heading and integrates it twice. Horizontal only (2-D): altitude is
passed through, since the visual fixes and the filter are horizontal too.

Body axes are (forward, right); heading is clockwise from true north, so the same matrix
``body_to_nav(psi)`` maps body -> (east, north) and back (it is its own inverse).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.geo import LocalFrame


@dataclass(frozen=True)
class InsSample:
    """One dead-reckoning output, as a flight controller's INS gives it.

    ``velocity_sigma_mps`` is an uncertainty of the velocity beyond the INS's own drift: where
    an implausible velocity was replaced by an older one, what the vehicle may have changed since.
    """

    time_s: float
    lat: float
    lon: float
    vel_east_mps: float
    vel_north_mps: float
    heading_deg: float
    alt_agl_m: float | None = None
    velocity_sigma_mps: float = 0.0


@dataclass(frozen=True)
class ImuErrors:
    """The drawn turn-on errors of one IMU: biases in body axes (forward, right), scales as fractions."""

    accel_bias_body_mps2: tuple[float, float]
    accel_scale: tuple[float, float]
    gyro_bias_dps: float
    gyro_scale: float


@dataclass(frozen=True)
class ImuErrorModel:
    """1-sigma error magnitudes of a horizontal IMU (two accelerometers and a yaw gyro).

    Biases are the residual turn-on bias left when GNSS is lost (after the autopilot's own
    calibration), per axis; walks are bias random walks; noises are white-noise densities
    (velocity / angle random walk); scale factors are per-axis fractional errors in ppm.
    """

    accel_bias_mps2: float = 0.0
    accel_bias_walk_mps2_per_sqrt_s: float = 0.0
    accel_noise_mps_per_sqrt_s: float = 0.0
    accel_scale_factor_ppm: float = 0.0
    gyro_bias_dps: float = 0.0
    gyro_bias_walk_dps_per_sqrt_s: float = 0.0
    gyro_noise_deg_per_sqrt_s: float = 0.0
    gyro_scale_factor_ppm: float = 0.0

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not (math.isfinite(value) and value >= 0.0):
                raise OrthonavError(f"IMU error model {item.name}: expected a number >= 0, got {value}")

    @classmethod
    def preset(cls, name: str) -> ImuErrorModel:
        """A named grade: "perfect", "tactical" or "consumer"."""
        try:
            return IMU_PRESETS[name]
        except KeyError:
            raise OrthonavError(
                f"IMU preset {name!r}: expected one of {', '.join(sorted(IMU_PRESETS))}"
            ) from None

    def draw(self, rng: np.random.Generator) -> ImuErrors:
        """One IMU's turn-on errors (what stays constant, apart from the bias walk, for a flight)."""
        accel_bias = rng.normal(0.0, self.accel_bias_mps2, 2)
        accel_scale = rng.normal(0.0, self.accel_scale_factor_ppm * 1e-6, 2)
        gyro_bias = rng.normal(0.0, self.gyro_bias_dps)
        gyro_scale = rng.normal(0.0, self.gyro_scale_factor_ppm * 1e-6)
        return ImuErrors(
            (float(accel_bias[0]), float(accel_bias[1])),
            (float(accel_scale[0]), float(accel_scale[1])),
            float(gyro_bias),
            float(gyro_scale),
        )


IMU_PRESETS = {
    "perfect": ImuErrorModel(),
    # Navigation-grade-lite ring-laser / high-end MEMS (HG1700 / ADIS1649x class).
    "tactical": ImuErrorModel(
        accel_bias_mps2=0.01,  # ~1 mg
        accel_bias_walk_mps2_per_sqrt_s=5e-5,
        accel_noise_mps_per_sqrt_s=5e-4,  # 0.03 m/s/sqrt(h)
        accel_scale_factor_ppm=300.0,
        gyro_bias_dps=3e-4,  # ~1 deg/h
        gyro_bias_walk_dps_per_sqrt_s=1e-6,
        gyro_noise_deg_per_sqrt_s=2e-3,  # ~0.12 deg/sqrt(h)
        gyro_scale_factor_ppm=150.0,
    ),
    # Autopilot-class MEMS (ICM-2xxxx / BMI088) after at-rest and in-flight calibration.
    "consumer": ImuErrorModel(
        accel_bias_mps2=0.05,  # ~5 mg
        accel_bias_walk_mps2_per_sqrt_s=5e-4,
        accel_noise_mps_per_sqrt_s=3e-3,  # ~300 ug/sqrt(Hz)
        accel_scale_factor_ppm=3000.0,
        gyro_bias_dps=0.05,  # 180 deg/h
        gyro_bias_walk_dps_per_sqrt_s=5e-4,
        gyro_noise_deg_per_sqrt_s=0.01,  # 0.6 deg/sqrt(h)
        gyro_scale_factor_ppm=3000.0,
    ),
}


def body_to_nav(heading_rad: float) -> np.ndarray:
    """(forward, right) -> (east, north) for a heading clockwise from north; also nav -> body."""
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    return np.array([[s, c], [c, -s]])


def wrap_rad(angle: float) -> float:
    """An angle in radians wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def heading_deg(heading_rad: float) -> float:
    """A heading in radians as degrees in [0, 360) (``%`` alone can round -1e-15 up to 360.0)."""
    deg = math.degrees(heading_rad) % 360.0
    return 0.0 if deg >= 360.0 else deg


class InsSimulator:
    """2-D strapdown INS (horizontal accelerometers + yaw gyro) started from the true state.

    ``errors`` holds the drawn turn-on errors, so tests and logs can relate drift to its causes;
    ``sample`` is the latest output (at construction: the true start state).
    """

    def __init__(
        self,
        model: ImuErrorModel,
        rng: np.random.Generator,
        time_s: float,
        lat: float,
        lon: float,
        vel_east_mps: float,
        vel_north_mps: float,
        heading_deg: float,
    ) -> None:
        self.model = model
        self.rng = rng
        self.errors = model.draw(rng)
        self.frame = LocalFrame(lat, lon)
        self.time_s = float(time_s)
        self.pos_m = np.zeros(2)
        self.vel_mps = np.array([vel_east_mps, vel_north_mps], dtype=float)
        self.true_heading_rad = math.radians(heading_deg)
        self.heading_rad = self.true_heading_rad
        self.accel_bias = np.array(self.errors.accel_bias_body_mps2)
        self.gyro_bias_dps = self.errors.gyro_bias_dps
        self.sample = self._sample(None)

    def step(
        self,
        time_s: float,
        accel_east_mps2: float,
        accel_north_mps2: float,
        yaw_rate_dps: float,
        alt_agl_m: float | None = None,
    ) -> InsSample:
        """Integrate the true nav-frame acceleration and yaw rate, constant over (last time, time_s]."""
        dt = time_s - self.time_s
        if not dt > 0.0:
            raise OrthonavError(f"INS step: time must increase, got {time_s} after {self.time_s}")
        if not all(math.isfinite(v) for v in (accel_east_mps2, accel_north_mps2, yaw_rate_dps)):
            raise OrthonavError("INS step: acceleration and yaw rate must be finite numbers")
        gyro_dps = self._measure_gyro(yaw_rate_dps, dt)
        true_mid = self.true_heading_rad + math.radians(yaw_rate_dps) * dt / 2.0
        ins_mid = self.heading_rad + math.radians(gyro_dps) * dt / 2.0
        accel_body = self._measure_accel(body_to_nav(true_mid) @ [accel_east_mps2, accel_north_mps2], dt)
        accel_nav = body_to_nav(ins_mid) @ accel_body
        self.pos_m += self.vel_mps * dt + 0.5 * accel_nav * dt * dt
        self.vel_mps += accel_nav * dt
        self.true_heading_rad += math.radians(yaw_rate_dps) * dt
        self.heading_rad += math.radians(gyro_dps) * dt
        self.time_s = float(time_s)
        self.sample = self._sample(alt_agl_m)
        return self.sample

    def _measure_accel(self, true_body: np.ndarray, dt: float) -> np.ndarray:
        """Body-axis accelerometer output averaged over dt; advances the bias walk."""
        noise = self.rng.normal(0.0, self.model.accel_noise_mps_per_sqrt_s / math.sqrt(dt), 2)
        measured = (1.0 + np.array(self.errors.accel_scale)) * true_body + self.accel_bias + noise
        self.accel_bias = self.accel_bias + self.rng.normal(
            0.0, self.model.accel_bias_walk_mps2_per_sqrt_s * math.sqrt(dt), 2
        )
        return measured

    def _measure_gyro(self, true_dps: float, dt: float) -> float:
        """Yaw gyro output averaged over dt (deg/s); advances the bias walk."""
        noise = self.rng.normal(0.0, self.model.gyro_noise_deg_per_sqrt_s / math.sqrt(dt))
        measured = (1.0 + self.errors.gyro_scale) * true_dps + self.gyro_bias_dps + noise
        self.gyro_bias_dps += self.rng.normal(0.0, self.model.gyro_bias_walk_dps_per_sqrt_s * math.sqrt(dt))
        return float(measured)

    def _sample(self, alt_agl_m: float | None) -> InsSample:
        lat, lon = self.frame.to_latlon(self.pos_m[0], self.pos_m[1])
        return InsSample(
            time_s=self.time_s,
            lat=float(lat),
            lon=float(lon),
            vel_east_mps=float(self.vel_mps[0]),
            vel_north_mps=float(self.vel_mps[1]),
            heading_deg=heading_deg(self.heading_rad),
            alt_agl_m=alt_agl_m,
        )

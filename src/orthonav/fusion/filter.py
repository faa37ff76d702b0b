"""Navigation filter: INS dead reckoning corrected by visual fixes (error-state Kalman filter).

Why an error-state Kalman filter in numpy rather than a gtsam fixed-lag smoother: the INS is
an external, already-integrated nominal (the autopilot's, or the simulator's) whose errors
evolve almost linearly, so an 11-state ESKF is exact enough, costs microseconds per step and
needs no optional dependency on a companion computer. Late fixes are handled by keeping a short
history and re-propagating from the capture time, which gives the smoother's latency benefit
for the one thing we need it for, while gtsam would add a heavy extra for marginal gain.

Error state (INS minus truth), 11 elements:
``[dp_east, dp_north, dv_east, dv_north, dheading, accel_bias_fwd, accel_bias_right, gyro_bias,
accel_scale_fwd, accel_scale_right, gyro_scale]``. Biases and scale factors are states (not
just noise) because they are constants of one flight: as noise they would make the covariance
grow like t^1.5 instead of the true t^2 during an outage, i.e. dishonestly. The INS output is
never modified (open loop): the estimate is always ``INS nominal - estimated error``. Where an
INS sample says its velocity is uncertain beyond the INS's drift (``velocity_sigma_mps``: a
held velocity), the growth of that variance is added to the velocity error's.

A ground velocity measured from the camera's frames (:mod:`orthonav.fusion.ground_velocity`) is
fused as a measurement of the velocity error, gated the same way: it keeps the velocity, and so the
track between fixes, on the ground's motion instead of the autopilot's own estimate.

While trusted, fixes far from the prediction are gated out as outliers. But when several in a
row are, and they agree with each other once the INS motion between them is removed, it is the
prediction that is wrong (a fault upstream of the filter that got through): the filter resets
on them, its velocity error estimate too, and says so.
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from orthonav.errors import OrthonavError, require_positive
from orthonav.fusion.ins import ImuErrorModel, InsSample, body_to_nav, heading_deg, wrap_rad
from orthonav.geo import LocalFrame, check_latlon
from orthonav.types import positive_definite, worst_sigma

if TYPE_CHECKING:
    from orthonav.fusion.ground_velocity import GroundVelocity
    from orthonav.types import Fix

log = logging.getLogger(__name__)

N_STATES = 11
POS, VEL, PSI, ACC_BIAS, GYRO_BIAS, ACC_SCALE, GYRO_SCALE = (
    slice(0, 2),
    slice(2, 4),
    4,
    slice(5, 7),
    7,
    slice(8, 10),
    10,
)
# Position sigma of a filter that has never been given a position (finite, so the maths stays finite).
UNKNOWN_SIGMA_M = 1e5
TIME_EPS_S = 1e-9
RESET_REASON = "reset"


@dataclass(frozen=True)
class FilterConfig:
    """Filter tuning. The process noise and the bias/scale priors come from ``imu``."""

    imu: ImuErrorModel = field(default_factory=lambda: ImuErrorModel.preset("consumer"))
    gate_probability: float = 0.999  # chi-square gate on the 2-D position innovation
    heading_fix_sigma_deg: float | None = 2.0  # None: ignore the heading of fixes
    initial_velocity_sigma_mps: float = 1.0
    initial_heading_sigma_deg: float = 10.0
    history_s: float = 30.0  # how late a fix may arrive; also the longest re-initialisation pair
    reinit_after_s: float = 120.0  # without an accepted fix -> "lost"
    lost_sigma_m: float = 1000.0  # position sigma beyond which the filter is "lost"
    fixed_within_s: float = 10.0  # status "fixed" this long after an accepted fix
    max_future_s: float = 0.5  # capture times this far past the newest INS sample count as "now"
    max_step_s: float = 0.5  # longest propagation sub-step
    reinit_candidates: int = 4  # earlier fixes kept to pair a new one with while lost
    reset_after_fixes: int = 3  # gated-out fixes in a row that, agreeing, reset a trusted filter
    # White noise on the velocity error beyond the IMU's: where the "INS" is an autopilot's
    # estimate, its velocity moves with whatever aids it (orthonav itself once GNSS is gone),
    # which no IMU error model describes.
    velocity_walk_mps_per_sqrt_s: float = 0.0
    # The same for the heading: an estimator's heading can step (as its aiding changes), and a
    # velocity measured in the camera's axes and turned with that heading carries the step until
    # the fixes' headings have told the filter of it.
    heading_walk_deg_per_sqrt_s: float = 0.0
    # Fixes this close in time share most of their error: consecutive frames overlap and match
    # the same map features, so a map feature placed 10 m off moves them all. A fix with another
    # accepted within the window leaves the position known no better than its own covariance
    # (the shared error cannot be averaged away: a run of fixes sharing one bias pulls the
    # estimate all the way to it), while the estimate still follows it at once. A shared fix
    # vaguer than unpinned_max_sigma_m is the exception: it adds little, and as a floor it would
    # widen the filter past the sigma at which unpinned fixes are taken, so there the floor is
    # the narrower of its covariance and the prediction's. 0 takes fixes as independent, as for
    # fixes far apart.
    fix_correlation_s: float = 0.0
    # Once fixes have been fused, beyond this position sigma the prediction no longer tells a
    # fix's place from a twin of ground that repeats: a fix no keypoints pin (Fix.unpinned) is
    # not fused, and several such fixes agreeing on a twin place do not re-initialise it. The
    # first fixes after an initialisation (a flight's start, an autopilot's reboot) are taken at
    # the sigma it gave: without them a correlation-only flight would never start again.
    unpinned_max_sigma_m: float = 50.0

    def __post_init__(self) -> None:
        if not 0.0 < self.gate_probability < 1.0:
            raise OrthonavError(f"filter gate_probability: expected 0 < p < 1, got {self.gate_probability}")
        positive = ("initial_velocity_sigma_mps", "initial_heading_sigma_deg", "history_s", "reinit_after_s")
        require_positive(
            "filter",
            self,
            (*positive, "lost_sigma_m", "fixed_within_s", "max_step_s", "unpinned_max_sigma_m"),
        )
        sigma = self.heading_fix_sigma_deg
        if sigma is not None and not (math.isfinite(sigma) and sigma > 0.0):
            raise OrthonavError(
                f"filter heading_fix_sigma_deg: expected a positive number or None, got {sigma}"
            )
        for name in ("velocity_walk_mps_per_sqrt_s", "heading_walk_deg_per_sqrt_s", "fix_correlation_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise OrthonavError(f"filter {name}: expected >= 0, got {value}")
        if not (self.max_future_s >= 0.0 and self.reinit_candidates >= 1 and self.reset_after_fixes >= 2):
            raise OrthonavError(
                "filter max_future_s must be >= 0, reinit_candidates >= 1 and reset_after_fixes >= 2"
            )

    @classmethod
    def for_imu(cls, model: ImuErrorModel, **changes: Any) -> FilterConfig:
        """A configuration whose process noise matches ``model`` (plus any other ``changes``)."""
        return cls(imu=model, **changes)

    @property
    def gate(self) -> float:
        """Mahalanobis distance gate for 2 degrees of freedom (chi-square quantile, closed form)."""
        return math.sqrt(-2.0 * math.log(1.0 - self.gate_probability))

    @property
    def heading_gate(self) -> float:
        """Normalised-innovation gate for the (1-D) heading at the same probability."""
        return _normal_quantile(0.5 + self.gate_probability / 2.0)


@dataclass(frozen=True)
class FixOutcome:
    """What the filter did with one fix, and why."""

    accepted: bool
    reason: str
    mahalanobis: float | None
    innovation_east_m: float | None  # fix minus estimate (for "reinitialised": the pair's residual)
    innovation_north_m: float | None
    latency_s: float  # filter time minus capture time

    @property
    def reset(self) -> bool:
        """The fix was one of several that agreed with each other and reset a trusted filter."""
        return self.reason.startswith(RESET_REASON)

    def to_dict(self) -> dict:
        return {
            "accepted": self.accepted,
            "reason": self.reason,
            "mahalanobis": _rounded(self.mahalanobis, 3),
            "innovation_east_m": _rounded(self.innovation_east_m, 3),
            "innovation_north_m": _rounded(self.innovation_north_m, 3),
            "latency_s": _rounded(self.latency_s, 3),
        }


@dataclass(frozen=True)
class VelocityOutcome:
    """What the filter did with one ground velocity, and why."""

    accepted: bool
    reason: str
    mahalanobis: float | None

    def to_dict(self) -> dict:
        distance = _rounded(self.mahalanobis, 3)
        return {"accepted": self.accepted, "reason": self.reason, "mahalanobis": distance}


@dataclass(frozen=True, eq=False)
class NavState:
    """The fused estimate at one instant."""

    time_s: float
    lat: float
    lon: float
    heading_deg: float
    vel_east_mps: float
    vel_north_mps: float
    covariance_enu_m2: np.ndarray
    heading_sigma_deg: float
    status: str  # "uninitialised" | "dead reckoning" | "fixed" | "lost"
    since_fix_s: float | None
    alt_agl_m: float | None
    velocity_covariance_enu_m2ps2: np.ndarray | None = None
    since_velocity_s: float | None = None  # since the newest fused ground velocity's time

    @property
    def sigma_m(self) -> float:
        """1-sigma of the worst horizontal direction."""
        if not np.all(np.isfinite(self.covariance_enu_m2)):
            return math.inf
        return worst_sigma(self.covariance_enu_m2)

    def to_dict(self) -> dict:
        return {
            "time_s": _rounded(self.time_s, 3),
            "lat": _rounded(self.lat, 8),
            "lon": _rounded(self.lon, 8),
            "heading_deg": _rounded(self.heading_deg, 3),
            "vel_east_mps": _rounded(self.vel_east_mps, 3),
            "vel_north_mps": _rounded(self.vel_north_mps, 3),
            "covariance_enu_m2": [[_rounded(v, 3) for v in row] for row in self.covariance_enu_m2.tolist()],
            "sigma_m": _rounded(self.sigma_m, 3),
            "heading_sigma_deg": _rounded(self.heading_sigma_deg, 3),
            "status": self.status,
            "since_fix_s": _rounded(self.since_fix_s, 3),
            "alt_agl_m": self.alt_agl_m,
            "velocity_sigma_mps": _rounded(self.velocity_sigma_mps, 3),
            "since_velocity_s": _rounded(self.since_velocity_s, 3),
        }

    @property
    def velocity_sigma_mps(self) -> float:
        """1-sigma of the velocity's worst horizontal direction (inf when unknown)."""
        cov = self.velocity_covariance_enu_m2ps2
        if cov is None or not np.all(np.isfinite(cov)):
            return math.inf
        return worst_sigma(cov)


def _rounded(value: float | None, digits: int) -> float | None:
    """JSON-safe: non-finite numbers become None."""
    return None if value is None or not math.isfinite(value) else round(float(value), digits)


def _normal_quantile(p: float) -> float:
    """Inverse standard normal CDF by bisection (no scipy needed for one number)."""
    lo, hi = -40.0, 40.0
    for _ in range(100):
        mid = (lo + hi) / 2.0
        if 0.5 * (1.0 + math.erf(mid / math.sqrt(2.0))) < p:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2.0


@dataclass(frozen=True, eq=False)
class _Nominal:
    """The INS output at one time, in the filter's ENU frame."""

    time_s: float
    pos_m: np.ndarray
    vel_mps: np.ndarray
    heading_rad: float
    alt_agl_m: float | None
    vel_var_m2ps2: float = 0.0  # the sample's velocity_sigma_mps squared


def _interpolate(a: _Nominal, b: _Nominal, time_s: float) -> _Nominal:
    """The INS at a time between two samples: cubic Hermite position, linear velocity and heading."""
    dt = b.time_s - a.time_s
    u = (time_s - a.time_s) / dt
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    pos = h00 * a.pos_m + h10 * dt * a.vel_mps + h01 * b.pos_m + h11 * dt * b.vel_mps
    heading = a.heading_rad + u * wrap_rad(b.heading_rad - a.heading_rad)
    vel_var = a.vel_var_m2ps2 + u * (b.vel_var_m2ps2 - a.vel_var_m2ps2)
    return _Nominal(time_s, pos, a.vel_mps + u * (b.vel_mps - a.vel_mps), heading, a.alt_agl_m, vel_var)


@dataclass(frozen=True, eq=False)
class _Measurement:
    """A visual fix in the filter frame; heading_rad None when its heading is not used."""

    time_s: float
    pos_m: np.ndarray
    cov_m2: np.ndarray
    heading_rad: float | None
    heading_var_rad2: float
    shared: bool = False  # another accepted fix shares its error (FilterConfig.fix_correlation_s)
    # A shared fix vaguer than this is no floor for the position (FilterConfig.fix_correlation_s).
    floor_max_sigma_m: float = math.inf

    def apply(self, nominal: _Nominal, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kalman update of the error state with this fix (position, and heading when used)."""
        H = np.zeros((2, N_STATES))
        H[:, POS] = np.eye(2)
        y = (nominal.pos_m - self.pos_m) - x[POS]
        R = self.cov_m2
        if self.heading_rad is not None:
            H = np.vstack([H, np.eye(N_STATES)[PSI]])
            y = np.append(y, wrap_rad(wrap_rad(nominal.heading_rad - self.heading_rad) - x[PSI]))
            R = np.block([[R, np.zeros((2, 1))], [np.zeros((1, 2)), np.array([[self.heading_var_rad2]])]])
        predicted_m2 = P[POS, POS].copy()
        x, P = _kalman_update(x, P, H, y, R)
        if not self.shared:
            return x, P
        floor_m2 = self.cov_m2
        if worst_sigma(floor_m2) > self.floor_max_sigma_m:
            floor_m2 = min((floor_m2, predicted_m2), key=worst_sigma)
        return x, _position_at_least(P, floor_m2)


@dataclass(frozen=True, eq=False)
class _Velocity:
    """A measured ground velocity (east, north) in the filter frame, turned from the camera's axes
    with the INS heading: the INS heading error turns it as much (see :meth:`NavFilter.update_velocity`)."""

    time_s: float
    vel_mps: np.ndarray
    cov_m2ps2: np.ndarray

    @property
    def H(self) -> np.ndarray:
        """INS velocity minus this measurement = dv - dheading * (v_north, -v_east)."""
        H = np.zeros((2, N_STATES))
        H[:, VEL] = np.eye(2)
        H[:, PSI] = -np.array([self.vel_mps[1], -self.vel_mps[0]])
        return H

    def residual(self, nominal: _Nominal, x: np.ndarray) -> np.ndarray:
        return (nominal.vel_mps - self.vel_mps) - self.H @ x

    def apply(self, nominal: _Nominal, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _kalman_update(x, P, self.H, self.residual(nominal, x), self.cov_m2ps2)


@dataclass(frozen=True, eq=False)
class _Reset:
    """(Re-)initialisation: the position is known to ``cov_m2`` at this time, whatever came before."""

    pos_m: np.ndarray
    cov_m2: np.ndarray
    heading_var_rad2: float | None  # None: keep the heading error estimate
    vel_var_m2ps2: float | None = None  # None: keep the velocity error estimate

    def apply(self, nominal: _Nominal, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, P = x.copy(), P.copy()
        _restart(x, P, POS, nominal.pos_m - self.pos_m, self.cov_m2)
        if self.heading_var_rad2 is not None:
            _restart(x, P, PSI, 0.0, self.heading_var_rad2)
        if self.vel_var_m2ps2 is not None:
            _restart(x, P, VEL, 0.0, np.eye(2) * self.vel_var_m2ps2)
        return x, P


def _restart(
    x: np.ndarray, P: np.ndarray, part: slice | int, value: np.ndarray | float, cov: np.ndarray | float
) -> None:
    """Set ``part`` of the error state to ``value`` with a covariance uncorrelated with the rest."""
    x[part] = value
    P[part, :] = 0.0
    P[:, part] = 0.0
    P[part, part] = cov


@dataclass(eq=False)
class _Node:
    """One point of the history: the INS there, the error estimate before and after its events."""

    nominal: _Nominal
    prior_x: np.ndarray
    prior_P: np.ndarray
    events: list[_Measurement | _Reset | _Velocity] = field(default_factory=list)
    x: np.ndarray = field(init=False)
    P: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.settle()

    @property
    def time_s(self) -> float:
        return self.nominal.time_s

    def settle(self) -> None:
        """Posterior = prior with this node's fixes/resets applied in arrival order."""
        x, P = self.prior_x, self.prior_P
        for event in self.events:
            x, P = event.apply(self.nominal, x, P)
        self.x, self.P = x, P


def _kalman_update(
    x: np.ndarray, P: np.ndarray, H: np.ndarray, y: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Standard update with the Joseph form, which keeps P symmetric positive definite."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    I_KH = np.eye(N_STATES) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    return x + K @ y, (P + P.T) / 2.0


def _position_at_least(P: np.ndarray, floor_m2: np.ndarray) -> np.ndarray:
    """``P`` with its position block raised to at least ``floor_m2`` (adding a PSD part keeps
    the whole positive semi-definite)."""
    values, vectors = np.linalg.eigh(floor_m2 - P[POS, POS])
    P = P.copy()
    P[POS, POS] += vectors @ np.diag(np.clip(values, 0.0, None)) @ vectors.T
    return P


def _derivative_body_to_nav(heading_rad: float) -> np.ndarray:
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    return np.array([[c, -s], [-s, -c]])


def _error_dynamics(
    x: np.ndarray, accel_nav: np.ndarray, heading_rad: float, rate_rps: float
) -> tuple[np.ndarray, float, np.ndarray]:
    """d(dv)/dt, d(dheading)/dt at the estimate, and the Jacobian F of the error dynamics.

    The INS rotated the measured body force (1+s)*f + b with its heading psi_ins = psi + dpsi, so
    truth is recovered as f = (f_ins - b)/(1+s) rotated with psi_ins - dpsi; likewise for the gyro.
    """
    scale = 1.0 + x[ACC_SCALE]
    force = (body_to_nav(heading_rad) @ accel_nav - x[ACC_BIAS]) / scale
    true_heading = heading_rad - x[PSI]
    rotation = body_to_nav(true_heading)
    gyro_scale = 1.0 + x[GYRO_SCALE]
    true_rate = (rate_rps - x[GYRO_BIAS]) / gyro_scale
    F = np.zeros((N_STATES, N_STATES))
    F[POS, VEL] = np.eye(2)
    F[VEL, PSI] = _derivative_body_to_nav(true_heading) @ force
    F[VEL, ACC_BIAS] = rotation / scale
    F[VEL, ACC_SCALE] = rotation * (force / scale)
    F[PSI, GYRO_BIAS] = 1.0 / gyro_scale
    F[PSI, GYRO_SCALE] = true_rate / gyro_scale
    return accel_nav - rotation @ force, rate_rps - true_rate, F


def _process_noise(
    imu: ImuErrorModel, velocity_walk_mps_per_sqrt_s: float = 0.0, heading_walk_deg_per_sqrt_s: float = 0.0
) -> np.ndarray:
    """Continuous-time white-noise densities driving the error state."""
    q = np.zeros(N_STATES)
    q[VEL] = imu.accel_noise_mps_per_sqrt_s**2 + velocity_walk_mps_per_sqrt_s**2
    q[PSI] = math.radians(imu.gyro_noise_deg_per_sqrt_s) ** 2 + math.radians(heading_walk_deg_per_sqrt_s) ** 2
    q[ACC_BIAS] = imu.accel_bias_walk_mps2_per_sqrt_s**2
    q[GYRO_BIAS] = math.radians(imu.gyro_bias_walk_dps_per_sqrt_s) ** 2
    return np.diag(q)


def _initial_covariance(config: FilterConfig) -> np.ndarray:
    """What is known before any fix: nothing of the position, the IMU's specified errors."""
    imu = config.imu
    p = np.zeros(N_STATES)
    p[POS] = UNKNOWN_SIGMA_M**2
    p[VEL] = config.initial_velocity_sigma_mps**2
    p[PSI] = math.radians(config.initial_heading_sigma_deg) ** 2
    p[ACC_BIAS] = imu.accel_bias_mps2**2
    p[GYRO_BIAS] = math.radians(imu.gyro_bias_dps) ** 2
    p[ACC_SCALE] = (imu.accel_scale_factor_ppm * 1e-6) ** 2
    p[GYRO_SCALE] = (imu.gyro_scale_factor_ppm * 1e-6) ** 2
    return np.diag(p)


def _propagate(
    x: np.ndarray, P: np.ndarray, a: _Nominal, b: _Nominal, Qc: np.ndarray, max_step_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Carry the error estimate and covariance from INS sample ``a`` to ``b``.

    The INS acceleration and turn rate are taken constant between samples (as the simulator
    integrates them); the step is cut into sub-steps so that the 2nd-order transition and noise
    integrals stay accurate over gaps in the INS stream.
    """
    dt = b.time_s - a.time_s
    if dt <= 0.0:
        return x, P
    accel = (b.vel_mps - a.vel_mps) / dt
    rate = wrap_rad(b.heading_rad - a.heading_rad) / dt
    steps = max(1, min(1000, math.ceil(dt / max_step_s - 1e-9)))
    h = dt / steps
    # The sample's own velocity variance grew: as white noise on the velocity over the interval.
    Qc = Qc.copy()
    Qc[VEL, VEL] += np.eye(2) * max(0.0, b.vel_var_m2ps2 - a.vel_var_m2ps2) / dt
    x, eye = x.copy(), np.eye(N_STATES)
    for k in range(steps):
        dv_dot, dpsi_dot, F = _error_dynamics(x, accel, a.heading_rad + rate * (k + 0.5) * h, rate)
        x[POS] += x[VEL] * h + 0.5 * dv_dot * h * h
        x[VEL] += dv_dot * h
        x[PSI] += dpsi_dot * h
        Phi = eye + F * h + (F @ F) * (h * h / 2.0)
        FQ = F @ Qc
        Q = Qc * h + (FQ + FQ.T) * (h * h / 2.0) + (FQ @ F.T) * (h**3 / 3.0)
        P = Phi @ P @ Phi.T + Q
    return x, (P + P.T) / 2.0


def _mahalanobis(residual: np.ndarray, cov: np.ndarray) -> float:
    return float(math.sqrt(max(0.0, residual @ np.linalg.solve(cov, residual))))


class NavFilter:
    """INS + visual fixes -> NavState, with gating, late-fix handling and re-initialisation."""

    def __init__(self, config: FilterConfig | None = None) -> None:
        self.config = config or FilterConfig()
        config = self.config
        self._Qc = _process_noise(
            config.imu, config.velocity_walk_mps_per_sqrt_s, config.heading_walk_deg_per_sqrt_s
        )
        self._frame: LocalFrame | None = None
        self._nodes: list[_Node] = []
        self._initialised = False
        self._pending_init: tuple[float, float, float, float] | None = None
        self._anchor_s: float | None = None  # newest accepted fix or initialisation (the "lost" clock)
        self._last_fix_s: float | None = None
        self._fused_since_start = False  # a fix fused since the last initialisation (a new start)
        self._candidates: list[_Measurement] = []
        self._disagreeing: list[_Measurement] = []  # the gated-out fixes since the last accepted one
        self._fix_times: list[float] = []  # capture times of the accepted fixes, for their sharing
        self._last_velocity_s: float | None = None

    # ---- public API -------------------------------------------------------------------------

    def initialise(
        self, time_s: float, lat: float, lon: float, sigma_m: float, heading_sigma_deg: float = 5.0
    ) -> None:
        """Position known to ``sigma_m`` at ``time_s`` (e.g. the last GNSS fix before loss).

        The INS heading is trusted to ``heading_sigma_deg``. Called before any INS sample, the
        position is taken as valid at the first sample.
        """
        check_latlon(lat, lon, "filter initialisation")
        for name, value in (("sigma_m", sigma_m), ("heading_sigma_deg", heading_sigma_deg)):
            if not (math.isfinite(value) and value > 0.0):
                raise OrthonavError(f"filter initialisation {name}: expected a positive number, got {value}")
        if not self._nodes:
            self._pending_init = (lat, lon, sigma_m, heading_sigma_deg)
            return
        time_s = self._initialisation_time(time_s)
        east, north = self._frame.to_enu(lat, lon)
        heading_var = math.radians(heading_sigma_deg) ** 2
        self._insert(time_s, _Reset(np.array([east, north], float), np.eye(2) * sigma_m**2, heading_var))
        self._initialised = True
        self._fused_since_start = False
        self._forget_fixes()
        self._anchor_s = time_s if self._anchor_s is None else max(self._anchor_s, time_s)

    def predict(self, ins: InsSample) -> NavState:
        """Propagate to ``ins.time_s``; the INS output is the nominal the error is relative to."""
        nominal = self._nominal(ins)
        if not self._nodes:
            self._start(nominal)
        elif nominal.time_s < self._nodes[-1].time_s:
            self._rebase(nominal)
        elif nominal.time_s > self._nodes[-1].time_s:
            last = self._nodes[-1]
            x, P = _propagate(last.x, last.P, last.nominal, nominal, self._Qc, self.config.max_step_s)
            self._nodes.append(_Node(nominal, x, P))
            self._trim()
        return self.state()

    def update(self, fix: Fix, capture_time_s: float) -> FixOutcome:
        """Fuse a fix of the frame captured at ``capture_time_s`` (at or before the filter time)."""
        latency = float(self._nodes[-1].time_s - capture_time_s) if self._nodes else math.nan
        problem = self._fix_problem(fix, capture_time_s)
        if problem is not None:
            return self._rejected(problem, latency)
        measurement = self._measurement(fix, min(capture_time_s, self._nodes[-1].time_s))
        if self._status() in ("uninitialised", "lost"):
            return self._reinitialise(measurement, latency)
        return self._gated_update(measurement, latency)

    def update_velocity(self, velocity: GroundVelocity) -> VelocityOutcome:
        """Fuse a measured ground velocity at its time; gated out where it disagrees with the
        estimate beyond the gate, and never fused while the filter is not trusted (uninitialised or
        lost: its velocity error then means nothing to gate against).

        The velocity was turned to east/north with the INS heading at the capture (the camera
        measures it in its own axes), so it carries the INS heading error: the measurement is of
        the velocity error and the heading error together. Taken as a velocity alone, an INS whose
        heading is off would be handed back its own velocity error, which it could then never see;
        the heading error the fixes' headings estimate is taken out instead."""
        cov = np.asarray(velocity.covariance_m2ps2, dtype=float)
        vel = np.array([velocity.east_mps, velocity.north_mps], float)
        problem = self._velocity_problem(velocity.time_s, vel, cov)
        if problem is not None:
            return VelocityOutcome(False, problem, None)
        time_s = min(velocity.time_s, self._nodes[-1].time_s)
        nominal, x, P = self._state_at(time_s)
        measurement = _Velocity(time_s, vel, (cov + cov.T) / 2.0)
        H = measurement.H
        distance = _mahalanobis(measurement.residual(nominal, x), H @ P @ H.T + measurement.cov_m2ps2)
        if distance > self.config.gate:
            return VelocityOutcome(False, f"mahalanobis {distance:.2f} > {self.config.gate:.2f}", distance)
        self._insert(time_s, measurement)
        last = self._last_velocity_s
        self._last_velocity_s = time_s if last is None else max(last, time_s)
        return VelocityOutcome(True, "accepted", distance)

    def _velocity_problem(self, time_s: float, vel: np.ndarray, cov: np.ndarray) -> str | None:
        """Why a ground velocity cannot be used at all (before gating), or None."""
        if not (cov.shape == (2, 2) and np.all(np.isfinite(cov)) and np.all(np.isfinite(vel))):
            return "velocity or covariance not finite (2x2 expected)"
        if not positive_definite(cov):
            return "covariance not positive definite"
        if not math.isfinite(time_s):
            return f"time not finite: {time_s}"
        problem = self._timing_problem(time_s)
        if problem is None and self._status() in ("uninitialised", "lost"):
            return f"navigation {self._status()}"
        return problem

    def state(self) -> NavState:
        """The current estimate (at the newest INS sample).

        Before any INS sample: time -inf (so ``sample.time_s > state.time_s`` holds), NaN position.
        """
        if not self._nodes:
            nan, cov = math.nan, np.full((2, 2), math.inf)
            return NavState(-math.inf, nan, nan, nan, nan, nan, cov, math.inf, "uninitialised", None, None)
        node = self._nodes[-1]
        nominal, x, P = node.nominal, node.x, node.P
        east, north = nominal.pos_m - x[POS]
        lat, lon = self._frame.to_latlon(east, north)
        vel = nominal.vel_mps - x[VEL]
        since = None if self._last_fix_s is None else node.time_s - self._last_fix_s
        return NavState(
            time_s=node.time_s,
            lat=float(lat),
            lon=float(lon),
            heading_deg=heading_deg(nominal.heading_rad - x[PSI]),
            vel_east_mps=float(vel[0]),
            vel_north_mps=float(vel[1]),
            covariance_enu_m2=P[POS, POS].copy(),
            heading_sigma_deg=math.degrees(math.sqrt(P[PSI, PSI])),
            status=self._status(),
            since_fix_s=since,
            alt_agl_m=nominal.alt_agl_m,
            velocity_covariance_enu_m2ps2=P[VEL, VEL].copy(),
            since_velocity_s=None if self._last_velocity_s is None else node.time_s - self._last_velocity_s,
        )

    # ---- timeline -----------------------------------------------------------------------------

    def _nominal(self, ins: InsSample) -> _Nominal:
        check_latlon(ins.lat, ins.lon, "INS sample")
        values = (ins.time_s, ins.vel_east_mps, ins.vel_north_mps, ins.heading_deg, ins.velocity_sigma_mps)
        if not all(math.isfinite(v) for v in values) or ins.velocity_sigma_mps < 0.0:
            raise OrthonavError(
                f"INS sample: time, velocity, its sigma (>= 0) and heading must be finite numbers, got {ins}"
            )
        if self._frame is None:
            self._frame = LocalFrame.around(ins.lat, ins.lon)
        east, north = self._frame.to_enu(ins.lat, ins.lon)
        return _Nominal(
            float(ins.time_s),
            np.array([east, north], float),
            np.array([ins.vel_east_mps, ins.vel_north_mps], float),
            math.radians(ins.heading_deg),
            ins.alt_agl_m,
            ins.velocity_sigma_mps**2,
        )

    def _start(self, nominal: _Nominal) -> None:
        self._nodes.append(_Node(nominal, np.zeros(N_STATES), _initial_covariance(self.config)))
        if self._pending_init is not None:
            pending, self._pending_init = self._pending_init, None
            self.initialise(nominal.time_s, *pending)

    def _rebase(self, nominal: _Nominal) -> None:
        """The INS clock went backwards: keep the estimate, restart the history on the new clock."""
        last = self._nodes[-1]
        offset = nominal.time_s - last.time_s
        log.warning("INS time went back %.3f s: filter history restarted on the new clock", -offset)
        self._nodes = [_Node(nominal, last.x, last.P)]
        self._anchor_s = None if self._anchor_s is None else self._anchor_s + offset
        self._last_fix_s = None if self._last_fix_s is None else self._last_fix_s + offset
        self._last_velocity_s = None
        self._forget_fixes()

    def _trim(self) -> None:
        """Forget nodes older than the history, keeping one at or before its start."""
        cutoff = self._nodes[-1].time_s - self.config.history_s
        drop = 0
        while drop + 1 < len(self._nodes) and self._nodes[drop + 1].time_s <= cutoff:
            drop += 1
        del self._nodes[:drop]

    def _find(self, time_s: float) -> tuple[int, bool]:
        """Index of the node at ``time_s`` (True) or of the first node after it (False)."""
        i = bisect.bisect_left(self._nodes, time_s - TIME_EPS_S, key=lambda node: node.time_s)
        return i, i < len(self._nodes) and self._nodes[i].time_s <= time_s + TIME_EPS_S

    def _nominal_at(self, time_s: float) -> _Nominal:
        i, exact = self._find(time_s)
        if exact:
            return self._nodes[i].nominal
        return _interpolate(self._nodes[i - 1].nominal, self._nodes[i].nominal, time_s)

    def _state_at(self, time_s: float) -> tuple[_Nominal, np.ndarray, np.ndarray]:
        """INS nominal, error estimate and covariance at a time within the history (no side effects)."""
        i, exact = self._find(time_s)
        if exact:
            node = self._nodes[i]
            return node.nominal, node.x.copy(), node.P.copy()
        prev = self._nodes[i - 1]
        nominal = _interpolate(prev.nominal, self._nodes[i].nominal, time_s)
        return nominal, *_propagate(prev.x, prev.P, prev.nominal, nominal, self._Qc, self.config.max_step_s)

    def _propagate_span(
        self, start: _Nominal, x: np.ndarray, P: np.ndarray, time_s: float
    ) -> tuple[_Nominal, np.ndarray, np.ndarray]:
        """Propagate through the stored INS samples to ``time_s``, ignoring the fixes applied there."""
        previous = start
        later = [node.nominal for node in self._nodes if start.time_s < node.time_s < time_s - TIME_EPS_S]
        for nominal in [*later, self._nominal_at(time_s)]:
            x, P = _propagate(x, P, previous, nominal, self._Qc, self.config.max_step_s)
            previous = nominal
        return previous, x, P

    def _insert(self, time_s: float, event: _Measurement | _Reset | _Velocity) -> None:
        """Apply an event at ``time_s`` (rewinding there) and re-propagate everything after it."""
        i, exact = self._find(time_s)
        if not exact:
            prev = self._nodes[i - 1]
            nominal = _interpolate(prev.nominal, self._nodes[i].nominal, time_s)
            x, P = _propagate(prev.x, prev.P, prev.nominal, nominal, self._Qc, self.config.max_step_s)
            self._nodes.insert(i, _Node(nominal, x, P))
        self._nodes[i].events.append(event)
        self._nodes[i].settle()
        for j in range(i + 1, len(self._nodes)):
            prev, node = self._nodes[j - 1], self._nodes[j]
            node.prior_x, node.prior_P = _propagate(
                prev.x, prev.P, prev.nominal, node.nominal, self._Qc, self.config.max_step_s
            )
            node.settle()

    def _initialisation_time(self, time_s: float) -> float:
        now, oldest = self._nodes[-1].time_s, self._nodes[0].time_s
        if not (math.isfinite(time_s) and oldest - TIME_EPS_S <= time_s <= now + self.config.max_future_s):
            raise OrthonavError(
                f"filter initialisation time {time_s}: expected a time within the INS history "
                f"[{oldest:.3f}, {now:.3f}] s"
            )
        return min(time_s, now)

    # ---- fixes --------------------------------------------------------------------------------

    def _fix_problem(self, fix: Fix, capture_time_s: float) -> str | None:
        """Why a fix cannot be used at all (before any gating), or None."""
        if not fix.accepted:
            return f"localizer: {fix.reason}"
        if fix.pose is None:
            return "no pose"
        sigma_m, most = (
            (self.state().sigma_m if self._nodes else UNKNOWN_SIGMA_M),
            self.config.unpinned_max_sigma_m,
        )
        if fix.unpinned and self._fused_since_start and not sigma_m <= most:
            return (
                "a correlation pose no keypoints pin, and a prediction of "
                f"+-{sigma_m:.0f} m that cannot tell it from a twin place (> {most:.0f} m)"
            )
        if fix.covariance_enu_m2 is None:
            return "no covariance"
        cov = np.asarray(fix.covariance_enu_m2, dtype=float)
        if cov.ndim != 2 or cov.shape[0] < 2 or cov.shape[1] < 2:
            return f"covariance: expected a 2x2 matrix, got shape {cov.shape}"
        if not (
            np.all(np.isfinite(cov[:2, :2])) and math.isfinite(fix.pose.lat) and math.isfinite(fix.pose.lon)
        ):
            return "covariance or position not finite"
        if not positive_definite(cov[:2, :2]):
            return "covariance not positive definite"
        # A fix vaguer than a lost filter tells nothing, and one taken while lost would
        # re-initialise the filter that wide.
        lost_m = self.config.lost_sigma_m
        if (sigma := worst_sigma(cov[:2, :2])) > lost_m:
            return f"a fix claiming +-{sigma:.0f} m, vaguer than a lost filter (> {lost_m:.0f} m)"
        if not math.isfinite(capture_time_s):
            return f"capture time not finite: {capture_time_s}"
        return self._timing_problem(capture_time_s)

    def _timing_problem(self, capture_time_s: float) -> str | None:
        if not self._nodes:
            return "no INS sample yet"
        now, oldest = self._nodes[-1].time_s, self._nodes[0].time_s
        if capture_time_s > now + self.config.max_future_s:
            return f"from the future: captured {capture_time_s - now:.2f} s after the newest INS sample"
        if capture_time_s < oldest - TIME_EPS_S or now - capture_time_s > self.config.history_s:
            return f"stale: captured {now - capture_time_s:.1f} s ago, history holds {now - oldest:.1f} s"
        return None

    def _measurement(self, fix: Fix, time_s: float) -> _Measurement:
        pose = fix.pose
        east, north = self._frame.to_enu(pose.lat, pose.lon)
        cov = np.asarray(fix.covariance_enu_m2, dtype=float)[:2, :2]
        sigma = self.config.heading_fix_sigma_deg
        use_heading = sigma is not None and math.isfinite(pose.heading_deg)
        return _Measurement(
            time_s,
            np.array([east, north], float),
            (cov + cov.T) / 2.0,
            math.radians(pose.heading_deg) if use_heading else None,
            math.radians(sigma) ** 2 if use_heading else 0.0,
        )

    def _gated_update(self, measurement: _Measurement, latency: float) -> FixOutcome:
        nominal, x, P = self._state_at(measurement.time_s)
        innovation = measurement.pos_m - (nominal.pos_m - x[POS])
        distance = _mahalanobis(innovation, P[POS, POS] + measurement.cov_m2)
        if distance > self.config.gate:
            return self._disagreeing_fix(measurement, latency, distance, innovation)
        measurement, note = self._gate_heading(nominal, x, P, measurement)
        self._insert(measurement.time_s, self._shared(measurement))
        self._accepted_at(measurement.time_s)
        self._disagreeing.clear()
        return FixOutcome(True, "accepted" + note, distance, *map(float, innovation), latency)

    def _disagreeing_fix(
        self, measurement: _Measurement, latency: float, distance: float, innovation: np.ndarray
    ) -> FixOutcome:
        """Gate the fix out, unless it is one of ``reset_after_fixes`` in a row that agree with each
        other: then the prediction is what is wrong, and the filter resets on them."""
        oldest = self._nodes[0].time_s
        recent = [m for m in self._disagreeing if m.time_s >= oldest]
        self._disagreeing = [*recent, measurement][-self.config.reset_after_fixes :]
        reason = f"mahalanobis {distance:.2f} > {self.config.gate:.2f}"
        fixes = sorted(self._disagreeing, key=lambda m: m.time_s)
        if len(fixes) < self.config.reset_after_fixes or not self._agree(fixes):
            return self._rejected(reason, latency, distance, innovation)
        off_m = float(np.linalg.norm(innovation))
        # The velocity error that would explain the disagreement since the last trusted position.
        since_s = max(measurement.time_s - self._anchor_s, self.config.max_step_s)
        velocity_sigma = max(self.config.initial_velocity_sigma_mps, off_m / since_s)
        self._reset_from(fixes, velocity_sigma**2)
        text = (
            f"{RESET_REASON}: {len(fixes)} fixes in a row agree with each other, {off_m:.0f} m from the "
            f"prediction ({reason})"
        )
        log.warning("filter %s", text)
        return FixOutcome(True, text, distance, *map(float, innovation), latency)

    def _agree(self, fixes: list[_Measurement]) -> bool:
        """Each fix (in time order) within the gate of the next, the INS motion between removed."""
        return all(self._pair_distance(a, b)[0] <= self.config.gate for a, b in itertools.pairwise(fixes))

    def _gate_heading(
        self, nominal: _Nominal, x: np.ndarray, P: np.ndarray, measurement: _Measurement
    ) -> tuple[_Measurement, str]:
        """Drop the heading of a fix whose position passed the gate but whose heading does not."""
        if measurement.heading_rad is None:
            return measurement, ""
        off = wrap_rad(wrap_rad(nominal.heading_rad - measurement.heading_rad) - x[PSI])
        normalised = abs(off) / math.sqrt(P[PSI, PSI] + measurement.heading_var_rad2)
        if normalised <= self.config.heading_gate:
            return measurement, ""
        note = f" (heading {math.degrees(abs(off)):.1f} deg off, {normalised:.1f} sigma: not used)"
        return replace(measurement, heading_rad=None), note

    def _reinitialise(self, measurement: _Measurement, latency: float) -> FixOutcome:
        """While lost: look for an earlier fix that agrees with this one once the INS motion is removed."""
        oldest = self._nodes[0].time_s
        self._candidates = [
            c
            for c in self._candidates
            if c.time_s >= oldest and abs(c.time_s - measurement.time_s) > TIME_EPS_S
        ]
        closest = math.inf
        for candidate in reversed(self._candidates):
            first, second = sorted((candidate, measurement), key=lambda m: m.time_s)
            distance, residual = self._pair_distance(first, second)
            if distance <= self.config.gate:
                self._reset_from([first, second])
                log.info("filter re-initialised from two fixes (pair mahalanobis %.2f)", distance)
                return FixOutcome(True, "reinitialised", distance, *map(float, residual), latency)
            closest = min(closest, distance)
        status = self._status()
        self._candidates = [*self._candidates, measurement][-self.config.reinit_candidates :]
        held = f"{status}: held for re-initialisation"
        if math.isinf(closest):
            return self._rejected(f"{held}, no earlier fix to pair with", latency)
        gate = self.config.gate
        return self._rejected(
            f"{held}, closest pair mahalanobis {closest:.2f} > {gate:.2f}", latency, closest
        )

    def _pair_distance(self, first: _Measurement, second: _Measurement) -> tuple[float, np.ndarray]:
        """How far apart two fixes are once the INS motion between them is removed, in sigmas."""
        start, x, P = self._state_at(first.time_s)
        x[POS] = 0.0
        P[POS, :] = 0.0
        P[:, POS] = 0.0
        end, x, P = self._propagate_span(start, x, P, second.time_s)
        ins_motion = (end.pos_m - start.pos_m) - x[POS]
        residual = (second.pos_m - first.pos_m) - ins_motion
        return _mahalanobis(residual, first.cov_m2 + second.cov_m2 + P[POS, POS]), residual

    def _reset_from(self, fixes: list[_Measurement], velocity_var_m2ps2: float | None = None) -> None:
        """Position from the first fix (in time order), then the others applied as ordinary fixes
        (they give velocity); the velocity error restarted at ``velocity_var_m2ps2`` unless None."""
        first, *rest = fixes
        self._insert(first.time_s, _Reset(first.pos_m, first.cov_m2, None, velocity_var_m2ps2))
        for fix in rest:
            nominal, x, P = self._state_at(fix.time_s)
            fix, _ = self._gate_heading(nominal, x, P, fix)
            self._insert(fix.time_s, self._shared(fix))
        self._initialised = True
        self._forget_fixes()
        self._accepted_at(fixes[-1].time_s)

    def _shared(self, measurement: _Measurement) -> _Measurement:
        """``measurement``, marked shared where another accepted fix lies within
        ``fix_correlation_s`` of it (before or after: a late fix overlaps those around it as much)."""
        window, times, time_s = self.config.fix_correlation_s, self._fix_times, measurement.time_s
        if window <= 0.0:
            return measurement
        del times[: bisect.bisect_left(times, time_s - self.config.history_s - window)]
        shared = bisect.bisect_left(times, time_s + window) > bisect.bisect_right(times, time_s - window)
        bisect.insort(times, time_s)
        return replace(measurement, shared=shared, floor_max_sigma_m=self.config.unpinned_max_sigma_m)

    def _forget_fixes(self) -> None:
        """A new start: no fix held for pairing or counted as disagreeing."""
        self._candidates.clear()
        self._disagreeing.clear()

    def _accepted_at(self, time_s: float) -> None:
        self._fused_since_start = True
        self._last_fix_s = time_s if self._last_fix_s is None else max(self._last_fix_s, time_s)
        self._anchor_s = time_s if self._anchor_s is None else max(self._anchor_s, time_s)

    def _rejected(
        self, reason: str, latency: float, distance: float | None = None, innovation: np.ndarray | None = None
    ) -> FixOutcome:
        log.info("fix rejected: %s", reason)
        east, north = (None, None) if innovation is None else map(float, innovation)
        return FixOutcome(False, reason, distance, east, north, latency)

    def _status(self) -> str:
        if not self._nodes or not self._initialised:
            return "uninitialised"
        node = self._nodes[-1]
        sigma = worst_sigma(node.P[POS, POS])
        if node.time_s - self._anchor_s > self.config.reinit_after_s or sigma > self.config.lost_sigma_m:
            return "lost"
        if self._last_fix_s is not None and node.time_s - self._last_fix_s <= self.config.fixed_within_s:
            return "fixed"
        return "dead reckoning"

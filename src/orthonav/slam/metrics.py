"""Trajectory and map errors: ATE, RPE and landmark error, all in metres.

ATE here is absolute: the RMSE of the horizontal position error against the truth in the
same ENU frame, with no alignment first. A navigation system is judged by where it says the
vehicle is; aligning (as SLAM papers often do) would hide exactly the drift that map fixes
remove. RPE is the RMSE of the error of each step's horizontal displacement (``delta``
keyframes apart) in the step's own heading: the local consistency, which drift and a common
heading offset do not dominate.
"""

from __future__ import annotations

import numpy as np

from orthonav.errors import OrthonavError


def _check(estimate: np.ndarray, truth: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    est, tru = np.asarray(estimate, float), np.asarray(truth, float)
    if est.ndim != 2 or est.shape != tru.shape or est.shape[1] < 2 or len(est) == 0:
        raise OrthonavError(
            f"{what}: expected estimate and truth as (N, 2+) arrays of one shape, "
            f"got {est.shape} and {tru.shape}"
        )
    return est[:, :2], tru[:, :2]


def ate_m(estimate_en: np.ndarray, truth_en: np.ndarray) -> float:
    """Absolute trajectory error: RMSE of the horizontal position error (no alignment)."""
    est, tru = _check(estimate_en, truth_en, "ATE")
    return float(np.sqrt(np.mean(np.sum((est - tru) ** 2, axis=1))))


def rpe_m(estimate: np.ndarray, truth: np.ndarray, delta: int = 1) -> float:
    """Relative pose error: RMSE of the error of each step's horizontal displacement over ``delta``
    keyframes, expressed in the step's starting pose (columns east, north, alt, yaw_deg), so a
    heading offset common to the whole track does not count."""
    est, tru = np.asarray(estimate, float), np.asarray(truth, float)
    _check(est, tru, "RPE")
    if est.shape[1] < 4:
        raise OrthonavError(f"RPE: expected (N, 4) east, north, alt, yaw_deg rows, got {est.shape}")
    if delta < 1 or len(est) <= delta:
        raise OrthonavError(f"RPE: need more than delta={delta} poses, got {len(est)}")
    errors = _local_steps(est, delta) - _local_steps(tru, delta)
    return float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))


def _local_steps(track: np.ndarray, delta: int) -> np.ndarray:
    """(N - delta, 2) displacements (right, forward) in the heading of each step's first pose."""
    d = track[delta:, :2] - track[:-delta, :2]
    yaw = np.radians(track[:-delta, 3])
    return np.column_stack(
        [d[:, 0] * np.cos(yaw) - d[:, 1] * np.sin(yaw), d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)]
    )


def landmark_errors_m(estimate_enu: np.ndarray, truth_enu: np.ndarray) -> np.ndarray:
    """Per-landmark 3D position error (m)."""
    est, tru = np.asarray(estimate_enu, float), np.asarray(truth_enu, float)
    if est.shape != tru.shape or (len(est) and est.shape[1] != 3):
        raise OrthonavError(f"landmark error: expected two (N, 3) arrays, got {est.shape}, {tru.shape}")
    return np.linalg.norm(est - tru, axis=1) if len(est) else np.zeros(0)

"""Calibration of a predicted probability of being right: does P(right) = 0.97 come true 97 %
of the time? Used on the acceptance model's held-out half when it is fitted, and on the
benchmark's own frames each time the cascade is benchmarked."""

from __future__ import annotations

import numpy as np

from orthonav.errors import OrthonavError

# Deciles of the accepted fixes' P, no bin under MIN_PER_BIN fixes (fewer bins then), each
# within TOLERANCE of its observed rate (the 5 points) or not.
CALIBRATION_BINS = 10
CALIBRATION_MIN_PER_BIN = 20
CALIBRATION_TOLERANCE = 0.05
WILSON_Z = 1.96  # a 95 % interval of a bin's observed rate


def calibration_table(
    p: np.ndarray,
    right: np.ndarray,
    bins: int = CALIBRATION_BINS,
    min_per_bin: int = CALIBRATION_MIN_PER_BIN,
    tolerance: float = CALIBRATION_TOLERANCE,
) -> dict:
    """Predicted P(right) against the observed rate of right poses, in equal-count bins of P.

    Equal counts, not equal widths: the accepted fixes all lie above the threshold (0.95), where
    ten equal-width bins would put them in one. With few fixes, fewer bins of ``min_per_bin``
    at least: a bin of 5 fixes can only be right at 0, 20, 40 ... %. Each bin gives its P range,
    mean P, observed rate with a 95 % Wilson interval (how far chance alone moves it: one
    wrong fix in 30 is 3 points) and whether the two are within ``tolerance``.
    """
    p, right = np.asarray(p, float), np.asarray(right, float)
    if len(p) != len(right):
        raise OrthonavError(f"calibration: {len(p)} probabilities for {len(right)} outcomes")
    count = min(bins, len(p) // min_per_bin) or min(len(p), 1)
    order = np.argsort(p, kind="stable")
    splits = np.array_split(order, count) if count else []
    rows = [_calibration_bin(p[idx], right[idx], tolerance) for idx in splits]
    return {
        "fixes": len(p),
        "tolerance": tolerance,
        "bins": rows,
        "within_tolerance": bool(rows) and all(row["within"] for row in rows),
    }


def _calibration_bin(p: np.ndarray, right: np.ndarray, tolerance: float) -> dict:
    n, predicted, observed = len(p), float(p.mean()), float(right.mean())
    # Wilson score interval: stays inside [0, 1] and is honest at rates near 1 with small n.
    z2 = WILSON_Z**2
    centre = (observed + z2 / (2 * n)) / (1 + z2 / n)
    half = WILSON_Z * np.sqrt(observed * (1 - observed) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return {
        "p_low": round(float(p.min()), 4),
        "p_high": round(float(p.max()), 4),
        "fixes": n,
        "predicted": round(predicted, 4),
        "observed": round(observed, 4),
        "observed_low": round(float(centre - half), 4),
        "observed_high": round(float(centre + half), 4),
        "gap": round(observed - predicted, 4),
        "within": bool(abs(observed - predicted) <= tolerance),
    }

"""Whether the accepted fixes' sigma tells the truth: the share within 1, 2 and 3 sigma, the mean
NEES, and how the sigma compares with the errors' 95th percentile (an over-cautious sigma costs
the autopilot too: it stops weighing the fixes).

The same figures in ``bench real`` and ``bench localize``, and the same targets for both.
"""

from __future__ import annotations

import numpy as np

from orthonav.types import Fix

# Every dataset and variant: this share of the accepted fixes within their 3 sigma, a mean NEES
# (2 ideal, for a horizontal position) no larger, and the median sigma at most this many times
# the 95th-percentile error.
COVERAGE_3SIGMA_TARGET = 0.9
MEAN_NEES_TARGET = 4.0
SIGMA_OVER_P95_TARGET = 3.0


def nees(fix: Fix, error_enu_m: np.ndarray) -> float:
    """The fix's normalized estimation error squared: the error through its covariance."""
    error = np.asarray(error_enu_m, float)
    return float(error @ np.linalg.solve(fix.covariance_enu_m2, error))


def sigma_coverage(errors_m: list[float], sigmas_m: list[float], nees_values: list[float]) -> dict:
    """The coverage figures of the accepted fixes (None where there are none)."""
    e, s, q = (np.asarray(v, float) for v in (errors_m, sigmas_m, nees_values))
    if not len(e):
        keys = ("within_1sigma", "within_2sigma", "within_3sigma", "mean_nees", "p95_m", "sigma_over_p95")
        return dict.fromkeys(keys)
    p95 = float(np.percentile(e, 95))
    return {
        **{f"within_{k}sigma": round(float(np.mean(e <= k * s)), 3) for k in (1, 2, 3)},
        "mean_nees": round(float(np.mean(q)), 2) if len(q) else None,
        "p95_m": round(p95, 2),
        "sigma_over_p95": round(float(np.median(s)) / max(p95, 1e-3), 2),
    }


def sigma_targets(row: dict) -> bool | None:
    """Whether a row's accepted fixes meet the three sigma targets (None: no fixes)."""
    if row.get("within_3sigma") is None:
        return None
    return (
        row["within_3sigma"] >= COVERAGE_3SIGMA_TARGET
        and (row["mean_nees"] or 0.0) <= MEAN_NEES_TARGET
        and row["sigma_over_p95"] <= SIGMA_OVER_P95_TARGET
    )

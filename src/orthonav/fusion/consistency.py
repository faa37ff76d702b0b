"""Whether a navigation filter's uncertainty holds: how often its true error leaves its own
sigma bounds, and its normalized estimation error squared (NEES).

A filter that says 5 m where it is 30 m off lets the autopilot trust a wrong position; its
error plot alone does not show it. For a consistent filter the 2-D NEES averages 2 (a
chi-squared variable with two degrees of freedom), and the error stays within 3 sigma of the
worst direction nearly all the time.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

CONSISTENT_NEES = 2.0  # the mean of a chi-squared variable with 2 degrees of freedom
SIGMA_BOUNDS = (1, 2, 3)


def nees(error_enu_m: Sequence[float], covariance_enu_m2: np.ndarray) -> float | None:
    """``e^T P^-1 e`` of the (east, north) error under the filter's 2x2 covariance; None where
    the covariance is not a finite, invertible one (a lost filter)."""
    cov = np.asarray(covariance_enu_m2, float)
    if not np.all(np.isfinite(cov)):
        return None
    try:
        solved = np.linalg.solve(cov, np.asarray(error_enu_m, float))
    except np.linalg.LinAlgError:
        return None
    return float(np.dot(error_enu_m, solved))


def consistency(
    errors_m: Sequence[float], sigmas_m: Sequence[float], nees_values: Sequence[float | None]
) -> dict[str, float | None]:
    """Summary keys: the share of samples whose error exceeds k times the filter's 1-sigma (of
    its worst direction), k in :data:`SIGMA_BOUNDS`, and the mean NEES (consistent: 2). Samples
    are taken at a fixed rate, so a share of samples is a share of time."""
    errors, sigmas = np.asarray(errors_m, float), np.asarray(sigmas_m, float)
    known = np.isfinite(errors) & np.isfinite(sigmas)
    shares: dict[str, float | None] = {
        f"nav_beyond_{k}sigma_share": round(float(np.mean(errors[known] > k * sigmas[known])), 3)
        if known.any()
        else None
        for k in SIGMA_BOUNDS
    }
    measured = [v for v in nees_values if v is not None and np.isfinite(v)]
    shares["nav_nees_mean"] = round(float(np.mean(measured)), 2) if measured else None
    return shares


def consistency_line(summary: dict) -> str:
    """One line for a picture: the time outside 1/2/3 sigma and the mean NEES ('' if unknown)."""
    shares = [summary.get(f"nav_beyond_{k}sigma_share") for k in SIGMA_BOUNDS]
    if any(share is None for share in shares):
        return ""
    bounds = ", ".join(str(k) for k in SIGMA_BOUNDS)
    line = f"time beyond the filter's {bounds} sigma: {', '.join(f'{share:.0%}' for share in shares)}"
    mean = summary.get("nav_nees_mean")
    if mean is not None:
        line += f"; mean NEES {mean:.1f} ({CONSISTENT_NEES:.0f} for a consistent filter)"
    return line

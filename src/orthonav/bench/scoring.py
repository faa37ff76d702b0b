"""How every benchmark scores its fixes, so that a figure of the same name means the same in each.

A fix's horizontal error against the truth; rates as shares of all frames (fixed, within X m,
wrong over X m); medians and quantiles of errors and of times; and whether the accepted fixes'
sigma tells the truth: the share within 1, 2 and 3 sigma, the mean NEES, and how the sigma
compares with the errors' 95th percentile (an over-cautious sigma costs the autopilot too: it
stops weighing the fixes). The sigma targets are the same for every benchmark.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from orthonav.geo import LocalFrame, distance_m
from orthonav.types import Fix

# Every dataset and variant: this share of the accepted fixes within their 3 sigma, a mean NEES
# (2 ideal, for a horizontal position) no larger, and the median sigma at most this many times
# the 95th-percentile error.
COVERAGE_3SIGMA_TARGET = 0.9
MEAN_NEES_TARGET = 4.0
SIGMA_OVER_P95_TARGET = 3.0
CHI2_2DOF_95 = 5.991  # 95 % of a chi-square with 2 degrees of freedom
SIGMA_KEYS = ("within_1sigma", "within_2sigma", "within_3sigma", "mean_nees", "p95_m", "sigma_over_p95")
# The tails of a time: the typical frame, the ones a deadline must allow for, the worst.
TAIL_PERCENTILES = {"p50": 50, "p95": 95, "p99": 99, "max": 100}


def error_m(truth_lat: float, truth_lon: float, lat: float, lon: float) -> float:
    """The horizontal distance of a position from the truth (m)."""
    return float(distance_m(truth_lat, truth_lon, lat, lon))


def error_enu_m(frame: LocalFrame, truth: tuple[float, float], position: tuple[float, float]) -> np.ndarray:
    """The position's error (east, north) in ``frame``: what its covariance is tested against."""
    return np.subtract(frame.to_enu(*position), frame.to_enu(*truth))


def nees(fix: Fix, error_enu: np.ndarray) -> float:
    """The fix's normalized estimation error squared: the error through its covariance (a
    chi-square of 2 dof where the covariance is honest)."""
    error = np.asarray(error_enu, float)
    return float(error @ np.linalg.solve(fix.covariance_enu_m2, error))


def rate(count: int, n: int, digits: int = 3) -> float:
    """``count`` as a share of ``n`` frames (0 where there are none): a rate over every frame,
    not only over the fixed ones."""
    return round(count / n, digits) if n else 0.0


def share(hits: Iterable[bool], n: int, digits: int = 3) -> float:
    """How many of ``hits`` are true, as a share of ``n`` frames."""
    return rate(int(np.sum(np.fromiter(hits, bool))), n, digits)


def within_rates(errors: np.ndarray, n: int, radii_m: Iterable[float], prefix: str = "within_") -> dict:
    """``{prefix}{r}m``: the share of ``n`` frames fixed within each radius."""
    e = np.asarray(errors, float)
    return {f"{prefix}{r:g}m": share(e <= r, n) for r in radii_m}


def wrong_rate(errors: np.ndarray, n: int, over_m: float) -> float:
    """The share of ``n`` frames fixed more than ``over_m`` from the truth."""
    return share(np.asarray(errors, float) > over_m, n)


def percentile(values: Iterable[float], q: float, digits: int = 1) -> float | None:
    """The ``q``-th percentile (None where there are no values)."""
    v = np.asarray(list(values), float)
    return round(float(np.percentile(v, q)), digits) if len(v) else None


def median(values: Iterable[float | None], digits: int | None = 1) -> float | None:
    """The median of the values present (None where none is; unrounded with ``digits`` None)."""
    present = [v for v in values if v is not None]
    if not present:
        return None
    value = float(np.median(present))
    return value if digits is None else round(value, digits)


def mean(values: Iterable[float], digits: int = 1) -> float | None:
    """The mean (None where there are no values)."""
    v = np.asarray(list(values), float)
    return round(float(np.mean(v)), digits) if len(v) else None


def quantiles(values: Iterable[float], digits: int = 1) -> dict[str, float] | None:
    """p50 / p95 / p99 / max (None where there are no values)."""
    v = list(values)
    return {k: percentile(v, q, digits) for k, q in TAIL_PERCENTILES.items()} if v else None


def stage_tails(timings: list[Mapping[str, float]], stages: Iterable[str]) -> dict[str, dict[str, float]]:
    """Each stage's quantiles over the frames that reached it (stages no frame reached left out)."""
    out = {}
    for stage in stages:
        tails = quantiles(t[stage] for t in timings if stage in t)
        if tails is not None:
            out[stage] = tails
    return out


def mean_per_frame(timings: list[Mapping[str, float]]) -> dict[str, float]:
    """Every timing's mean over all frames, 0 where a frame did not reach that stage: unlike
    the medians, these add up to the mean total (the rest is what no stage timed)."""
    keys = dict.fromkeys(k for t in timings for k in t)
    return {k: round(sum(t.get(k, 0.0) for t in timings) / len(timings), 1) for k in keys} if timings else {}


def sigma_coverage(errors_m: list[float], sigmas_m: list[float], nees_values: list[float]) -> dict:
    """The coverage figures of the accepted fixes (None where there are none)."""
    e, s, q = (np.asarray(v, float) for v in (errors_m, sigmas_m, nees_values))
    if not len(e):
        return dict.fromkeys(SIGMA_KEYS)
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

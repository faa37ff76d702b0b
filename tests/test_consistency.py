"""The filter's consistency measures: the time its error spends beyond its own sigma, and NEES."""

from __future__ import annotations

import numpy as np
import pytest

from orthonav.fusion.consistency import consistency, consistency_line, nees


def test_nees_weighs_the_error_by_the_covariance() -> None:
    assert nees((3.0, 4.0), np.diag([9.0, 16.0])) == pytest.approx(2.0)
    assert nees((3.0, 0.0), np.diag([1.0, 100.0])) == pytest.approx(9.0)
    assert nees((1.0, 1.0), np.full((2, 2), np.inf)) is None  # a lost filter has none
    assert nees((1.0, 1.0), np.zeros((2, 2))) is None


def test_shares_beyond_each_sigma_and_the_mean_nees() -> None:
    summary = consistency([1.0, 3.0, 5.0, 7.0], [2.0] * 4, [0.25, 2.25, None, 12.25])
    assert summary == {
        "nav_beyond_1sigma_share": 0.75,
        "nav_beyond_2sigma_share": 0.5,
        "nav_beyond_3sigma_share": 0.25,
        "nav_nees_mean": pytest.approx(4.92, abs=0.01),
    }
    line = consistency_line(summary)
    shares = "time beyond the filter's 1, 2, 3 sigma: 75%, 50%, 25%"
    assert line == f"{shares}; mean NEES 4.9 (2 for a consistent filter)"
    empty = consistency([], [], [])
    assert empty["nav_nees_mean"] is None and consistency_line(empty) == ""

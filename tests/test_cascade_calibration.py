"""Calibration of the cascade's acceptance: predicted P(right) against the observed rate of right
poses in equal-count bins, on scores whose answer is known, and from ``bench acceptance`` on
real NAIP frames (its JSON, its table and its reliability diagram)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import naip_path
from typer.testing import CliRunner

from orthonav.bench.acceptance import TEST_HALF, reliability_png
from orthonav.bench.calibration import calibration_table
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.localize import AcceptanceModel
from orthonav.localize.acceptance import SHIPPED_ACCEPTANCE
from orthonav.models import shipped_model_path
from orthonav.viz.calibration import plot_reliability

# Ten groups of 30 fixes around these P, exactly round(P x 30) of each right.
LEVELS = (0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.96, 0.98, 1.0)
PER_LEVEL = 30


def _calibrated(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Scores whose groups are right exactly as often as they say, shuffled."""
    p = np.concatenate([np.clip(level + rng.uniform(-0.004, 0.004, PER_LEVEL), 0, 1) for level in LEVELS])
    right = np.concatenate([np.arange(PER_LEVEL) < round(level * PER_LEVEL) for level in LEVELS])
    order = rng.permutation(len(p))
    return p[order], right[order].astype(float)


def test_calibrated_scores_give_deciles_each_within_five_points() -> None:
    p, right = _calibrated(np.random.default_rng(0))
    table = calibration_table(p, right)
    assert table["fixes"] == 300 and len(table["bins"]) == 10 and table["within_tolerance"]
    for level, row in zip(LEVELS, table["bins"], strict=True):
        assert row["fixes"] == PER_LEVEL and row["within"]
        assert row["predicted"] == pytest.approx(level, abs=0.005)
        assert row["observed"] == pytest.approx(round(level * PER_LEVEL) / PER_LEVEL, abs=1e-4)
        assert row["observed_low"] <= row["observed"] <= row["observed_high"]
    # Wilson's interval of 30 right out of 30: 30 / (30 + 1.96^2), not the degenerate [1, 1].
    assert table["bins"][-1]["observed_low"] == pytest.approx(30 / (30 + 1.96**2), abs=1e-4)


def test_overconfident_scores_miss_the_target_in_every_bin() -> None:
    """P 0.99 where 16 in 20 are right: 19 points too sure, in each of the five bins of 20."""
    p = np.linspace(0.985, 0.995, 100)
    right = (np.arange(100) % 5 != 0).astype(float)
    table = calibration_table(p, right)
    assert [row["fixes"] for row in table["bins"]] == [20] * 5
    assert not table["within_tolerance"] and not any(row["within"] for row in table["bins"])
    assert all(row["gap"] == pytest.approx(-0.19, abs=0.01) for row in table["bins"])


@pytest.mark.parametrize(("fixes", "bins"), [(45, 2), (19, 1), (7, 1), (0, 0)])
def test_few_fixes_make_fewer_equal_count_bins(fixes: int, bins: int) -> None:
    table = calibration_table(np.linspace(0.95, 1.0, fixes), np.ones(fixes))
    counts = [row["fixes"] for row in table["bins"]]
    assert len(counts) == bins and sum(counts) == fixes and (not counts or max(counts) - min(counts) <= 1)
    assert table["within_tolerance"] == (fixes > 0)  # no fixes: nothing shows the target is met
    with pytest.raises(OrthonavError, match="3 probabilities for 2 outcomes"):
        calibration_table(np.ones(3), np.ones(2))


def test_reliability_diagram_is_drawn(tmp_path: Path) -> None:
    table = calibration_table(*_calibrated(np.random.default_rng(1)))
    out = plot_reliability(table, tmp_path / "reliability.png", "synthetic")
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 400 and image.shape[1] > 800


def test_bench_acceptance_reports_calibration_on_the_held_out_half(tmp_path: Path) -> None:
    """A small real fit (2009 and 2020, a few frames): whatever the model, the table in its JSON
    counts exactly the held-out fixes it accepts, and the right ones among them."""
    data = tmp_path / "naip"
    data.mkdir()
    for year in ("20090818", "20200831"):
        (data / naip_path(year).name).symlink_to(naip_path(year))
    out = tmp_path / "model.json"
    args = ["bench", "acceptance", "--data", str(data), "--frames", "10", "--same-date-frames", "3"]
    result = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "calibration: the fixes accepted on the east half" in result.output
    assert "bins within 5 points" in result.output
    written = json.loads(out.read_text())
    model = AcceptanceModel.from_dict(written)
    records = json.loads(out.with_name("model_records.json").read_text())["records"]
    held_out = [r for r in records if r["half"] == TEST_HALF and r["pose"]]
    # Every evidence is measured for the fit to choose from: the blocks too, which no model
    # after the gradient correlation weighs (so its cascades do not measure them in flight).
    assert any(r["quality"]["verify_blocks_at_pose"] > 0.0 for r in records if r["pose"])
    p = np.array([model.probability(r["quality"]) for r in held_out])
    accepted = [r for r, pi in zip(held_out, p, strict=True) if pi >= model.threshold]
    bins = written["calibration"]["bins"]
    assert sum(row["fixes"] for row in bins) == len(accepted) > 0
    right = sum(r["error_m"] <= written["config"]["false_m"] for r in accepted)
    assert sum(row["observed"] * row["fixes"] for row in bins) == pytest.approx(right, abs=1e-3)
    assert all(row["within"] == (abs(row["gap"]) <= 0.05) for row in bins)
    assert all(a["p_high"] <= b["p_low"] for a, b in itertools.pairwise(bins))
    assert cv2.imread(str(reliability_png(out))) is not None

    # The shipped model scored on the same records (no frames run), as the fit was scored.
    shipped = shipped_model_path(SHIPPED_ACCEPTANCE)
    scored_out = tmp_path / "shipped_scored.json"
    args = ["bench", "acceptance", "--refit", "--records", str(out.with_name("model_records.json"))]
    result = CliRunner().invoke(
        app, [*args, "--frames", "10", "--score", str(shipped), "--out", str(scored_out)]
    )
    assert result.exit_code == 0, result.output
    assert f"scored: {shipped}" in result.output
    scored = json.loads(scored_out.read_text())
    reference = AcceptanceModel.load(shipped)
    assert scored["coef"] == pytest.approx(list(reference.coef), abs=1e-6)
    p = np.array([reference.probability(r["quality"]) for r in held_out])
    accepted = p >= reference.threshold
    assert sum(row["fixes"] for row in scored["calibration"]["bins"]) == int(accepted.sum())
    assert scored["data"]["frames"] == len(records)
    assert not (tmp_path / "shipped_scored_records.json").exists()

    # A refit keeps the records' settings: one given that they were not collected with is refused.
    records_json = str(out.with_name("model_records.json"))
    for option, value, collected in (
        ("--coarse-backbone", "trained", "'gradient'"),
        ("--frames", "50", "10"),
    ):
        args = ["bench", "acceptance", "--refit", option, value, "--records", records_json]
        result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "refit.json")])
        assert isinstance(result.exception, OrthonavError), result.output
        assert f"collected with {option[2:].replace('-', '_')}={collected}, not " in str(result.exception)
    assert not (tmp_path / "refit.json").exists()

    # Evidence left out by name is not weighed; a name that is not evidence is refused.
    args = ["bench", "acceptance", "--refit", "--records", records_json, "--out", str(tmp_path / "less.json")]
    result = CliRunner().invoke(app, [*args, "--without", "rmse_px, verify_relative_margin"])
    assert result.exit_code == 0, result.output
    less = json.loads((tmp_path / "less.json").read_text())["features"]
    assert set(written["features"]) - set(less) == {"rmse_px", "verify_relative_margin"}
    result = CliRunner().invoke(app, [*args, "--without", "trunk_margin"])
    assert isinstance(result.exception, OrthonavError), result.output
    assert "--without: ['trunk_margin'] is not evidence of this model" in str(result.exception)

    # Records collected without the trunk's agreement cannot fit a model that weighs it.
    args = ["bench", "acceptance", "--refit", "--trunk", "--records", records_json]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "trunk.json")])
    assert isinstance(result.exception, OrthonavError), result.output
    assert "collected without the trunk's agreement" in str(result.exception)

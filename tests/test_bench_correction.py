"""The INS-correction benchmark on real NAIP imagery, cut down to two dates and a few frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import SHARED_DATA, naip_path
from typer.testing import CliRunner

from orthonav.bench.correction import CorrectionBenchConfig, run_correction_benchmark
from orthonav.cli.main import app
from orthonav.errors import OrthonavError

DATES = ("20150926", "20200831")


@pytest.fixture(scope="module")
def two_dates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data folder of two NAIP dates, linked (not copied) from ../shared/data."""
    folder = tmp_path_factory.mktemp("naip-correction")
    for date in DATES:
        source = naip_path(date)
        (folder / source.name).symlink_to(source)
    return folder


def _config(**changes) -> CorrectionBenchConfig:
    base = {
        "frames": 2,
        "eval_dates": DATES,
        "backbones": ("gradient",),
        "sizes": (224,),
        "initial_errors_m": (15.0, 100.0),
        "keypoint_features": ("orb",),
        "route_length_m": 1500.0,
    }
    return CorrectionBenchConfig(**{**base, **changes})


def test_rows_route_targets_and_outputs(two_dates: Path, tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    result = run_correction_benchmark(two_dates, None, out, _config(), progress=False)

    # (gradient + orb keypoints) x 2 initial errors; every row pools both ordered date pairs.
    assert {(r["method"], r["initial_m"]) for r in result["rows"]} == {
        (m, e) for m in ("gradient", "keypoints:orb") for e in (15.0, 100.0)
    }
    for row in result["rows"]:
        assert row["n"] == 4
        assert 0.0 <= row["false_rate"] <= row["fix_rate"] <= 1.0
    gradient = [r for r in result["rows"] if r["method"] == "gradient"]
    # Dense correlation recovers most cross-date frames from 15 m and from 100 m.
    assert all(r["within_2px"] >= 0.5 for r in gradient), gradient
    # The same frames went through both methods: one record per frame, error and method.
    assert len(result["records"]) == 2 * 2 * 2 * 2
    route = result["route"]["stats"]
    assert route["corrected (gradient)"]["corrections_accepted"] > 0
    assert route["corrected (gradient)"]["mean_m"] < route["INS alone"]["mean_m"]
    assert any("100 ms" in name for name in result["targets"])
    written = json.loads(out.read_text())
    assert written["config"]["eval_dates"] == list(DATES)
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert out.with_name("bench_route.png").stat().st_size > 10_000


def test_neon_cross_season_rows(two_dates: Path, tmp_path: Path) -> None:
    neon = SHARED_DATA / "neon_sjer"
    if not (neon / "2017").is_dir():
        pytest.skip(f"real NEON data not available: {neon} is missing")
    plots = tmp_path / "neon"
    for year in ("2017", "2018"):
        (plots / year).mkdir(parents=True)
        for name in ("SJER_002.tif", "SJER_004.tif"):
            (plots / year / name).symlink_to(neon / year / name)
    config = _config(keypoint_features=(), initial_errors_m=(15.0,), neon_errors_m=(2.0,))
    result = run_correction_benchmark(two_dates, plots, tmp_path / "b.json", config, progress=False)

    rows = result["neon"]["rows"]
    assert result["neon"]["plots"] == 2
    assert [(r["method"], r["initial_m"], r["n"]) for r in rows] == [("gradient", 2.0, 4)]
    assert any(name.startswith("NEON") for name in result["targets"])


def test_bad_configuration_is_a_clear_error(two_dates: Path, tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="at least two"):
        _config(eval_dates=("20150926",))
    with pytest.raises(OrthonavError, match="match date '19990101'"):
        run_correction_benchmark(
            two_dates, None, tmp_path / "b.json", _config(eval_dates=("20150926", "19990101"))
        )
    runner = CliRunner()
    result = runner.invoke(app, ["bench", "correction", "--data", str(two_dates), "--sizes", "big"])
    assert result.exit_code != 0
    assert "--sizes" in str(result.exception)

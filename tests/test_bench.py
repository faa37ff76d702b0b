"""The localization benchmark on real NAIP imagery, cut down to two years and a few frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import naip_path
from typer.testing import CliRunner

from orthonav.bench import LocalizeBenchConfig, run_localize_benchmark
from orthonav.cli.main import app
from orthonav.errors import OrthonavError


@pytest.fixture(scope="module")
def two_years(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data folder of two NAIP years, linked (not copied) from ../shared/data."""
    folder = tmp_path_factory.mktemp("naip2")
    for year in ("20180716", "20200831"):
        source = naip_path(year)
        (folder / source.name).symlink_to(source)
    return folder


def test_benchmark_rows_metrics_and_outputs(two_years: Path, tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    config = LocalizeBenchConfig(frames=3, features=("orb", "sift"))
    result = run_localize_benchmark(two_years, None, out, config, progress=False)

    # 2 backends x (2 same-date + 2 ordered cross-date pairs x 2 prior modes) = 12 rows.
    assert len(result["rows"]) == 12
    assert {r["features"] for r in result["rows"]} == {"orb", "sift"}
    same = [r for r in result["rows"] if r["condition"] == "same-date"]
    assert len(same) == 4
    for row in same:
        assert row["fix_rate"] >= 2 / 3, row
        assert row["centre_within_2px"] >= 2 / 3, row
        assert row["total_ms"] > 0
    assert all(r["false_fix_rate"] == 0.0 for r in result["rows"]), "a cross-date frame was fixed > 50 m off"
    assert json.loads(out.read_text())["config"]["frames"] == 3
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(result["summary"]["targets"]) == {
        "orb same-date centre within 2 map px >= 98 %",
        "orb same-date median time <= 50 ms",
        "false-fix rate < 1 % everywhere",
    }


def test_unknown_backend_is_refused_before_any_work() -> None:
    with pytest.raises(OrthonavError, match="bench features \\['nope'\\]"):
        LocalizeBenchConfig(features=("orb", "nope"))


def test_cli_prints_both_tables(two_years: Path, tmp_path: Path) -> None:
    out = tmp_path / "cli.json"
    result = CliRunner().invoke(
        app,
        [
            "bench",
            "localize",
            "--data",
            str(two_years),
            "--highres",
            str(tmp_path / "none"),
            "--frames",
            "2",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "pooled by backend and condition" in result.output
    assert "orb: same-date / prior" in result.output
    assert out.exists()

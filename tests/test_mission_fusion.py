"""Missions flown with INS + visual fixes + filter: GNSS loss, drift, latency, honest covariance.

The real case: map and frames from the real NAIP 2020 orthophoto (the thesis's same-date
setting; frames with photometric changes), GNSS lost from the start, a consumer-grade IMU;
the same mission flown by the INS alone. Cross-date missions, where ORB does not match this
rural imagery and learned backends do, are measured by ``orthonav bench mission``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import NAIP_ALT_M, naip_path

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.mapdb import MapPackage
from orthonav.sim import MissionConfig, run_mission


def _read(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _naip_mission(package: MapPackage, **changes) -> MissionConfig:
    lat, lon = package.grid.pixel_to_latlon(
        [0.25 * package.grid.width, 0.75 * package.grid.width],
        [0.25 * package.grid.height, 0.75 * package.grid.height],
    )
    config = MissionConfig(
        float(lat[0]),
        float(lon[0]),
        float(lat[1]),
        float(lon[1]),
        alt_agl_m=NAIP_ALT_M,
        seed=3,
        max_time_s=400.0,
    )
    return dataclasses.replace(config, **changes)


@pytest.fixture(scope="module")
def naip_runs(
    naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera, tmp_path_factory
) -> dict[str, Path]:
    """The same mission with visual fixes and by the INS alone."""
    runs = {}
    for name, visual in (("visual", True), ("ins", False)):
        run_dir = tmp_path_factory.mktemp(f"mission_{name}") / "run"
        config = _naip_mission(naip_map, visual_fixes=visual)
        run_mission(naip_map, naip_raster, camera, config, run_dir, progress=False)
        runs[name] = run_dir
    return runs


def test_mission_arrives_on_fused_fixes_where_the_ins_alone_drifts(naip_runs) -> None:
    visual = json.loads((naip_runs["visual"] / "summary.json").read_text())
    ins = json.loads((naip_runs["ins"] / "summary.json").read_text())
    print(f"\nvisual: {visual}\nINS alone: {ins}")
    assert visual["arrived"] and visual["arrived_true"]
    assert visual["fused_rate"] >= 0.6
    assert visual["nav_error_mean_m"] < 25.0
    # The INS alone starts in the same 100 m start zone and only drifts from there.
    assert ins["fused_rate"] == 0.0
    assert ins["nav_error_max_m"] > 3 * visual["nav_error_mean_m"]
    assert ins["nav_error_mean_m"] > visual["nav_error_mean_m"]


@pytest.mark.parametrize("name", ["visual", "ins"])
def test_filter_covariance_is_honest_with_and_without_fixes(naip_runs, name: str) -> None:
    """The true error stays within 3 sigma nearly always: the covariance is not a decoration."""
    nav = _read(naip_runs[name] / "nav.jsonl")
    inside = np.mean([r["nav_error_m"] <= 3.0 * r["nav_sigma_m"] for r in nav])
    assert inside >= 0.9, f"{name}: only {inside:.0%} of states within 3 sigma"
    if name == "ins":
        sigmas = [r["nav_sigma_m"] for r in nav]
        assert sigmas[-1] > sigmas[len(sigmas) // 4]  # without fixes the uncertainty grows


@pytest.mark.parametrize("name", ["visual", "ins"])
def test_summary_says_how_often_the_filter_left_its_sigma_and_its_nees(naip_runs, name: str) -> None:
    """summary.json reports the time outside 1, 2 and 3 sigma and the mean NEES, as measured from
    nav.jsonl; the trajectory picture says it under the error plot's title."""
    summary = json.loads((naip_runs[name] / "summary.json").read_text())
    nav = _read(naip_runs[name] / "nav.jsonl")
    for k in (1, 2, 3):
        outside = np.mean([r["nav_error_m"] > k * r["nav_sigma_m"] for r in nav])
        assert summary[f"nav_beyond_{k}sigma_share"] == pytest.approx(outside, abs=1e-3)
    nees = [r["nav_nees"] for r in nav if r["nav_nees"] is not None]
    assert len(nees) > 0.9 * len(nav)
    assert summary["nav_nees_mean"] == pytest.approx(np.mean(nees), abs=0.01)
    # NEES weighs the error by the whole covariance, the shares by its worst direction only.
    for r in (r for r in nav if r["nav_nees"] is not None):
        assert r["nav_nees"] >= 0.95 * (r["nav_error_m"] / r["nav_sigma_m"]) ** 2, r


def test_navigation_log_is_steady_and_fixes_are_fused_at_capture_time(naip_runs) -> None:
    nav = _read(naip_runs["visual"] / "nav.jsonl")
    assert np.allclose(np.diff([r["time_s"] for r in nav]), 1.0, atol=1e-6)
    steps = _read(naip_runs["visual"] / "steps.jsonl")
    config = MissionConfig(**json.loads((naip_runs["visual"] / "config.json").read_text())["mission"])
    for step in steps:
        assert step["filter"]["latency_s"] == pytest.approx(config.fix_latency_s, abs=1e-6)
        assert step["nav_time_s"] == pytest.approx(step["time_s"] + config.fix_latency_s, abs=1e-6)
        if not step["accepted"]:
            assert not step["fused"] and step["filter"]["reason"].startswith("localizer:")


def test_gnss_aids_the_filter_until_it_is_lost(
    terrain_map: MapPackage, terrain_raster, camera, tmp_path
) -> None:
    lat, lon = terrain_map.grid.pixel_to_latlon(
        [0.2 * terrain_map.grid.width, 0.8 * terrain_map.grid.width],
        [0.2 * terrain_map.grid.height, 0.8 * terrain_map.grid.height],
    )
    config = MissionConfig(
        float(lat[0]), float(lon[0]), float(lat[1]), float(lon[1]), gnss_loss_s=20.0, seed=1, imu="consumer"
    )
    run_mission(terrain_map, terrain_raster, camera, config, tmp_path, progress=False)
    nav = _read(tmp_path / "nav.jsonl")
    steps = _read(tmp_path / "steps.jsonl")
    before = [r for r in nav if r["time_s"] < config.gnss_loss_s]
    assert len(before) >= 19 and max(r["nav_error_m"] for r in before) < 4 * config.gnss_sigma_m
    assert max(r["nav_sigma_m"] for r in before[5:]) < 2 * config.gnss_sigma_m
    # Frames are taken only once GNSS is gone, every step_s from then on.
    assert steps[0]["time_s"] == pytest.approx(config.gnss_loss_s)
    assert np.allclose(np.diff([s["time_s"] for s in steps]), config.step_s)


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"fix_latency_s": 5.0}, "fix_latency_s"),
        ({"imu": "navy-grade"}, "navy-grade"),
        ({"gnss_loss_s": -1.0}, "gnss_loss_s"),
        ({"ins_rate_hz": 0.0}, "ins_rate_hz"),
    ],
)
def test_bad_mission_options_are_named(changes: dict, expected: str) -> None:
    with pytest.raises(OrthonavError, match=expected):
        MissionConfig(47.0, -99.0, 47.01, -99.01, **changes)


def test_cross_date_mission_on_dense_correlation_fixes(
    naip_map: MapPackage, naip_raster, camera, tmp_path
) -> None:
    """Frames from 2015 over the 2020 map, where ORB does not match: seed B's gradient correlation
    around the filter's estimate feeds the same filter, and the vehicle really arrives."""
    corrector = Corrector(naip_raster, camera, CorrectionConfig(backbone="gradient"))
    with GeoRaster(naip_path("20150926")) as frames:
        run_mission(
            naip_map, frames, camera, _naip_mission(naip_map), tmp_path, progress=False, fix_source=corrector
        )
    summary = json.loads((tmp_path / "summary.json").read_text())
    print(f"\ncorrelation, 2015 frames on the 2020 map: {summary}")
    assert summary["arrived"] and summary["arrived_true"]
    assert summary["fused_rate"] >= 0.5 and summary["nav_error_mean_m"] < 30.0
    steps = _read(tmp_path / "steps.jsonl")
    method = json.loads((tmp_path / "config.json").read_text())["fix_source"]
    assert method.startswith("correction:gradient")
    assert {s["fix"]["method"] for s in steps if s["accepted"]} == {method}


class _CtrlCAfter:
    """A fix source that lets ``n`` frames through, then acts as if Ctrl-C came mid-frame."""

    method = "keypoints"

    def __init__(self, inner, n: int) -> None:
        self.inner, self.n, self.calls = inner, n, 0

    def localize(self, frame, prior, candidates=None):
        self.calls += 1
        if self.calls > self.n:
            raise KeyboardInterrupt
        return self.inner.localize(frame, prior, candidates)


def test_ctrl_c_mid_mission_keeps_every_finished_step(
    naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera, tmp_path: Path
) -> None:
    """The interrupted frame is dropped; the steps before it, the summary and the plot are written."""
    from orthonav.localize import Localizer
    from orthonav.sim.mission import INTERRUPTED

    source = _CtrlCAfter(Localizer(naip_map, camera), 3)
    result = run_mission(
        naip_map, naip_raster, camera, _naip_mission(naip_map), tmp_path, progress=False, fix_source=source
    )
    assert result.end_reason == INTERRUPTED and result.steps == 3
    assert len(_read(tmp_path / "steps.jsonl")) == 3
    assert json.loads((tmp_path / "summary.json").read_text())["end_reason"] == "interrupted"
    assert (tmp_path / "trajectory.png").stat().st_size > 10_000

"""The cascade as the default fix source of every command: ``orthonav localize``, ``simulate``
and ``fly`` run it where the map's orthophoto is there, its fixes are fused, and where the
orthophoto is gone (or another raster lies at its path) they fall back to keypoints and say why,
once.

Frames from 2015 over the 2020 map: across dates, where the keypoints alone rarely match."""

from __future__ import annotations

import json
import shutil
import threading
from contextlib import ExitStack
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import CAMERA, NAIP_ALT_M, naip_path, rendered_frames, write_naip_crop
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import (
    Cascade,
    Fallback,
    Localizer,
    open_fix_source,
    open_fix_sources,
    warm_up,
    warm_up_maps,
)
from orthonav.mapdb import MapPackage

FRAMES_YEAR = "20150926"
WRONG_M = 25.0
runner = CliRunner()


def _read(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _cascades(source: object) -> list[Cascade]:
    """Every cascade of a fix source, in the order asked (chains of chains flattened)."""
    if isinstance(source, Fallback):
        return [cascade for each in source.sources for cascade in _cascades(each)]
    assert isinstance(source, Cascade), source
    return [source]


def _backbones(source: object) -> list[str]:
    return [cascade.coarse.corrector.config.backbone for cascade in _cascades(source)]


def _methods(fixes: list[dict]) -> set[str]:
    """The fixes' methods, without the chain's stage (``(cascade-orientation, fallback 2 of 2)``)."""
    return {fix["method"].split(" (")[0] for fix in fixes}


def _latlon(package: MapPackage, fx: float, fy: float) -> str:
    lat, lon = package.grid.pixel_to_latlon(fx * package.grid.width, fy * package.grid.height)
    return f"{float(lat)},{float(lon)}"


def _simulate(package: MapPackage, out: Path, *extra: str, max_time_s: float = 60.0):
    args = ["simulate", str(package.path), "--start", _latlon(package, 0.25, 0.25)]
    args += ["--target", _latlon(package, 0.75, 0.75), "--frames-from", str(naip_path(FRAMES_YEAR))]
    args += ["--altitude", str(NAIP_ALT_M), "--max-time", str(max_time_s), "--seed", "3", "--out", str(out)]
    return runner.invoke(app, [*args, *extra])


@pytest.fixture()
def moved_map(naip_map: MapPackage, tmp_path: Path) -> MapPackage:
    """A copy of the NAIP map whose manifest records its orthophoto where there is none."""
    copy = tmp_path / "moved_map"
    shutil.copytree(naip_map.path, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["source"]["path"] = str(tmp_path / "elsewhere" / "ortho.tif")
    (copy / "manifest.json").write_text(json.dumps(manifest))
    return MapPackage(copy)


def test_localize_runs_the_cascade_by_default_and_names_it(naip_map: MapPackage, tmp_path: Path) -> None:
    """``orthonav localize`` with no ``--fix-source``: frames of another year than the map are
    localized by the cascade on the map's own keypoints (ORB here), the first line says so, and
    the table names, for each frame, the fix source that answered. Keypoints alone fix fewer."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rows = [["name", "lat", "lon", "altitude", "heading", "pitch", "roll", "sigma_m"]]
    with GeoRaster(naip_path(FRAMES_YEAR)) as frames_from:
        for i, (_, frame, p) in enumerate(rendered_frames(np.random.default_rng(5), frames_from, 4)):
            cv2.imwrite(str(folder / f"f{i}.png"), frame)
            rows.append([f"f{i}.png", p.lat, p.lon, p.alt_agl_m, p.heading_deg, p.pitch_deg, p.roll_deg, 200])
    priors = tmp_path / "priors.csv"
    priors.write_text("\n".join(",".join(str(v) for v in row) for row in rows) + "\n")
    args = ["localize", str(naip_map.path), str(folder), "--priors", str(priors)]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "default.jsonl")])
    assert result.exit_code == 0, result.output
    assert "fix source: cascade" in result.output and "cascade:orb" in result.stdout
    default = _read(tmp_path / "default.jsonl")
    assert _methods(default) == {"cascade:orb"}
    keypoints = runner.invoke(app, [*args, "--fix-source", "keypoints", "--out", str(tmp_path / "kp.jsonl")])
    assert keypoints.exit_code == 0 and "fix source: keypoints" in keypoints.output
    fixed = [sum(fix["accepted"] for fix in _read(tmp_path / name)) for name in ("default.jsonl", "kp.jsonl")]
    assert fixed[0] >= 2 and fixed[0] > fixed[1], fixed


def test_simulate_flies_on_cascade_fixes_by_default(naip_map: MapPackage, tmp_path: Path) -> None:
    result = _simulate(naip_map, tmp_path / "run")
    assert result.exit_code == 0, result.output
    assert "fix source: cascade" in result.output
    assert "warmed up in" in result.output and "centre (fixed)" in result.output, result.output
    # Where its parts run, said at start-up (the trunk's graph ships with orthonav).
    assert "cascade:orb: keypoints on OpenCV" in result.output, result.output
    assert "frame-to-map check by the trained CNN on ONNX Runtime (resnet18_naip.onnx)" in result.output
    assert "trained trunk" not in result.output, result.output  # a name only its authors know
    assert json.loads((tmp_path / "run" / "config.json").read_text())["fix_source"] == "cascade:orb"
    steps = _read(tmp_path / "run" / "steps.jsonl")
    assert _methods([s["fix"] for s in steps]) == {"cascade:orb"}
    fused = [s for s in steps if s["fused"]]
    assert len(fused) >= 0.75 * len(steps) >= 9, [s["reason"] for s in steps]
    assert all(s["error_m"] <= WRONG_M and 0.9 <= s["fix"]["quality"]["p_correct"] <= 1 for s in fused)


def test_without_its_orthophoto_the_default_falls_back_to_keypoints_and_says_why(
    moved_map: MapPackage, tmp_path: Path
) -> None:
    result = _simulate(moved_map, tmp_path / "run", max_time_s=10.0)
    assert result.exit_code == 0, result.output
    missing = moved_map.manifest["source"]["path"]
    said = [line for line in result.output.splitlines() if "keypoints instead of the cascade" in line]
    assert len(said) == 1 and missing in said[0], result.output
    assert "moved_map: not warmed up, its first frame will be slower" in result.output, result.output
    assert json.loads((tmp_path / "run" / "config.json").read_text())["fix_source"] == "keypoints"
    asked = _simulate(moved_map, tmp_path / "asked", "--fix-source", "cascade", max_time_s=10.0)
    assert isinstance(asked.exception, OrthonavError), asked.output
    assert "fix source cascade" in str(asked.exception) and missing in str(asked.exception)


def test_another_raster_at_the_orthophotos_path_is_not_taken_for_it(
    moved_map: MapPackage, tmp_path: Path
) -> None:
    """A crop of the map's own year lies where the orthophoto was: same area, not the same raster."""
    impostor = Path(moved_map.manifest["source"]["path"])
    impostor.parent.mkdir()
    write_naip_crop("20200831", (0, 0, 400, 300), impostor)
    with ExitStack() as stack:
        chosen = open_fix_source(stack, moved_map, CAMERA)
        assert isinstance(chosen.source, Localizer) and chosen.name == "keypoints"
        assert f"{impostor} is not the orthophoto" in chosen.fallback, chosen.fallback
        with pytest.raises(OrthonavError, match=r"fix source correlation: .* is not the orthophoto"):
            open_fix_source(stack, moved_map, CAMERA, "correlation")


@pytest.mark.parametrize("name", ["cascade", "correlation"])
def test_warm_up_fixes_the_maps_own_picture_at_its_centre(naip_map: MapPackage, name: str) -> None:
    """What a flight runs before its first frame: a real pass through the fix source, on a
    frame it must fix (the map's own picture), so a broken start-up shows before take-off."""
    with ExitStack() as stack:
        chosen = open_fix_source(stack, naip_map, CAMERA, name)
        assert chosen.raster is not None and chosen.raster.path == naip_map.source_path
        fix = warm_up(chosen.source, chosen.raster, CAMERA, NAIP_ALT_M)
        assert fix.accepted, fix.reason
        centre = chosen.raster.center_latlon
        assert distance_m(*centre, fix.pose.centre_lat, fix.pose.centre_lon) < 5.0
        assert open_fix_source(stack, naip_map, CAMERA, "keypoints").raster is None


def test_fix_source_names_are_checked(naip_map: MapPackage, tmp_path: Path) -> None:
    with ExitStack() as stack:
        default = open_fix_source(stack, naip_map, CAMERA)
        # The gradient correlation's cascade, then the orientation's where it rejects the frame.
        assert _backbones(default.source) == ["gradient", "orientation"] and not default.fallback
        assert "no global index" in default.note
        with pytest.raises(OrthonavError, match=r"fix source 'orb': expected one of cascade, keypoints"):
            open_fix_source(stack, naip_map, CAMERA, "orb")
    base = ["fly", "--map", str(naip_map.path), "--frames", str(tmp_path), "--duration", "1"]
    both = runner.invoke(app, [*base, "--correlate", str(naip_path("20200831")), "--fix-source", "cascade"])
    assert isinstance(both.exception, OrthonavError)
    assert "--correlate" in str(both.exception) and "--fix-source cascade" in str(both.exception)


def test_fly_fuses_cascade_fixes_by_default_and_keeps_its_output_rate(
    naip_map: MapPackage, naip_raster: GeoRaster, tmp_path: Path
) -> None:
    """The companion as a user starts it, against a simulated vehicle flying 2015 imagery: the
    cascade's fixes are fused, and localizing (a worker thread) never stalls the output."""
    pytest.importorskip("pymavlink")
    from orthonav.mavlink.link import MavLink
    from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

    # Over the lakes by the raster's centre: the frames' land agrees less than their shores, and
    # the cascade's fixes claim part of the land search's reach (test_water_shore.py).
    lat, lon = naip_raster.center_latlon
    config = SimVehicleConfig(
        *destination(lat, lon, 270.0, 700.0), *destination(lat, lon, 90.0, 1000.0),
        speed_mps=20.0, alt_agl_m=NAIP_ALT_M, frame_rate_hz=2.0,
    )  # fmt: skip
    duration_s = 14.0
    companion = MavLink("udpin:127.0.0.1:0", role="companion").open()
    port = companion.local_port
    companion.close()  # a free port for fly to listen on
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    with GeoRaster(naip_path(FRAMES_YEAR)) as frames_from:
        link = MavLink(f"udpout:127.0.0.1:{port}", role="vehicle")
        vehicle = SimVehicle(config, link, frames_from, CAMERA, frames_dir, tmp_path / "vehicle")
        graded: dict = {}
        thread = threading.Thread(target=lambda: graded.update(vehicle.run(duration_s + 2.0)), daemon=True)
        thread.start()
        args = [
            "fly",
            "--map",
            str(naip_map.path),
            "--frames",
            str(frames_dir),
            "--duration",
            str(duration_s),
            "--independent-attitude",  # sim-vehicle's body camera: its attitude is the truth
        ]
        result = runner.invoke(
            app, [*args, "--connect", f"udpin:127.0.0.1:{port}", "--log-dir", str(tmp_path)]
        )
        thread.join(timeout=60.0)
    assert result.exit_code == 0, result.output
    assert "fix source: cascade" in result.output
    records = _read(tmp_path / "companion.jsonl")
    fixes = [r for r in records if r["kind"] == "fix"]
    assert _methods([r["fix"] for r in fixes]) == {"cascade:orb"}
    fused = [r for r in fixes if r["filter"]["accepted"]]
    ms = [r["fix"]["timings"]["total_ms"] for r in fixes]
    print(
        f"\nfly: {len(fused)} of {len(fixes)} cascade fixes fused; ms per frame: median {np.median(ms):.0f}"
    )
    assert len(fused) >= 5 and all("p_correct" in r["fix"]["quality"] for r in fused)
    sent = [r["time_s"] for r in records if r["kind"] == "sent"]
    assert len(sent) >= 20 and max(np.diff(sent)) < 1.0, "the output stalled while a frame was localized"
    assert graded["errors"]["GPS_INPUT"]["median_m"] < 15.0, graded


def test_a_flight_can_fall_back_on_another_map(naip_map: MapPackage, tmp_path: Path) -> None:
    """``fly --fallback MAP``: the chosen fix source, then the same kind of source on each
    fallback map, each warmed up before the flight (keypoints alone on the map's orthophoto); a
    fallback that is not a map package stops fly before it connects."""
    with ExitStack() as stack:
        opened = open_fix_sources(stack, naip_map, CAMERA, "keypoints", fallbacks=[naip_map.path])
        source = opened.source
        assert isinstance(source, Fallback)
        assert source.names == ["orb", "orb-2"] and all(isinstance(s, Localizer) for s in source.sources)
        warmed = [line for line in warm_up_maps(opened, CAMERA) if "warmed up in" in line]
    assert len(warmed) == 2 and all("(fixed)" in line for line in warmed), warmed
    base = ["fly", "--map", str(naip_map.path), "--frames", str(tmp_path), "--duration", "1"]
    missing = runner.invoke(app, [*base, "--fallback", str(tmp_path / "nomap")])
    assert isinstance(missing.exception, OrthonavError) and "nomap" in str(missing.exception)


def test_a_flight_can_take_the_trained_coarse_correlation(naip_map: MapPackage) -> None:
    """``fly --coarse-backbone trained``: the cascade's coarse stage, and the fallback map's, run
    the CNN correlation; by default the gradient one, then the orientation one."""
    with ExitStack() as stack:
        chain = open_fix_sources(
            stack, naip_map, CAMERA, "cascade", fallbacks=[naip_map.path], coarse_backbone="trained"
        ).source
        default = open_fix_sources(stack, naip_map, CAMERA, None).source
    assert [s.coarse.corrector.config.backbone for s in chain.sources] == ["trained", "trained"]
    # Maps of one orthophoto read it opened once: its in-memory views are built once.
    first, second = chain.sources
    assert first.coarse.raster is second.coarse.raster
    assert first.coarse.raster is not _cascades(default)[0].coarse.raster
    assert _backbones(default) == ["gradient", "orientation"]


def test_the_trunk_check_is_chosen_on_the_command_line(
    naip_map: MapPackage, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--trunk-check auto|on|off`` (fly, localize, bench localize) sets every cascade's
    ``trunk_check``, the fallback map's too; ``on`` where the trunk does not load stops before
    the first frame, saying what failed; a value that is none of the three is refused by name."""
    with ExitStack() as stack:
        for value in (True, False, None):
            chain = open_fix_sources(
                stack, naip_map, CAMERA, "cascade", fallbacks=[naip_map.path], trunk_check=value
            ).source
            assert [s.config.trunk_check for s in _cascades(chain)] == [value] * 4  # 2 maps, 2 each
        off = open_fix_sources(stack, naip_map, CAMERA, None, trunk_check=False).source
        assert all(not s.acceptance.uses_trunk and "trunk" not in s.__dict__ for s in _cascades(off))

        def missing(runtime: str) -> None:
            raise ImportError("no trunk here", name="onnxruntime")

        monkeypatch.setattr("orthonav.localize.cascade.trained_trunk", missing)
        with pytest.raises(OrthonavError, match="trunk check on: the trained CNN does not load"):
            open_fix_source(stack, naip_map, CAMERA, "cascade", trunk_check=True)
    frame = tmp_path / "frame.png"
    frame.write_bytes(b"")
    for command in (
        ["localize", str(naip_map.path), str(frame)],
        ["fly", "--map", str(naip_map.path), "--frames", str(tmp_path), "--duration", "1"],
        ["bench", "localize", "--data", str(tmp_path)],
    ):
        result = runner.invoke(app, [*command, "--trunk-check", "sometimes"])
        assert isinstance(result.exception, OrthonavError), (command, result.output)
        assert "--trunk-check 'sometimes': expected one of auto, on, off" in str(result.exception)

"""What a newcomer reads: a mission's summary says honestly whether it arrived, the map build's
bar moves tile by tile, and ``orthonav serve`` on a busy port fails before announcing a URL."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from typer.testing import CliRunner

import orthonav.mapdb.build as map_build
from orthonav.camera import Camera
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.mapdb import TilingConfig, build_map
from orthonav.sim.mission import MissionResult

runner = CliRunner()


def _result(arrived: bool, true_distance_m: float, fixes_fused: int, steps: int = 20) -> MissionResult:
    return MissionResult(
        run_dir=Path("run"),
        arrived=arrived,
        end_reason="arrived (by estimate)" if arrived else "time limit",
        steps=steps,
        flight_time_s=100.0,
        true_distance_to_target_m=true_distance_m,
        arrival_radius_m=60.0,
        fix_rate=fixes_fused / steps,
        fused_rate=fixes_fused / steps,
        fixes_fused=fixes_fused,
    )


def test_summary_says_not_arrived_when_only_the_estimate_arrived() -> None:
    summary = _result(arrived=True, true_distance_m=127.0, fixes_fused=12).summary()
    assert summary["arrived"] is True and summary["arrived_true"] is False
    assert summary["success"] is False
    assert summary["true_distance_to_target_m"] == 127.0 and summary["arrival_radius_m"] == 60.0
    assert summary["outcome"].startswith("NOT arrived") and "127 m from the target" in summary["outcome"]
    # Side by side, the verdict first: a reader of the printed table sees it before anything else.
    keys = list(summary)
    assert keys[:2] == ["outcome", "success"]
    assert keys.index("arrived_true") == keys.index("arrived") + 1
    assert keys.index("true_distance_to_target_m") == keys.index("arrived_true") + 1


def test_summary_without_fixes_is_no_success_even_on_the_target() -> None:
    summary = _result(arrived=True, true_distance_m=20.0, fixes_fused=0).summary()
    assert summary["arrived"] and summary["arrived_true"] and not summary["success"]
    assert (
        "not on visual fixes" in summary["outcome"]
        and "no visual fix fused in 20 frames" in summary["outcome"]
    )


def test_summary_of_a_real_arrival_and_of_a_time_limit() -> None:
    good = _result(arrived=True, true_distance_m=31.0, fixes_fused=14).summary()
    assert good["success"] and good["outcome"].startswith("arrived by estimate and by truth")
    late = _result(arrived=False, true_distance_m=400.0, fixes_fused=3).summary()
    assert not late["success"] and late["outcome"].startswith("not arrived (time limit)")


def test_map_build_bar_moves_per_tile(terrain_tif: Path, camera: Camera, tmp_path: Path, monkeypatch) -> None:
    """One update per tile, not one per 32-tile chunk (which could sit at 0 for minutes)."""
    updates: list[int] = []

    class Bar:
        def __init__(self, *args, total: int, initial: int = 0, **kwargs) -> None:
            self.total = total

        def __enter__(self) -> Bar:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def update(self, n: int = 1) -> None:
            updates.append(n)

    monkeypatch.setattr(map_build, "tqdm", Bar)
    package = build_map(terrain_tif, tmp_path / "map", camera, TilingConfig(nominal_alt_m=300.0))
    assert updates == [1] * len(package)


def test_serve_on_a_busy_port_fails_before_printing_a_url(tmp_path: Path) -> None:
    pytest.importorskip("uvicorn")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = runner.invoke(app, ["serve", "--data", str(tmp_path / "web"), "--port", str(port)])
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    message = str(result.exception)
    assert f"port {port}" in message and "already in use" in message and "\n" not in message
    assert "http://" not in result.output


def test_bind_sockets_listens_on_a_free_port() -> None:
    pytest.importorskip("uvicorn")
    from orthonav.web.server import bind_sockets

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sockets = bind_sockets("127.0.0.1", port)
    try:
        assert [s.getsockname()[1] for s in sockets] == [port]
        sockets[0].listen()
        with pytest.raises(OrthonavError, match=f"port {port} on 127.0.0.1 is already in use"):
            bind_sockets("127.0.0.1", port)
    finally:
        for sock in sockets:
            sock.close()

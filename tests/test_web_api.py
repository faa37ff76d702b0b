"""The web service's JSON API on the real NAIP map: tiles, uploads, builds, live missions, past
runs, and every kind of bad input answered with a 4xx and a clear message, never a 500."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.windows import Window

pytest.importorskip("fastapi", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("rio_tiler", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("httpx", reason="the FastAPI test client needs httpx (test extra)")

import httpx
import morecantile
from conftest import naip_path
from fastapi import HTTPException
from fastapi.testclient import TestClient
from helpers_geotiff import textured, write_geotiff
from helpers_web import (
    MAP_NAME,
    free_port,
    linked_data_dir,
    mission_request,
    open_request,
    read_response,
    served,
    wait_for_run,
    wait_for_steps,
    web_data_dir,
)
from typer.testing import CliRunner

from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.mapdb import MapPackage
from orthonav.web import WebSettings, create_app, make_server
from orthonav.web.tiles import TileRenderer, TileTooCoarse, min_zoom, render_tile

UPLOAD_LIMIT = 4_000_000  # the NAIP GeoTIFFs are ~2.5 MB
WEB_MERCATOR = morecantile.tms.get("WebMercatorQuad")


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return web_data_dir(tmp_path_factory.mktemp("web"))


@pytest.fixture(scope="module")
def client(data_dir: Path):
    settings = WebSettings(data_dir, max_upload_bytes=UPLOAD_LIMIT, allowed_hosts=("testserver",))
    with TestClient(create_app(settings)) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def package(data_dir: Path) -> MapPackage:
    return MapPackage(data_dir / "maps" / MAP_NAME)


@pytest.fixture(scope="module")
def finished_run(client, package) -> dict:
    """One mission, followed live through its event stream from the moment it was queued."""
    response = client.post("/api/runs", json=mission_request(package))
    assert response.status_code == 202, response.text
    run_id = response.json()["id"]
    events: list[tuple[str, dict]] = []
    with client.stream("GET", f"/api/runs/{run_id}/events") as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        kind = None
        for line in stream.iter_lines():
            if line.startswith("event: "):
                kind = line.removeprefix("event: ")
            elif line.startswith("data: "):
                events.append((kind, json.loads(line.removeprefix("data: "))))
    return {"id": run_id, "events": events, "run": client.get(f"/api/runs/{run_id}").json()}


def _tile_at(lat: float, lon: float, zoom: int) -> str:
    tile = WEB_MERCATOR.tile(lon, lat, zoom)
    return f"{tile.z}/{tile.x}/{tile.y}"


def _png(content: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None, "not a PNG"
    return image


# --- maps and tiles ----------------------------------------------------------------------------


def test_maps_are_listed_with_bounds_and_their_tiles_show_the_orthophoto(client, package) -> None:
    maps = client.get("/api/maps").json()
    assert [m["name"] for m in maps] == [MAP_NAME]
    (south, west), (north, east) = maps[0]["bounds"]
    lat, lon = package.grid.center_latlon
    assert south < lat < north and west < lon < east
    assert maps[0]["backend"] == "orb" and maps[0]["summary"]["tiles"].startswith("20 ")

    inside = client.get(f"/api/maps/{MAP_NAME}/tiles/{_tile_at(lat, lon, 15)}.png")
    assert inside.status_code == 200 and inside.headers["content-type"] == "image/png"
    image = _png(inside.content)
    assert image.shape == (256, 256, 4)
    assert (image[..., 3] == 255).mean() > 0.99, "a tile inside the map is fully covered"
    assert image[..., :3].std() > 10, "real imagery, not a flat fill"

    corner = client.get(f"/api/maps/{MAP_NAME}/tiles/{_tile_at(north, west, 14)}.png")
    alpha = _png(corner.content)[..., 3]
    assert 0.0 < (alpha == 255).mean() < 1.0, "the map's corner tile is partly transparent"


@pytest.mark.parametrize(
    ("path", "status", "message"),
    [
        ("14/0/0.png", 404, "outside the orthophoto"),
        ("3/9/0.png", 400, "below 2^3"),
        ("25/0/0.png", 422, "z:"),
        ("10/-1/0.png", 422, "x:"),
        ("10/a/0.png", 422, "x:"),
    ],
)
def test_bad_tile_requests_are_4xx(client, path: str, status: int, message: str) -> None:
    response = client.get(f"/api/maps/{MAP_NAME}/tiles/{path}")
    assert response.status_code == status and message in response.json()["detail"]


def test_16_bit_orthophotos_are_stretched_to_8_bit_tiles(tmp_path: Path) -> None:
    data = textured(256, 256).astype(np.uint16) * 40 + 1000  # 1800..10400 of 65535
    path = write_geotiff(tmp_path / "deep.tif", data)
    with GeoRaster(path) as raster:
        lat, lon = raster.center_latlon
    image = _png(render_tile(path, *map(int, _tile_at(lat, lon, 17).split("/"))))
    rgb = image[..., :3][image[..., 3] == 255]
    assert rgb.size and rgb.min() < 30 and rgb.max() > 225, "the 2-98 % stretch spans the 8-bit range"


def test_a_small_orthophoto_is_refused_at_world_zooms_at_once() -> None:
    """rio-tiler reprojects a tile's whole extent at the source's resolution: over the 4.7 km NAIP
    crop a zoom-5 tile took 90 s and 1.7 GB. It is refused at once with the zoom that works, and
    a tile at that zoom renders in a fraction of a second (a tenth, here)."""
    path = naip_path("20200831")
    lowest = min_zoom(path, path.stat().st_mtime)
    assert 5 < lowest < 13
    with GeoRaster(path) as raster:
        lat, lon = raster.center_latlon
    start = time.perf_counter()
    with pytest.raises(TileTooCoarse, match=rf"zoom in to {lowest} or more"):
        render_tile(path, *map(int, _tile_at(lat, lon, 5).split("/")))
    assert time.perf_counter() - start < 1.0
    start = time.perf_counter()
    assert _png(render_tile(path, *map(int, _tile_at(lat, lon, lowest).split("/")))).shape == (256, 256, 4)
    assert time.perf_counter() - start < 2.0


def test_unknown_or_traversing_map_names_are_4xx(client) -> None:
    assert client.get("/api/maps/nope/tiles/1/0/0.png").status_code == 404
    for name in ("..%2F..%2Fmaps", ".hidden", "a%20b"):
        assert client.get(f"/api/maps/{name}/tiles/1/0/0.png").status_code in (400, 404), name
    assert "map name '.hidden'" in client.get("/api/maps/.hidden").json()["detail"]


class HeldRenders:
    """Stands in for ``render_tile``: each render holds its thread until ``release`` is set (or
    ``HOLD_S`` passed), recording the tiles rendered and how many rendered at once."""

    HOLD_S = 5.0
    PNG = b"\x89PNG\r\n\x1a\n"

    def __init__(self) -> None:
        self.tiles: list[tuple[int, int, int]] = []
        self.most_at_once = 0
        self.release = threading.Event()
        self._running = 0
        self._lock = threading.Lock()

    def __call__(self, path: Path, z: int, x: int, y: int) -> bytes:
        with self._lock:
            self.tiles.append((z, x, y))
            self._running += 1
            self.most_at_once = max(self.most_at_once, self._running)
        self.release.wait(self.HOLD_S)
        with self._lock:
            self._running -= 1
        return self.PNG

    def wait_for(self, count: int) -> None:
        deadline = time.monotonic() + 5.0
        while len(self.tiles) < count:
            assert time.monotonic() < deadline, f"{len(self.tiles)} tiles rendering, expected {count}"
            time.sleep(0.02)


@pytest.fixture
def held_renders(monkeypatch) -> Iterator[HeldRenders]:
    held = HeldRenders()
    monkeypatch.setattr("orthonav.web.tiles.render_tile", held)
    yield held
    held.release.set()


def _tile_url(url: str, x: int) -> str:
    return f"{url}/api/maps/{MAP_NAME}/tiles/15/{x}/0.png"


def _timed_get(url: str) -> tuple[httpx.Response, float]:
    start = time.monotonic()
    response = httpx.get(url, timeout=30.0)
    return response, time.monotonic() - start


def test_tiles_render_a_few_at_a_time_and_a_busy_server_answers_503(
    tmp_path: Path, package, held_renders: HeldRenders
) -> None:
    """Many tile requests at once cost one render's memory each only up to the worker count; each
    waits at most its time budget, then is told to retry (the render it started is kept)."""
    settings = WebSettings(linked_data_dir(tmp_path, package), tile_workers=1, tile_timeout_s=1.0)
    with served(settings) as (url, _, _), ThreadPoolExecutor(4) as pool:
        first = pool.submit(_timed_get, _tile_url(url, 0))
        held_renders.wait_for(1)
        waiting = [pool.submit(_timed_get, _tile_url(url, x)) for x in (1, 2, 3)]
        for response, elapsed in [first.result(), *(future.result() for future in waiting)]:
            assert response.status_code == 503, response.text
            assert response.headers["retry-after"] == "2" and "retry shortly" in response.json()["detail"]
            assert elapsed < 3.0
        assert held_renders.most_at_once == 1 and held_renders.tiles == [(15, 0, 0)], held_renders.tiles
        held_renders.release.set()
        time.sleep(0.2)  # the first tile's render ends, into the cache
        retried = httpx.get(_tile_url(url, 0))
    assert retried.status_code == 200 and retried.content == HeldRenders.PNG
    assert held_renders.tiles == [(15, 0, 0)], "the retry was served from the cache"


def test_a_tile_whose_client_left_while_it_waited_is_not_rendered(
    tmp_path: Path, package, held_renders: HeldRenders
) -> None:
    settings = WebSettings(linked_data_dir(tmp_path, package), tile_workers=1)
    with served(settings) as (url, _, _), ThreadPoolExecutor(1) as pool:
        first = pool.submit(_timed_get, _tile_url(url, 0))
        held_renders.wait_for(1)
        path = _tile_url(url, 1).removeprefix(url)
        gone = open_request(url, f"GET {path}")
        time.sleep(0.3)  # its request waits for the one render slot
        gone.close()
        time.sleep(0.5)  # the server notices within its poll
        held_renders.release.set()
        assert first.result()[0].status_code == 200
        assert httpx.get(_tile_url(url, 2)).status_code == 200
    assert held_renders.tiles == [(15, 0, 0), (15, 2, 0)], "the abandoned tile 15/1/0 was not rendered"


def test_a_tile_answered_503_is_not_rendered_when_the_render_thread_frees_at_once(
    held_renders: HeldRenders,
) -> None:
    """The client may act on a 503 before the server's event loop turns again: the tile that was
    given up on must already be out of the render queue when the answer goes out."""

    async def never_left() -> bool:
        return False

    async def request(renderer: TileRenderer, x: int, answered: list[int]) -> str:
        try:
            await renderer.render(Path(__file__), 15, x, 0, never_left)
        except HTTPException as refusal:
            answered.append(x)
            if len(answered) == 4:  # the last answer is out: the held render ends at once
                held_renders.release.set()
            time.sleep(0.01)  # the loop's thread is slow to come back
            return str(refusal.status_code)
        return "200"

    async def four_at_once() -> list[str]:
        renderer, answered = TileRenderer(1, 1.0, threading.Event()), []
        first = asyncio.create_task(request(renderer, 0, answered))
        while not held_renders.tiles:
            await asyncio.sleep(0.02)
        statuses = await asyncio.gather(first, *(request(renderer, x, answered) for x in (1, 2, 3)))
        await asyncio.sleep(0.3)  # a queued tile would render now
        renderer.shutdown()
        return statuses

    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # the render thread takes its next job as soon as it can
    try:
        assert asyncio.run(four_at_once()) == ["503"] * 4
    finally:
        sys.setswitchinterval(previous)
    assert held_renders.tiles == [(15, 0, 0)], "tiles answered 503 were rendered afterwards"


# --- missions ----------------------------------------------------------------------------------


def test_a_mission_streams_tracks_fixes_and_frames_then_its_summary(client, finished_run) -> None:
    events, run = finished_run["events"], finished_run["run"]
    kinds = [kind for kind, _ in events]
    states = [data["state"] for kind, data in events if kind == "state"]
    assert states[-1] == "done" and set(states) <= {"queued", "running", "done"}
    steps = [data for kind, data in events if kind == "step"]
    nav = [data for kind, data in events if kind == "nav"]
    summary = events[-1][1]["summary"]
    print(f"\nmission: {len(steps)} steps, {len(nav)} nav records, summary {summary}")
    assert kinds[-1] == "state" and summary["steps"] == len(steps) == len(run["steps"])
    running = next(
        i for i, (kind, data) in enumerate(events) if kind == "state" and data["state"] == "running"
    )
    assert running < kinds.index("step"), "steps were streamed while the mission flew"
    assert len(nav) == len(run["nav"]) > len(steps) >= 3
    assert summary["fix_rate"] >= 0.8 and summary["nav_error_median_m"] < 30.0
    for record in nav:  # both tracks, every second
        assert {"true_lat", "true_lon", "nav_lat", "nav_lon", "nav_error_m", "nav_status"} <= set(record)
    frame = client.get(steps[-1]["frame_url"])
    assert frame.status_code == 200 and cv2.imdecode(np.frombuffer(frame.content, np.uint8), 1).shape == (
        480,
        640,
        3,
    )
    assert steps[0]["fix"]["quality"]["inliers"] > 0
    # Each keypoint fix's matches: the frame beside the map's orthophoto (480 x 480 px).
    assert all(step["matches_url"] for step in steps if step["fix"]["quality"].get("inliers", 0) > 0)
    matches = client.get(steps[-1]["matches_url"])
    assert matches.status_code == 200
    assert cv2.imdecode(np.frombuffer(matches.content, np.uint8), 1).shape == (480, 640 + 480, 3)


def test_a_finished_run_is_listed_and_its_outputs_download(client, finished_run, data_dir: Path) -> None:
    run_id = finished_run["id"]
    listed = {run["id"]: run for run in client.get("/api/runs").json()}
    assert listed[run_id]["state"] == "done" and listed[run_id]["request"]["map"] == MAP_NAME
    files = {f["path"] for f in client.get(f"/api/runs/{run_id}/files").json()}
    assert {"trajectory.png", "steps.jsonl", "nav.jsonl", "summary.json", "config.json"} <= files
    run_dir = data_dir / "runs" / run_id
    for name in ("trajectory.png", "steps.jsonl", "summary.json"):
        response = client.get(f"/api/runs/{run_id}/files/{name}")
        assert response.status_code == 200 and response.content == (run_dir / name).read_bytes()


def test_runs_with_each_fix_source_compare_side_by_side(client, package, finished_run) -> None:
    ids = [finished_run["id"]]
    for source in ("correlation", "ins"):
        run = client.post(
            "/api/runs", json=mission_request(package, fix_source=source, max_time_s=30.0)
        ).json()
        assert wait_for_run(client, run["id"])["state"] == "done"
        ids.append(run["id"])
    compared = client.get("/api/compare?" + "&".join(f"run={run_id}" for run_id in ids)).json()["runs"]
    assert [run["id"] for run in compared] == ids
    assert [run["request"]["fix_source"] for run in compared] == ["cascade", "correlation", "ins"]
    fused = [run["summary"]["fused_rate"] for run in compared]
    assert fused[0] > 0.5 and fused[1] > 0.5 and fused[2] == 0.0, fused
    # Dense correlation has no point matches: its frames are shown bare.
    correlation = client.get(f"/api/runs/{ids[1]}").json()["steps"]
    assert all(step["frame_url"] and step["matches_url"] is None for step in correlation)
    assert client.get(f"/api/compare?run={ids[0]}").status_code == 422  # two at least
    assert client.get(f"/api/compare?run={ids[0]}&run=nope").status_code == 404


def test_frames_from_an_uploaded_orthophoto_of_another_year(client, package, data_dir: Path) -> None:
    """Frames from NAIP 2018 over the 2020 map: ORB rarely matches across years, and every
    rejected frame says why."""
    upload = client.put("/api/orthophotos/naip2018", content=naip_path("20180716").read_bytes())
    assert upload.status_code == 201, upload.text
    assert "naip2018" in [o["name"] for o in client.get("/api/orthophotos").json()]
    body = mission_request(package, frames_from="naip2018", max_time_s=30.0)
    run = wait_for_run(client, client.post("/api/runs", json=body).json()["id"])
    assert run["state"] == "done"
    assert run["config"]["frames_from"] == str(data_dir / "orthophotos" / "naip2018.tif")
    rejected = [step for step in run["steps"] if not step["accepted"]]
    assert rejected and all(step["reason"] for step in rejected)


@pytest.mark.parametrize(
    ("changes", "status", "message"),
    [
        ({"start": {"lat": 95.0, "lon": -99.15}}, 422, "start.lat"),
        ({"target": {"lat": 47.02}}, 422, "target.lon: Field required"),
        ({"speed_mps": -1}, 422, "speed_mps"),
        ({"speed_mps": "fast"}, 422, "speed_mps"),
        ({"warp_drive": True}, 422, "warp_drive"),
        ({"fix_source": "magic"}, 422, "fix_source"),
        ({"frames_from": "../../etc/passwd"}, 422, "frames_from"),
        ({"imu": "bogus"}, 400, "IMU preset 'bogus'"),
        ({"step_s": 0.4}, 400, "fix_latency_s"),
        ({"start": {"lat": 48.0, "lon": -99.15}}, 400, "start 48.000000, -99.150000: outside the map"),
        ({"map": "nope"}, 404, "map 'nope'"),
        ({"frames_from": "never-uploaded"}, 404, "orthophoto 'never-uploaded'"),
    ],
)
def test_bad_mission_requests_are_4xx_with_a_clear_message(
    client, package, changes: dict, status: int, message: str
) -> None:
    before = [run["id"] for run in client.get("/api/runs").json()]
    response = client.post("/api/runs", json=mission_request(package, **changes))
    assert response.status_code == status and message in response.json()["detail"], response.text
    assert [run["id"] for run in client.get("/api/runs").json()] == before, "a refused mission leaves no run"


def test_a_body_that_is_not_json_is_422(client) -> None:
    response = client.post("/api/runs", content=b"{not json", headers={"content-type": "application/json"})
    assert response.status_code == 422 and response.json()["detail"]


def test_a_mission_that_fails_says_why_and_the_service_goes_on(client, package, monkeypatch) -> None:
    def broken(*args, **kwargs):
        raise OrthonavError("frames.tif: not a readable GeoTIFF (truncated)")

    monkeypatch.setattr("orthonav.web.jobs.run_mission", broken)
    run = wait_for_run(client, client.post("/api/runs", json=mission_request(package)).json()["id"])
    assert run["state"] == "failed" and run["error"] == "frames.tif: not a readable GeoTIFF (truncated)"

    monkeypatch.setattr("orthonav.web.jobs.run_mission", lambda *a, **k: 1 / 0)
    run = wait_for_run(client, client.post("/api/runs", json=mission_request(package)).json()["id"])
    assert run["state"] == "failed" and run["error"].startswith("ZeroDivisionError")
    assert client.get("/api/maps").status_code == 200


def test_a_mission_failure_names_no_server_path(client, package, data_dir: Path, monkeypatch) -> None:
    chunk = data_dir / "maps" / MAP_NAME / "features" / "chunk_0000000.npy"
    for exc in (OrthonavError(f"{chunk}: checksum mismatch"), ValueError(f"cannot read {chunk.parent}")):

        def broken(*args, exc: Exception = exc, **kwargs):
            raise exc

        monkeypatch.setattr("orthonav.web.jobs.run_mission", broken)
        run = wait_for_run(client, client.post("/api/runs", json=mission_request(package)).json()["id"])
        assert run["state"] == "failed" and str(data_dir) not in run["error"], run["error"]
        assert run["error"] in ("chunk_0000000.npy: checksum mismatch", "ValueError: cannot read features")


def test_a_flying_mission_is_cancelled_between_frames_and_writes_its_outputs(client, package) -> None:
    slow = mission_request(package, speed_mps=5.0)  # about 75 frames to the target
    flying = client.post("/api/runs", json=slow).json()["id"]
    waiting = client.post("/api/runs", json=slow).json()["id"]
    wait_for_steps(client, flying, 2)
    assert client.get(f"/api/runs/{waiting}").json()["state"] == "queued"

    cancelled = client.post(f"/api/runs/{waiting}/cancel")
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    stopping = client.post(f"/api/runs/{flying}/cancel")
    assert stopping.status_code == 202 and stopping.json()["cancel_requested"]

    run = wait_for_run(client, flying, timeout_s=10.0)
    print(f"\ncancelled after {run['summary']['steps']} steps")
    assert run["state"] == "cancelled" and run["end_reason"] == "cancelled"
    assert run["summary"]["end_reason"] == "cancelled" and 2 <= run["summary"]["steps"] < 20
    assert len(run["steps"]) == run["summary"]["steps"] and run["nav"]
    assert {"trajectory.png", "summary.json", "steps.jsonl"} <= {f["path"] for f in run["files"]}

    time.sleep(0.5)  # the worker has moved past the cancelled run: it never flew
    never = client.get(f"/api/runs/{waiting}").json()
    assert never["state"] == "cancelled" and never["end_reason"] == "cancelled before it started"
    assert never["summary"] is None and never["steps"] == []
    again = client.post(f"/api/runs/{flying}/cancel")
    assert again.status_code == 409 and "only a queued or running mission" in again.json()["detail"]
    assert client.post("/api/runs/nope/cancel").status_code == 404


def _follow(http, path: str) -> None:
    """Read an event stream to its end, as the page does (a closed connection ends it too)."""
    with contextlib.suppress(httpx.HTTPError):
        http.get(path, timeout=60.0)


def test_stopping_the_server_cancels_the_flying_mission(tmp_path: Path, package) -> None:
    """Even with a page following the mission (its event stream open), the server stops within a
    frame or two, and the run is recorded as cancelled with its outputs."""
    with (
        served(WebSettings(linked_data_dir(tmp_path, package))) as (url, server, thread),
        httpx.Client(base_url=url) as http,
    ):
        run_id = http.post("/api/runs", json=mission_request(package, speed_mps=5.0)).json()["id"]
        wait_for_steps(http, run_id, 1)
        follower = threading.Thread(target=_follow, args=(http, f"/api/runs/{run_id}/events"))
        follower.start()
        time.sleep(0.3)
        stopped = time.monotonic()
        server.should_exit = True
        thread.join(timeout=20.0)
        print(f"\nserver stopped in {time.monotonic() - stopped:.2f} s")
        assert not thread.is_alive(), "the server waited for the mission"
    state = json.loads((tmp_path / "runs" / run_id / "web.json").read_text())
    summary = json.loads((tmp_path / "runs" / run_id / "summary.json").read_text())
    assert state["state"] == "cancelled" and summary["end_reason"] == "cancelled"
    follower.join(timeout=5.0)
    assert not follower.is_alive(), "the event stream ended with the mission"


def _wait_until_serving(url: str, process: subprocess.Popen) -> None:
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and process.poll() is None:
        with contextlib.suppress(httpx.TransportError):
            if httpx.get(f"{url}/api/maps").status_code == 200:
                return
        time.sleep(0.1)
    output = process.stderr.read() if process.poll() is not None else ""
    pytest.fail(f"orthonav serve did not start: {output}")


def test_sigterm_stops_orthonav_serve_promptly_with_requests_open(tmp_path: Path, package) -> None:
    """SIGTERM (a service manager's stop) while a page follows a flying mission and an upload has
    stalled: the process exits within seconds with code 0, the mission recorded as cancelled and
    the partial upload gone."""
    data = linked_data_dir(tmp_path / "data", package)
    port = free_port()
    command = [sys.executable, "-m", "orthonav.cli.main", "serve", "--data", str(data), "--port", str(port)]
    process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        _wait_until_serving(url, process)
        with httpx.Client(base_url=url) as http:
            run_id = http.post("/api/runs", json=mission_request(package, speed_mps=5.0)).json()["id"]
            wait_for_steps(http, run_id, 1)
            follower = threading.Thread(target=_follow, args=(http, f"/api/runs/{run_id}/events"))
            follower.start()
            stalled = open_request(url, "PUT /api/orthophotos/stalled", b"II*\x00", content_length=10**6)
            time.sleep(0.5)
            assert list((data / "orthophotos").glob(".upload-*")), "the upload is being received"
            stopped = time.monotonic()
            process.send_signal(signal.SIGTERM)
            code = process.wait(timeout=15.0)
            elapsed = time.monotonic() - stopped
            stalled.close()
            follower.join(timeout=5.0)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    print(f"\nstopped by SIGTERM in {elapsed:.2f} s")
    assert code == 0 and elapsed < 5.0, process.stderr.read()
    assert json.loads((data / "runs" / run_id / "web.json").read_text())["state"] == "cancelled"
    assert not list((data / "orthophotos").iterdir()), "no partial upload is left"


def test_too_many_waiting_missions_are_refused(tmp_path: Path, package) -> None:
    settings = WebSettings(tmp_path, max_pending_runs=1, allowed_hosts=("testserver",))
    app = create_app(settings)
    (tmp_path / "maps" / MAP_NAME).symlink_to(package.path)
    app.state.store.new_run({"map": MAP_NAME})  # one already waiting
    response = TestClient(app).post("/api/runs", json=mission_request(package))
    assert response.status_code == 429 and "already waiting" in response.json()["detail"]


def test_a_mission_on_a_damaged_map_is_refused_before_it_starts(tmp_path: Path, package) -> None:
    """One bit flipped in a feature chunk: the request is refused (409) naming the chunk by its
    file name only, and no run is made."""
    copy = tmp_path / "maps" / MAP_NAME
    shutil.copytree(package.path, copy)
    chunk = sorted((copy / "features").glob("chunk_*.npy"))[-1]
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x01
    chunk.write_bytes(bytes(data))
    client = TestClient(create_app(WebSettings(tmp_path, allowed_hosts=("testserver",))))
    response = client.post("/api/runs", json=mission_request(package))
    detail = response.json()["detail"]
    assert response.status_code == 409 and "map package damaged" in detail, response.text
    assert f"{chunk.name} checksum mismatch" in detail and str(tmp_path) not in detail
    assert client.get("/api/runs").json() == []


def test_a_restart_fails_unfinished_runs_and_drops_partial_uploads(tmp_path: Path) -> None:
    app = create_app(WebSettings(tmp_path))
    run_id = app.state.store.new_run({"map": MAP_NAME})
    app.state.store.set_run_state(run_id, state="running")
    partial = app.state.store.upload_folder() / "half.tif"
    partial.write_bytes(b"II*\x00")
    restarted = create_app(WebSettings(tmp_path))
    state = restarted.state.store.run_state(run_id)
    assert state["state"] == "failed" and "interrupted" in state["error"]
    assert not partial.parent.exists() and (tmp_path / "orthophotos").is_dir()


# --- uploads and map builds ----------------------------------------------------------------------


def _orthophoto_files(data_dir: Path) -> set[str]:
    return {p.name for p in (data_dir / "orthophotos").iterdir()}


def test_upload_then_build_a_map_with_progress(client, data_dir: Path) -> None:
    assert (
        client.put("/api/orthophotos/up2020", content=naip_path("20200831").read_bytes()).status_code == 201
    )
    assert client.put("/api/orthophotos/up2020", content=b"II*\x00").status_code == 409
    job = client.post("/api/maps", json={"name": "built", "orthophoto": "up2020", "altitude_m": 1000}).json()
    assert job["state"] in ("queued", "running")
    deadline = time.monotonic() + 60.0
    while job["state"] not in ("done", "failed") and time.monotonic() < deadline:
        time.sleep(0.2)
        job = client.get(f"/api/jobs/{job['id']}").json()
    assert job["state"] == "done", job["error"]
    assert job["tiles_total"] == 20 and job["tiles_done"] == 20
    maps = {m["name"]: m for m in client.get("/api/maps").json()}
    assert maps["built"]["summary"]["source"] == "up2020.tif"  # by name: the server's folders stay private
    assert str(data_dir) not in json.dumps(maps)
    conflict = client.post("/api/maps", json={"name": "built", "orthophoto": "up2020"})
    assert conflict.status_code == 409 and "already exists" in conflict.json()["detail"]


@pytest.mark.parametrize(
    ("body", "status", "message"),
    [
        ({"name": "x1", "orthophoto": "missing"}, 404, "orthophoto 'missing'"),
        ({"name": "x1", "orthophoto": "naip2018", "features": "nosuch"}, 400, "features 'nosuch'"),
        ({"name": "x1", "orthophoto": "naip2018", "altitude_m": 0}, 422, "altitude_m"),
        ({"name": "../x", "orthophoto": "naip2018"}, 422, "name"),
    ],
)
def test_bad_build_requests_are_4xx(client, body: dict, status: int, message: str) -> None:
    response = client.post("/api/maps", json=body)
    assert response.status_code == status and message in response.json()["detail"]


def test_uploads_over_the_size_limit_are_refused_and_nothing_is_kept(client, data_dir: Path) -> None:
    before = _orthophoto_files(data_dir)
    response = client.put("/api/orthophotos/big", content=b"II*\x00" + bytes(UPLOAD_LIMIT))
    assert response.status_code == 413 and "limit" in response.json()["detail"]

    def chunks():  # no Content-Length: the limit is enforced while streaming
        yield b"II*\x00"
        for _ in range(5):
            yield bytes(UPLOAD_LIMIT // 4)

    response = client.put("/api/orthophotos/big", content=chunks())
    assert response.status_code == 413
    assert _orthophoto_files(data_dir) == before


def test_a_refused_upload_reaches_a_client_that_sends_the_whole_body_first(tmp_path: Path) -> None:
    """urllib sends 'Connection: close' and the whole body before it reads the answer: a refusal
    sent before the body was read must still reach it (not a connection reset)."""
    settings = WebSettings(tmp_path, max_upload_bytes=1_000_000, body_idle_s=1.0)
    with served(settings) as (url, _, _):
        (tmp_path / "orthophotos" / "taken.tif").write_bytes(b"II*\x00")
        for name, status, message in [("taken", 409, "already uploaded"), ("big", 413, "than the limit")]:
            for _ in range(3):
                upload = urllib.request.Request(
                    f"{url}/api/orthophotos/{name}", data=b"II*\x00" + bytes(8_000_000), method="PUT"
                )
                with pytest.raises(urllib.error.HTTPError) as refused:
                    urllib.request.urlopen(upload, timeout=10.0)
                assert refused.value.code == status
                assert message in json.loads(refused.value.read())["detail"]
        # Far more than can be read in time: what arrives is read, then the answer closes the connection.
        huge = open_request(url, "PUT /api/orthophotos/huge", bytes(100_000), content_length=10**10)
        start = time.monotonic()
        with huge:
            status, headers, body = read_response(huge, timeout_s=5.0)
        assert status == 413 and headers["connection"] == "close" and b"limit" in body
        assert time.monotonic() - start < 3.0
    assert [p.name for p in (tmp_path / "orthophotos").iterdir()] == ["taken.tif"]


def test_a_body_that_stops_arriving_is_refused_and_nothing_is_kept(tmp_path: Path) -> None:
    """A client that declares more than it sends: 408 after the idle timeout, the partial upload
    removed, the connection closed (the rest of the body may still come)."""
    with served(WebSettings(tmp_path, body_idle_s=1.0)) as (url, _, _):
        upload = open_request(url, "PUT /api/orthophotos/cut", b"II*\x00" + bytes(6), content_length=100_000)
        # Seen before the 1 s idle timeout removes it (polled: a loaded machine can be slow to start).
        deadline = time.monotonic() + 0.9
        while not list((tmp_path / "orthophotos").glob(".upload-*")) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert list((tmp_path / "orthophotos").glob(".upload-*")), "the upload is being received"
        mission = open_request(url, "POST /api/runs", b'{"map": "x"', content_length=1000)
        for sock in (upload, mission):
            start = time.monotonic()
            with sock:
                status, headers, body = read_response(sock, timeout_s=5.0)
            assert status == 408 and headers["connection"] == "close", body
            assert "nothing received for 1 s" in json.loads(body)["detail"]
            assert time.monotonic() - start < 2.0
        assert httpx.get(f"{url}/api/orthophotos").json() == []
    assert not list((tmp_path / "orthophotos").iterdir())


def test_a_json_body_larger_than_any_request_is_refused_as_it_arrives(client) -> None:
    """FastAPI reads a JSON body whole into memory: a huge one would cost the server its size."""
    huge = b'{"map": "' + b"x" * (2 << 20) + b'"}'
    response = client.post("/api/runs", content=huge, headers={"content-type": "application/json"})
    assert response.status_code == 413 and "at most 1048576 bytes" in response.json()["detail"]
    small = client.post("/api/runs", json={"map": "nope"})
    assert small.status_code in (400, 404, 422), small.text


@pytest.mark.parametrize(
    ("content", "status", "message"),
    [
        (b"\x89PNG\r\n\x1a\n" + bytes(100), 415, "not a TIFF"),
        (b"<script>alert(1)</script>", 415, "not a TIFF"),
        (b"", 415, "too short"),
        (b"II*\x00" + bytes(200), 400, "upload bad"),
    ],
)
def test_only_valid_geotiffs_are_accepted(client, data_dir: Path, content, status, message) -> None:
    before = _orthophoto_files(data_dir)
    response = client.put("/api/orthophotos/bad", content=content)
    assert response.status_code == status and message in response.json()["detail"], response.text
    assert _orthophoto_files(data_dir) == before


def test_tiffs_that_are_not_usable_orthophotos_are_refused_with_the_reason(client, tmp_path: Path) -> None:
    plain = write_geotiff(tmp_path / "plain.tif", textured(64, 64), crs=None)
    response = client.put("/api/orthophotos/plain", content=plain.read_bytes())
    assert response.status_code == 400
    assert response.json()["detail"].startswith("upload plain: has no coordinate reference system")
    truncated = naip_path("20200831").read_bytes()[:300_000]
    response = client.put("/api/orthophotos/cut", content=truncated)
    assert response.status_code == 400 and response.json()["detail"].startswith("upload cut")


def test_an_upload_named_as_its_file_is_stored_under_that_name(
    client, data_dir: Path, tmp_path: Path
) -> None:
    """``naip2020.tif`` (the name on the uploader's disk) is the orthophoto naip2020, stored as
    naip2020.tif, not naip2020.tif.tif; either spelling then names it."""
    tif = write_geotiff(tmp_path / "small.tif", textured(64, 64))
    response = client.put("/api/orthophotos/naip2020.tif", content=tif.read_bytes())
    assert response.status_code == 201 and response.json()["name"] == "naip2020", response.text
    files = _orthophoto_files(data_dir)
    assert "naip2020.tif" in files and not any(name.endswith(".tif.tif") for name in files)
    assert "naip2020" in [o["name"] for o in client.get("/api/orthophotos").json()]
    again = client.put("/api/orthophotos/naip2020.TIFF", content=tif.read_bytes())
    assert again.status_code == 409 and "already uploaded" in again.json()["detail"]


def test_build_errors_carry_no_server_path_and_no_command_line_option(tmp_path: Path) -> None:
    """A folder left where the map would go, and an orthophoto too large to build unasked: the
    page says what is wrong by the API's names, and nothing about --overwrite or --yes."""
    (tmp_path / "maps" / "leftover").mkdir(parents=True)
    (tmp_path / "orthophotos").mkdir()
    write_geotiff(tmp_path / "orthophotos" / "small.tif", textured(64, 64))
    profile = {"driver": "GTiff", "width": 200_000, "height": 200_000, "count": 1, "dtype": "uint8"}
    profile |= {"crs": "EPSG:26914", "transform": Affine(0.1, 0, 485899.0, 0, -0.1, 5209246.0)}
    with rasterio.open(
        tmp_path / "orthophotos" / "vast.tif", "w", **profile, tiled=True, sparse_ok=True, BIGTIFF="YES"
    ) as vast:  # one textured corner, no other block written: a few megabytes on disk
        vast.write(textured(2048, 2048, bands=1), window=Window(0, 0, 2048, 2048))
    settings = WebSettings(tmp_path, allowed_hosts=("testserver",))
    with TestClient(create_app(settings)) as test_client:
        requests = [{"name": "leftover", "orthophoto": "small"}, {"name": "vast", "orthophoto": "vast"}]
        requests[1]["altitude_m"] = 100.0  # 230 x 230 tiles of 20 km
        ids = [test_client.post("/api/maps", json=request).json()["id"] for request in requests]
        errors = [wait_for_job(test_client, job_id)["error"] for job_id in ids]
    for error in errors:
        assert str(tmp_path) not in error and "--" not in error, error
    assert errors[0] == "map 'leftover': already exists (choose another name)"
    assert (
        errors[1].startswith("orthophoto 'vast': 200000 x 200000 px") and "crop the orthophoto" in errors[1]
    )


def wait_for_job(client, job_id: str, timeout_s: float = 60.0) -> dict:
    """The build job once it has finished or failed."""
    deadline = time.monotonic() + timeout_s
    job = client.get(f"/api/jobs/{job_id}").json()
    while job["state"] not in ("done", "failed") and time.monotonic() < deadline:
        time.sleep(0.2)
        job = client.get(f"/api/jobs/{job_id}").json()
    return job


@pytest.mark.parametrize("name", [".hidden", "a b", "x" * 65])
def test_upload_names_are_single_safe_components(client, name: str) -> None:
    response = client.put(f"/api/orthophotos/{name}", content=naip_path("20200831").read_bytes()[:4])
    assert response.status_code == 400 and "orthophoto name" in response.json()["detail"]


# --- file serving, hosts, headers, schema, CLI -----------------------------------------------------


def test_no_file_outside_a_run_can_be_read(client, finished_run, data_dir: Path) -> None:
    run_id = finished_run["id"]
    (data_dir / "runs" / run_id / "link").symlink_to("/etc/hostname")
    for path in (
        f"/api/runs/{run_id}/files/..%2F..%2F..%2Fmaps%2F{MAP_NAME}%2Fmanifest.json",
        f"/api/runs/{run_id}/files/%2e%2e/%2e%2e/orthophotos/naip2018.tif",
        f"/api/runs/{run_id}/files//etc/hostname",
        f"/api/runs/{run_id}/files/link",
        f"/api/runs/{run_id}/files/frames",
        f"/api/runs/{run_id}/files/summary.json%00.png",
        "/api/runs/..%2Fmaps/files/manifest.json",
        "/static/..%2F..%2Fweb%2Fapp.py",
    ):
        response = client.get(path)
        assert response.status_code in (400, 404), path
        assert b"orthonav-map" not in response.content and b"import" not in response.content


def test_requests_for_other_host_names_are_refused(client) -> None:
    assert client.get("/api/maps", headers={"host": "attacker.example"}).status_code == 400
    assert client.get("/api/maps").status_code == 200


def test_the_page_loads_only_its_own_assets_with_strict_headers(client) -> None:
    page = client.get("/")
    assert page.status_code == 200 and '<div id="map"' in page.text
    assert page.headers["content-security-policy"].startswith("default-src 'self'")
    assert page.headers["x-content-type-options"] == "nosniff"
    assets = re.findall(r'(?:src|href)="([^"]*)"', page.text)
    assert assets and all(a.startswith(("/static/", "/api/", "data:")) for a in assets), assets
    script = client.get("/static/app.js").text
    assert "http://" not in script and "https://" not in script
    for asset in ("leaflet.js", "leaflet.css", "LICENSE", "images/marker-icon.png"):
        assert client.get(f"/static/vendor/leaflet/{asset}").status_code == 200, asset


def test_the_api_is_described_by_its_openapi_schema(client) -> None:
    schema = client.get("/api/openapi.json").json()
    for path in (
        "/api/maps",
        "/api/maps/{name}/tiles/{z}/{x}/{y}.png",
        "/api/orthophotos/{name}",
        "/api/runs",
    ):
        assert path in schema["paths"], path
    assert "/api/runs/{run_id}/events" in schema["paths"]
    assert "post" in schema["paths"]["/api/runs/{run_id}/cancel"]
    assert (
        schema["components"]["schemas"]["MissionRequest"]["properties"]["speed_mps"]["exclusiveMinimum"] == 0
    )
    assert client.get("/docs").status_code == 404  # the interactive docs would load from a CDN


def test_serve_binds_to_loopback_by_default(monkeypatch, tmp_path: Path) -> None:
    from orthonav.cli.main import app

    started, bound = [], []
    # The port is bound first (a port in use fails before the URL is printed) and handed to uvicorn.
    fake_bind = lambda host, port: bound.append((host, port)) or []  # noqa: E731
    monkeypatch.setattr("orthonav.web.server.bind_sockets", fake_bind)
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: started.append(server.config))
    result = CliRunner().invoke(app, ["serve", "--data", str(tmp_path / "d")])
    assert result.exit_code == 0, result.output
    assert started[0].host == "127.0.0.1" and started[0].port == 8000 and bound[0] == ("127.0.0.1", 8000)
    result = CliRunner().invoke(app, ["serve", "--data", str(tmp_path / "d"), "--host", "0.0.0.0"])
    assert "warning" in result.output and started[1].host == "0.0.0.0"
    result = CliRunner().invoke(app, ["serve", "--port", "70000"])
    assert isinstance(result.exception, OrthonavError) and "--port" in str(result.exception)


def test_serve_without_the_web_extra_says_what_to_install(monkeypatch) -> None:
    from orthonav.cli.main import app

    for module in [name for name in sys.modules if name.startswith("orthonav.web")]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, "fastapi", None)  # as if it were not installed
    result = CliRunner().invoke(app, ["serve"])
    assert isinstance(result.exception, OrthonavError) and "orthonav[web]" in str(result.exception)


@pytest.mark.parametrize(("host", "foreign_host_status"), [("127.0.0.1", 400), ("0.0.0.0", 200)])
def test_only_a_wider_bind_accepts_any_host_name(tmp_path: Path, host: str, foreign_host_status: int) -> None:
    server = make_server(WebSettings(tmp_path), host, 0)
    response = TestClient(server.config.app).get("/api/maps", headers={"host": "box.lan"})
    assert response.status_code == foreign_host_status


def test_a_boolean_is_not_a_number(client) -> None:
    """Strict request models: "speed_mps": true is refused with the field named, not flown at 1 m/s."""
    body = {
        "map": "naip2020",
        "start": {"lat": 47.02, "lon": -99.16},
        "target": {"lat": 47.02, "lon": -99.14},
    }
    response = client.post("/api/runs", json={**body, "speed_mps": True})
    assert response.status_code == 422 and "speed_mps" in response.text
    response = client.post("/api/runs", json={**body, "start": {"lat": True, "lon": -99.16}})
    assert response.status_code == 422


def test_a_zoom_too_far_out_for_the_orthophoto_is_refused_quickly(tmp_path: Path) -> None:
    """A large orthophoto without overviews: a zoom-0 tile would read all of it (minutes, gigabytes);
    it is refused at once with the zoom that works; overviews (gdaladdo) lower that zoom."""
    import time

    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling

    from orthonav.web.store import NotFound
    from orthonav.web.tiles import MAX_READ_PX, min_zoom, render_tile

    path = tmp_path / "big.tif"
    size = 3 * MAX_READ_PX
    profile = {"driver": "GTiff", "width": size, "height": size, "count": 1, "dtype": "uint8"}
    profile |= {"crs": "EPSG:32614", "transform": Affine(0.5, 0, 500000, 0, -0.5, 5200000)}
    with rasterio.open(path, "w", tiled=True, compress="deflate", **profile) as ds:
        ds.write(np.full((1, 512, 512), 90, np.uint8), window=rasterio.windows.Window(0, 0, 512, 512))
    lowest = min_zoom(path, path.stat().st_mtime)
    assert lowest > 5
    start = time.perf_counter()
    with pytest.raises(NotFound, match=rf"zoom in to {lowest} or more"):
        render_tile(path, 0, 0, 0)
    assert time.perf_counter() - start < 1.0
    with rasterio.open(path, "r+") as ds:
        ds.build_overviews([2, 4, 8, 16], Resampling.average)
    assert min_zoom(path, path.stat().st_mtime) < lowest

"""What one client can make the server do is bounded: an upload's validation by its bytes, map
builds and missions by a queue cap, a mission's files by a quota and all runs by a total, a
request's head and body by deadlines, and memory handed back after a large request. Each holds
with a margin on a busy machine (time allowances stretched by the measured slowdown)."""

from __future__ import annotations

import errno
import json
import resource
import shutil
import signal
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import rasterio
from affine import Affine
from rasterio.windows import Window

pytest.importorskip("fastapi", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("httpx", reason="the FastAPI test client needs httpx (test extra)")

from conftest import naip_path
from fastapi.testclient import TestClient
from helpers_geotiff import textured
from helpers_timing import slowdown
from helpers_web import (
    MAP_NAME,
    linked_data_dir,
    mission_request,
    open_request,
    read_response,
    served,
    wait_for_run,
    web_data_dir,
)

from orthonav.mapdb import MapPackage
from orthonav.web import WebSettings, create_app
from orthonav.web.jobs import folder_bytes

ANSWER_S = 2.0  # on an idle machine; times the slowdown on a busy one


@pytest.fixture(scope="module")
def slow() -> float:
    return slowdown()


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    return MapPackage(web_data_dir(tmp_path_factory.mktemp("web")) / "maps" / MAP_NAME)


def sparse_geotiff(path: Path, size_px: int) -> Path:
    """A GeoTIFF declaring ``size_px`` x ``size_px`` RGB pixels that holds one textured 1024 px
    corner: every other block is absent (GDAL reads it as zeros), so the file is a few MB."""
    profile = {"driver": "GTiff", "width": size_px, "height": size_px, "count": 3, "dtype": "uint8"}
    profile |= {"crs": "EPSG:32614", "transform": Affine(1, 0, 500000, 0, -1, 5200000)}
    with rasterio.open(
        path, "w", **profile, tiled=True, blockxsize=256, blockysize=256, sparse_ok=True
    ) as ds:
        ds.write(textured(1024, 1024), window=Window(0, 0, 1024, 1024))
    return path


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def test_an_upload_declaring_far_more_pixels_than_it_holds_is_refused_before_any_block_is_read(
    tmp_path: Path, slow: float
) -> None:
    """Reading every declared block of a 100000 x 100000 px sparse file costs tens of seconds and
    gigabytes; its header alone says it declares thousands of times its size."""
    body = sparse_geotiff(tmp_path / "vast.tif", 100_000).read_bytes()
    assert len(body) < 8e6
    peak_before = peak_rss_mb()
    with TestClient(create_app(WebSettings(tmp_path / "data", allowed_hosts=("testserver",)))) as client:
        start = time.monotonic()
        response = client.put("/api/orthophotos/vast", content=body)
        elapsed = time.monotonic() - start
        assert response.status_code == 413, response.text
        detail = response.json()["detail"]
        assert "100000 x 100000 px" in detail and "sparse" in detail and str(tmp_path) not in detail
        assert elapsed < ANSWER_S * slow, elapsed
        assert client.get("/api/orthophotos").json() == []
    assert peak_rss_mb() - peak_before < 500
    assert not list((tmp_path / "data" / "orthophotos").iterdir())


def test_an_ordinary_upload_is_still_read_whole(tmp_path: Path) -> None:
    """The NAIP quarter-quad (deflate, about its own size decoded) passes; so does a small sparse
    file, whose every block costs little to read."""
    with TestClient(create_app(WebSettings(tmp_path, allowed_hosts=("testserver",)))) as client:
        naip = client.put("/api/orthophotos/naip", content=naip_path("20200831").read_bytes())
        assert naip.status_code == 201, naip.text
        small = sparse_geotiff(tmp_path / "small.tif", 4096).read_bytes()
        assert client.put("/api/orthophotos/small", content=small).status_code == 201


def rss_mb() -> float:
    """This process's resident memory now (Linux)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * resource.getpagesize() / 1e6


def test_the_memory_a_large_validation_takes_is_handed_back(tmp_path: Path) -> None:
    """Every block of 20000 x 20000 px (1.2 GB decoded) read: GDAL's default cache would keep a
    gigabyte of them, and glibc the heap they took."""
    body = sparse_geotiff(tmp_path / "large.tif", 20_000).read_bytes()
    settings = WebSettings(tmp_path / "data", max_decoded_ratio=1000.0, allowed_hosts=("testserver",))
    with TestClient(create_app(settings)) as client:
        before = rss_mb()
        assert client.put("/api/orthophotos/large", content=body).status_code == 201
        assert rss_mb() - before < 300


def test_map_builds_are_queued_with_a_cap(tmp_path: Path) -> None:
    (tmp_path / "orthophotos").mkdir()
    shutil.copy(naip_path("20200831"), tmp_path / "orthophotos" / "naip.tif")
    settings = WebSettings(tmp_path, max_pending_builds=2, allowed_hosts=("testserver",))
    with TestClient(create_app(settings)) as client:
        answers = [
            client.post("/api/maps", json={"name": f"m{k}", "orthophoto": "naip", "altitude_m": 1000})
            for k in range(5)
        ]
        assert [a.status_code for a in answers] == [202, 202, 429, 429, 429], [a.text for a in answers]
        assert "2 map builds are already waiting or running" in answers[2].json()["detail"]
        assert len(client.get("/api/jobs").json()) == 2


def test_a_mission_stops_at_its_quota_and_old_runs_make_room(tmp_path: Path, package: MapPackage) -> None:
    """Frames 1 s apart over 1.9 km: 63 frames and their match pictures, were it not stopped."""
    quota = 400_000
    settings = WebSettings(
        linked_data_dir(tmp_path, package),
        max_run_bytes=quota,
        max_runs_bytes=int(1.5 * quota),
        allowed_hosts=("testserver",),
    )
    with TestClient(create_app(settings)) as client:
        first = client.post("/api/runs", json=mission_request(package, step_s=1.0)).json()["id"]
        run = wait_for_run(client, first)
        assert run["state"] == "cancelled" and "the limit of one mission" in run["end_reason"], run
        assert run["summary"] is not None  # stopped between frames, its summary written
        written = folder_bytes(tmp_path / "runs" / first)
        # It stops within a second of reaching the quota: a few frames over, not the whole flight.
        assert quota < written < quota + 40 * written / len(run["steps"]), (written, len(run["steps"]))
        assert len(run["steps"]) < 0.5 * 1900 / 30
        second = client.post("/api/runs", json=mission_request(package, step_s=1.0)).json()["id"]
        assert client.get(f"/api/runs/{first}").status_code == 404  # removed to make room
        assert [r["id"] for r in client.get("/api/runs").json()] == [second]
        wait_for_run(client, second)


@contextmanager
def _file_size_limit(max_bytes: int) -> Iterator[None]:
    """This process's writes capped at ``max_bytes`` per file (SIGXFSZ ignored: they fail)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (max_bytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


def test_an_upload_the_server_cannot_store_is_507_without_its_paths(tmp_path: Path) -> None:
    body = naip_path("20200831").read_bytes()
    with TestClient(create_app(WebSettings(tmp_path, allowed_hosts=("testserver",)))) as client:
        with _file_size_limit(len(body) // 2):
            response = client.put("/api/orthophotos/naip", content=body)
        assert response.status_code == 507, response.text
        detail = response.json()["detail"]
        assert errno.errorcode[errno.EFBIG] in detail and str(tmp_path) not in detail
        assert client.get("/api/orthophotos").json() == []


def _closed(sock: socket.socket, timeout_s: float) -> bytes:
    """What the server sent before closing the connection (fails if it is still open)."""
    sock.settimeout(timeout_s)
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    return data


def test_a_request_head_that_never_ends_is_answered_408_and_closed(tmp_path: Path, slow: float) -> None:
    """A head that stops short (a slowloris sends it a byte at a time), and a connection that
    sends nothing, are closed after ``header_timeout_s``; a head sent in two parts within it is
    answered as usual."""
    with served(WebSettings(tmp_path, header_timeout_s=2.0)) as (url, _, _):
        host, port = url.removeprefix("http://").split(":")
        silent = socket.create_connection((host, int(port)))
        start = time.monotonic()
        partial = socket.create_connection((host, int(port)))
        partial.sendall(b"GET /api/maps HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        for _ in range(3):  # each byte well within the deadline, none ending the head
            time.sleep(0.1)
            partial.sendall(b"X")
        with partial:
            answer = _closed(partial, timeout_s=2.0 + ANSWER_S * slow)
        assert answer.startswith(b"HTTP/1.1 408") and b"not received whole within 2 s" in answer, answer
        assert 2.0 <= time.monotonic() - start < 2.0 + ANSWER_S * slow
        with silent:
            assert _closed(silent, timeout_s=ANSWER_S * slow) == b""
        split = socket.create_connection((host, int(port)))
        with split:
            split.sendall(b"GET /api/maps HTTP/1.1\r\n")
            time.sleep(0.3)
            split.sendall(b"Host: 127.0.0.1\r\n\r\n")
            status, _, body = read_response(split, timeout_s=ANSWER_S * slow)
        assert status == 200 and json.loads(body) == []


def test_a_body_that_trickles_in_is_refused(tmp_path: Path, slow: float) -> None:
    """A byte now and then never trips the idle timeout; past it the body must keep a rate."""
    settings = WebSettings(tmp_path, body_idle_s=1.0, body_min_bytes_per_s=10_000)
    with served(settings) as (url, _, _):
        upload = open_request(url, "PUT /api/orthophotos/slow", b"II*\x00", content_length=1_000_000)
        start = time.monotonic()
        with upload:
            upload.settimeout(0.3)
            while time.monotonic() - start < 10.0 * slow:
                try:
                    upload.sendall(bytes(100))
                    if upload.recv(1, socket.MSG_PEEK):
                        break
                except TimeoutError:
                    continue
            status, headers, body = read_response(upload, timeout_s=ANSWER_S * slow)
        assert status == 408 and headers["connection"] == "close", body
        assert "slower than the 10000 bytes/s" in json.loads(body)["detail"]
        assert time.monotonic() - start < 1.0 + ANSWER_S * slow
    assert not list((tmp_path / "orthophotos").iterdir())

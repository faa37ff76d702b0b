"""Shared by the web tests: a data folder holding the real NAIP 2020 map, short missions, and
the server run in a thread on a free loopback port.

At 1000 m the whole NAIP quarter-quad (934 x 723 px, 5 m/px) is a 20-tile map built in about
a second; a mission across a third of it flies in a few seconds with ORB fixes.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import CAMERA, NAIP_ALT_M, naip_path

from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.web import WebSettings, make_server

MAP_NAME = "naip2020"
RUN_TIMEOUT_S = 60.0
ENDED = ("done", "failed", "cancelled")


def web_data_dir(root: Path) -> Path:
    """``root`` laid out as ``orthonav serve --data`` expects, with one map package built."""
    build_map(
        naip_path("20200831"),
        root / "maps" / MAP_NAME,
        CAMERA,
        TilingConfig(nominal_alt_m=NAIP_ALT_M),
        progress=False,
    )
    return root


def map_fraction(package: MapPackage, fx: float, fy: float) -> dict[str, float]:
    """The WGS84 point at a fraction of the map's width and height."""
    lat, lon = package.grid.pixel_to_latlon(fx * package.grid.width, fy * package.grid.height)
    return {"lat": float(lat), "lon": float(lon)}


def mission_request(package: MapPackage, **changes) -> dict:
    """A short mission (about 1.9 km at 30 m/s) over the NAIP map."""
    return {
        "map": MAP_NAME,
        "start": map_fraction(package, 0.3, 0.65),
        "target": map_fraction(package, 0.7, 0.35),
        "alt_agl_m": NAIP_ALT_M,
        "speed_mps": 30.0,
        "seed": 1,
        **changes,
    }


def wait_for_run(client, run_id: str, timeout_s: float = RUN_TIMEOUT_S) -> dict:
    """Poll the API until the run has ended (done, failed or cancelled)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        run = client.get(f"/api/runs/{run_id}").json()
        if run["state"] in ENDED:
            return run
        time.sleep(0.2)
    pytest.fail(f"run {run_id} still {run['state']} after {timeout_s} s")


def wait_for_steps(client, run_id: str, steps: int, timeout_s: float = RUN_TIMEOUT_S) -> dict:
    """Poll the API until the run has logged ``steps`` frames (it must still be flying)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        run = client.get(f"/api/runs/{run_id}").json()
        if len(run["steps"]) >= steps:
            return run
        assert run["state"] in ("queued", "running"), run
        time.sleep(0.1)
    pytest.fail(f"run {run_id}: fewer than {steps} steps after {timeout_s} s")


def linked_data_dir(root: Path, package: MapPackage) -> Path:
    """``root`` as a data folder whose one map is ``package`` (linked, not built again)."""
    (root / "maps").mkdir(parents=True, exist_ok=True)
    (root / "maps" / MAP_NAME).symlink_to(package.path)
    return root


def open_request(
    url: str, request: str, body: bytes = b"", content_length: int | None = None
) -> socket.socket:
    """A connection to the server at ``url`` on which ``request`` ("METHOD /path") was sent, with
    ``body`` and a Content-Length header saying ``content_length`` (if given), as a raw client
    would: nothing waits for the server."""
    host, port = url.removeprefix("http://").split(":")
    length = "" if content_length is None else f"Content-Length: {content_length}\r\n"
    sock = socket.create_connection((host, int(port)))
    sock.sendall(f"{request} HTTP/1.1\r\nHost: {host}\r\n{length}\r\n".encode() + body)
    return sock


def read_response(sock: socket.socket, timeout_s: float) -> tuple[int, dict[str, str], bytes]:
    """Status, headers (lower-case names) and body of one response with a Content-Length."""
    sock.settimeout(timeout_s)
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"the server closed the connection before a response ({data!r})")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    fields = (line.partition(":") for line in lines)
    headers = {name.strip().lower(): value.strip() for name, _, value in fields}
    while len(body) < int(headers.get("content-length", 0)):
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection within the response body")
        body += chunk
    return int(status_line.split()[1]), headers, body


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def served(settings: WebSettings) -> Iterator[tuple[str, object, threading.Thread]]:
    """``orthonav serve`` in a thread on a free loopback port: (URL, uvicorn server, thread).
    Leaving the block stops the server as Ctrl-C would."""
    port = free_port()
    server = make_server(settings, "127.0.0.1", port)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 15.0
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            pytest.fail("the web server did not start")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}", server, thread
    finally:
        server.should_exit = True
        thread.join(timeout=30.0)

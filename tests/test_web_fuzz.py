"""Every route of the web app (found from the app itself, so a new route is fuzzed too) called
with hostile input: path parameters with '..', NUL, unicode or thousands of characters, random
query strings and methods, JSON bodies of the wrong types and shapes (huge numbers, NaN, booleans
for numbers), bodies that are not JSON, TIFFs cut short or corrupted. Never a 5xx, every answer
within ``LATENCY_S`` (stretched by the machine's measured slowdown: another process taking a
core makes answers late, not wrong), no request that leaves the process much larger, and the
memory the server keeps once the fuzz's missions have ended bounded.

Each parameter is sometimes given a value that exists (the map, a finished run, one of the map's
tiles) so that the fuzz reaches past the 404s: tiles are rendered and missions start (each is
cancelled at once)."""

from __future__ import annotations

import gc
import json
import os
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote, urlencode

import morecantile
import pytest

pytest.importorskip("fastapi", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("rio_tiler", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("httpx", reason="the FastAPI test client needs httpx (test extra)")

from conftest import naip_path
from fastapi.testclient import TestClient
from helpers_timing import slowdown
from helpers_web import MAP_NAME, wait_for_run, wait_for_steps, web_data_dir
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from starlette.routing import Mount

from orthonav.web import WebSettings, create_app
from orthonav.web.memory import release_memory

LATENCY_S = 2.0  # on an idle machine; times the slowdown on a busy one
EXAMPLES_PER_ROUTE = 60
RETAINED_MB = 64  # kept after the fuzz, its missions ended and freed memory handed back
STEP_GROWTH_MB = 256  # after any one request: a transient working set, not a runaway allocation
METHODS = ("GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS")
PARAM = re.compile(r"\{(\w+)(?::\w+)?\}")
RUN_ID = "20200101-000000-abcdef"  # a finished run, made by hand
TIFF_HEAD = naip_path("20200831").read_bytes()[:65536]
WEB_MERCATOR = morecantile.tms.get("WebMercatorQuad")

# Values a field of any type may be given: numbers at and past every bound, non-numbers.
EDGE_VALUES = st.sampled_from(
    [
        0,
        -1,
        1,
        -0.0,
        1e-300,
        1e308,
        -1e308,
        2**31,
        2**63,
        2**64 + 1,
        10**40,
        True,
        False,
        None,
        "",
        "1",
        [],
        {},
    ]
)
JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**80), 2**80)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=30),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4)
    ),
    max_leaves=20,
)
HOSTILE = EDGE_VALUES | JSON_VALUES | st.fixed_dictionaries({"lat": EDGE_VALUES, "lon": JSON_VALUES})
SEGMENTS = st.one_of(
    st.sampled_from(
        [
            "..",
            "../..",
            "..%2F..",
            "%00",
            "a%00b",
            "%ff",
            "%C0%AF",
            ".hidden",
            "",
            " ",
            "%2e%2e",
            "//",
            "\x00",
            "é",
        ]
    ),
    st.text(max_size=20),
    st.integers(-(2**70), 2**70).map(str),
    st.integers(0, 30).map(str),
    st.integers(64, 5000).map(lambda n: "x" * n),
)
# A real TIFF cut short, some of its header bytes changed: GDAL's parsing of a hostile upload.
CORRUPT_TIFFS = st.builds(
    lambda length, flips: bytes(_flipped(TIFF_HEAD[:length], flips)),
    st.integers(4, len(TIFF_HEAD)),
    st.lists(st.tuples(st.integers(4, 4095), st.integers(0, 255)), max_size=8),
)


def _flipped(data: bytes, flips: list[tuple[int, int]]) -> bytearray:
    out = bytearray(data)
    for position, value in flips:
        if position < len(out):
            out[position] = value
    return out


@dataclass
class Fuzzed:
    """What the fuzz found: slowest answer, the request after which the memory grew most over the
    largest before it, the missions it started; and the machine's slowdown, the most measured (at
    the start and at each late answer)."""

    slowdown: float = 1.0
    requests: int = 0
    slowest_s: float = 0.0
    peak_mb: float = 0.0
    largest_growth: tuple[float, str] = (0.0, "")
    statuses: dict[int, int] = field(default_factory=dict)
    missions: list[str] = field(default_factory=list)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    """The app over the NAIP map and one finished run, with small limits."""
    data = web_data_dir(tmp_path_factory.mktemp("fuzz"))
    run = data / "runs" / RUN_ID
    (run / "frames").mkdir(parents=True)
    (run / "web.json").write_text(json.dumps({"id": RUN_ID, "state": "done", "request": {"map": MAP_NAME}}))
    (run / "steps.jsonl").write_text(json.dumps({"step": 0, "accepted": True}) + "\n")
    (run / "nav.jsonl").write_text(json.dumps({"t": 0.0, "nav_error_m": 1.0}) + "\n")
    (run / "summary.json").write_text(json.dumps({"steps": 1}))
    limits = WebSettings(
        data, max_upload_bytes=1 << 20, allowed_hosts=("testserver",), max_pending_runs=2, body_idle_s=1.0
    )
    return create_app(limits)


@pytest.fixture(scope="module")
def client(app) -> Iterator[TestClient]:
    with TestClient(app) as test_client:  # leaving it stops the missions the fuzz started
        yield test_client


def _routes(app) -> list[tuple[str, tuple[str, ...]]]:
    """(path template, methods) of every route: the API's from its OpenAPI schema (FastAPI may
    keep an included router as one entry of ``app.routes``), the others (the page, the schema, a
    mounted app as '{mount}/{path}') from ``app.routes``."""
    routes: dict[str, set[str]] = {}
    for path, operations in app.openapi()["paths"].items():
        routes.setdefault(path, set()).update(method.upper() for method in operations)
    for route in app.routes:
        if isinstance(route, Mount):
            routes[route.path + "/{path:path}"] = {"GET", "HEAD"}
        elif getattr(route, "path", None) and getattr(route, "methods", None):
            routes.setdefault(route.path, set()).update(route.methods)
    return [(path, tuple(sorted(methods))) for path, methods in sorted(routes.items())]


def _existing(client: TestClient) -> list[dict[str, str]]:
    """Path parameters naming things that exist: the map and one of its tiles at zooms from the
    whole world to centimetres, the finished run and its files, a static asset."""
    (south, west), (north, east) = client.get(f"/api/maps/{MAP_NAME}").json()["bounds"]
    names = {"name": MAP_NAME, "run_id": RUN_ID, "path": "summary.json"}
    centres = [
        WEB_MERCATOR.tile((west + east) / 2, (south + north) / 2, z) for z in (0, 8, 11, 13, 15, 17, 24)
    ]
    tiles = [(t.z, t.x + dx, t.y + dy) for t in centres for dx, dy in ((0, 0), (1, 1), (-2, 0))]
    return [{**names, "z": str(z), "x": str(x), "y": str(y)} for z, x, y in tiles] + [
        {**names, "path": "vendor/leaflet/leaflet.js"},
        {**names, "path": "frames"},
    ]


def _json_bodies(app, template: str) -> st.SearchStrategy[object]:
    """Bodies for a route with a JSON model: its example (when it has one) with up to two fields,
    or an unknown one, given hostile values; any JSON value otherwise."""
    schema = app.openapi()
    for operation in schema["paths"].get(template, {}).values():
        ref = (
            operation.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema", {})
        )
        if "$ref" in ref:
            model = schema["components"]["schemas"][ref["$ref"].rsplit("/", 1)[1]]
            example = model.get("examples", [{}])[0]
            fields = st.sampled_from([*model["properties"], "unexpected"])
            changes = st.dictionaries(
                fields, HOSTILE | st.sampled_from(list(example.values()) or [None]), max_size=2
            )
            shaped = changes.map(lambda changed, base=example: {**base, **changed})
            return st.one_of(shaped, shaped, JSON_VALUES)
    return JSON_VALUES


@st.composite
def requests(draw, app, template: str, methods: tuple[str, ...], existing: list[dict[str, str]]) -> dict:
    """One hostile request for the route at ``template``."""
    known = draw(st.sampled_from(existing))

    def parameter(match: re.Match) -> str:
        value = draw(st.sampled_from([known[match[1]]]) | SEGMENTS) if match[1] in known else draw(SEGMENTS)
        return quote(value, safe=draw(st.sampled_from(["", "/", "/%"])))

    path = PARAM.sub(parameter, template)
    keys = st.sampled_from(["run", "z", "name", "x"]) | st.text(max_size=5)
    query = draw(st.dictionaries(keys, st.lists(SEGMENTS | st.just(RUN_ID), max_size=3), max_size=3))
    if query:
        path += "?" + urlencode(query, doseq=True)
    method = draw(st.sampled_from(methods if draw(st.integers(0, 3)) else METHODS))  # mostly the route's
    kind = draw(st.sampled_from(["none", "json", "json", "bytes", "tiff", "text"]))
    headers, content = {}, None
    if kind == "json":
        content = json.dumps(draw(_json_bodies(app, template))).encode()  # NaN and Infinity included
        headers["content-type"] = "application/json"
    elif kind != "none":
        bodies = {"bytes": st.binary(max_size=2048), "tiff": CORRUPT_TIFFS, "text": st.text(max_size=200)}
        content = draw(bodies[kind])
        content = content.encode() if isinstance(content, str) else content
        headers["content-type"] = draw(
            st.sampled_from(["application/json", "image/tiff", "text/plain", "x/y"])
        )
    return {"method": method, "url": path, "content": content, "headers": headers}


def _rss_mb() -> float:
    """The process's resident memory now. Not its lifetime peak (ru_maxrss): in a full test run
    that peak is set by earlier tests, and any later drift past it would be blamed on the fuzz."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _settled_rss_mb() -> float:
    """Resident memory once garbage is collected and freed heap handed back, as the server does
    after a large request or a mission: what is left is what the process keeps."""
    gc.collect()
    release_memory()
    return _rss_mb()


def _send(client: TestClient, request: dict, fuzzed: Fuzzed) -> None:
    """Send it and check the answer. A mission it started is cancelled at once."""
    start = time.perf_counter()
    response = client.request(**request)
    latency = time.perf_counter() - start
    what = f"{request['method']} {request['url'][:200]}"
    assert response.status_code < 500, f"{what}: {response.status_code} {response.text[:300]}"
    if latency >= LATENCY_S * fuzzed.slowdown:  # late, or the machine got busier since measured
        fuzzed.slowdown = max(fuzzed.slowdown, slowdown())
    assert latency < LATENCY_S * fuzzed.slowdown, (
        f"{what}: answered in {latency:.2f} s (slowdown {fuzzed.slowdown:.2f})"
    )
    if response.status_code == 202 and request["url"].startswith("/api/runs"):
        fuzzed.missions.append(response.json()["id"])
        client.post(f"/api/runs/{fuzzed.missions[-1]}/cancel")
    now_mb = _rss_mb()
    fuzzed.largest_growth = max(fuzzed.largest_growth, (now_mb - fuzzed.peak_mb, what))
    fuzzed.peak_mb, fuzzed.slowest_s = max(fuzzed.peak_mb, now_mb), max(fuzzed.slowest_s, latency)
    fuzzed.requests += 1
    fuzzed.statuses[response.status_code] = fuzzed.statuses.get(response.status_code, 0) + 1


def test_no_route_answers_5xx_slowly_or_grows_memory_under_hostile_input(app, client) -> None:
    routes = _routes(app)
    assert {"/api/runs", "/api/maps/{name}/tiles/{z}/{x}/{y}.png", "/static/{path:path}"} <= {
        r[0] for r in routes
    }
    existing = _existing(client)
    # Warm-up: every route with existing names, and a mission flown a few frames, so that caches,
    # imports and a mission's working set are not counted.
    for template, methods in routes:
        for known in existing:
            client.request(methods[0], PARAM.sub(lambda m, k=known: k.get(m[1], "x"), template))
    mission = app.openapi()["components"]["schemas"]["MissionRequest"]["examples"][0]
    run_id = client.post("/api/runs", json=mission).json()["id"]
    wait_for_steps(client, run_id, 3)
    client.post(f"/api/runs/{run_id}/cancel")
    wait_for_run(client, run_id)
    before = _settled_rss_mb()
    fuzzed = Fuzzed(slowdown=slowdown(), peak_mb=before)
    for template, methods in routes:

        @settings(
            max_examples=EXAMPLES_PER_ROUTE,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        )
        @given(request=requests(app, template, methods, existing))
        def fuzz(request: dict) -> None:
            _send(client, request, fuzzed)

        fuzz()
    for run_id in fuzzed.missions:
        wait_for_run(client, run_id)
    retained = _settled_rss_mb() - before
    statuses = dict(sorted(fuzzed.statuses.items()))
    print(
        f"\n{fuzzed.requests} requests over {len(routes)} routes: statuses {statuses}, "
        f"slowest {fuzzed.slowest_s:.3f} s (slowdown {fuzzed.slowdown:.2f}), "
        f"memory peak +{fuzzed.peak_mb - before:.1f} MB, kept +{retained:.1f} MB"
    )
    assert fuzzed.largest_growth[0] < STEP_GROWTH_MB, (
        f"the memory grew {fuzzed.largest_growth[0]:.0f} MB after {fuzzed.largest_growth[1]}"
    )
    assert retained < RETAINED_MB, f"the server kept {retained:.0f} MB after the fuzz"
    assert fuzzed.statuses.get(200, 0) > fuzzed.requests // 10, "the fuzz reaches past the 4xx"

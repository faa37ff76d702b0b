"""Routes of the JSON API: maps and their tiles, orthophoto uploads, map builds, missions, runs.

Nothing is computed here: maps come from ``orthonav.mapdb``, tiles from rio-tiler, missions
and their logs, summaries and plots from ``orthonav.sim``; the routes validate, start work
and hand files and records over.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import threading
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from orthonav.atomic import WRITE_ERRNOS, file_error
from orthonav.errors import OrthonavError
from orthonav.features import available_backends
from orthonav.frames import MATCHES_PREFIX
from orthonav.fusion import IMU_PRESETS
from orthonav.web.bodies import RequestBody
from orthonav.web.jobs import FIX_SOURCES, BuildPlan, Jobs, MissionPlan, failure_message
from orthonav.web.models import BuildRequest, MissionRequest
from orthonav.web.store import TERMINAL, Conflict, DataStore, http_status
from orthonav.web.tiles import MAX_ZOOM, TileRenderer
from orthonav.web.uploads import validate_geotiff
from orthonav.web.waiting import ClientLeft, Closing

TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # classic and BigTIFF, both byte orders
POLL_S = 0.25
CLIENT_LEFT = 499  # the status logged for a request whose client left before its answer (nginx's)
# Where run_mission saves frame N with save_frames, and the picture of its fix's matches.
FRAME_NAME = "frames/frame_{:05d}.jpg"
MATCHES_NAME = "frames/" + MATCHES_PREFIX + "{:05d}.jpg"

router = APIRouter(prefix="/api")


def _store(request: Request) -> DataStore:
    return request.app.state.store


def _jobs(request: Request) -> Jobs:
    return request.app.state.jobs


def _tiles(request: Request) -> TileRenderer:
    return request.app.state.tiles


Store = Annotated[DataStore, Depends(_store)]
JobsDep = Annotated[Jobs, Depends(_jobs)]


# --- maps and tiles -------------------------------------------------------------------------


@router.get("/options", summary="Choices for the forms: fix sources, feature backends, IMU grades")
def options(request: Request) -> dict:
    return {
        "fix_sources": FIX_SOURCES,
        "features": available_backends(),
        "imu": sorted(IMU_PRESETS),
        "max_upload_bytes": request.app.state.settings.max_upload_bytes,
    }


@router.get("/maps", summary="Map packages, with summary and WGS84 bounds (or why one cannot be opened)")
def list_maps(store: Store) -> list[dict]:
    return [store.map_info(name).to_dict() for name in store.map_names()]


@router.get("/maps/{name}", summary="One map package")
def get_map(name: str, store: Store) -> dict:
    store.open_map(name)  # 404 for an unknown map
    return store.map_info(name).to_dict()


@router.get(
    "/maps/{name}/tiles/{z}/{x}/{y}.png",
    summary="XYZ (Web Mercator) PNG tile of the map's orthophoto",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, 404: {"description": "no imagery in this tile"}},
)
async def map_tile(
    name: str,
    z: Annotated[int, PathParam(ge=0, le=MAX_ZOOM)],
    x: Annotated[int, PathParam(ge=0)],
    y: Annotated[int, PathParam(ge=0)],
    request: Request,
    store: Store,
) -> Response:
    if x >= 2**z or y >= 2**z:
        raise OrthonavError(f"tile {z}/{x}/{y}: x and y must be below 2^{z} = {2**z}")
    source = await run_in_threadpool(store.map_source, name)
    try:
        png = await _tiles(request).render(source, z, x, y, request.is_disconnected)
    except ClientLeft:  # nobody is left to read the answer
        return Response(status_code=CLIENT_LEFT)
    return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=600"})


@router.post("/maps", status_code=202, summary="Build a map package from an uploaded orthophoto")
def start_build(body: BuildRequest, store: Store, jobs: JobsDep) -> dict:
    if body.name in store.map_names() or jobs.building(body.name):
        raise Conflict(f"map {body.name!r}: already exists or is being built; choose another name")
    store.existing_orthophoto(body.orthophoto)
    if body.features not in available_backends():
        raise OrthonavError(
            f"features {body.features!r}: expected one of {', '.join(available_backends())} (installed here)"
        )
    fields = body.model_dump()
    plan = BuildPlan(map_name=fields.pop("name"), **fields)
    return jobs.submit_build(plan).to_dict()


@router.get("/jobs", summary="Map builds, newest first")
def list_jobs(jobs: JobsDep) -> list[dict]:
    return [job.to_dict() for job in jobs.build_jobs()]


@router.get("/jobs/{job_id}", summary="One map build: state, tiles done of total, error")
def get_job(job_id: str, jobs: JobsDep) -> dict:
    return jobs.build_job(job_id).to_dict()


# --- orthophotos ------------------------------------------------------------------------------


@router.get("/orthophotos", summary="Uploaded orthophotos (to build maps from, or to render frames from)")
def list_orthophotos(store: Store) -> list[dict]:
    return store.orthophotos()


@router.put(
    "/orthophotos/{name}",
    status_code=201,
    summary="Upload a GeoTIFF (the request body is the file); validated before it is kept",
    openapi_extra={
        "requestBody": {"content": {"image/tiff": {"schema": {"type": "string", "format": "binary"}}}}
    },
)
async def upload_orthophoto(name: str, request: Request, store: Store) -> dict:
    body, settings = RequestBody(request), request.app.state.settings
    try:
        return await _upload(name, body, store, settings.max_upload_bytes, settings.max_decoded_ratio)
    except (HTTPException, OrthonavError) as exc:
        raise await _refusal(body, exc) from None
    except OSError as exc:  # the server's disk is full, or its file size limit reached
        raise await _refusal(body, CannotStore(exc)) from None


async def _upload(
    name: str, body: RequestBody, store: DataStore, limit: int, max_decoded_ratio: float
) -> dict:
    dest = store.orthophoto_path(name)
    if dest.exists():
        raise Conflict(f"orthophoto {name!r}: already uploaded; choose another name")
    if body.declared_length is not None and body.declared_length > limit:
        raise HTTPException(
            413, f"upload of {body.declared_length} bytes: larger than the limit of {limit} bytes"
        )
    work = store.upload_folder()
    try:
        received = await _receive(body, work / dest.name, limit)
        await run_in_threadpool(validate_geotiff, received, name, max_decoded_ratio)
        try:
            os.link(received, dest)  # never replaces a file of the same name uploaded meanwhile
        except FileExistsError:
            raise Conflict(f"orthophoto {name!r}: already uploaded; choose another name") from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {"name": dest.stem, "size_bytes": dest.stat().st_size}


class CannotStore(HTTPException):
    """A write of the server's own that failed (507 for a full disk or quota, else 500), said
    without the server's paths."""

    def __init__(self, exc: OSError) -> None:
        status = 507 if exc.errno in WRITE_ERRNOS else 500
        super().__init__(status, f"the server cannot store it: {file_error(exc, show_path=False)}")


async def _refusal(body: RequestBody, exc: HTTPException | OrthonavError) -> Exception:
    """The refusal to answer an upload with, once what is left of its body has been read: a
    client still sending when the server closes gets a reset instead of the answer. A body too
    large or too slow to read within the drain budget is answered with 'Connection: close' (as
    a refusal that reads no more of it already is)."""
    if body.ended or isinstance(exc, Closing) or await body.drain():
        return exc
    if isinstance(exc, HTTPException):
        return Closing(exc.status_code, exc.detail)
    return Closing(http_status(exc), str(exc))


async def _receive(body: RequestBody, out: Path, limit: int) -> Path:
    """Stream the body to ``out``; stop at the size limit or as soon as it is not a TIFF."""
    head = b""
    with open(out, "wb") as fh:
        async for chunk in body.chunks():
            if body.received > limit:
                raise HTTPException(413, f"upload larger than the limit of {limit} bytes")
            if len(head) < 4:
                head += chunk[: 4 - len(head)]
                if len(head) == 4 and head not in TIFF_MAGIC:
                    raise HTTPException(415, "not a TIFF file: only GeoTIFF orthophotos are accepted")
            fh.write(chunk)
    if len(head) < 4:
        raise HTTPException(415, f"{body.received} bytes received: too short for a GeoTIFF")
    return out


# --- missions and runs -------------------------------------------------------------------------


@router.post("/runs", status_code=202, summary="Start a simulated mission; it runs in the background")
def start_mission(body: MissionRequest, store: Store, jobs: JobsDep) -> dict:
    plan = _plan(body, store)
    if jobs.pending_runs() >= jobs.max_pending_runs:
        raise HTTPException(
            429, f"{jobs.max_pending_runs} missions are already waiting or flying; retry later"
        )
    return store.run_state(jobs.submit_mission(plan, body.model_dump()))


def _plan(body: MissionRequest, store: Store) -> MissionPlan:
    """Everything that can be checked before the mission starts, checked (4xx, not a failed run)."""
    package = store.open_map(body.map)
    try:  # a damaged chunk met in flight would fail the mission over its area
        package.require_intact()
    except OrthonavError as exc:
        raise Conflict(failure_message(exc)) from None
    config = body.to_config()
    for what, point in (("start", body.start), ("target", body.target)):
        if not package.grid.contains_latlon(point.lat, point.lon):
            raise OrthonavError(
                f"{what} {point.lat:.6f}, {point.lon:.6f}: outside the map {body.map!r}; "
                "pick a point on the orthophoto"
            )
    source = store.map_source(body.map)
    frames = store.existing_orthophoto(body.frames_from) if body.frames_from else source
    return MissionPlan(body.map, config, frames, body.fix_source)


@router.get("/runs", summary="Past and current runs, newest first: state, request, summary")
def list_runs(store: Store) -> list[dict]:
    return [_run_entry(store, run_id) for run_id in store.run_ids()]


@router.get("/runs/{run_id}", summary="One run: state, config, summary, every step and navigation record")
def get_run(run_id: str, store: Store) -> dict:
    run_dir = store.run_dir(run_id)
    config = run_dir / "config.json"
    return {
        **_run_entry(store, run_id),
        "config": json.loads(config.read_text()) if config.is_file() else None,
        "steps": [_with_frame(run_id, run_dir, r) for r in _read_jsonl(run_dir / "steps.jsonl")[0]],
        "nav": _read_jsonl(run_dir / "nav.jsonl")[0],
        "files": store.run_files(run_id),
    }


@router.post(
    "/runs/{run_id}/cancel",
    status_code=202,
    summary="Cancel a mission: a queued one never starts, a flying one stops at its next frame",
)
def cancel_run(run_id: str, store: Store, jobs: JobsDep) -> dict:
    store.run_dir(run_id)  # 404 for an unknown run
    return jobs.cancel_mission(run_id)


@router.get("/compare", summary="Several runs side by side: request and summary of each")
def compare_runs(
    store: Store, run: Annotated[list[str], Query(min_length=2, max_length=8, description="run ids")]
) -> dict:
    return {"runs": [_run_entry(store, run_id) for run_id in run]}


@router.get(
    "/runs/{run_id}/events",
    summary="Server-sent events: 'nav' (1 Hz) and 'step' (per frame) records as written, 'state' changes",
    response_class=StreamingResponse,
)
def run_events(run_id: str, request: Request, store: Store) -> StreamingResponse:
    store.run_dir(run_id)  # 404 before the stream starts
    return StreamingResponse(
        _events(store, run_id, request.app.state.stopping),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache"},
    )


async def _events(store: DataStore, run_id: str, stopping: threading.Event) -> AsyncIterator[str]:
    """Follow the run's logs until it ends (done, cancelled or failed) or the server stops; a
    finished run is replayed whole.

    The state is read before the logs, so once it reads as ended the logs read after it are
    complete.
    """
    run_dir = store.run_dir(run_id)
    offsets = {"nav": 0, "step": 0}
    last = None
    while True:
        state = store.run_state(run_id)
        for kind, file in (("nav", "nav.jsonl"), ("step", "steps.jsonl")):
            records, offsets[kind] = _read_jsonl(run_dir / file, offsets[kind])
            for record in records:
                yield _sse(kind, _with_frame(run_id, run_dir, record) if kind == "step" else record)
        if state != last:
            yield _sse("state", {**state, "summary": store.run_summary(run_id)})
            last = state
        if state.get("state") in TERMINAL or stopping.is_set():
            return
        await asyncio.sleep(POLL_S)


def _sse(event: str, data: dict) -> str:
    return f"event: {event}\ndata: {json.dumps(data)}\n\n"


@router.get("/runs/{run_id}/files", summary="The run's output files (logs, summary, config, PNGs, frames)")
def list_run_files(run_id: str, store: Store) -> list[dict]:
    return store.run_files(run_id)


@router.get("/runs/{run_id}/files/{path:path}", summary="Download one output file of a run")
def get_run_file(run_id: str, path: str, store: Store) -> FileResponse:
    return FileResponse(store.run_file(run_id, path))


def _run_entry(store: DataStore, run_id: str) -> dict:
    return {**store.run_state(run_id), "summary": store.run_summary(run_id)}


def _with_frame(run_id: str, run_dir: Path, step: dict) -> dict:
    """The step with the URLs of its frame and of its matches picture (None where not saved:
    a fix source without point matches, or a fix that never reached RANSAC, has none)."""
    urls = {}
    for key, pattern in (("frame_url", FRAME_NAME), ("matches_url", MATCHES_NAME)):
        name = pattern.format(step["step"])
        urls[key] = f"/api/runs/{run_id}/files/{name}" if (run_dir / name).is_file() else None
    return {**step, **urls}


def _read_jsonl(path: Path, offset: int = 0) -> tuple[list[dict], int]:
    """Complete lines from byte ``offset`` on (a line being written is left for the next read)."""
    if not path.is_file():
        return [], offset
    with open(path, "rb") as fh:
        fh.seek(offset)
        data = fh.read()
    end = data.rfind(b"\n") + 1
    return [json.loads(line) for line in data[:end].splitlines() if line.strip()], offset + end

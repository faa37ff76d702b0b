"""The web application: the JSON API, the Leaflet page and its vendored assets, and the guards
a local service without accounts needs (allowed Host names, strict browser headers, user
errors as 4xx with their message)."""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.datastructures import MutableHeaders
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from orthonav import __version__
from orthonav.atomic import file_error
from orthonav.errors import OrthonavError
from orthonav.web.api import CannotStore, router
from orthonav.web.bodies import BodyIdleTimeout
from orthonav.web.jobs import Jobs
from orthonav.web.store import DataStore, http_status
from orthonav.web.tiles import TileRenderer, default_tile_workers

log = logging.getLogger(__name__)
STATIC_DIR = Path(__file__).parent / "static"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    # Everything the page needs is served here: no CDN, no inline script.
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data: blob:; connect-src 'self'; frame-ancestors 'none'; base-uri 'none'"
    ),
}


@dataclass(frozen=True)
class WebSettings:
    """What the service serves and its limits."""

    data_dir: Path
    max_upload_bytes: int = 1 << 30
    # Host names requests may address (DNS-rebinding guard); ("*",) accepts any.
    allowed_hosts: tuple[str, ...] = LOOPBACK_HOSTS
    max_pending_runs: int = 4
    # Map builds waiting or running (each one a process that takes a core for minutes).
    max_pending_builds: int = 2
    # A mission is stopped once its run folder (logs, frames) holds this much, and finished runs
    # are removed, oldest first, to keep all runs within max_runs_bytes.
    max_run_bytes: int = 250_000_000
    max_runs_bytes: int = 4_000_000_000
    # An upload whose pixels would take more than this many times its size once decoded is refused
    # before any block is read: validating it costs what its pixels take, and a sparse or extremely
    # compressed file declares far more than it holds (ordinary compression stays well below).
    max_decoded_ratio: float = 100.0
    # A request's head (request line and headers) must arrive whole within this, counted from the
    # connection's start or from the end of its previous answer; else the connection is closed.
    header_timeout_s: float = 10.0
    # A request body that sends nothing for this long is refused (408) and its connection closed;
    # so is one that arrives slower than body_min_bytes_per_s on average once body_idle_s has passed.
    body_idle_s: float = 30.0
    body_min_bytes_per_s: float = 1000.0
    # Tiles rendered at once, and how long a tile request may wait for its tile (then 503).
    tile_workers: int = field(default_factory=default_tile_workers)
    tile_timeout_s: float = 10.0
    # On stop, requests still open this long after (an upload, a stream) are cut off.
    shutdown_grace_s: float = 2.0


class SecurityHeaders:
    """Adds ``SECURITY_HEADERS`` to every HTTP response (a plain ASGI wrapper, stream-safe)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for key, value in SECURITY_HEADERS.items():
                    headers.setdefault(key, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)


def create_app(settings: WebSettings) -> FastAPI:
    """The application over ``settings.data_dir`` (maps/, orthophotos/, runs/ are created)."""
    store = DataStore(settings.data_dir)
    store.interrupt_unfinished_runs()
    store.remove_partial_uploads()
    jobs = Jobs(
        store,
        max_pending_runs=settings.max_pending_runs,
        max_pending_builds=settings.max_pending_builds,
        max_run_bytes=settings.max_run_bytes,
        max_runs_bytes=settings.max_runs_bytes,
    )
    stopping = threading.Event()  # set by the server as it stops: waiting requests give up
    tiles = TileRenderer(settings.tile_workers, settings.tile_timeout_s, stopping)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        yield
        tiles.shutdown()
        jobs.shutdown()

    app = FastAPI(
        title="orthonav",
        version=__version__,
        description="Plan simulated missions over map packages, watch them fly, compare runs.",
        openapi_url="/api/openapi.json",
        docs_url=None,  # the interactive docs load their scripts from a CDN; the schema is enough
        redoc_url=None,
        lifespan=lifespan,
    )
    app.state.settings, app.state.store, app.state.jobs = settings, store, jobs
    app.state.tiles, app.state.stopping = tiles, stopping
    app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    _add_error_handlers(app)
    app.add_middleware(
        BodyIdleTimeout,
        idle_s=settings.body_idle_s,
        min_bytes_per_s=settings.body_min_bytes_per_s,
        stopping=stopping,
    )
    app.add_middleware(SecurityHeaders)
    if "*" not in settings.allowed_hosts:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(settings.allowed_hosts))
    return app


def _add_error_handlers(app: FastAPI) -> None:
    """User errors as 4xx with one readable ``detail``; never a 500 for bad input. The server's
    own files failing (a full disk) is a 507 or 500 that says so, without its paths."""

    @app.exception_handler(OrthonavError)
    async def user_error(_: Request, exc: OrthonavError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=http_status(exc))

    @app.exception_handler(OSError)
    async def cannot_store(_: Request, exc: OSError) -> JSONResponse:
        log.error("%s", file_error(exc))  # the operator's to fix, with the path only they see
        refusal = CannotStore(exc)
        return JSONResponse({"detail": refusal.detail}, status_code=refusal.status_code)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        detail = "; ".join(_describe(error) for error in errors)
        return JSONResponse({"detail": detail, "errors": _jsonable(errors)}, status_code=422)


def _describe(error: dict) -> str:
    """'start.lat: Input should be less than or equal to 90 (got 95)'."""
    loc = [str(part) for part in error.get("loc", ()) if part not in ("body", "path", "query")]
    value = error.get("input")
    got = f" (got {repr(value)[:80]})" if value is not None and not isinstance(value, dict) else ""
    return f"{'.'.join(loc) or 'request'}: {error.get('msg', 'invalid')}{got}"


def _jsonable(errors: list[dict]) -> list[dict]:
    return [{"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")} for e in errors]

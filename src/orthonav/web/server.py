"""The uvicorn server for the app: loopback by default, every Host accepted only when bound wider;
stopping it cancels the missions first."""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import signal
import socket
import threading
from collections.abc import Iterator
from dataclasses import replace
from types import FrameType

import uvicorn

from orthonav.errors import OrthonavError
from orthonav.web.app import WebSettings, create_app
from orthonav.web.jobs import Jobs


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class _Server(uvicorn.Server):
    """uvicorn waits for open responses before the app's own shutdown: the app is told first
    (event streams end, requests waiting for a body or a tile are answered 503) and missions are
    cancelled (each stops at its next frame). Requests still open after the grace period
    (``WebSettings.shutdown_grace_s``) are cancelled.

    SIGTERM stops it as Ctrl-C does, and the process then exits with code 0: uvicorn raises the
    signal again once stopped, for the handler that was in place before it, which is ours."""

    def __init__(self, config: uvicorn.Config, jobs: Jobs, stopping: threading.Event) -> None:
        super().__init__(config)
        self.jobs = jobs
        self.stopping = stopping

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self.stopping.set()
        self.jobs.cancel_all()
        await super().shutdown(sockets)

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():  # signals are the main thread's
            with super().capture_signals():
                yield
            return
        previous = signal.signal(signal.SIGTERM, self._stop)
        try:
            with super().capture_signals():
                yield
        finally:
            signal.signal(signal.SIGTERM, previous)

    def _stop(self, signum: int, frame: FrameType | None) -> None:
        """A stop asked for (again, once stopped: nothing left to do)."""
        self.should_exit = True


def make_server(settings: WebSettings, host: str = "127.0.0.1", port: int = 8000) -> uvicorn.Server:
    """A server not yet started (``run()`` blocks; tests run it in a thread).

    Bound to a loopback address only loopback Host names are accepted (a web page elsewhere
    cannot reach the API through DNS rebinding); bound wider, the operator chose to expose it.
    """
    if not is_loopback(host):
        settings = replace(settings, allowed_hosts=("*",))
    app = create_app(settings)
    config = uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level="warning",
        access_log=False,
        timeout_graceful_shutdown=settings.shutdown_grace_s,
    )
    return _Server(config, app.state.jobs, app.state.stopping)


def bind_sockets(host: str, port: int) -> list[socket.socket]:
    """The listening sockets for ``host:port`` (one per address the name resolves to, as uvicorn
    would bind), bound before anything is announced: a port in use is one clear error, not a URL
    printed and then uvicorn's exit. Give them to ``server.run(sockets=...)``."""
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise OrthonavError(f"--host {host}: cannot be resolved ({exc.strerror})") from None
    sockets: list[socket.socket] = []
    try:
        for family, kind, proto, _, address in dict.fromkeys(infos):
            sockets.append(_bound(family, kind, proto, address, host, port))
    except OrthonavError:
        for sock in sockets:
            sock.close()
        raise
    return sockets


def _bound(family: int, kind: int, proto: int, address: tuple, host: str, port: int) -> socket.socket:
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if family == socket.AF_INET6:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise OrthonavError(
                f"port {port} on {host} is already in use (another orthonav serve?): "
                "choose another with --port"
            ) from None
        raise OrthonavError(f"cannot listen on {host} port {port}: {exc.strerror or exc}") from None
    return sock

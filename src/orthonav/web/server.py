"""The uvicorn server for the app: loopback by default, every Host accepted only when bound wider;
a request's head given a deadline; stopping it cancels the missions first."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import ipaddress
import signal
import socket
import threading
from collections.abc import Iterator
from dataclasses import replace
from types import FrameType
from typing import Any

import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

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


class HeadTimeoutProtocol(H11Protocol):
    """uvicorn's HTTP/1.1 connection with a deadline for each request's head: from the
    connection's start, and from the end of each answer, the next request line and headers must
    arrive whole within ``head_timeout_s``, else the connection is closed (with a 408 when part of
    a head had come). uvicorn alone closes a connection idle after an answer, but not one that
    sends a head a byte at a time, nor one that never sends a first request."""

    def __init__(self, *args: Any, head_timeout_s: float, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.head_timeout_s = head_timeout_s
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        if self._in_request():  # a head has arrived: its body and answer have their own bounds
            self._disarm()

    def handle_websocket_upgrade(self, event: Any) -> None:  # an h11.Request
        self._disarm()  # the connection is the WebSocket protocol's from here
        super().handle_websocket_upgrade(event)

    def on_response_complete(self) -> None:
        self._arm()  # first: the parent handles a pipelined request, which disarms it again
        super().on_response_complete()

    def _in_request(self) -> bool:
        return self.cycle is not None and not self.cycle.response_complete

    def _arm(self) -> None:
        self._disarm()
        self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_timed_out)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.transport.is_closing() or self._in_request():
            return
        if self.conn.trailing_data[0]:  # part of a head: say why (h11 cannot answer before a request)
            text = f"request head: not received whole within {self.head_timeout_s:g} s".encode()
            self.transport.write(
                b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
                b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(text), text)
            )
        self.transport.close()


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
        http=functools.partial(HeadTimeoutProtocol, head_timeout_s=settings.header_timeout_s),
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

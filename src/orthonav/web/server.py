"""The uvicorn server for the app: loopback by default, every Host accepted only when bound wider;
stopping it cancels the missions first."""

from __future__ import annotations

import ipaddress
import socket
from dataclasses import replace

import uvicorn

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
    """uvicorn waits for open responses before the app's own shutdown; a page following a
    mission keeps its event stream open until the mission ends, so missions are cancelled
    first (each stops at its next frame, and its stream ends with it)."""

    def __init__(self, config: uvicorn.Config, jobs: Jobs) -> None:
        super().__init__(config)
        self.jobs = jobs

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self.jobs.cancel_all()
        await super().shutdown(sockets)


def make_server(settings: WebSettings, host: str = "127.0.0.1", port: int = 8000) -> uvicorn.Server:
    """A server not yet started (``run()`` blocks; tests run it in a thread).

    Bound to a loopback address only loopback Host names are accepted (a web page elsewhere
    cannot reach the API through DNS rebinding); bound wider, the operator chose to expose it.
    """
    if not is_loopback(host):
        settings = replace(settings, allowed_hosts=("*",))
    app = create_app(settings)
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False)
    return _Server(config, app.state.jobs)

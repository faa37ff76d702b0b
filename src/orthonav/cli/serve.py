"""``orthonav serve``: the web interface (maps, live missions, past runs) on this machine."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from orthonav.errors import OrthonavError

console = Console(stderr=True)


def serve(
    data: Annotated[
        Path, typer.Option(help="Data folder: maps/ (map packages), orthophotos/ (uploads), runs/.")
    ] = Path("orthonav-web"),
    host: Annotated[
        str, typer.Option(help="Address to listen on. Anything but loopback exposes an API without accounts.")
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.")] = 8000,
    max_upload_mb: Annotated[float, typer.Option(help="Largest GeoTIFF upload accepted (MB).")] = 1024.0,
) -> None:
    """Serve the web interface: plan missions on the map, watch them fly, compare runs.

    Ctrl-C or SIGTERM stops it within seconds (missions are cancelled first); SIGTERM exits with 0.
    """
    if not (0 < port < 65536):
        raise OrthonavError(f"--port {port}: expected 1-65535")
    if not max_upload_mb > 0:
        raise OrthonavError(f"--max-upload-mb {max_upload_mb}: expected a positive size")
    try:
        from orthonav.web import WebSettings, is_loopback, make_server
        from orthonav.web.server import bind_sockets
    except ImportError as exc:
        raise OrthonavError(
            f"the web interface needs its extra: pip install 'orthonav[web]' ({exc})"
        ) from None
    settings = WebSettings(data.resolve(), max_upload_bytes=int(max_upload_mb * 1e6))
    sockets = bind_sockets(host, port)  # a port in use fails here, before any URL is printed
    try:
        server = make_server(settings, host, port)
    except BaseException:
        for sock in sockets:
            sock.close()
        raise
    if not is_loopback(host):
        console.print(
            f"[bold yellow]warning:[/] listening on {host}: anyone who can reach this port can upload "
            "files and start missions (there are no accounts)"
        )
    console.print(f"orthonav web interface: http://{host}:{port}/  (data in {settings.data_dir})")
    server.run(sockets=sockets)

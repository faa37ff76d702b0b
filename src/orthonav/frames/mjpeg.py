"""A camera served as MJPEG over HTTP, the stream most IP and companion cameras give.

``multipart/x-mixed-replace`` with one JPEG per part: every client gets each frame published
after it connected (never an older one: a late frame would be stamped as if it were new by a
reader that takes the receive time as capture time). Each part carries ``Content-Length`` so a
reader (FFmpeg's ``mpjpeg`` demuxer, which ``open_live_source("http://...")`` uses) hands the
frame over when its last byte arrives instead of waiting for the next boundary, one frame
period later; ``X-Timestamp`` carries the capture time (UNIX s) for readers that look.

Standard-library ``http.server``, one thread per client; a client that goes away or stalls
(``client_timeout_s``) ends its own thread only. :meth:`MjpegServer.close` ends every client's
stream and joins the threads.
"""

from __future__ import annotations

import errno
import logging
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import cv2
import numpy as np

from orthonav.errors import OrthonavError

log = logging.getLogger(__name__)

BOUNDARY = "orthonavframe"
DEFAULT_PATH = "/camera.mjpg"


@dataclass(frozen=True)
class _Jpeg:
    number: int  # 1, 2... in publication order
    data: bytes
    capture_time_s: float


@dataclass
class StreamStats:
    """What the server did: frames published, clients served, clients that went away mid-stream."""

    frames: int = 0
    clients: int = 0
    disconnects: int = 0

    def to_dict(self) -> dict:
        return {"frames": self.frames, "clients": self.clients, "disconnects": self.disconnects}


class MjpegServer:
    """``http://host:port/camera.mjpg``: the newest published frame to every connected client.

    ``open`` binds (port 0: a free one, see :attr:`port`) and serves on a thread; ``publish``
    encodes a frame once for all clients; ``close`` stops. Binds 127.0.0.1 unless told otherwise:
    a camera stream has no authentication.
    """

    poll_s = 0.2  # how often waiting threads look whether the server is closing
    client_timeout_s = 5.0  # a client that takes no data for this long is dropped

    def __init__(
        self, port: int, host: str = "127.0.0.1", path: str = DEFAULT_PATH, jpeg_quality: int = 90
    ) -> None:
        if not 0 <= port <= 65535:
            raise OrthonavError(f"camera stream port: expected 0..65535, got {port}")
        if not path.startswith("/"):
            raise OrthonavError(f"camera stream path: expected one starting with '/', got {path!r}")
        if not 1 <= jpeg_quality <= 100:
            raise OrthonavError(f"camera stream jpeg_quality: expected 1..100, got {jpeg_quality}")
        self.host, self.path, self.jpeg_quality = host, path, jpeg_quality
        self._port = port
        self.stats = StreamStats()
        self._cond = threading.Condition()
        self._latest: _Jpeg | None = None
        self._closed = threading.Event()
        self._httpd: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self._httpd.server_address[1] if self._httpd is not None else self._port

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}{self.path}"

    def open(self) -> MjpegServer:
        """Bind and start serving (idempotent); a port in use raises :class:`OrthonavError`."""
        if self._httpd is not None:
            return self
        try:
            httpd = ThreadingHTTPServer((self.host, self._port), _handler_for(self))
        except OSError as exc:
            raise OrthonavError(_bind_error(self.host, self._port, exc)) from exc
        self._closed.clear()
        self._httpd = httpd
        self._thread = threading.Thread(
            target=httpd.serve_forever, args=(self.poll_s,), name=f"mjpeg {self.url}", daemon=True
        )
        self._thread.start()
        log.info("camera stream: serving %s", self.url)
        return self

    def publish(self, image: np.ndarray, capture_time_s: float) -> None:
        """Encode ``image`` (BGR) as JPEG and hand it to every connected client."""
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise OrthonavError(f"camera stream: cannot encode a {image.shape} {image.dtype} image as JPEG")
        with self._cond:
            self.stats.frames += 1
            self._latest = _Jpeg(self.stats.frames, data.tobytes(), capture_time_s)
            self._cond.notify_all()

    def next_frame(self, after: int) -> _Jpeg | None:
        """The newest frame numbered above ``after``, waiting for one; None once closing."""
        with self._cond:
            while not self._closed.is_set():
                latest = self._latest
                if latest is not None and latest.number > after:
                    return latest
                self._cond.wait(self.poll_s)
        return None

    def newest_number(self) -> int:
        """Number of the newest frame published so far (0: none): a new client starts after it."""
        with self._cond:
            return self._latest.number if self._latest is not None else 0

    def count(self, clients: int = 0, disconnects: int = 0) -> None:
        """Tally clients that connected and that went away (client threads call it)."""
        with self._cond:
            self.stats.clients += clients
            self.stats.disconnects += disconnects

    def close(self) -> None:
        """End every client's stream, stop serving, release the port (idempotent)."""
        if self._httpd is None:
            return
        self._closed.set()
        with self._cond:
            self._cond.notify_all()
        self._httpd.shutdown()
        self._httpd.server_close()  # joins the client threads
        if self._thread is not None:
            self._thread.join()
        self._httpd = self._thread = None
        log.info("camera stream: closed (%s)", self.stats.to_dict())

    def __enter__(self) -> MjpegServer:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _bind_error(host: str, port: int, exc: OSError) -> str:
    if exc.errno == errno.EADDRINUSE:
        return (
            f"camera stream {host}:{port}: the port is already in use (another sim-vehicle or server?); "
            "choose another port"
        )
    return f"camera stream {host}:{port}: cannot listen there ({exc.strerror or exc})"


def _handler_for(server: MjpegServer) -> type[BaseHTTPRequestHandler]:
    """A request handler class bound to ``server`` (http.server makes one handler per request)."""

    class Handler(_StreamHandler):
        stream = server
        timeout = server.client_timeout_s

    return Handler


class _StreamHandler(BaseHTTPRequestHandler):
    stream: MjpegServer
    protocol_version = "HTTP/1.0"  # the stream ends when the connection does

    def do_GET(self) -> None:
        if self.path.split("?", 1)[0] != self.stream.path:
            self.send_error(404, f"the camera stream is at {self.stream.path}")
            return
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache, no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.stream.count(clients=1)
        log.info("camera stream: client %s:%d connected", *self.client_address[:2])
        try:
            self._send_frames()
        except OSError as exc:  # broken pipe, reset, timed out: this client is gone, the others stay
            self.stream.count(disconnects=1)
            log.info("camera stream: client %s:%d went away (%s)", *self.client_address[:2], exc)

    def _send_frames(self) -> None:
        sent = self.stream.newest_number()
        while (jpeg := self.stream.next_frame(sent)) is not None:
            head = (
                f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg.data)}\r\n"
                f"X-Timestamp: {jpeg.capture_time_s:.6f}\r\n\r\n"
            )
            self.wfile.write(head.encode("ascii") + jpeg.data + b"\r\n")
            self.wfile.flush()
            sent = jpeg.number
        self.wfile.write(f"--{BOUNDARY}--\r\n".encode("ascii"))  # the server is closing: a clean end

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("camera stream: " + format, *args)

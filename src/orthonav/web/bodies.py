"""Request bodies read with bounds: a body that stops arriving, or trickles in, is refused (408)
instead of holding its request open forever, and what is left of a refused upload is read and
discarded (within a budget) before the refusal is sent, so the client reads the 4xx instead of a
connection reset.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator

from fastapi import HTTPException
from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from orthonav.web.waiting import Closing, bounded_wait

# What a refused upload may still cost: its remaining body is discarded up to this many bytes,
# for up to this long; past either the refusal is sent with 'Connection: close'.
DRAIN_MAX_BYTES = 64 << 20
DRAIN_MAX_S = 2.0
# Every JSON request of the API is a few hundred bytes; FastAPI reads a JSON body whole into
# memory, so anything larger is refused before it is read.
JSON_MAX_BYTES = 1 << 20


class BodyStalled(Closing):
    """No byte of the request body for ``idle_s``: the rest may never come (a client that declared
    more than it sends), so the connection is closed with the answer."""

    def __init__(self, idle_s: float, received: int) -> None:
        super().__init__(
            408,
            f"request body: nothing received for {idle_s:g} s after {received} bytes; "
            "the body must arrive whole (as long as its Content-Length says), without pauses",
        )


class BodyTooSlow(Closing):
    """A body arriving byte by byte holds its request as long as a stalled one would."""

    def __init__(self, min_bytes_per_s: float, received: int, elapsed_s: float) -> None:
        super().__init__(
            408,
            f"request body: {received} bytes in {elapsed_s:.0f} s, slower than the "
            f"{min_bytes_per_s:g} bytes/s a body must keep to",
        )


class JsonTooLarge(Closing):
    def __init__(self) -> None:
        super().__init__(413, f"request body: a JSON body may be at most {JSON_MAX_BYTES} bytes")


class BodyIdleTimeout:
    """ASGI wrapper that bounds the wait for each part of a request body to ``idle_s`` (raising
    :class:`BodyStalled` in the route reading it) and ends it when the server stops; waits after
    the body has ended (a streamed response listening for the client to leave) are not bounded.
    Past its first ``idle_s`` the body must also have arrived at ``min_bytes_per_s`` on average
    (else :class:`BodyTooSlow`), as a byte now and then would hold it open without limit.
    A JSON body longer than ``JSON_MAX_BYTES`` raises :class:`JsonTooLarge` as it arrives."""

    def __init__(
        self, app: ASGIApp, idle_s: float, min_bytes_per_s: float, stopping: threading.Event
    ) -> None:
        self.app = app
        self.idle_s = idle_s
        self.min_bytes_per_s = min_bytes_per_s
        self.stopping = stopping

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ended, received = False, 0
        limit = JSON_MAX_BYTES if _is_json(scope) else None
        loop = asyncio.get_running_loop()
        start = loop.time()

        async def receive_within_idle() -> Message:
            nonlocal ended, received
            if ended:
                return await receive()
            try:
                message = await bounded_wait(receive, self.idle_s, self.stopping)
            except TimeoutError:
                raise BodyStalled(self.idle_s, received) from None
            received += len(message.get("body", b""))
            if limit is not None and received > limit:
                raise JsonTooLarge()
            ended = message["type"] != "http.request" or not message.get("more_body", False)
            elapsed_s = loop.time() - start
            if not ended and received < self.min_bytes_per_s * (elapsed_s - self.idle_s):
                raise BodyTooSlow(self.min_bytes_per_s, received, elapsed_s)  # past its first idle_s
            return message

        await self.app(scope, receive_within_idle, send)


def _is_json(scope: Scope) -> bool:
    content_type = dict(scope["headers"]).get(b"content-type", b"")
    return content_type.split(b";")[0].strip().lower() == b"application/json"


class RequestBody:
    """A request body read in parts, which knows whether it has been read to its end."""

    def __init__(self, request: Request) -> None:
        self._receive = request.receive
        declared = request.headers.get("content-length", "")
        # The HTTP server has checked the header's syntax; isascii() keeps '²' (a digit) out.
        self.declared_length = int(declared) if declared.isascii() and declared.isdigit() else None
        self.ended = False
        self.received = 0

    async def chunks(self) -> AsyncIterator[bytes]:
        """The body's parts as they arrive; a client that leaves before the end is a 400 (nobody
        reads it, but the request ends quietly)."""
        while not self.ended:
            message = await self._receive()
            if message["type"] == "http.disconnect":
                self.ended = True
                raise HTTPException(400, f"request body: the client left after {self.received} bytes")
            self.ended = not message.get("more_body", False)
            chunk = message.get("body", b"")
            self.received += len(chunk)
            yield chunk

    async def drain(self) -> bool:
        """Read and discard the rest of the body, within ``DRAIN_MAX_BYTES`` and ``DRAIN_MAX_S``;
        whether it was read to its end."""
        discarded = 0
        try:
            async with asyncio.timeout(DRAIN_MAX_S):
                async for chunk in self.chunks():
                    discarded += len(chunk)
                    if discarded > DRAIN_MAX_BYTES:
                        return False
        except (TimeoutError, HTTPException):  # too slow, stalled, or the client left
            return self.ended
        return True

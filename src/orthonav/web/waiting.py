"""Bounded waits for requests: what a request waits for (its body, its tile) is given up when it
takes too long, when the server stops, or when the client has left, instead of holding the
request (and the server's stop) open."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from typing import TypeVar

from fastapi import HTTPException

T = TypeVar("T")
POLL_S = 0.1  # how often a wait checks for the server's stop and the client's departure
CLOSE = {"Connection": "close"}


class Closing(HTTPException):
    """A refusal sent with 'Connection: close': the rest of the request will not be read."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(status, detail, headers=CLOSE)


class ServerStopping(Closing):
    """A request still waiting when the server stops: answered at once, not cut off later."""

    def __init__(self) -> None:
        super().__init__(503, "the server is stopping; send the request again once it is back")


class ClientLeft(Exception):
    """The client closed its connection while its request waited: nobody reads an answer."""


async def bounded_wait(
    step: Callable[[], Awaitable[T]],
    timeout_s: float,
    stopping: threading.Event,
    client_left: Callable[[], Awaitable[bool]] | None = None,
) -> T:
    """What ``step()`` returns. ``step`` is awaited ``POLL_S`` at a time, cancelled and called
    again in between (it must allow that: an ASGI ``receive``, a shielded future); raises
    TimeoutError after ``timeout_s``, :class:`ServerStopping` once ``stopping`` is set and
    :class:`ClientLeft` once ``client_left()`` says so."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while True:
        poll = asyncio.timeout(min(POLL_S, max(0.0, deadline - loop.time())))
        try:
            async with poll:
                return await step()
        except TimeoutError:
            if not poll.expired():
                raise  # step's own
        if stopping.is_set():
            raise ServerStopping()
        if client_left is not None and await client_left():
            raise ClientLeft
        if loop.time() >= deadline:
            raise TimeoutError

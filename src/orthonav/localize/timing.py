"""Stage timings and the frame's time budget.

Every fix carries the milliseconds each of its stages took. A companion computer localizing a
frame an interval gives a budget: the stages check it before costly work
(:class:`FrameDeadline`), so a frame that cannot be finished in time ends with what was verified
so far, or a rejection that says which stage the deadline stopped, instead of a late fix.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from orthonav.errors import OrthonavError

DEADLINE = "deadline"


def elapsed_ms(start: float) -> float:
    """Milliseconds since ``start``, a :func:`time.perf_counter` reading."""
    return (time.perf_counter() - start) * 1000.0


def check_budget_ms(budget_ms: float | None, what: str) -> None:
    """A frame budget is None (unbounded) or a positive number of milliseconds."""
    if budget_ms is not None and not (math.isfinite(budget_ms) and budget_ms > 0):
        raise OrthonavError(f"{what}: expected a frame budget in milliseconds > 0 (or none), got {budget_ms}")


class DeadlineSpent(OrthonavError):
    """The frame's budget was spent before a stage's costly work: the stage did not run."""


class FrameDeadline:
    """One frame's budget, counted from its start; None: unbounded (offline runs)."""

    def __init__(self, budget_ms: float | None) -> None:
        self.budget_ms = budget_ms
        self.start = time.perf_counter()

    @property
    def spent(self) -> bool:
        """Whether no time is left (never for an unbounded frame)."""
        return self.budget_ms is not None and elapsed_ms(self.start) >= self.budget_ms

    def left_ms(self) -> float:
        """Milliseconds left (infinite for an unbounded frame)."""
        return math.inf if self.budget_ms is None else self.budget_ms - elapsed_ms(self.start)

    def why(self, stage: str) -> str:
        """The rejection reason for a frame stopped before ``stage``."""
        budget, spent = f"{self.budget_ms:.0f} ms", f"{elapsed_ms(self.start):.0f} ms"
        return f"{DEADLINE}: the frame's {budget} budget stopped it before {stage} ({spent} in)"

    def check(self, stage: str) -> None:
        """Raises :class:`DeadlineSpent` naming ``stage`` where the budget is spent."""
        if self.spent:
            raise DeadlineSpent(self.why(stage))


class FrameClock:
    """The deadline of the frame being localized, shared by the cascades of a chain: the first
    starts it, a later one asked for the same frame (the chain's second correlation) continues
    it, so the chain as a whole keeps to the budget."""

    def __init__(self, budget_ms: float | None) -> None:
        check_budget_ms(budget_ms, "frame_budget_ms")
        self.budget_ms = budget_ms
        self._running: tuple[np.ndarray, object, FrameDeadline] | None = None

    def start(self, frame: np.ndarray, prior: object) -> FrameDeadline:
        """A new deadline for ``frame`` (localized with ``prior``)."""
        deadline = FrameDeadline(self.budget_ms)
        self._running = (frame, prior, deadline)
        return deadline

    def resume(self, frame: np.ndarray, prior: object) -> FrameDeadline:
        """The running deadline where it is this very frame and prior, else a new one."""
        running = self._running
        if running is not None and running[0] is frame and running[1] is prior:
            return running[2]
        return self.start(frame, prior)

    @contextmanager
    def unbounded(self) -> Iterator[None]:
        """Frames started within run without a budget: a warm-up must pay every stage's first
        load, which a flight's first frames would otherwise pay."""
        budget_ms, self.budget_ms = self.budget_ms, None
        try:
            yield
        finally:
            self.budget_ms = budget_ms


class StageCost:
    """What a stage took on the last frames it ran with a budget (their median): a stage is
    started only where the time left affords it, since once started it cannot be cut short.
    A skipped stage lowers the expectation a little (``SKIPPED_SHARE``), so a stage slowed for a
    while (a busy spell, a first load) is tried again and measured anew, not skipped for good."""

    SKIPPED_SHARE = 0.8

    def __init__(self, frames: int = 16) -> None:
        self._recent: deque[float] = deque(maxlen=frames)

    def add(self, ms: float, deadline: FrameDeadline) -> None:
        """The stage's time on a frame of ``deadline`` (an unbounded one, a warm-up, not kept)."""
        if deadline.budget_ms is not None:
            self._recent.append(ms)

    def skipped(self) -> None:
        """The stage was not started: expect a little less next time."""
        self._recent.append(self.SKIPPED_SHARE * self.expected_ms)

    @property
    def expected_ms(self) -> float:
        """The median of the recent times; 0 before the stage has run."""
        return float(np.median(self._recent)) if self._recent else 0.0

    def affordable(self, deadline: FrameDeadline) -> bool:
        """Whether ``deadline`` leaves the stage its expected time."""
        return deadline.left_ms() > self.expected_ms

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
    """One frame's budget, counted from its start; None: unbounded (offline runs).

    ``measured``: whether the stages' times on this frame say what they take (:class:`StageCost`):
    by default where it has a budget; a warm-up's second pass, after the first paid the loads,
    says it too. ``reserved_ms``: time kept for what must follow (:meth:`keeping`)."""

    def __init__(
        self, budget_ms: float | None, measured: bool | None = None, reserved_ms: float = 0.0
    ) -> None:
        self.budget_ms = budget_ms
        self.measured = budget_ms is not None if measured is None else measured
        self.reserved_ms = reserved_ms
        self.start = time.perf_counter()

    @property
    def warming(self) -> bool:
        """Whether this is a warm-up's measured pass (no budget, its times kept)."""
        return self.budget_ms is None and self.measured

    def keeping(self, reserved_ms: float) -> FrameDeadline:
        """The same frame's deadline with ``reserved_ms`` more kept for what follows (the checks
        of a pose found, which must run before it may be used)."""
        kept = FrameDeadline(self.budget_ms, self.measured, self.reserved_ms + reserved_ms)
        kept.start = self.start
        return kept

    @property
    def spent(self) -> bool:
        """Whether no time is left (never for an unbounded frame)."""
        return self.left_ms() <= 0.0

    def left_ms(self) -> float:
        """Milliseconds left, less those reserved (infinite for an unbounded frame)."""
        if self.budget_ms is None:
            return math.inf
        return self.budget_ms - self.reserved_ms - elapsed_ms(self.start)

    def stop_at(self, then_ms: float = 0.0) -> float | None:
        """The :func:`time.perf_counter` reading by which a step must end to leave ``then_ms``
        (and the reserve) for what follows; None for an unbounded frame."""
        if self.budget_ms is None:
            return None
        return self.start + (self.budget_ms - self.reserved_ms - then_ms) / 1000.0

    def why(self, stage: str) -> str:
        """The rejection reason for a frame stopped before ``stage``."""
        return self._stopped(f"it before {stage}")

    def why_stopped(self, step: str) -> str:
        """The rejection reason for a frame whose ``step`` was stopped at :meth:`stop_at`."""
        return self._stopped(step)

    def _stopped(self, what: str) -> str:
        budget, spent = f"{self.budget_ms:.0f} ms", f"{elapsed_ms(self.start):.0f} ms"
        return f"{DEADLINE}: the frame's {budget} budget stopped {what} ({spent} in)"

    def check(self, stage: str) -> None:
        """Raises :class:`DeadlineSpent` naming ``stage`` where the budget is spent."""
        if self.spent:
            raise DeadlineSpent(self.why(stage))

    def unaffordable(self, cost: StageCost, stage: str, then_ms: float = 0.0, units: float = 1.0) -> str:
        """Why ``stage`` may not start (the budget spent, or less left than it usually takes and
        ``then_ms`` for what must follow it); empty where it may. ``units``: the work it faces,
        where ``cost`` is kept per unit of work (:meth:`StageCost.affordable`). A stage not
        started counts as skipped (:meth:`StageCost.skipped`)."""
        if cost.affordable(self, then_ms, units):
            return ""
        expected_ms = cost.likely_ms * units + then_ms
        cost.skipped()
        if self.spent:
            return self.why(stage)
        return f"{self.why(stage)}: {self.left_ms():.0f} ms left, it takes about {expected_ms:.0f} ms"


class FrameClock:
    """The deadline of the frame being localized, shared by the cascades of a chain: the first
    starts it, a later one asked for the same frame (the chain's second correlation) continues
    it, so the chain as a whole keeps to the budget."""

    def __init__(self, budget_ms: float | None) -> None:
        check_budget_ms(budget_ms, "frame_budget_ms")
        self.budget_ms = budget_ms
        self._running: tuple[np.ndarray, object, FrameDeadline] | None = None
        self.warming = False  # within :meth:`unbounded`

    def start(self, frame: np.ndarray, prior: object, measured: bool | None = None) -> FrameDeadline:
        """A new deadline for ``frame`` (localized with ``prior``); ``measured`` as
        :class:`FrameDeadline`'s."""
        deadline = FrameDeadline(self.budget_ms, measured)
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
        load, which a flight's first frames would otherwise pay (``warming`` meanwhile: a
        cascade then localizes its frame twice, the second time measured, so that the first
        frames with a budget know what each stage takes)."""
        budget_ms, self.budget_ms, self.warming = self.budget_ms, None, True
        try:
            yield
        finally:
            self.budget_ms, self.warming = budget_ms, False


class StageCost:
    """What a stage took on the last measured frames it ran on (frames with a budget, a
    warm-up's once loaded): a stage is started only where the time left affords what it took on
    most of them (:attr:`likely_ms`, their upper quartile), since once started it cannot be cut
    short (an ONNX Runtime pass can: it is stopped at the deadline instead, see
    :func:`~orthonav.models.onnx.runtime.runs_stop_at`), and one started with only its median
    time left overruns on every other frame. A step that must follow one stopped at the deadline
    (the pose after the matching, the verification after the keypoint stage) is kept its time on
    nearly all of them (:attr:`kept_ms`): what it overruns by, nothing can stop.
    A skipped stage lowers the expectation a little (``SKIPPED_SHARE``), so a stage slowed for a
    while (a busy spell, a first load) is tried again and measured anew, not skipped for good;
    and one skipped ``MAX_SKIPS`` frames running forgets its times and is tried on the next:
    after a long busy spell (the process starved of the CPU) every recent time is a slow one,
    and lowering them a little per skip would keep a required search skipped, and every frame
    rejected, for tens of frames after the spell has ended."""

    SKIPPED_SHARE = 0.8
    MAX_SKIPS = 8

    def __init__(self, frames: int = 16) -> None:
        self._recent: deque[float] = deque(maxlen=frames)
        self._skips = 0  # frames running the stage was not started on

    def add(self, ms: float, deadline: FrameDeadline) -> None:
        """The stage's time on a frame of ``deadline`` (kept where it is measured: not an offline
        frame, nor a warm-up's first, which pays the loads)."""
        if deadline.measured:
            self._recent.append(ms)
            self._skips = 0

    def skipped(self) -> None:
        """The stage was not started: expect a little less next time, or, skipped
        ``MAX_SKIPS`` frames running, nothing until it has been measured again."""
        self._skips += 1
        if self._skips >= self.MAX_SKIPS:
            self._recent.clear()
            self._skips = 0
        else:
            self._recent.append(self.SKIPPED_SHARE * self.expected_ms)

    @property
    def expected_ms(self) -> float:
        """The median of the recent times; 0 before the stage has run."""
        return float(np.median(self._recent)) if self._recent else 0.0

    @property
    def likely_ms(self) -> float:
        """The upper quartile of the recent times (what the stage is given); 0 before it has run."""
        return float(np.percentile(self._recent, 75)) if self._recent else 0.0

    @property
    def kept_ms(self) -> float:
        """The 90th percentile of the recent times (what is kept for the stage where it must
        follow another); 0 before it has run."""
        return float(np.percentile(self._recent, 90)) if self._recent else 0.0

    def affordable(self, deadline: FrameDeadline, then_ms: float = 0.0, units: float = 1.0) -> bool:
        """Whether ``deadline`` leaves the stage its likely time and ``then_ms`` after it; for a
        cost kept per unit of work (a view's pixels), its likely time for ``units`` of it."""
        return deadline.left_ms() > self.likely_ms * units + then_ms

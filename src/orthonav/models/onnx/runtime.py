"""Which engine runs a learned part (torch or ONNX Runtime) and how ONNX Runtime runs on this
CPU: one thread per physical core, no spinning; a run stopped at the time its caller sets."""

from __future__ import annotations

import importlib.util
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, TypeVar

from orthonav.errors import OrthonavError

T = TypeVar("T")

RUNTIMES = ("auto", "torch", "onnx")
RUNTIME_ENV = "ORTHONAV_RUNTIME"


def torch_importable() -> bool:
    """Whether torch could be imported, without importing it."""
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):  # ValueError: sys.modules["torch"] is None (blocked)
        return False


def resolve_runtime(runtime: str, default: str | None = None) -> str:
    """``torch`` or ``onnx`` for a configured runtime. ``auto``: $ORTHONAV_RUNTIME if set, else
    ``default`` if given, else torch where it is installed (the behaviour before ONNX), else ONNX
    Runtime."""
    if runtime not in RUNTIMES:
        raise OrthonavError(f"runtime {runtime!r}: expected one of {', '.join(RUNTIMES)}")
    if runtime != "auto":
        return runtime
    chosen = os.environ.get(RUNTIME_ENV, "").strip()
    if chosen:
        if chosen not in ("torch", "onnx"):
            raise OrthonavError(f"${RUNTIME_ENV}={chosen!r}: expected torch or onnx")
        return chosen
    if default is not None:
        return default
    return "torch" if torch_importable() else "onnx"


def prefer_onnx(runtime: str) -> str:
    """``torch`` or ``onnx`` for a configured runtime, ``auto`` taking ONNX Runtime wherever it is
    installed (unless $ORTHONAV_RUNTIME says otherwise): for networks whose ONNX export is faster
    on a CPU and agrees with torch."""
    installed = importlib.util.find_spec("onnxruntime") is not None
    return resolve_runtime(runtime, default="onnx" if installed else None)


def physical_cores() -> int:
    """Physical cores this process may run on (its CPU affinity, a container's CPU quota): one
    thread per core, as hyperthreads share the vector units a convolution needs, and threads
    beyond the cores only wait for each other."""
    cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set(range(os.cpu_count() or 1))
    cores = set()
    for cpu in cpus:
        siblings = Path(f"/sys/devices/system/cpu/cpu{cpu}/topology/thread_siblings_list")
        try:
            cores.add(siblings.read_text().strip())
        except OSError:
            cores.add(str(cpu))
    return max(1, min(len(cores), _cpu_quota() or len(cores)))


def _cpu_quota() -> int | None:
    """CPUs a cgroup v2 quota allows (``cpu.max``: "quota period", or "max"), rounded up."""
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        return None if quota == "max" else max(1, -(-int(quota) // int(period)))
    except (OSError, ValueError, ZeroDivisionError):
        return None


def onnxruntime_module() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise OrthonavError(
            "the ONNX runtime needs onnxruntime: pip install 'orthonav[onnx]' "
            "(or run the model under torch: pip install 'orthonav[learned]')"
        ) from None
    return onnxruntime


def session_options(threads: int | None = None) -> Any:
    """One pool of ``threads`` (default: the physical cores) and no spinning: on a small shared
    CPU a spinning worker takes the core another thread needs (2 threads on 2 busy cores ran
    twice as slow with spinning on)."""
    ort = onnxruntime_module()
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or physical_cores()
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only: the quantised graphs' notes are not for users
    return options


# When the ONNX Runtime runs of this context must end (a time.perf_counter reading; None: never).
_STOP_AT: ContextVar[float | None] = ContextVar("orthonav_onnx_stop_at", default=None)


class RunStopped(RuntimeError):
    """An ONNX Runtime run stopped (or not started) at the time its caller set (:func:`runs_stop_at`)."""


@contextmanager
def runs_stop_at(stop_at: float | None) -> Iterator[None]:
    """ONNX Runtime runs within (:func:`run_session`) stop at ``stop_at``, a
    :func:`time.perf_counter` reading (None: no limit; within another limit, the earlier holds).
    A network's pass cannot be cut from Python once started, and where the load rises within it,
    it runs on past a frame's deadline; the runtime checks a stop flag between the graph's
    nodes, so a step cut there ends within a node's time of ``stop_at``."""
    outer = _STOP_AT.get()
    if stop_at is not None and outer is not None:
        stop_at = min(stop_at, outer)
    token = _STOP_AT.set(stop_at if stop_at is not None else outer)
    try:
        yield
    finally:
        _STOP_AT.reset(token)


def until_stopped(stop_at: float | None, step: Callable[..., T], *args: Any) -> T | None:
    """``step(*args)`` with its ONNX Runtime runs stopped at ``stop_at`` (:func:`runs_stop_at`);
    None where they were: a caller short of time gives up the step, not the frame's other work."""
    try:
        with runs_stop_at(stop_at):
            return step(*args)
    except RunStopped:
        return None


def run_session(session: Any, feed: dict[str, Any], outputs: list[str] | None = None) -> list[Any]:
    """``session.run(outputs, feed)``, stopped at the time :func:`runs_stop_at` set (raises
    :class:`RunStopped`)."""
    stop_at = _STOP_AT.get()
    if stop_at is None:
        return session.run(outputs, feed)
    left_s = stop_at - time.perf_counter()
    if left_s <= 0.0:
        raise RunStopped("no time left to start the run")
    options = onnxruntime_module().RunOptions()
    timer = threading.Timer(left_s, setattr, (options, "terminate", True))
    timer.start()
    try:
        return session.run(outputs, feed, options)
    except Exception:  # the runtime's own error types have no stable import path
        if options.terminate:
            raise RunStopped("the run was stopped at its time limit") from None
        raise
    finally:
        timer.cancel()

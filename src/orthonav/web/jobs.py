"""Work the service runs in the background: missions (in a thread) and map builds (a process).

A mission is flown by ``orthonav.sim.run_mission`` itself; its state (queued, running, done,
cancelled, failed and why) lives in the run folder beside the logs the mission writes, so a run
reads the same live, after the mission, and after a restart of the service. A cancelled mission
stops between two frames and still writes its summary and plot. A map build is the
``orthonav map build`` command in its own process: the same code path as the CLI, the server
stays responsive, and its progress is the build's own progress bar, read from its output.

What they may cost is bounded: missions and builds waiting or running are capped (more are
refused with 429), a mission is stopped once its run folder holds its quota, and finished runs
are removed, oldest first, to keep all runs within theirs.
"""

from __future__ import annotations

import logging
import os
import re
import secrets
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path

from orthonav.atomic import file_error
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.localize import CASCADE, CORRELATION, KEYPOINTS, open_fix_source
from orthonav.mapdb import MapPackage
from orthonav.sim import SIMULATED_WORLD, MissionConfig, run_mission
from orthonav.sim.mission import CANCELLED
from orthonav.types import FixSource
from orthonav.web.memory import release_memory
from orthonav.web.store import TERMINAL, Conflict, DataStore, NotFound, TooMany

log = logging.getLogger(__name__)

FIX_SOURCES = {
    "cascade": "correlation, then keypoints near it, the pose verified against the map (fly's default)",
    "map": "keypoints, with the feature backend the map was built with",
    "correlation": "dense gradient correlation against the map's orthophoto (no learned weights)",
    "ins": "no visual fixes: the INS alone",
}
_PROGRESS = re.compile(r"map build:\s*\d+%.*?\|\s*(\d+)/(\d+)")
# What `orthonav map build` advises on the command line, said as a web user can act on it.
_CLI_ADVICE = {
    "pass --yes to build it anyway, or crop": "crop",
    "(use --overwrite to replace it)": "(choose another name)",
}
# A file path on the server (not the API's own /api/... routes): shown by its last part only.
_SERVER_PATH = re.compile(r"(?<![\w.])(?!/api/)/(?:[^\s/:;,'\"()]+/)+([^\s/:;,'\"()]+)")
# How often a flying mission's run folder is measured against its quota: it may overshoot by
# what a mission writes in this long.
QUOTA_CHECK_S = 1.0


@dataclass(frozen=True)
class MissionPlan:
    """A validated mission request: what ``run_mission`` is called with."""

    map_name: str
    config: MissionConfig
    frames_from: Path
    fix_source: str


# The page's fix sources by the library's names; "ins" flies without visual fixes.
_SOURCE_NAMES = {"cascade": CASCADE, "map": KEYPOINTS, "correlation": CORRELATION}


def _fix_source(name: str, package: MapPackage, stack: ExitStack) -> FixSource | None:
    """The page's fix source ``name`` over ``package`` (None for ins: no visual fixes)."""
    if name not in _SOURCE_NAMES:
        return None
    chosen = open_fix_source(stack, package, package.camera, _SOURCE_NAMES[name], localizer=SIMULATED_WORLD)
    return chosen.source


def failure_message(exc: BaseException) -> str:
    """What the page shows: a user error as it is, a file system error without the server's
    path, anything else with its type; a server path in either named by its last part only (the
    server's folders stay private)."""
    if isinstance(exc, OSError):
        return f"the server cannot write the run: {file_error(exc, show_path=False)}"
    message = str(exc) if isinstance(exc, OrthonavError) else f"{type(exc).__name__}: {exc}"
    return _SERVER_PATH.sub(r"\1", message)


def folder_bytes(folder: Path) -> int:
    """What the files under ``folder`` hold (0 for a folder removed meanwhile)."""
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_size
            except FileNotFoundError:  # removed as it was listed
                continue
    return total


class RunQuota:
    """Whether a run folder has grown past ``max_bytes``, measured at most every ``QUOTA_CHECK_S``
    (a mission's frames make thousands of files; each check lists them all)."""

    def __init__(self, folder: Path, max_bytes: int) -> None:
        self.folder = folder
        self.max_bytes = max_bytes
        self.reached = False
        self._next_check = 0.0

    def __call__(self) -> bool:
        now = time.monotonic()
        if not self.reached and now >= self._next_check:
            self._next_check = now + QUOTA_CHECK_S
            self.reached = folder_bytes(self.folder) > self.max_bytes
        return self.reached

    def end_reason(self) -> str | None:
        """Why the mission was stopped, if the quota stopped it."""
        if not self.reached:
            return None
        return f"stopped: its files reached {self.max_bytes / 1e6:g} MB, the limit of one mission"


def fly_mission(
    store: DataStore,
    run_id: str,
    plan: MissionPlan,
    should_stop: Callable[[], bool] | None = None,
    stop_reason: Callable[[], str | None] = lambda: None,
) -> None:
    """Fly one mission into its run folder (already marked running); every failure is recorded
    with its reason, and a stop asked for by ``should_stop`` as cancelled, with ``stop_reason()``
    as its end reason where it gives one."""
    try:
        package = store.open_map(plan.map_name)
        with ExitStack() as stack:
            frames = stack.enter_context(GeoRaster(plan.frames_from))
            result = run_mission(
                package,
                frames,
                package.camera,
                plan.config,
                store.runs_dir / run_id,
                progress=False,
                fix_source=_fix_source(plan.fix_source, package, stack),
                should_stop=should_stop,
            )
    except Exception as exc:  # reported on the page; the service keeps running
        if not isinstance(exc, OrthonavError):
            log.exception("mission %s failed", run_id)
        store.set_run_state(run_id, state="failed", error=failure_message(exc), finished=time.time())
        return
    state = "cancelled" if result.end_reason == CANCELLED else "done"
    end_reason = (stop_reason() if state == "cancelled" else None) or result.end_reason
    store.set_run_state(run_id, state=state, end_reason=end_reason, finished=time.time())


@dataclass
class BuildJob:
    """A map build in progress: tiles done of total, and why it failed if it did."""

    id: str
    map_name: str
    orthophoto: str
    state: str = "queued"
    error: str | None = None
    tiles_done: int = 0
    tiles_total: int | None = None
    created: float = field(default_factory=time.time)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class BuildPlan:
    """A validated build request: the ``orthonav map build`` options."""

    map_name: str
    orthophoto: str
    altitude_m: float
    hfov_deg: float
    width: int
    height: int
    features: str
    max_keypoints: int


class Jobs:
    """Missions one at a time in a worker thread, map builds one at a time in a subprocess.

    Each queued or flying mission has a stop flag: set while it waits, it never starts; set
    while it flies, the mission ends at its next frame. The lock makes 'start' and 'cancel'
    exclusive, so a run is never both cancelled and started.
    """

    def __init__(
        self,
        store: DataStore,
        max_pending_runs: int,
        max_pending_builds: int,
        max_run_bytes: int,
        max_runs_bytes: int,
    ) -> None:
        self.store = store
        self.max_pending_runs = max_pending_runs
        self.max_pending_builds = max_pending_builds
        self.max_run_bytes = max_run_bytes
        self.max_runs_bytes = max_runs_bytes
        self._missions = ThreadPoolExecutor(1, thread_name_prefix="orthonav-mission")
        self._builds = ThreadPoolExecutor(1, thread_name_prefix="orthonav-build")
        self._build_jobs: dict[str, BuildJob] = {}
        self._processes: set[subprocess.Popen] = set()
        self._stops: dict[str, threading.Event] = {}
        self._lock = threading.Lock()

    # --- missions ----------------------------------------------------------------------

    def pending_runs(self) -> int:
        return sum(self.store.run_state(r).get("state") not in TERMINAL for r in self.store.run_ids())

    def submit_mission(self, plan: MissionPlan, request: dict) -> str:
        self._make_room()
        run_id = self.store.new_run(request)
        stop = threading.Event()
        with self._lock:
            self._stops[run_id] = stop
        self._missions.submit(self._fly, run_id, plan, stop)
        return run_id

    def _fly(self, run_id: str, plan: MissionPlan, stop: threading.Event) -> None:
        try:
            with self._lock:
                if stop.is_set():  # cancelled while it waited; its state says so already
                    return
                self.store.set_run_state(run_id, state="running", started=time.time())
            quota = RunQuota(self.store.runs_dir / run_id, self.max_run_bytes)
            fly_mission(self.store, run_id, plan, lambda: stop.is_set() or quota(), quota.end_reason)
        finally:
            with self._lock:
                self._stops.pop(run_id, None)
            release_memory()

    def cancel_mission(self, run_id: str) -> dict:
        """Stop a mission: at once if it waits, at its next frame if it flies (state follows)."""
        with self._lock:
            state = self.store.run_state(run_id)
            stop = self._stops.get(run_id)
            if stop is None or state.get("state") in TERMINAL:
                raise Conflict(
                    f"run {run_id}: {state.get('state')}; only a queued or running mission can be cancelled"
                )
            return self._cancel(run_id, state, stop, "cancelled before it started")

    def _make_room(self) -> None:
        """Remove finished runs, oldest first, until the runs and a new mission's quota fit in
        ``max_runs_bytes``; runs waiting or flying are kept whatever they take. One request at a
        time: two would count the same runs and remove them twice."""
        with self._lock:
            sizes = {run_id: folder_bytes(self.store.runs_dir / run_id) for run_id in self.store.run_ids()}
            excess = sum(sizes.values()) + self.max_run_bytes - self.max_runs_bytes
            for run_id in reversed(sizes):  # oldest first
                if excess <= 0:
                    return
                if self.store.run_state(run_id).get("state") in TERMINAL:
                    self.store.remove_run(run_id)
                    excess -= sizes[run_id]
                    log.info("run %s removed to make room for a new mission", run_id)

    def _cancel(self, run_id: str, state: dict, stop: threading.Event, queued_reason: str) -> dict:
        stop.set()
        if state.get("state") == "queued":
            return self.store.set_run_state(
                run_id, state="cancelled", end_reason=queued_reason, finished=time.time()
            )
        return self.store.set_run_state(run_id, cancel_requested=time.time())

    # --- map builds --------------------------------------------------------------------

    def submit_build(self, plan: BuildPlan) -> BuildJob:
        job = BuildJob("build-" + secrets.token_hex(4), plan.map_name, plan.orthophoto)
        with self._lock:
            if sum(j.state not in TERMINAL for j in self._build_jobs.values()) >= self.max_pending_builds:
                raise TooMany(
                    f"{self.max_pending_builds} map builds are already waiting or running; retry later"
                )
            self._build_jobs[job.id] = job
        self._builds.submit(self._build, job, plan)
        return job

    def build_job(self, job_id: str) -> BuildJob:
        with self._lock:
            job = self._build_jobs.get(job_id)
        if job is None:
            raise NotFound(f"job {job_id!r}: no such job")
        return job

    def build_jobs(self) -> list[BuildJob]:
        with self._lock:
            return sorted(self._build_jobs.values(), key=lambda j: j.created, reverse=True)

    def building(self, map_name: str) -> bool:
        return any(j.map_name == map_name and j.state not in TERMINAL for j in self.build_jobs())

    def _build(self, job: BuildJob, plan: BuildPlan) -> None:
        job.state = "running"
        try:
            error = self._run_build(job, self._build_command(plan))
        except (OrthonavError, OSError) as exc:  # the orthophoto went away, or no process could start
            error = failure_message(exc)
        job.state, job.error = ("failed", self._for_web_user(error, plan)) if error else ("done", None)

    def _for_web_user(self, error: str, plan: BuildPlan) -> str:
        """A build's error with the server's files named as the API names them, and the command
        line's advice (``--yes``, ``--overwrite``) as the page offers it: the server's folders
        stay private, and a web user has no command line."""
        named = {
            str(self.store.orthophoto_path(plan.orthophoto)): f"orthophoto {plan.orthophoto!r}",
            str(self.store.map_dir(plan.map_name)): f"map {plan.map_name!r}",
            **_CLI_ADVICE,
        }
        for text, said in named.items():
            error = error.replace(text, said)
        return _SERVER_PATH.sub(r"\1", error)

    def _build_command(self, plan: BuildPlan) -> list[str]:
        return [
            *(sys.executable, "-m", "orthonav.cli.main", "map", "build"),
            str(self.store.existing_orthophoto(plan.orthophoto)),
            *("--out", str(self.store.map_dir(plan.map_name))),
            *("--altitude", str(plan.altitude_m), "--hfov", str(plan.hfov_deg)),
            *("--width", str(plan.width), "--height", str(plan.height)),
            *("--features", plan.features, "--max-keypoints", str(plan.max_keypoints)),
        ]

    def _run_build(self, job: BuildJob, command: list[str]) -> str | None:
        """Run the command, following its progress bar; the error line it printed, if any."""
        process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        with self._lock:
            self._processes.add(process)
        error = None
        assert process.stderr is not None
        for line in process.stderr:  # universal newlines: each progress redraw ('\r') is a line
            if match := _PROGRESS.search(line):
                job.tiles_done, job.tiles_total = int(match[1]), int(match[2])
            elif line.startswith("error:"):
                error = line.removeprefix("error:").strip()
            elif line.strip():
                log.debug("map build %s: %s", job.map_name, line.rstrip())
        code = process.wait()
        with self._lock:
            self._processes.discard(process)
        if code != 0:
            return error or f"the map build stopped with exit code {code}"
        return None

    def cancel_all(self) -> None:
        """Cancel every queued mission and the flying one (which stops at its next frame)."""
        with self._lock:
            for run_id, stop in self._stops.items():
                if not stop.is_set():
                    self._cancel(
                        run_id, self.store.run_state(run_id), stop, "the server stopped before it started"
                    )

    def shutdown(self) -> None:
        """Stop builds in progress (they resume when started again), cancel the missions and
        wait for the flying one to write its outputs (one frame at most)."""
        with self._lock:
            for process in self._processes:
                process.terminate()
        self.cancel_all()
        self._builds.shutdown(wait=False, cancel_futures=True)
        self._missions.shutdown(wait=True, cancel_futures=True)

"""The web service's data folder: map packages, uploaded orthophotos and mission runs.

Every name that reaches the file system from a request is checked against one pattern (no
separators, no leading dot), and every file served from a run is resolved and required to lie
inside that run: no request can name a path outside the data folder.
"""

from __future__ import annotations

import json
import re
import secrets
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from orthonav.atomic import write_json_atomic
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_NAME = re.compile(NAME_PATTERN)
_TIFF_SUFFIX = re.compile(r"\.tiff?$", re.IGNORECASE)
MANIFEST = "manifest.json"
RUN_STATE = "web.json"  # the service's own record of a run: request, state, error
UPLOAD_PREFIX = ".upload-"
TERMINAL = ("done", "failed", "cancelled")


class NotFound(OrthonavError):
    """A named map, orthophoto, run or file that does not exist (HTTP 404)."""


class Conflict(OrthonavError):
    """A name that is already taken, or a map that cannot serve as it is (HTTP 409)."""


class TooMany(OrthonavError):
    """More work asked for than the server takes on at once (HTTP 429)."""


def http_status(exc: OrthonavError) -> int:
    """The HTTP status a user error is answered with: 404, 409, 429, else 400."""
    statuses = {NotFound: 404, Conflict: 409, TooMany: 429}
    return next((code for kind, code in statuses.items() if isinstance(exc, kind)), 400)


def check_name(name: str, what: str) -> str:
    """A user-chosen name usable as one path component, or a clear error."""
    if not _NAME.match(name) or ".." in name:
        raise OrthonavError(
            f"{what} name {name!r}: expected 1-64 letters, digits, '_', '-' or '.', "
            "starting with a letter or digit"
        )
    return name


def orthophoto_name(name: str) -> str:
    """The name an orthophoto is stored and listed under: one given as the file is named on the
    uploader's disk (``naip2020.tif``) keeps its stem, and is stored as ``naip2020.tif``."""
    check_name(name, "orthophoto")
    return check_name(_TIFF_SUFFIX.sub("", name), "orthophoto")


@dataclass(frozen=True)
class MapInfo:
    """A listed map package: its summary and WGS84 bounds, or why it cannot be opened."""

    name: str
    summary: dict | None
    bounds: list[list[float]] | None  # [[south, west], [north, east]]
    backend: str | None
    error: str | None = None

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "summary": self.summary,
            "bounds": self.bounds,
            "backend": self.backend,
            "error": self.error,
        }


class DataStore:
    """Folders under one data directory, and the open map packages (cached by manifest time)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.maps_dir = root / "maps"
        self.orthophotos_dir = root / "orthophotos"
        self.runs_dir = root / "runs"
        for folder in (self.maps_dir, self.orthophotos_dir, self.runs_dir):
            folder.mkdir(parents=True, exist_ok=True)
        self._packages: dict[str, tuple[float, MapPackage]] = {}
        self._lock = threading.Lock()
        self._state_lock = threading.Lock()  # one read-modify-write of a run's state at a time

    # --- maps --------------------------------------------------------------------------

    def map_dir(self, name: str) -> Path:
        return self.maps_dir / check_name(name, "map")

    def map_names(self) -> list[str]:
        return sorted(
            p.name for p in self.maps_dir.iterdir() if _NAME.match(p.name) and (p / MANIFEST).is_file()
        )

    def open_map(self, name: str) -> MapPackage:
        """The package, opened (and validated) once per version of its manifest."""
        manifest = self.map_dir(name) / MANIFEST
        if not manifest.is_file():
            raise NotFound(f"map {name!r}: no such map package in {self.maps_dir}")
        mtime = manifest.stat().st_mtime
        with self._lock:
            cached = self._packages.get(name)
            if cached is None or cached[0] != mtime:
                cached = (mtime, MapPackage(manifest.parent))
                self._packages[name] = cached
            return cached[1]

    def map_info(self, name: str) -> MapInfo:
        try:
            package = self.open_map(name)
        except OrthonavError as exc:
            return MapInfo(name, None, None, None, str(exc).replace(str(self.root), "…"))
        # The server's folders are its own business: files by name only.
        summary = {**package.summary(), "path": name, "source": package.source_path.name}
        return MapInfo(name, summary, package.grid.bounds_latlon(), package.backend_name)

    def map_source(self, name: str) -> Path:
        """The orthophoto a map was built from (its tiles are served from it)."""
        source = self.open_map(name).source_path
        if not source.is_file():
            raise NotFound(f"map {name!r}: its orthophoto {source} is missing")
        return source

    # --- orthophotos -------------------------------------------------------------------

    def orthophoto_path(self, name: str) -> Path:
        return self.orthophotos_dir / f"{orthophoto_name(name)}.tif"

    def existing_orthophoto(self, name: str) -> Path:
        path = self.orthophoto_path(name)
        if not path.is_file():
            raise NotFound(f"orthophoto {name!r}: not uploaded (see GET /api/orthophotos)")
        return path

    def remove_partial_uploads(self) -> None:
        """Uploads cut short by a stopped server (each is received in its own hidden folder)."""
        for folder in self.orthophotos_dir.glob(UPLOAD_PREFIX + "*"):
            shutil.rmtree(folder, ignore_errors=True)

    def upload_folder(self) -> Path:
        """A fresh hidden folder to receive one upload in."""
        folder = self.orthophotos_dir / f"{UPLOAD_PREFIX}{secrets.token_hex(6)}"
        folder.mkdir()
        return folder

    def orthophotos(self) -> list[dict]:
        return [
            {"name": p.stem, "size_bytes": p.stat().st_size}
            for p in sorted(self.orthophotos_dir.glob("*.tif"))
            if _NAME.match(p.stem)
        ]

    # --- runs --------------------------------------------------------------------------

    def new_run(self, request: dict) -> str:
        """A fresh run folder with its request recorded, state ``queued``."""
        run_id = time.strftime("%Y%m%d-%H%M%S-") + secrets.token_hex(3)
        (self.runs_dir / run_id).mkdir()
        self.set_run_state(run_id, state="queued", error=None, request=request, created=time.time())
        return run_id

    def run_dir(self, run_id: str) -> Path:
        path = self.runs_dir / check_name(run_id, "run")
        if not (path / RUN_STATE).is_file():
            raise NotFound(f"run {run_id!r}: no such run")
        return path

    def run_state(self, run_id: str) -> dict:
        return json.loads((self.run_dir(run_id) / RUN_STATE).read_text())

    def set_run_state(self, run_id: str, **changes: object) -> dict:
        path = self.runs_dir / run_id / RUN_STATE
        with self._state_lock:
            state = json.loads(path.read_text()) if path.is_file() else {"id": run_id}
            state.update(changes)
            write_json_atomic(path, state)
        return state

    def run_summary(self, run_id: str) -> dict | None:
        path = self.run_dir(run_id) / "summary.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def run_ids(self) -> list[str]:
        """Newest first."""
        return sorted(
            (p.name for p in self.runs_dir.iterdir() if _NAME.match(p.name) and (p / RUN_STATE).is_file()),
            reverse=True,
        )

    def remove_run(self, run_id: str) -> None:
        """A finished run's folder, removed with everything in it."""
        shutil.rmtree(self.run_dir(run_id), ignore_errors=True)

    def interrupt_unfinished_runs(self) -> None:
        """Runs left queued or running by a previous server process can never finish."""
        for run_id in self.run_ids():
            if self.run_state(run_id).get("state") not in TERMINAL:
                self.set_run_state(run_id, state="failed", error="interrupted: the server stopped")

    def run_files(self, run_id: str) -> list[dict]:
        root = self.run_dir(run_id)
        return [
            {"path": p.relative_to(root).as_posix(), "size_bytes": p.stat().st_size}
            for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.startswith(".")
        ]

    def run_file(self, run_id: str, relative: str) -> Path:
        """A file inside the run folder; anything resolving outside it is 'not found'."""
        root = self.run_dir(run_id).resolve()
        try:
            path = (root / relative).resolve()
            found = path.is_relative_to(root) and path.is_file()
        except (OSError, ValueError):  # e.g. a NUL byte in the name
            found = False
        if not found:
            raise NotFound(f"run {run_id}: no file {relative!r}")
        return path

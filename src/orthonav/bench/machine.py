"""What a benchmark ran on, written beside its numbers: the CPU, its threads, the libraries,
orthonav's own code and how busy the machine was. A time means little without them, another
process taking a core slows every row alike, and a result from a checkout with edits not yet
committed reproduces from no commit."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import cv2

# Libraries whose version can move a benchmark's numbers (the learned ones where installed).
LIBRARIES = ("numpy", "opencv-python-headless", "scipy", "rasterio", "torch", "onnxruntime")


class LoadWatch:
    """The machine's load average when a benchmark starts; :meth:`record` adds it at the end."""

    def __init__(self) -> None:
        self.before = os.getloadavg()

    def record(self, threads: int | None = None) -> dict:
        """The machine and its load now and at the start; ``threads``: the learned parts' own."""
        usable = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count() or 1)
        torch = sys.modules.get("torch")  # only where a learned backend has loaded it
        return {
            "cpu": cpu_name(),
            "cpus": os.cpu_count(),
            "usable_cpus": len(usable),
            "opencv_threads": cv2.getNumThreads(),
            "torch_threads": torch.get_num_threads() if torch is not None else None,
            "threads": threads,
            "load_avg_before": [round(x, 2) for x in self.before],
            "load_avg_after": [round(x, 2) for x in os.getloadavg()],
            "python": platform.python_version(),
            "libraries": {name: _version(name) for name in LIBRARIES},
            "orthonav": code_version(),
        }


def code_version() -> dict:
    """orthonav's version and, where it runs from a git checkout, the commit and whether its
    sources differ from it (``modified``); None for what cannot be told (an installed wheel)."""
    source = Path(__file__).resolve().parents[1]
    # A copy installed inside some other checkout (a venv in the project's folder) is not tracked there.
    tracked = _git(source, "ls-files", "--", "__init__.py")
    commit = _git(source, "rev-parse", "HEAD") if tracked else None
    changes = _git(source, "status", "--porcelain", "--untracked-files=no", "--", ".") if commit else None
    return {
        "version": _version("orthonav"),
        "commit": commit,
        "modified": None if changes is None else bool(changes),
    }


def _git(where: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=where, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def cpu_name() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "")


def machine_line(machine: dict) -> str:
    """One line for a summary or a picture: the CPU, its cores and how loaded they were."""
    before, after = machine["load_avg_before"][0], machine["load_avg_after"][0]
    return (
        f"{machine['cpu'] or 'CPU'}: {machine['usable_cpus']} of {machine['cpus']} cores, "
        f"load {before:.1f} -> {after:.1f}"
    )


def _version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None

"""Localize a set of frame files, each with its own prior: what ``orthonav localize FOLDER`` and
a library user's batch run share."""

from __future__ import annotations

import statistics
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from orthonav.errors import OrthonavError
from orthonav.frames import load_frame
from orthonav.types import Fix, FixSource, Prior


def localize_files(
    source: FixSource, paths: Sequence[Path], priors: Mapping[str, Prior], default: Prior
) -> Iterator[tuple[Path, Fix]]:
    """(path, fix) per frame file, in order; a frame's prior is ``priors[file name]``, else
    ``default``. A file that cannot be read or localized is a rejection with its reason, so one
    bad frame does not end the batch."""
    for path in paths:
        try:
            fix = source.localize(load_frame(path), priors.get(path.name, default))
        except OrthonavError as exc:
            fix = Fix(False, str(exc))
        yield path, fix


@dataclass
class BatchSummary:
    """Counts and timings of a batch, for its one-line summary."""

    frames: int = 0
    fixed: int = 0
    sigmas_m: list[float] = field(default_factory=list)
    times_ms: list[float] = field(default_factory=list)

    def add(self, fix: Fix) -> None:
        self.frames += 1
        self.times_ms.append(float(fix.timings_ms.get("total_ms", 0.0)))
        if fix.accepted:
            self.fixed += 1
            if fix.sigma_m is not None:
                self.sigmas_m.append(fix.sigma_m)

    def line(self, elapsed_s: float) -> str:
        share = 100.0 * self.fixed / self.frames if self.frames else 0.0
        parts = [f"{self.fixed} of {self.frames} frames fixed ({share:.0f} %)"]
        if self.sigmas_m:
            parts.append(f"median sigma {statistics.median(self.sigmas_m):.1f} m")
        if self.times_ms:
            parts.append(f"median {statistics.median(self.times_ms):.0f} ms per frame")
        parts.append(f"{elapsed_s:.1f} s in all")
        return ", ".join(parts)

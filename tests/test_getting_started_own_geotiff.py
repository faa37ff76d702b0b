"""The getting-started page's "Your own GeoTIFF" section, run as a newcomer runs it: every command
of its code blocks, in order, from a project root beside the shared data set, with the NAIP
orthophoto the page suggests. Only the folder example needs the user's own photos."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from conftest import SHARED_DATA, naip_path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "getting-started.md"
SECTION = "## Your own GeoTIFF"
USERS_OWN = ["orthonav localize mymap photos/ --priors priors.csv --out fixes.jsonl --plot fixes.png"]


def section_commands() -> list[str]:
    """The commands of the section's bash blocks, continuation lines joined."""
    text = PAGE.read_text()
    start = text.index(SECTION)
    section = text[start : text.index("\n## ", start + len(SECTION))]
    blocks = re.findall(r"```bash\n(.*?)```", section, re.S)
    return [
        line.strip() for block in blocks for line in block.replace("\\\n", " ").splitlines() if line.strip()
    ]


def test_every_command_of_the_section_runs(tmp_path: Path) -> None:
    naip_path("20200831")  # skips without the shared data
    (tmp_path / "shared").symlink_to(SHARED_DATA.parent)
    root = tmp_path / "project"
    root.mkdir()
    commands = section_commands()
    assert [c for c in commands if c in USERS_OWN] == USERS_OWN
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env["COLUMNS"] = "200"
    outputs = {}
    for command in commands:
        if command in USERS_OWN:
            continue
        proc = subprocess.run(["bash", "-c", command], cwd=root, env=env, capture_output=True, text=True)
        assert proc.returncode == 0, (command, proc.stdout[-2000:], proc.stderr[-2000:])
        outputs[command] = proc.stdout
    info = next(out for command, out in outputs.items() if command.startswith("orthonav map info"))
    for key in ("centre_latlon", "south_west_latlon", "north_east_latlon", "size_m"):
        assert key in info
    single = next(out for command, out in outputs.items() if "frame_00000.jpg" in command)
    assert "1 of 1 frames fixed" in single, single
    assert sum(command.startswith("orthonav simulate") for command in outputs) == 2

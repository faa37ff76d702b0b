"""``orthonav fly`` as a newcomer meets it: a base install without pymavlink is told the extra at
once, and a folder of frames or a silent autopilot is said to be waited for, not met in silence."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from typer.testing import CliRunner

from orthonav.bench.faults import free_udp_port
from orthonav.cli.main import app
from orthonav.mapdb import MapPackage

WITHOUT_PYMAVLINK = """
import sys
sys.modules["pymavlink"] = None  # as in a base install: importing it fails
from orthonav.cli.main import main
sys.argv = ["orthonav", *sys.argv[1:]]
main()
"""


def test_fly_without_pymavlink_names_the_extra_before_any_work(tmp_path: Path) -> None:
    """One line and exit 2, before the map is even opened (it does not exist here): no warm-up,
    no traceback."""
    args = ["fly", "--map", str(tmp_path / "no.map"), "--frames", str(tmp_path)]
    proc = subprocess.run(
        [sys.executable, "-c", WITHOUT_PYMAVLINK, *args], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "error: MAVLink needs pymavlink: pip install 'orthonav[mavlink]'"
    ], proc.stderr


def test_fly_says_it_watches_the_folder_and_waits_for_the_autopilot(
    terrain_map: MapPackage, tmp_path: Path
) -> None:
    """The images already in the folder are passed over, and it says so with their count; a line
    says what the companion waits for on the link."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("old_1.jpg", "old_2.jpg"):
        cv2.imwrite(str(frames / name), np.full((48, 64, 3), 128, np.uint8))
    connect = f"udpin:127.0.0.1:{free_udp_port()}"
    args = ["fly", "--map", str(terrain_map.path), "--frames", str(frames), "--connect", connect]
    args += ["--duration", "0.5", "--log-dir", str(tmp_path / "log")]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert any(
        line.startswith(f"camera: watching {frames} for new frames; 2 image(s) already there passed over")
        for line in lines
    ), result.output
    assert any(
        line.startswith(f"autopilot: waiting for its HEARTBEAT and telemetry on {connect}") for line in lines
    ), result.output


def test_fly_takes_the_map_and_out_as_the_other_commands_and_prints_a_summary_table(
    terrain_map: MapPackage, tmp_path: Path
) -> None:
    """``fly MAP --out DIR`` as ``simulate MAP --out DIR``; the summary a table of rounded values,
    not a Python dict."""
    frames = tmp_path / "frames"
    frames.mkdir()
    args = ["fly", str(terrain_map.path), "--frames", str(frames), "--out", str(tmp_path / "log")]
    args += ["--connect", f"udpin:127.0.0.1:{free_udp_port()}", "--duration", "0.3"]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert (tmp_path / "log" / "summary.json").is_file()
    assert "{'" not in result.output and "frames_dropped" in result.output, result.output
    assert "link " in result.output, result.output  # the link's counts flattened under its name


def test_fly_ctrl_c_exits_130_with_its_summary(terrain_map: MapPackage, tmp_path: Path, monkeypatch) -> None:
    """Ctrl-C ends the flight with its log and summary written, and the exit code says interrupted."""
    from orthonav.mavlink.companion import Companion

    def interrupted(self: Companion, now: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(Companion, "step", interrupted)
    frames = tmp_path / "frames"
    frames.mkdir()
    args = ["fly", str(terrain_map.path), "--frames", str(frames), "--out", str(tmp_path / "log")]
    args += ["--connect", f"udpin:127.0.0.1:{free_udp_port()}"]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 130, result.output
    assert (tmp_path / "log" / "summary.json").is_file()


def test_fly_refuses_two_different_maps(terrain_map: MapPackage, tmp_path: Path) -> None:
    args = ["fly", str(terrain_map.path), "--map", str(tmp_path), "--frames", str(tmp_path)]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code != 0 and "name two maps" in str(result.exception), result.output

"""``orthonav map build`` interrupted as a user or a service manager does it: the message, the exit
code, and a rerun that resumes where the build stopped and says so, whatever the map's size."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.sim.terrain import TerrainConfig, write_terrain_geotiff

runner = CliRunner()
# A 160 x 120 camera at 200 m over a 512 m map: 16 tiles, fewer than one feature chunk.
SMALL_MAP = ["--width", "160", "--height", "120", "--hfov", "60", "--altitude", "200", "--scale-coef", "1.0"]
TILES = 16
BUILT_BEFORE_SIGNAL = 5
# Runs the CLI with ORB's extract blocking after some tiles, so that the signal finds the build
# in the middle of a tile whatever the machine's speed.
BLOCKING_BUILD = """
import sys, time
from orthonav.cli.main import main
from orthonav.features import create_backend

cls = type(create_backend("orb"))
original, calls, block_at = cls.extract, [], int(sys.argv[1])

def extract(self, gray, mask=None):
    if len(calls) == block_at:
        time.sleep(600)
    calls.append(1)
    return original(self, gray, mask)

cls.extract = extract
sys.argv = ["orthonav", *sys.argv[2:]]
main()
"""


@pytest.fixture(scope="module")
def ortho(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_terrain_geotiff(
        tmp_path_factory.mktemp("ortho") / "ortho.tif", TerrainConfig(size_px=512, gsd_m=1.0)
    )


def wait_for(condition, timeout_s: float, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the build did not reach the tile in time"
        time.sleep(0.1)


def test_sigterm_keeps_the_tiles_and_a_rerun_resumes_there(ortho: Path, tmp_path: Path) -> None:
    """SIGTERM in the middle of a 16-tile build: one line saying what is kept, exit code 130 as
    for Ctrl-C; the rerun says it resumes at the tiles built and counts only the others."""
    out = tmp_path / "small.map"
    args = ["map", "build", str(ortho), "--out", str(out), *SMALL_MAP]
    progress = tmp_path / "small.map.partial" / "progress"
    proc = subprocess.Popen(
        [sys.executable, "-c", BLOCKING_BUILD, str(BUILT_BEFORE_SIGNAL), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        wait_for(lambda: len(list(progress.glob("tile_*.sha256"))) >= BUILT_BEFORE_SIGNAL, 120.0, proc)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == (
        "interrupted: results written so far are kept (a map build resumes when rerun)"
    )
    assert not out.exists()
    saved = len(list(progress.glob("tile_*.sha256")))  # tiles without texture need no extract
    assert saved >= BUILT_BEFORE_SIGNAL

    result = runner.invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert f"resuming: {saved} of {TILES} tiles already built (in {out}.partial)" in lines
    summary = next(line for line in lines if line.startswith(f"{TILES} tiles:"))
    assert summary.startswith(f"{TILES} tiles: {TILES - saved} built in "), summary
    assert summary.endswith(f", {saved} reused from the interrupted build"), summary


def test_an_uninterrupted_build_counts_every_tile_as_built(ortho: Path, tmp_path: Path) -> None:
    result = runner.invoke(
        app,
        ["map", "build", str(ortho), "--out", str(tmp_path / "m.map"), *SMALL_MAP],
        env={"COLUMNS": "200"},
    )
    assert result.exit_code == 0, result.output
    assert "resuming" not in result.output
    summary = next(line for line in result.output.splitlines() if line.startswith(f"{TILES} tiles:"))
    assert summary.startswith(f"{TILES} tiles: {TILES} built in ") and "reused" not in summary, summary

"""An output that cannot be written (a full device, the file size limit, a path under a file) is
one line naming the file and what is wrong, and exit code 2, from the console entry point itself:
never a traceback, never a process killed by SIGXFSZ."""

from __future__ import annotations

import os
import resource
import stat
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import pytest
from conftest import CAMERA
from helpers_web import free_port

from orthonav.atomic import atomic_path, file_error, open_output, write_text_atomic
from orthonav.bench.faults import free_udp_port
from orthonav.geo import GeoRaster
from orthonav.mapdb import MapPackage

CLI_TIMEOUT_S = 120


def run_cli(args: list[str], max_file_bytes: int | None = None) -> subprocess.CompletedProcess:
    """``orthonav ARGS`` as a user runs it (the console entry point), its file size limit set."""
    limit: Callable[[], None] | None = None
    if max_file_bytes is not None:

        def limit() -> None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    return subprocess.run(
        [sys.executable, "-c", "from orthonav.cli.main import main; main()", *args],
        capture_output=True,
        text=True,
        timeout=CLI_TIMEOUT_S,
        preexec_fn=limit,
        # A bytecode cache written at import would meet the limit before the entry point runs.
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )


def assert_one_line(result: subprocess.CompletedProcess, *expected: str) -> None:
    """Exit code 2 and a last stderr line 'error: ...' holding each of ``expected``, no traceback."""
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert "Traceback" not in result.stderr, result.stderr[-2000:]
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: "), last
    for text in expected:
        assert text in last, last


@pytest.fixture(scope="module")
def frame(naip_raster: GeoRaster, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One camera-sized crop of the NAIP map's own orthophoto."""
    from orthonav.geo.raster import PixelWindow

    rgb = naip_raster.read_rgb(PixelWindow(100, 100, CAMERA.width, CAMERA.height))
    path = tmp_path_factory.mktemp("frame") / "frame.jpg"
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("not a folder")
    return path


@pytest.mark.parametrize("option", ["--out", "--plot"])
def test_localize_output_to_a_full_device_is_one_line(naip_map: MapPackage, frame: Path, option: str) -> None:
    result = run_cli(["localize", str(naip_map.path), str(frame), "--altitude", "1000", option, "/dev/full"])
    assert_one_line(result, "/dev/full", "no space left", "ENOSPC")
    assert stat.S_ISCHR(os.stat("/dev/full").st_mode)  # written to, never replaced
    assert not Path("/dev/full.png").exists()  # nor a plot written beside it under another name


def test_a_plot_to_a_device_leaves_no_page_beside_it(naip_map: MapPackage, frame: Path) -> None:
    """The interactive page goes beside a plot file, never beside a device: ``/dev/null.html``
    is made by root and refused (EACCES) to anyone else."""
    page = Path("/dev/null.html")
    assert not page.exists()
    try:
        result = run_cli(
            ["localize", str(naip_map.path), str(frame), "--altitude", "1000", "--plot", "/dev/null"]
        )
        assert result.returncode == 0, result.stderr[-2000:]
        assert not page.exists()
    finally:
        page.unlink(missing_ok=True)


def test_a_plot_in_a_format_matplotlib_cannot_write_is_one_line(
    naip_map: MapPackage, frame: Path, tmp_path: Path
) -> None:
    plot = tmp_path / "fixes.xyz"
    result = run_cli(["localize", str(naip_map.path), str(frame), "--altitude", "1000", "--plot", str(plot)])
    assert_one_line(result, str(plot), "png", "not 'xyz'")


def test_localize_out_and_plot_under_a_file_are_one_line(
    naip_map: MapPackage, frame: Path, a_file: Path
) -> None:
    base = ["localize", str(naip_map.path), str(frame), "--altitude", "1000"]
    assert_one_line(
        run_cli([*base, "--out", str(a_file / "fixes.jsonl")]), str(a_file / "fixes.jsonl"), "ENOTDIR"
    )
    assert_one_line(
        run_cli([*base, "--plot", str(a_file / "fixes.png")]), str(a_file / "fixes.png"), "ENOTDIR"
    )


def test_outputs_past_the_file_size_limit_are_one_line_not_a_kill(
    naip_map: MapPackage, frame: Path, tmp_path: Path
) -> None:
    """Past ``ulimit -f`` the kernel sends SIGXFSZ, which kills a process that does not ignore it."""
    out, plot = tmp_path / "fixes.jsonl", tmp_path / "fixes.png"
    base = ["localize", str(naip_map.path), str(frame), "--altitude", "1000"]
    assert_one_line(run_cli([*base, "--out", str(out)], max_file_bytes=0), str(out), "EFBIG", "ulimit -f")
    # The fixes fit; the plot does not, and no half-written plot is left.
    result = run_cli([*base, "--out", str(out), "--plot", str(plot)], max_file_bytes=64 * 1024)
    assert_one_line(result, str(plot), "EFBIG")
    assert not plot.exists() and not list(tmp_path.glob(".fixes.*"))


def test_fly_log_dir_that_cannot_be_written_is_one_line(
    naip_map: MapPackage, frame: Path, a_file: Path, tmp_path: Path
) -> None:
    """Under a file, or past the file size limit: the flight ends with one line naming the log."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / frame.name).write_bytes(frame.read_bytes())
    base = ["fly", "--map", str(naip_map.path), "--frames", str(frames), "--duration", "1"]
    base += ["--connect", f"udpin:127.0.0.1:{free_udp_port()}"]
    assert_one_line(run_cli([*base, "--log-dir", str(a_file / "logs")]), str(a_file / "logs"), "ENOTDIR")
    logs = tmp_path / "logs"
    assert_one_line(run_cli([*base, "--log-dir", str(logs)], max_file_bytes=0), str(logs), "EFBIG")


@pytest.mark.parametrize("data", ["/dev/full", "under-a-file"])
def test_serve_data_that_cannot_be_a_folder_is_one_line(data: str, a_file: Path) -> None:
    folder = data if data.startswith("/") else str(a_file / "data")
    assert_one_line(run_cli(["serve", "--data", folder, "--port", str(free_port())]), folder, "ENOTDIR")


def test_a_write_error_names_the_file_written_not_its_temporary(tmp_path: Path, a_file: Path) -> None:
    with pytest.raises(NotADirectoryError) as caught, atomic_path(a_file / "x.json") as tmp:
        tmp.write_text("{}")
    assert caught.value.filename == str(a_file / "x.json")
    assert (
        file_error(caught.value)
        == f"{a_file / 'x.json'}: a part of the path is a file, not a folder (ENOTDIR)"
    )
    assert file_error(caught.value, show_path=False) == "a part of the path is a file, not a folder (ENOTDIR)"
    with pytest.raises(OSError, match="No space") as caught, open_output("/dev/full") as fh:
        fh.write("x" * 100_000)
    assert caught.value.filename == "/dev/full"


def test_a_device_or_pipe_is_written_to_never_replaced(tmp_path: Path) -> None:
    """Renaming a temporary over /dev/null would leave a plain file where the device was (a pipe
    stands in for the device here, so that a failure harms nothing)."""
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    received: list[str] = []
    reader = threading.Thread(target=lambda: received.append(pipe.read_text()), daemon=True)
    reader.start()
    write_text_atomic(pipe, "through the pipe")
    reader.join(timeout=10.0)
    assert received == ["through the pipe"] and stat.S_ISFIFO(pipe.stat().st_mode)


# Any command, here one that waits, run through the console entry point.
WAITING_COMMAND = """
import sys, time
from orthonav.cli import main as entry

def waiting():
    print("ready", flush=True)
    time.sleep(120)

entry.app = waiting
entry.main()
"""


def test_sigterm_ends_any_command_in_one_line_as_ctrl_c_does() -> None:
    """A supervisor's SIGTERM to localize, replay or simulate: exit code 130 and the one line
    saying what is kept, as for Ctrl-C; not a silent death."""
    proc = subprocess.Popen(
        [sys.executable, "-c", WAITING_COMMAND], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        proc.terminate()
        _, stderr = proc.communicate(timeout=CLI_TIMEOUT_S)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1].startswith("interrupted: results written so far are kept")

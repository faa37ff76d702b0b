"""Fault injection over the real ``fly`` and ``sim-vehicle`` processes (``orthonav bench faults``).

Every scenario flies for 28 s over UDP loopback (three at a time): garbage and corrupt packets,
a spoofer beside the autopilot, after its silence and before its first packet, link loss, an
autopilot reboot elsewhere, boot time stepping both ways, a bank beyond 60 deg, velocities the
vehicle cannot have (too fast, one glitch, a bias, NaN), a stalled camera, late, reordered and
damaged frames, a starved companion, and a damaged map. No position the vehicle receives may be
more than 3 sigma or 50 m off, nothing may go to the spoofer, and navigation must be back within
10 s of the fault's end (of the start, where the spoofer talks from before it); on a damaged map
``fly`` must refuse to start, saying so in one line, and the vehicle get nothing. Each scenario
must also show that its fault happened, so a relay that injected nothing cannot pass.

The spans the companion must act within (the fault, the flight after it, the 10 s to be back)
are stretched by the machine's measured slowdown: another process taking a core costs time, not
a failure, and a fault gives a slower companion as many frames to show its trace. The benchmark
reports the unstretched times beside the machine's load. The safety checks are not stretched.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import pytest

pytest.importorskip("pymavlink")

from conftest import naip_path
from helpers_timing import slowdown

from orthonav.bench.faults import (
    SCENARIOS,
    FaultBenchConfig,
    child_process,
    run_fault_benchmark,
    summary_line,
)
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage


def said(text: str) -> Callable[[dict], bool]:
    return lambda evidence: any(text in event for event in evidence["events"])


# What the companion must have seen of each fault.
INJECTED: dict[str, Callable[[dict], bool]] = {
    "none": lambda e: e["bad_packets"] == 0 and e["ignored_packets"] == 0,
    "garbage": lambda e: e["bad_packets"] >= 50,
    "corrupt": lambda e: e["bad_packets"] >= 20,
    "spoof": lambda e: e["ignored_packets"] >= 50,
    "spoof-after-silence": lambda e: e["ignored_packets"] >= 50 and said("link silent")(e),
    "spoof-first": lambda e: e["ignored_packets"] >= 20,
    "link-loss": said("link silent"),
    "reboot": said("reboot"),
    "time-ahead": said("boot time jump"),
    "time-back": said("reboot"),
    "bank": said("attitude beyond"),
    "velocity-fast": said("LOCAL_POSITION_NED: 350.0 m/s"),
    "velocity-glitch": said("telemetry velocity"),
    "velocity-bias": said("telemetry velocity rejected"),
    "velocity-nan-local": said("velocity not finite"),
    "camera-stall": lambda e: e["frames_lost"] >= 8,
    "late-frames": lambda e: e["oldest_fix_s"] >= 2.0,
    "reordered": lambda e: e["fixes_out_of_order"] >= 2,
    "starved": lambda e: e["longest_silence_s"] >= 1.0,
    "corrupt-frames": lambda e: e["frames_damaged"] >= 5 and e["frames_refused"] >= 2,
    "damaged-map": lambda e: e["refusal"] is not None,
}
FLOWN = [name for name, fault in SCENARIOS.items() if fault.refusal is None]
REFUSED = [name for name, fault in SCENARIOS.items() if fault.refusal is not None]


@pytest.fixture(scope="module")
def fault_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("faults") / "bench_faults.json"


@pytest.fixture(scope="module")
def fault_config() -> FaultBenchConfig:
    """The benchmark's settings, the spans the companion must act within stretched by the slowdown."""
    nominal, factor = FaultBenchConfig(parallel=3), slowdown()
    print(f"\nslowdown {factor:.2f}: the fault, the flight after it and the time to recover stretched")
    return replace(
        nominal,
        fault_s=nominal.fault_s * factor,
        after_s=nominal.after_s * factor,
        resume_within_s=nominal.resume_within_s * factor,
    )


@pytest.fixture(scope="module")
def fault_bench(naip_map: MapPackage, fault_out: Path, fault_config: FaultBenchConfig) -> dict:
    return run_fault_benchmark(naip_map, naip_path("20200831"), fault_out, fault_config)


def test_every_scenario_is_covered_by_an_injection_check() -> None:
    assert set(INJECTED) == set(SCENARIOS)


@pytest.mark.parametrize("scenario", FLOWN)
def test_no_wrong_position_reaches_the_autopilot_and_navigation_returns(
    fault_bench: dict, fault_config: FaultBenchConfig, scenario: str
) -> None:
    row = next(r for r in fault_bench["rows"] if r["scenario"] == scenario)
    print(f"\n{scenario}: { {k: v for k, v in row.items() if k != 'track'} }")
    assert row["fly_exit"] == 0, "fly did not stop cleanly on SIGTERM"
    assert INJECTED[scenario](row["evidence"]), f"the fault left no trace: {row['evidence']}"
    assert row["positions"] >= 40, "too few positions graded to judge"
    assert row["wrong"] == 0 and row["unverifiable"] == 0, [
        p for p in row["track"] if p[1] is None or p[1] > p[2]
    ]
    assert row["leaked"] == 0
    assert row["resumed_s"] is not None, "navigation never came back after the fault"
    assert row["resumed_s"] <= fault_config.resume_within_s
    assert row["passed"]


@pytest.mark.parametrize("scenario", REFUSED)
def test_fly_refuses_to_start_on_what_it_cannot_fly_with_and_sends_nothing(
    fault_bench: dict, scenario: str
) -> None:
    row = next(r for r in fault_bench["rows"] if r["scenario"] == scenario)
    print(f"\n{scenario}: { {k: v for k, v in row.items() if k != 'track'} }")
    assert row["fly_exit"] == 2, "fly did not refuse with its one-line error"
    assert INJECTED[scenario](row["evidence"]), f"no refusal said: {row['evidence']}"
    assert row["positions"] == 0 and row["leaked"] == 0
    assert row["passed"]


def test_the_benchmark_writes_its_json_and_picture(fault_bench: dict, fault_out: Path) -> None:
    written = json.loads(fault_out.read_text())
    assert written["rows"] == fault_bench["rows"]
    assert {"cpu", "usable_cpus", "load_avg_before", "load_avg_after", "libraries"} <= set(written["machine"])
    assert fault_out.with_suffix(".png").stat().st_size > 20_000
    assert (fault_out.with_suffix("") / "reboot" / "vehicle-rebooted" / "received.jsonl").exists()
    assert summary_line(fault_bench).startswith(
        f"{len(SCENARIOS)} of {len(SCENARIOS)} fault scenarios passed"
    )


def test_bad_settings_are_refused_with_the_choices() -> None:
    with pytest.raises(OrthonavError, match="fault scenarios meteor: expected some of none, garbage"):
        FaultBenchConfig(scenarios=("meteor",))
    with pytest.raises(OrthonavError, match="parallel 0"):
        FaultBenchConfig(parallel=0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_a_child_process_dies_with_a_parent_killed_outright(tmp_path: Path) -> None:
    """A benchmark killed by SIGKILL (or a segfault) runs no cleanup: its children must still go,
    as SITL and fly orphaned by a crashed `bench sitl` did not."""
    pid_file = tmp_path / "child.pid"
    parent_script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from orthonav.bench.faults import child_process\n"
        "with child_process([sys.executable, '-c', 'import time; time.sleep(120)'], None) as child:\n"
        f"    Path({str(pid_file)!r}).write_text(str(child.pid))\n"
        "    time.sleep(120)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", parent_script])
    try:
        deadline = time.monotonic() + 60.0
        while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
            time.sleep(0.05)
        child_pid = int(pid_file.read_text())
        assert _alive(child_pid)
    finally:
        parent.kill()
        parent.wait(timeout=30)
    deadline = time.monotonic() + 30.0
    while _alive(child_pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child_pid)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for a reaper that may never come does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")


def test_a_child_process_left_running_is_stopped_even_when_itself_stopped(tmp_path: Path) -> None:
    """With a grace period a child that ends on SIGTERM does so (SITL, fly: their logs closed);
    without one, or stopped by SIGSTOP (a frozen-companion fault), it is continued and killed."""
    script = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)\n"
    )

    def started(log: Path) -> None:
        deadline = time.monotonic() + 30.0
        while "ready" not in (log.read_text() if log.exists() else "") and time.monotonic() < deadline:
            time.sleep(0.05)

    for name, grace_s, stop, code in (
        ("term", 10.0, False, 3),
        ("kill", 0.0, False, -9),
        ("frozen", 10.0, True, 3),
    ):
        log = tmp_path / f"{name}.out"
        with child_process([sys.executable, "-c", script], log, grace_s=grace_s) as child:
            started(log)
            if stop:
                child.send_signal(signal.SIGSTOP)
        assert child.returncode == code, name

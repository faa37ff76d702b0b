"""How much slower than when idle this machine runs now, for the tests that judge wall time.

A test that judges how soon something happens (a web answer, navigation back after a fault)
stretches its allowance by :func:`slowdown`: another process taking a core then costs time, not
a failure. What must hold however busy the machine is (no wrong position sent, no 5xx) is
asserted without it; the benchmarks report their times beside the machine's load.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

LOOP_CPU_S = 0.3  # CPU time each busy loop spins for
START_IN_S = 0.5  # every loop's interpreter has started by then, so they spin together
_BUSY_LOOP = """
import sys, time
start, cpu_s = float(sys.argv[1]), float(sys.argv[2])
while time.time() < start:
    time.sleep(0.002)
wall0, cpu0 = time.perf_counter(), time.process_time()
while time.process_time() - cpu0 < cpu_s:
    pass
print((time.perf_counter() - wall0) / (time.process_time() - cpu0))
"""


def slowdown() -> float:
    """Wall time over CPU time of busy loops, one per usable CPU, spun at once: about 1 on an idle
    machine, 1.5 with one core of two taken by another process. The slowest loop's, at least 1."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    start = f"{time.time() + START_IN_S:.3f}"
    loops = [
        subprocess.Popen(
            [sys.executable, "-I", "-c", _BUSY_LOOP, start, str(LOOP_CPU_S)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(cpus)
    ]
    return max(1.0, *(float(loop.communicate()[0]) for loop in loops))

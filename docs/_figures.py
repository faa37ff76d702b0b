"""The figures the README and the benchmark overview quote, each read from one result file in
docs/benchmarks/results/, so that the two cannot disagree with each other or with the file.

A page carries a table between ``<!-- figures: NAME -->`` and ``<!-- /figures -->``. The site's
build fills it from the result files (docs/hooks.py); ``python docs/_figures.py`` writes the same
tables into README.md and docs/benchmarks/index.md, which GitHub shows as committed, and a test
fails when what is committed is not what the files say.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

DOCS = Path(__file__).resolve().parent
RESULTS = DOCS / "benchmarks" / "results"
PAGES = {
    DOCS.parent / "README.md": "docs/benchmarks/results/",
    DOCS / "benchmarks" / "index.md": "results/",
    DOCS / "benchmarks" / "real.md": "results/",
}

BLOCK = re.compile(r"(<!-- figures: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /figures -->)", re.S)


@cache
def result(name: str) -> dict:
    return json.loads((RESULTS / name).read_text())


def real_row(name: str, features: str, variant: str, fix_source: str = "keypoints") -> dict:
    rows = result(name)["rows"]
    return next(
        r for r in rows if (r["features"], r["variant"], r["fix_source"]) == (features, variant, fix_source)
    )


def across_dates(name: str, condition: str = "cross-date", prior: str = "prior") -> dict:
    summary = result(name)["summary"]
    return next(v for k, v in summary.items() if k.endswith(f": {condition} / {prior}"))


def pairs_at_90(name: str) -> int:
    rows = result(name)["rows"]
    return sum(
        r["centre_within_10m"] >= 0.9 for r in rows if (r["condition"], r["prior"]) == ("cross-date", "prior")
    )


def pairs(name: str) -> int:
    rows = result(name)["rows"]
    return sum((r["condition"], r["prior"]) == ("cross-date", "prior") for r in rows)


def latency(name: str, features: str) -> dict:
    return next(r["latency"] for r in result(name)["rows"] if r["features"] == features)


def correction(name: str, runtime: str, size: int) -> dict:
    return next(r for r in result(name)["corrections"] if (r["runtime"], r["size"]) == (runtime, size))


def pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def ms(x: float) -> str:
    return f"{x:.0f} ms"


@dataclass(frozen=True)
class Figure:
    """One measured value: what it is, where it is read, and (for a target) its line."""

    what: str
    file: str
    value: Callable[[], str]
    line: str = ""
    met: Callable[[], bool] | None = None


REAL_ORB = "bench_real_default.json"
REAL_ALIKED = "bench_real_quick_512.json"
TARGETS = "bench_localize_targets_aliked.json"
LOST = "bench_localize_cascade_lost_tiles10.json"
LOOP_2009 = "bench_speed_loop_chain_2009_again.json"
LOOP = "bench_speed_loop_again.json"
FAULTS = "bench_faults.json"
DEMO = "demo_summary.json"
SPEED = "bench_speed.json"
RUNTIME = "bench_runtime_correction.json"

HEADLINE = [
    Figure(
        "Demo (synthetic terrain, GNSS lost): map fixes fused",
        DEMO,
        lambda: f"{result(DEMO)['fixes_fused']} of {result(DEMO)['steps']}",
    ),
    Figure("Demo: navigation error, median", DEMO, lambda: f"{result(DEMO)['nav_error_median_m']:.1f} m"),
    Figure(
        "52 real photos, ORB on the DSM with roll and pitch: fixed",
        REAL_ORB,
        lambda: pct(real_row(REAL_ORB, "orb", "dsm+att")["fixed"]),
    ),
    Figure(
        "52 real photos, ORB: drone position error, median",
        REAL_ORB,
        lambda: f"{real_row(REAL_ORB, 'orb', 'dsm+att')['median_m']:.2f} m",
    ),
    Figure(
        "52 real photos, ORB: fixes more than 10 m off",
        REAL_ORB,
        lambda: str(real_row(REAL_ORB, "orb", "dsm+att")["false_fixes"]),
    ),
    Figure(
        "52 real photos, ALIKED (512 px) on the DSM with roll and pitch: fixed",
        REAL_ALIKED,
        lambda: pct(real_row(REAL_ALIKED, "aliked", "dsm+att")["fixed"]),
    ),
    Figure(
        "52 real photos, ALIKED: time a photo, median",
        REAL_ALIKED,
        lambda: ms(real_row(REAL_ALIKED, "aliked", "dsm+att")["total_ms"]),
    ),
    Figure(
        "Across dates, 200 m prior, ALIKED cascade: frame centres within 10 m",
        TARGETS,
        lambda: pct(across_dates(TARGETS)["centre_within_10m"]),
    ),
    Figure(
        "Across dates, 200 m prior: fixes more than 25 m off",
        TARGETS,
        lambda: pct(across_dates(TARGETS)["false_25m_rate"]),
    ),
    Figure(
        "Across dates, lost (no prior), ORB cascade: within 25 m",
        LOST,
        lambda: pct(across_dates(LOST, prior="no prior")["centre_within_25m"]),
    ),
    Figure(
        "Companion loop, ALIKED cascade, 2009 frames over the 2020 map: p95 capture to message",
        LOOP_2009,
        lambda: ms(latency(LOOP_2009, "aliked")["latency_p95_ms"]),
    ),
    Figure(
        "Fault injection on the real fly and sim-vehicle processes: scenarios passed",
        FAULTS,
        lambda: f"{result(FAULTS)['passed']} of {len(result(FAULTS)['rows'])}",
    ),
]

TARGET_TABLE = [
    Figure(
        "200 m prior: NAIP year pairs with >= 90 % of frame centres within 10 m (ALIKED cascade)",
        TARGETS,
        lambda: f"{pairs_at_90(TARGETS)} of {pairs(TARGETS)}",
        "20 of 20",
        lambda: pairs_at_90(TARGETS) == pairs(TARGETS),
    ),
    Figure(
        "same date: frame centres within 10 m",
        TARGETS,
        lambda: pct(across_dates(TARGETS, "same-date")["centre_within_10m"]),
        ">= 97 %",
        lambda: across_dates(TARGETS, "same-date")["centre_within_10m"] >= 0.97,
    ),
    Figure(
        "across dates: fixes more than 25 m off",
        TARGETS,
        lambda: pct(across_dates(TARGETS)["false_25m_rate"]),
        "< 0.5 %",
        lambda: across_dates(TARGETS)["false_25m_rate"] < 0.005,
    ),
    Figure(
        "P(right) within 5 points of the observed rate in every decile",
        TARGETS,
        lambda: "yes" if _calibrated(TARGETS) else "no",
        "yes",
        lambda: _calibrated(TARGETS),
    ),
    Figure(
        "ALIKED cascade with a prior: time a frame, median",
        TARGETS,
        lambda: ms(across_dates(TARGETS)["median_total_ms"]),
        "<= 300 ms",
        lambda: across_dates(TARGETS)["median_total_ms"] <= 300,
    ),
    Figure(
        "ORB keypoints with a prior, across dates: time a frame, median",
        SPEED,
        lambda: ms(_speed_row("orb")["naip"]["cross-date"]["total_ms"]),
        "<= 30 ms",
        lambda: _speed_row("orb")["naip"]["cross-date"]["total_ms"] <= 30,
    ),
    Figure(
        "lost (no prior): frame centres within 25 m",
        LOST,
        lambda: pct(across_dates(LOST, prior="no prior")["centre_within_25m"]),
        ">= 70 %",
        lambda: across_dates(LOST, prior="no prior")["centre_within_25m"] >= 0.70,
    ),
    Figure(
        "lost (no prior): time a frame, median",
        LOST,
        lambda: f"{across_dates(LOST, prior='no prior')['median_total_ms'] / 1000:.2f} s",
        "<= 1 s",
        lambda: across_dates(LOST, prior="no prior")["median_total_ms"] <= 1000,
    ),
    Figure(
        "real photos, ALIKED (512 px, DSM, roll and pitch): time a photo, median",
        REAL_ALIKED,
        lambda: ms(real_row(REAL_ALIKED, "aliked", "dsm+att")["total_ms"]),
        "<= 400 ms",
        lambda: real_row(REAL_ALIKED, "aliked", "dsm+att")["total_ms"] <= 400,
    ),
    Figure(
        "real photos, ORB (DSM, roll and pitch): time a photo, median",
        REAL_ORB,
        lambda: ms(real_row(REAL_ORB, "orb", "dsm+att")["total_ms"]),
        "<= 100 ms",
        lambda: real_row(REAL_ORB, "orb", "dsm+att")["total_ms"] <= 100,
    ),
    Figure(
        "trained correction's trunk at 224 px on ONNX Runtime",
        RUNTIME,
        lambda: ms(correction(RUNTIME, "onnx-fp32", 224)["trunk_ms"]),
        "<= 40 ms",
        lambda: correction(RUNTIME, "onnx-fp32", 224)["trunk_ms"] <= 40,
    ),
    Figure(
        "companion loop, ALIKED cascade, map's own date: p95 capture to message",
        LOOP,
        lambda: ms(latency(LOOP, "aliked")["latency_p95_ms"]),
        "<= 400 ms",
        lambda: latency(LOOP, "aliked")["latency_p95_ms"] <= 400,
    ),
    Figure(
        "companion loop, ALIKED cascade, 2009 frames over the 2020 map: p95 capture to message",
        LOOP_2009,
        lambda: ms(latency(LOOP_2009, "aliked")["latency_p95_ms"]),
        "<= 400 ms",
        lambda: latency(LOOP_2009, "aliked")["latency_p95_ms"] <= 400,
    ),
    Figure(
        "companion loop, the same worst case: frames dropped of 60",
        LOOP_2009,
        lambda: str(latency(LOOP_2009, "aliked")["frames_dropped"]),
        "<= 12",
        lambda: latency(LOOP_2009, "aliked")["frames_dropped"] <= 60 / 5,
    ),
]


def _calibrated(name: str) -> bool:
    return next(v for k, v in result(name)["summary"]["targets"].items() if "P(right)" in k)


def _speed_row(features: str) -> dict:
    return next(r for r in result(SPEED)["rows"] if r["features"] == features)


def _link(file: str, prefix: str) -> str:
    return f"[{file.removesuffix('.json')}]({prefix}{file})"


def headline(prefix: str) -> str:
    lines = ["| result | value | from |", "|---|---|---|"]
    lines += [f"| {f.what} | {f.value()} | {_link(f.file, prefix)} |" for f in HEADLINE]
    return "\n".join(lines) + "\n"


def targets(prefix: str) -> str:
    lines = ["| target | line | measured | met | from |", "|---|---|---|---|---|"]
    lines += [
        f"| {f.what} | {f.line} | {f.value()} | {'yes' if f.met() else '**no**'} | {_link(f.file, prefix)} |"
        for f in TARGET_TABLE
    ]
    return "\n".join(lines) + "\n"


def real_default(prefix: str) -> str:
    """Every row of `orthonav bench real` run with its defaults, and the machine that ran it."""
    machine = result(REAL_ORB)["machine"]
    libraries = ", ".join(f"{k} {v}" for k, v in machine["libraries"].items() if v)
    lines = [
        "| variant | fixed | within 3 m | median | false (> 10 m) | within 3 sigma | ms a photo |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['variant']} | {pct(r['fixed'])} | {pct(r['within_3m'])} | {r['median_m']:.2f} m | "
        f"{r['false_fixes']} | {pct(r['within_3sigma'])} | {r['total_ms']:.0f} |"
        for r in result(REAL_ORB)["rows"]
    ]
    lines += [
        "",
        f"{machine['cpu']}, {machine['usable_cpus']} cores, {machine['opencv_threads']} OpenCV threads, load "
        f"{machine['load_avg_before'][0]} -> {machine['load_avg_after'][0]}; Python {machine['python']}, "
        f"{libraries} ({_link(REAL_ORB, prefix)}).",
    ]
    return "\n".join(lines) + "\n"


TABLES = {"headline": headline, "targets": targets, "real-default": real_default}


def fill(text: str, prefix: str) -> str:
    """``text`` with every figures block rewritten from the result files (links relative to ``prefix``)."""
    return BLOCK.sub(lambda m: m.group(1) + TABLES[m.group("name")](prefix) + m.group(4), text)


def main() -> None:
    for page, prefix in PAGES.items():
        page.write_text(fill(page.read_text(), prefix))


if __name__ == "__main__":
    main()

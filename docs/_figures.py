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
from decimal import ROUND_HALF_UP, Decimal
from functools import cache
from pathlib import Path

DOCS = Path(__file__).resolve().parent
RESULTS = DOCS / "benchmarks" / "results"
PAGES = {
    DOCS.parent / "README.md": "docs/benchmarks/results/",
    **{
        DOCS / "benchmarks" / f"{page}.md": "results/"
        for page in (
            "index",
            "real",
            "localize",
            "mission",
            "scale",
            "slam",
            "correction",
            "odometry",
            "speed",
            "sitl",
        )
    },
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


def rounded(x: float, digits: int = 0) -> str:
    """``x`` to ``digits`` decimals, halves away from zero (as the pages' hand-written figures were)."""
    return str(Decimal(str(x)).quantize(Decimal(1).scaleb(-digits), ROUND_HALF_UP))


def pct(x: float) -> str:
    return f"{rounded(100 * x, 1)} %"


def ms(x: float) -> str:
    return f"{rounded(x)} ms"


def seconds(x_ms: float) -> str:
    return f"{x_ms / 1000:.2f} s"


def yes_no(x: bool) -> str:
    return "yes" if x else "no"


@dataclass(frozen=True)
class Figure:
    """One measured value: what it is, the result file it is read from, how it is shown and, for a
    target, its line (``at_most`` or ``at_least``, in the value's own units)."""

    what: str
    file: str
    read: Callable[[], float]
    show: Callable[[float], str] = str
    at_most: float | None = None
    at_least: float | None = None

    def line(self) -> str:
        if isinstance(self.at_least, bool):
            return self.show(self.at_least)
        if self.at_most is not None:
            return f"<= {self.show(self.at_most)}"
        return f">= {self.show(self.at_least)}"

    def met(self) -> bool:
        value = self.read()
        return (self.at_most is None or value <= self.at_most) and (
            self.at_least is None or value >= self.at_least
        )


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


def _real_orb(key: str) -> Callable[[], float]:
    return lambda: real_row(REAL_ORB, "orb", "dsm+att")[key]


def _real_aliked(key: str) -> Callable[[], float]:
    return lambda: real_row(REAL_ALIKED, "aliked", "dsm+att")[key]


def _across(name: str, key: str, condition: str = "cross-date", prior: str = "prior") -> Callable[[], float]:
    return lambda: across_dates(name, condition, prior)[key]


def _loop(name: str, key: str) -> Callable[[], float]:
    return lambda: latency(name, "aliked")[key]


def _of(total: Callable[[], int]) -> Callable[[float], str]:
    return lambda n: f"{n} of {total()}"


HEADLINE = [
    Figure(
        "Demo (synthetic terrain, GNSS lost): map fixes fused",
        DEMO,
        lambda: result(DEMO)["fixes_fused"],
        _of(lambda: result(DEMO)["steps"]),
    ),
    Figure(
        "Demo: navigation error, median", DEMO, lambda: result(DEMO)["nav_error_median_m"], "{:.1f} m".format
    ),
    Figure("52 real photos, ORB on the DSM with roll and pitch: fixed", REAL_ORB, _real_orb("fixed"), pct),
    Figure(
        "52 real photos, ORB: drone position error, median",
        REAL_ORB,
        _real_orb("median_m"),
        "{:.2f} m".format,
    ),
    Figure("52 real photos, ORB: fixes more than 10 m off", REAL_ORB, _real_orb("false_fixes")),
    Figure(
        "52 real photos, ALIKED (512 px) on the DSM with roll and pitch: fixed",
        REAL_ALIKED,
        _real_aliked("fixed"),
        pct,
    ),
    Figure("52 real photos, ALIKED: time a photo, median", REAL_ALIKED, _real_aliked("total_ms"), ms),
    Figure(
        "Across dates, 200 m prior, ALIKED cascade: frame centres within 10 m",
        TARGETS,
        _across(TARGETS, "centre_within_10m"),
        pct,
    ),
    Figure(
        "Across dates, 200 m prior: fixes more than 25 m off",
        TARGETS,
        _across(TARGETS, "false_25m_rate"),
        pct,
    ),
    Figure(
        "Across dates, lost (no prior), ORB cascade: frame centres within 25 m",
        LOST,
        _across(LOST, "centre_within_25m", prior="no prior"),
        pct,
    ),
    Figure(
        "Companion loop, ALIKED cascade, 2009 frames over the 2020 map: p95 capture to message",
        LOOP_2009,
        _loop(LOOP_2009, "latency_p95_ms"),
        ms,
    ),
    Figure(
        "Fault injection on the real fly and sim-vehicle processes: scenarios passed",
        FAULTS,
        lambda: result(FAULTS)["passed"],
        _of(lambda: len(result(FAULTS)["rows"])),
    ),
]

TARGET_TABLE = [
    Figure(
        "200 m prior: NAIP year pairs with >= 90 % of frame centres within 10 m (ALIKED cascade)",
        TARGETS,
        lambda: pairs_at_90(TARGETS),
        _of(lambda: pairs(TARGETS)),
        at_least=20,
    ),
    Figure(
        "same date: frame centres within 10 m",
        TARGETS,
        _across(TARGETS, "centre_within_10m", "same-date"),
        pct,
        at_least=0.97,
    ),
    Figure(
        "across dates: fixes more than 25 m off",
        TARGETS,
        _across(TARGETS, "false_25m_rate"),
        pct,
        at_most=0.005,
    ),
    Figure(
        "P(right) within 5 points of the observed rate in every decile",
        TARGETS,
        lambda: _calibrated(TARGETS),
        yes_no,
        at_least=True,
    ),
    Figure(
        "ALIKED cascade with a prior: time a frame, median",
        TARGETS,
        _across(TARGETS, "median_total_ms"),
        ms,
        at_most=300,
    ),
    Figure(
        "ORB keypoints with a prior, across dates: time a frame, median",
        SPEED,
        lambda: _speed_row("orb")["naip"]["cross-date"]["total_ms"],
        ms,
        at_most=30,
    ),
    Figure(
        "lost (no prior): frame centres within 25 m",
        LOST,
        _across(LOST, "centre_within_25m", prior="no prior"),
        pct,
        at_least=0.70,
    ),
    Figure(
        "lost (no prior): time a frame, median",
        LOST,
        _across(LOST, "median_total_ms", prior="no prior"),
        seconds,
        at_most=1000,
    ),
    Figure(
        "real photos, ALIKED (512 px, DSM, roll and pitch): time a photo, median",
        REAL_ALIKED,
        _real_aliked("total_ms"),
        ms,
        at_most=400,
    ),
    Figure(
        "real photos, ORB (DSM, roll and pitch): time a photo, median",
        REAL_ORB,
        _real_orb("total_ms"),
        ms,
        at_most=100,
    ),
    Figure(
        "trained correction's trunk at 224 px on ONNX Runtime",
        RUNTIME,
        lambda: correction(RUNTIME, "onnx-fp32", 224)["trunk_ms"],
        ms,
        at_most=40,
    ),
    Figure(
        "companion loop, ALIKED cascade, map's own date: p95 capture to message",
        LOOP,
        _loop(LOOP, "latency_p95_ms"),
        ms,
        at_most=400,
    ),
    Figure(
        "companion loop, ALIKED cascade, 2009 frames over the 2020 map: p95 capture to message",
        LOOP_2009,
        _loop(LOOP_2009, "latency_p95_ms"),
        ms,
        at_most=400,
    ),
    Figure(
        "companion loop, the same worst case: frames dropped of 60",
        LOOP_2009,
        _loop(LOOP_2009, "frames_dropped"),
        at_most=12,
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
    lines += [f"| {f.what} | {f.show(f.read())} | {_link(f.file, prefix)} |" for f in HEADLINE]
    return "\n".join(lines) + "\n"


def targets(prefix: str) -> str:
    lines = ["| target | line | measured | met | from |", "|---|---|---|---|---|"]
    lines += [
        f"| {f.what} | {f.line()} | {f.show(f.read())} | {yes_no(f.met()).replace('no', '**no**')} | "
        f"{_link(f.file, prefix)} |"
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


@dataclass(frozen=True)
class Rows:
    """A page's leading table: one row per entry of a result file, one number a cell."""

    files: tuple[str, ...]
    rows: Callable[[dict], list[tuple[str, dict]]]  # a result file -> (label, values) per row
    label: str
    columns: tuple[tuple[str, str, Callable[[float], str]], ...]  # (header, key, show)

    def __call__(self, prefix: str) -> str:
        lines = [
            "| " + " | ".join([self.label, *(c[0] for c in self.columns)]) + " |",
            "|---" * (1 + len(self.columns)) + "|",
        ]
        for file in self.files:
            for label, values in self.rows(result(file)):
                cells = [
                    "-" if values.get(key) is None else show(values[key]) for _, key, show in self.columns
                ]
                lines.append("| " + " | ".join([label, *cells]) + " |")
        lines += ["", "From " + ", ".join(_link(f, prefix) for f in self.files) + "."]
        return "\n".join(lines) + "\n"


def _summary_rows(data: dict) -> list[tuple[str, dict]]:
    return [(k, v) for k, v in data["summary"].items() if isinstance(v, dict) and "n" in v]


LOCALIZE = Rows(
    (TARGETS, "bench_localize_targets_orb.json"),
    _summary_rows,
    "fix source: condition / prior",
    (
        ("frames", "n", str),
        ("fixed", "fix_rate", pct),
        ("centre within 10 m", "centre_within_10m", pct),
        ("within 25 m", "within_25m", pct),
        ("more than 25 m off", "false_25m_rate", pct),
        ("median time", "median_total_ms", ms),
    ),
)
SIGMA_COLUMNS = (
    ("within 1 sigma", "within_1sigma", pct),
    ("2 sigma", "within_2sigma", pct),
    ("3 sigma", "within_3sigma", pct),
    ("mean NEES", "mean_nees", "{:.2f}".format),
    ("p95 error", "p95_m", "{:.2f} m".format),
    ("sigma / p95 error", "sigma_over_p95", "{:.2f}".format),
)
SIGMA_REAL = Rows(
    ("bench_real_sigma.json",),
    lambda data: [(f"{r['features']} {r['fix_source']} {r['variant']}", r) for r in data["rows"]],
    "backend, fix source, variant",
    (("fixed", "fixed", pct), ("median sigma", "median_sigma_m", "{:.2f} m".format), *SIGMA_COLUMNS),
)


def _sigma_rows(data: dict) -> list[tuple[str, dict]]:
    """A run's pooled rows; where it rendered drone-scale frames, those alone (the one NAIP year
    beside them repeats the NAIP run's), named with their altitude band."""
    rows = _summary_rows(data)
    low, high = data["config"]["highres_alt_m"]
    band = f"{low:g} m" if low == high else f"{low:g}-{high:g} m"
    drone = [(k.replace("high-res", f"high-res {band}"), v) for k, v in rows if "high-res" in k]
    return drone or rows


SIGMA_LOCALIZE = Rows(
    (
        "bench_localize_sigma_naip.json",
        "bench_localize_sigma_highres.json",
        "bench_localize_sigma_relief.json",
    ),
    _sigma_rows,
    "fix source: condition / prior",
    (("frames", "n", str), ("fixed", "fix_rate", pct), *SIGMA_COLUMNS),
)


def _tilt_rows(data: dict) -> list[tuple[str, dict]]:
    """A tilt run's pooled rows, named with the frames' tilt and their priors' attitude error."""
    config = data["config"]
    setup = f"+-{config['max_tilt_deg']:g} deg, attitude off {config['attitude_noise_deg']:g} deg"
    return [(f"{setup}: {name.split(': ', 1)[1]}", values) for name, values in _summary_rows(data)]


TILT = Rows(
    tuple(f"bench_localize_tilt_{name}.json" for name in ("level", "body", "body_noise1", "body_noise2")),
    _tilt_rows,
    "tilt, attitude error (1-sigma): condition / prior",
    (
        ("frames", "n", str),
        ("fixed", "fix_rate", pct),
        ("centre within 10 m", "centre_within_10m", pct),
        ("more than 25 m off", "false_25m_rate", pct),
        *SIGMA_COLUMNS[2:],
    ),
)
MISSION = Rows(
    ("bench_mission.json",),
    lambda data: list(data["summary"].items()),
    "fix source",
    (
        ("missions", "missions", str),
        ("arrived (true)", "arrived_true", pct),
        ("navigation error, median", "nav_error_median_m", "{:.1f} m".format),
        ("frames fused", "fused_rate", pct),
        ("time a frame", "step_ms_median", ms),
    ),
)
RELOCALIZE = Rows(
    ("bench_relocalize.json",),
    lambda data: [(f"{r['km2']} km², {r['condition']}", r) for r in data["rows"]],
    "map",
    (
        ("tiles", "tiles", str),
        ("recall@10", "recall@10", pct),
        ("fixed (index top 10)", "fixed index", pct),
        ("time (index)", "ms index", ms),
        ("fixed (every tile)", "fixed all tiles", pct),
        ("time (every tile)", "ms all tiles", ms),
    ),
)
SLAM = Rows(
    ("bench_slam.json",),
    lambda data: [(r["setup"], r) for r in data["summary"]],
    "setup",
    (
        ("ATE UAV 1", "ATE UAV 1 (m)", "{:.1f} m".format),
        ("ATE all UAVs", "ATE all UAVs (m)", "{:.1f} m".format),
        ("RPE", "RPE (m)", "{:.2f} m".format),
        ("landmark error", "landmark error (m)", "{:.1f} m".format),
        ("s a run", "s per run", "{:.1f}".format),
    ),
)

CORRECTION = Rows(
    ("bench_correction.json",),
    lambda data: [(f"{r['method']}, {r['size']} px", r) for r in data["rows"] if r["initial_m"] == 100],
    "method, from a 100 m error",
    (
        ("fixed", "fix_rate", pct),
        ("drone error, median", "median_m", "{:.1f} m".format),
        ("centre within 2 map px", "centre_within_2px", pct),
        ("false", "false_rate", pct),
        ("time", "median_ms", ms),
    ),
)
ODOMETRY = Rows(
    ("bench_odometry.json",),
    lambda data: [(r["config"], r) for r in data["summary"]],
    "features / model",
    (
        ("pairs", "pairs", str),
        ("with motion", "ok", str),
        ("distance error, median", "median_abs_distance_error_m", "{:.2f} m".format),
        (
            "heading-change error (consistent pairs)",
            "consistent_median_abs_dyaw_error_deg",
            "{:.2f} deg".format,
        ),
        ("time a pair", "median_ms", ms),
    ),
)


def _speed_rows(data: dict) -> list[tuple[str, dict]]:
    return [
        (
            f"{r['features']} on {r['engine']}",
            {
                "same": r["naip"]["same-date"]["total_ms"],
                "cross": r["naip"]["cross-date"]["total_ms"],
                "photo": (r.get("real") or {}).get("total_ms"),
                "fixed": (r.get("real") or {}).get("fixed"),
                "mb": r["peak_rss_mb"],
            },
        )
        for r in data["rows"]
    ]


SPEED_TABLE = Rows(
    ("bench_speed_disk_onnx.json",),
    _speed_rows,
    "backend",
    (
        ("NAIP same-date", "same", ms),
        ("NAIP cross-date", "cross", ms),
        ("Seneca photo", "photo", ms),
        ("Seneca fixed", "fixed", pct),
        ("peak memory", "mb", "{:.0f} MB".format),
    ),
)


def _tail_rows(data: dict) -> list[tuple[str, dict]]:
    """Per run and NAIP condition: each stage's p50 / p95 and the total's tails, with accuracy."""
    out = []
    for r in data["rows"]:
        source = r["fix_source"] if r["fix_source"] != "keypoints" else "keypoints alone"
        for condition, part in r["naip"].items():
            tails = part["tails_ms"]
            stages = {f"{k}_{p}": v[p] for k, v in tails.items() for p in ("p50", "p95", "p99", "max")}
            out.append((f"{r['features']} {source}, {condition}", part | stages))
    return out


SPEED_TAILS = Rows(
    ("bench_speed_baseline.json",),
    _tail_rows,
    "run, NAIP frames",
    (
        ("extract p50", "extract_ms_p50", ms),
        ("extract p95", "extract_ms_p95", ms),
        ("match p50", "match_ms_p50", ms),
        ("match p95", "match_ms_p95", ms),
        ("pose p50", "pose_ms_p50", ms),
        ("pose p95", "pose_ms_p95", ms),
        ("frame p50", "total_ms_p50", ms),
        ("frame p95", "total_ms_p95", ms),
        ("frame p99", "total_ms_p99", ms),
        ("frame max", "total_ms_max", ms),
        ("centre within 10 m", "centre_within_10m", pct),
        ("false (> 50 m)", "false_fix_rate", pct),
    ),
)


def _sitl_rows(data: dict) -> list[tuple[str, dict]]:
    hfov = data["config"]["hfov_deg"]
    lens = "" if hfov == 60 else f", {hfov:g} deg lens"
    # A flight with parameters set over its scenario's says which: it is not the scenario as coded.
    lens += "".join(f", `{name} {value:g}`" for name, value in data["config"].get("extra_params") or ())
    return [
        (
            f"`{r['name']}`{lens}",
            {
                **r,
                **(r.get("orthonav_messages") or {}),
                "ekf_failsafe": any("EKF Failsafe" in text for text in r["failsafes"]),
                "lane_switches": sum("lane switch" in text for text in r["failsafes"]),
                "tilt_off_p95": ((r.get("tilt_error_deg") or {}).get("gnss_off") or {}).get("p95"),
            },
        )
        for r in data["rows"]
    ]


SITL = Rows(
    (
        "bench_sitl.json",
        "bench_sitl_velocity.json",
        "bench_sitl_velocity_third.json",
        "bench_sitl_velocity_fourth.json",
        "bench_sitl_velocity_drag.json",
        "bench_sitl_body_camera.json",
        "bench_sitl_body_camera_floor.json",
        "bench_sitl_body_camera_attitude.json",
        "bench_sitl_body_camera_refused.json",
        "bench_sitl_twin_place_refused.json",
        "bench_sitl_wide.json",
        "bench_sitl_wide_velocity.json",
        "bench_sitl_extnav.json",
        "bench_sitl_extnav_wide.json",
        "bench_sitl_odometry_wide.json",
        "bench_sitl_flow.json",
        "bench_sitl_flow_posne.json",
        "bench_sitl_flow_accp.json",
        "bench_sitl_flow_velocity_walk.json",
        "bench_sitl_flow_velocity_default.json",
        "bench_sitl_flow_velocity_xeon.json",
        "bench_sitl_spoofed.json",
        "bench_sitl_spoofed_switch.json",
        "bench_sitl_spoofed_extnav_switch.json",
        "bench_sitl_plane.json",
        "bench_sitl_plane_wide.json",
        "bench_sitl_plane_velocity.json",
        "bench_sitl_plane_velocity_xeon.json",
        "bench_sitl_plane_body_camera.json",
        "bench_sitl_plane_body_camera_fused.json",
    ),
    _sitl_rows,
    "flight",
    (
        ("completed", "completed", yes_no),
        ("GNSS off or spoofed", "gnss_off_s", "{:.0f} s".format),
        ("autopilot error p50", "horizontal_error_p50_m", "{:.1f} m".format),
        ("p95", "horizontal_error_p95_m", "{:.1f} m".format),
        ("max", "horizontal_error_max_m", "{:.0f} m".format),
        ("landed from plan", "landing_error_m", "{:.0f} m".format),
        ("EKF failsafe", "ekf_failsafe", yes_no),
        ("EKF lane switches", "lane_switches", str),
        ("orthonav messages", "sent", str),
        ("wrong after GNSS loss", "wrong_gnss_off", str),
        ("autopilot tilt error p95 (GNSS off)", "tilt_off_p95", "{:.1f} deg".format),
        ("on the spoofer", "followed_spoofer_share", "{:.0%}".format),
    ),
)


def _sitl_fault_rows(data: dict) -> list[tuple[str, dict]]:
    return [
        (
            f"`{r['name']}`",
            {
                **r,
                **(r.get("orthonav_messages") or {}),
                "window": r["fault_window_s"],
                "ekf_failsafe": any("EKF Failsafe" in text for text in r["failsafes"]),
            },
        )
        for r in data["rows"]
    ]


def _window(seconds: list[float]) -> str:
    return f"{seconds[0]:.0f} to {seconds[1]:.0f} s"


SITL_FAULTS = Rows(
    ("bench_sitl_faults.json",),
    _sitl_fault_rows,
    "flight",
    (
        ("fault (from GNSS loss)", "window", _window),
        ("fixes fused in it", "fixes_in_fault", str),
        ("next fix after it", "resumed_s", "{:.1f} s".format),
        ("orthonav messages", "sent", str),
        ("wrong", "wrong", str),
        ("autopilot error p95, GNSS off", "horizontal_error_p95_m", "{:.1f} m".format),
        ("max, 60 s after the fault", "autopilot_error_after_max_m", "{:.1f} m".format),
        ("steepest bank", "max_bank_deg", "{:.0f} deg".format),
        ("EKF failsafe", "ekf_failsafe", yes_no),
        ("completed", "completed", yes_no),
        ("passed", "passed", yes_no),
    ),
)


def _floor_rows(data: dict) -> list[tuple[str, dict]]:
    """One row per inlier floor: the whole flight, the lowest height it measured at, and the
    descent's heights below 250 m, where the floors differ."""
    rows = []
    for r in data["rows"]:
        measured = [band for band in r["heights"] if band["n"]]
        low = [band for band in measured if band["from_m"] < 250.0]
        lowest = min(band["from_m"] for band in measured)
        low_n = sum(band["n"] for band in low)
        graded = r["all"]
        values = {
            **graded,
            "errors": " / ".join(
                f"{graded[k]:.2f}" for k in ("error_p50_mps", "error_p95_mps", "error_max_mps")
            )
            + " m/s",
            "within_3": graded["within_1_2_3_sigma"][2],
            "lowest": f"{lowest:.0f}-{lowest + 50:.0f} m",
            "low_n": low_n,
            "low_within_3": sum(band["n"] * band["within_1_2_3_sigma"][2] for band in low) / max(1, low_n),
            "low_worst": max((band["worst_sigmas"] for band in low), default=None),
        }
        rows.append((str(r["min_inliers"]), values))
    return rows


FRAME_VELOCITY_FLOOR = Rows(
    ("bench_frame_velocity_floor.json",),
    _floor_rows,
    "inlier floor",
    (
        ("velocities", "n", str),
        ("error p50 / p95 / max", "errors", str),
        ("within 3 sigma", "within_3", pct),
        ("worst", "worst_sigmas", "{:.1f} sigma".format),
        ("lowest height measured", "lowest", str),
        ("velocities below 250 m", "low_n", str),
        ("their within 3 sigma", "low_within_3", pct),
        ("their worst", "low_worst", "{:.1f} sigma".format),
    ),
)


TABLES = {
    "headline": headline,
    "targets": targets,
    "real-default": real_default,
    "localize": LOCALIZE,
    "sigma-real": SIGMA_REAL,
    "sigma-localize": SIGMA_LOCALIZE,
    "localize-tilt": TILT,
    "mission": MISSION,
    "relocalize": RELOCALIZE,
    "slam": SLAM,
    "correction": CORRECTION,
    "odometry": ODOMETRY,
    "speed": SPEED_TABLE,
    "speed-tails": SPEED_TAILS,
    "sitl": SITL,
    "sitl-faults": SITL_FAULTS,
    "frame-velocity-floor": FRAME_VELOCITY_FLOOR,
}


def fill(text: str, prefix: str) -> str:
    """``text`` with every figures block rewritten from the result files (links relative to ``prefix``)."""
    return BLOCK.sub(lambda m: m.group(1) + TABLES[m.group("name")](prefix) + m.group(4), text)


def main() -> None:
    for page, prefix in PAGES.items():
        page.write_text(fill(page.read_text(), prefix))


if __name__ == "__main__":
    main()

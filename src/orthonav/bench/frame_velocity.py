"""The ground velocity between frames (``fly --frame-velocity``) on a SITL flight's kept frames,
against SIMSTATE: how far off it is, whether its covariance covers that, what it costs per frame.

``python -m orthonav.bench.frame_velocity FLIGHT_DIR --hfov 90 --out result.json``: FLIGHT_DIR is
one flight of ``bench sitl`` (its ``camera/`` frames, ``track.json`` and ``fly/companion.jsonl``,
whose ATTITUDE and GLOBAL_POSITION_INT give each frame's heading and height, as in flight). Every
frame from 30 s before GNSS went to the end is added in turn; each velocity is compared with the
true mean velocity over its pair's captures, and the autopilot's own velocity at its mid-time with
the same truth. Rows per part of the flight (before GNSS went, then between the route's waypoints)
and per 50 m of height. ``--min-inliers 100 40`` grades the flight once per inlier floor
(``VelocityConfig.min_inliers``): how much lower a lower floor measures, and at what cover.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.camera import Camera
from orthonav.fusion.ground_velocity import FrameVelocity, VelocityConfig, VelocityError
from orthonav.geo import LocalFrame

BEFORE_GNSS_OFF_S = 30.0
MIN_HEIGHT_M = 40.0  # the SITL camera renders nothing lower
HEIGHT_BAND_M = 50.0


def _telemetry(log: Path) -> tuple[np.ndarray, np.ndarray]:
    """(time, yaw rad) of ATTITUDE and (time, height m, v_east, v_north) of GLOBAL_POSITION_INT."""
    attitude, position = [], []
    with open(log) as lines:
        for line in lines:
            record = json.loads(line)
            if record["kind"] != "recv":
                continue
            msg = record["msg"]
            if record["type"] == "ATTITUDE":
                attitude.append((record["time_s"], msg["yaw"]))
            elif record["type"] == "GLOBAL_POSITION_INT":
                position.append(
                    (record["time_s"], msg["relative_alt"] / 1e3, msg["vy"] / 1e2, msg["vx"] / 1e2)
                )
    return np.array(attitude), np.array(position)


def _nearest(samples: np.ndarray, time_s: float) -> np.ndarray:
    return samples[min(np.searchsorted(samples[:, 0], time_s), len(samples) - 1)]


def measure(flight: Path, hfov_deg: float, min_inliers: int = VelocityConfig.min_inliers) -> dict:
    """Every velocity of the flight's frames, graded; see the module docstring."""
    track = json.loads((flight / "track.json").read_text())
    truth = np.array(track["truth"], float)
    off = float(track["gnss_off_at"])
    frame = LocalFrame.around(*track["home"])
    east, north = frame.to_enu(truth[:, 1], truth[:, 2])

    def position(t: float) -> np.ndarray:
        return np.array([np.interp(t, truth[:, 0], east), np.interp(t, truth[:, 0], north)])

    attitude, telemetry = _telemetry(flight / "fly" / "companion.jsonl")
    velocity = FrameVelocity(Camera.from_hfov(640, 480, hfov_deg), VelocityConfig(min_inliers=min_inliers))
    rows, costs, refused, refused_at = [], [], Counter(), Counter()
    for path in sorted((flight / "camera").glob("frame_*.jpg")):
        captured = int(path.stem.split("_")[1]) / 1e6
        height = _nearest(telemetry, captured)[1]
        if captured < off - BEFORE_GNSS_OFF_S or height < MIN_HEIGHT_M:
            velocity.reset()
            continue
        image = cv2.imread(str(path))
        started = time.perf_counter()
        try:
            measured = velocity.add(image, captured, height, math.degrees(_nearest(attitude, captured)[1]))
        except VelocityError as exc:
            refused[re.sub(r"\d+", "N", str(exc).split(":")[1].split("(")[0].strip())] += 1
            refused_at[_band(height)] += 1
            continue
        finally:
            costs.append(time.perf_counter() - started)
        if measured is None:
            continue
        half = measured.baseline_s / 2.0
        true = (position(measured.time_s + half) - position(measured.time_s - half)) / measured.baseline_s
        error = np.array([measured.east_mps, measured.north_mps]) - true
        own = _nearest(telemetry, measured.time_s)[2:4] - true
        mahalanobis = math.sqrt(error @ np.linalg.solve(measured.covariance_m2ps2, error))
        rows.append(
            (
                measured.time_s - off,
                np.linalg.norm(error),
                np.linalg.norm(own),
                mahalanobis,
                measured.sigma_mps,
                height,
            )
        )
    # Per velocity: time, error, the autopilot's error, Mahalanobis distance, sigma, height.
    data = np.array(rows, float).reshape(-1, 6)
    waypoints = [t - off for t, _ in track["reached"] if t > off]
    parts = [(-BEFORE_GNSS_OFF_S, 0.0), *zip([0.0, *waypoints], [*waypoints, math.inf], strict=True)]
    heights = data[:, 5]
    bands = sorted(set(refused_at) | {_band(h) for h in heights})
    return {
        "flight": str(flight),
        "hfov_deg": hfov_deg,
        "min_inliers": min_inliers,
        "frames": len(costs),
        "velocities": len(data),
        "refused": dict(refused.most_common()),
        "cost_p50_ms": round(float(np.median(costs)) * 1e3, 1),
        "cost_p95_ms": round(float(np.percentile(costs, 95)) * 1e3, 1),
        "all": _grade(data),
        "parts": [
            {
                "from_s": round(a, 1),
                "to_s": round(b, 1) if math.isfinite(b) else None,
                **_grade(data[(data[:, 0] >= a) & (data[:, 0] < b)]),
            }
            for a, b in parts
        ],
        "heights": [
            {
                "from_m": band,
                "refused": refused_at[band],
                **_grade(data[(heights >= band) & (heights < band + HEIGHT_BAND_M)]),
            }
            for band in bands
        ],
    }


def _band(height_m: float) -> float:
    """The lower bound of the height band ``height_m`` lies in."""
    return math.floor(height_m / HEIGHT_BAND_M) * HEIGHT_BAND_M


def _grade(data: np.ndarray) -> dict:
    """Error percentiles of the measured and the autopilot's velocity, and the covariance's cover."""
    if not len(data):
        return {"n": 0}

    def pct(values: np.ndarray, q: float) -> float:
        return round(float(np.percentile(values, q)), 2)

    error, own, mahalanobis = data[:, 1], data[:, 2], data[:, 3]
    return {
        "n": len(data),
        "error_p50_mps": pct(error, 50),
        "error_p95_mps": pct(error, 95),
        "error_max_mps": round(float(error.max()), 2),
        "sigma_p50_mps": pct(data[:, 4], 50),
        # Shares to set beside a 2-D normal's (chi-square with two degrees of freedom): an honest
        # covariance covers at least as much.
        "within_1_2_3_sigma": [round(float(np.mean(mahalanobis <= k)), 3) for k in (1, 2, 3)],
        "worst_sigmas": round(float(mahalanobis.max()), 1),
        "autopilot_error_p50_mps": pct(own, 50),
        "autopilot_error_p95_mps": pct(own, 95),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("flights", type=Path, nargs="+", help="bench sitl flight folders")
    parser.add_argument("--hfov", type=float, nargs="+", default=[90.0], help="each flight's lens (deg)")
    parser.add_argument(
        "--min-inliers",
        type=int,
        nargs="+",
        default=[VelocityConfig.min_inliers],
        help="inlier floors to grade",
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if len(args.hfov) != len(args.flights):
        parser.error("--hfov: one lens per flight")
    if min(args.min_inliers) < 3:
        parser.error("--min-inliers: a similarity fit needs at least 3 inliers")
    load = LoadWatch()
    rows = [
        measure(flight, hfov, floor)
        for flight, hfov in zip(args.flights, args.hfov, strict=True)
        for floor in args.min_inliers
    ]
    write_json_atomic(args.out, {"rows": rows, "machine": load.record()})
    for row in rows:
        keys = ("flight", "hfov_deg", "min_inliers", "velocities", "cost_p50_ms", "all")
        print(json.dumps({k: row[k] for k in keys}))


if __name__ == "__main__":
    main()

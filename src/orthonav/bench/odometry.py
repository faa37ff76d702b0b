"""``orthonav bench odometry``: frame-to-frame VO on real drone photos vs their GNSS and gimbal yaw.

Every consecutive photo pair, every (backend, model) configuration side by side: the VO
displacement in the previous image's axes against the GNSS displacement (pyproj geodesics)
turned into those axes by the previous photo's recorded heading; the VO heading change against
the recorded heading change. ``heading_offset_deg`` says where the image top really pointed
(GNSS course minus the VO direction of travel) relative to the recorded heading: near 0 when
the XMP heading describes the image, near 180 where it does not.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import median
from orthonav.errors import OrthonavError
from orthonav.flightlog.photos import read_photos
from orthonav.odometry.motion import METHODS, MotionConfig
from orthonav.odometry.sequence import LocalMap, run_photos


@dataclass(frozen=True)
class OdometryBenchConfig:
    features: tuple[str, ...] = ("orb", "sift")
    methods: tuple[str, ...] = METHODS
    max_side_px: int = 1280

    def __post_init__(self) -> None:
        bad = set(self.methods) - set(METHODS)
        if bad:
            raise OrthonavError(f"--methods: unknown {sorted(bad)}; expected {', '.join(METHODS)}")


def run_odometry_benchmark(
    photos: Path, out_json: Path, config: OdometryBenchConfig, progress: bool = True
) -> dict:
    """All configurations over the photo folder; JSON and a PNG written beside ``out_json``."""
    watch = LoadWatch()
    from orthonav.viz.odometry import plot_odometry_bench

    flight = read_photos(photos)
    motion_config = MotionConfig(max_side_px=config.max_side_px)
    rows, summary, names = [], [], []
    combos = [(f, m) for f in config.features for m in config.methods]
    for features, method in tqdm(combos, desc="bench odometry", disable=not progress):
        name = f"{features}/{method}"
        names.append(name)
        local_map = LocalMap()
        steps = [
            s for s in run_photos(flight, features, method, motion_config, local_map=local_map) if s.index > 0
        ]
        pair_rows = [{"config": name, **s.to_dict()} for s in steps]
        rows.extend(pair_rows)
        summary.append(_summarise(name, pair_rows, len(local_map)))
    result = {
        "config": asdict(config),
        "photos": str(photos),
        "pairs": len(flight) - 1,
        "summary": summary,
        "rows": rows,
        "machine": watch.record(),
    }
    write_json_atomic(out_json, result)
    plot_odometry_bench(rows, names, out_json.with_suffix(".png"))
    return result


def _summarise(name: str, rows: list[dict], landmarks: int) -> dict:
    ok = [r for r in rows if r["ok"]]
    consistent = [r for r in ok if abs(r.get("heading_offset_deg", 0.0)) < 30.0]

    return {
        "config": name,
        "pairs": len(rows),
        "ok": len(ok),
        "median_displacement_error_m": median([r["displacement_error_m"] for r in ok], 2),
        "median_abs_distance_error_m": median([abs(r["distance_error_m"]) for r in ok], 2),
        "median_abs_dyaw_error_deg": median([abs(r["dyaw_error_deg"]) for r in ok], 2),
        "heading_consistent": len(consistent),
        "consistent_median_displacement_error_m": median([r["displacement_error_m"] for r in consistent], 2),
        "consistent_median_abs_dyaw_error_deg": median([abs(r["dyaw_error_deg"]) for r in consistent], 2),
        "heading_flipped": sum(1 for r in ok if abs(r.get("heading_offset_deg", 0.0)) > 150.0),
        "median_ms": median([1000.0 * r["elapsed_s"] for r in ok], 2),
        "landmarks": landmarks,
        "reasons": sorted({r["reason"].split(":")[0] for r in rows if not r["ok"]}),
    }

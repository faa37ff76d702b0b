"""``orthonav odometry`` (VO over a photo folder) and the ``bench odometry`` / ``bench robustness``
commands."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table
from tqdm import tqdm

from orthonav.cli.output import table_console


def odometry(
    photos: Annotated[Path, typer.Argument(help="Folder of geotagged (DJI EXIF/XMP) nadir photos.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (steps.jsonl, track.png).")],
    features: Annotated[str, typer.Option(help="Feature backend (orb, sift, aliked, ...).")] = "orb",
    method: Annotated[str, typer.Option(help="homography (ground plane) or essential (3D scene).")] = (
        "homography"
    ),
    max_side: Annotated[int, typer.Option(help="Frames are shrunk to this longest side (px).")] = 1280,
    key_objects: Annotated[
        bool, typer.Option(help="Also build the key-object map (keyobjects.npz, keyobjects.json).")
    ] = True,
    direction: Annotated[str, typer.Option(help="Camera direction name in the key-object map.")] = "nadir",
) -> None:
    """Visual odometry over a photo sequence: per-step motion, errors vs GNSS/gimbal, track plot,
    and the key-object map (per keyframe and direction, clouds relative to the base viewpoint)."""
    from orthonav.atomic import write_json_atomic, write_text_atomic
    from orthonav.flightlog.photos import read_photos
    from orthonav.geo import LocalFrame
    from orthonav.odometry.keymap import KeyObjectConfig, KeyObjectMapBuilder
    from orthonav.odometry.motion import MotionConfig
    from orthonav.odometry.sequence import LocalMap, run_photos
    from orthonav.viz.odometry import plot_vo_track

    flight = read_photos(photos)
    out.mkdir(parents=True, exist_ok=True)
    local_map = LocalMap()
    builder = None
    if key_objects and flight.camera is not None:
        ko_config = KeyObjectConfig(direction=direction, max_side_px=max_side)
        builder = KeyObjectMapBuilder(flight.camera, ko_config)
    config = MotionConfig(max_side_px=max_side)
    steps = list(
        tqdm(
            run_photos(flight, features, method, config, local_map=local_map, key_objects=builder),
            total=len(flight),
            desc="odometry",
        )
    )
    if builder is not None:
        model = builder.build([s.index for s in steps if s.keyframe])
        model.save(out / "keyobjects.npz")
        write_json_atomic(out / "keyobjects.json", model.summary())
    write_text_atomic(out / "steps.jsonl", "".join(json.dumps(s.to_dict()) + "\n" for s in steps))
    write_json_atomic(
        out / "config.json",
        {
            "photos": str(photos),
            "features": features,
            "method": method,
            "max_side_px": max_side,
            "landmarks": len(local_map),
        },
    )
    first = flight.photos[0]
    frame = LocalFrame.around(first.lat, first.lon)
    east, north = frame.to_enu([p.lat for p in flight.photos], [p.lon for p in flight.photos])
    h0 = math.radians(first.heading_deg or 0.0)
    vo = [s.pose for s in steps if s.pose is not None]
    vo_e = [east[0] + p.x_m * math.cos(h0) + p.y_m * math.sin(h0) for p in vo]
    vo_n = [north[0] - p.x_m * math.sin(h0) + p.y_m * math.cos(h0) for p in vo]
    plot_vo_track(
        {"GNSS": (list(east), list(north)), f"VO {features}/{method}": (vo_e, vo_n)},
        out / "track.png",
        f"{photos.name}: VO (first photo's heading) vs GNSS",
    )
    table = Table(title=f"visual odometry {features}/{method}", box=None)
    for col in ("photo", "ok", "right m", "fwd m", "dyaw", "err m", "dyaw err", "inl", "reason"):
        table.add_column(col, justify="right")
    for s in steps[1:]:
        e, m = s.errors(), s.motion
        table.add_row(
            s.name,
            "yes" if m else "[red]no[/]",
            *(f"{v:.2f}" if m else "" for v in ((m.right_m, m.forward_m, m.dyaw_deg) if m else (0, 0, 0))),
            f"{e['displacement_error_m']:.2f}" if e else "",
            f"{e['dyaw_error_deg']:.1f}" if e else "",
            str(m.inliers) if m else "",
            s.reason[:60],
        )
    table_console.print(table)
    table_console.print(
        f"{sum(s.motion is not None for s in steps[1:])}/{len(steps) - 1} steps, "
        f"{len(local_map)} landmarks; written {out / 'steps.jsonl'} and {out / 'track.png'}"
    )
    if builder is not None:
        table_console.print(
            f"key-object map: {len(model.key_points)} key points, {model.summary()['objects']} objects; "
            f"written {out / 'keyobjects.npz'} and {out / 'keyobjects.json'}"
        )

"""``orthonav correction``: correct an INS prior from one frame; train a correction trunk."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from orthonav.cli.inputs import camera_from_options, parse_area, parse_latlon
from orthonav.errors import OrthonavError

if TYPE_CHECKING:
    from orthonav.camera import Camera
    from orthonav.frames import FrameSource
    from orthonav.models.dataset import TripletConfig, TripletSet

correction_app = typer.Typer(
    help="INS drift correction by dense correlation of the frame with the orthophoto.", no_args_is_help=True
)

_BACKBONE_HELP = (
    "gradient (no learning), trained (the shipped model or --model), or an untrained "
    "vgg11 / resnet18 / mobilenetv2 trunk."
)


@correction_app.command("run")
def correction_run(
    ortho: Annotated[Path, typer.Argument(help="Map orthophoto (GeoTIFF).")],
    frame: Annotated[Path, typer.Argument(help="Camera frame image.")],
    prior: Annotated[str, typer.Option(help="Prior position LAT,LON (deg) from the INS.")],
    altitude: Annotated[float, typer.Option(help="Altitude above ground (m).")],
    heading: Annotated[float, typer.Option(help="Heading (deg clockwise from north).")],
    pitch: Annotated[
        float | None, typer.Option(help="Pitch from the autopilot (deg; with --roll). Default: unknown.")
    ] = None,
    roll: Annotated[
        float | None, typer.Option(help="Roll from the autopilot (deg; with --pitch). Default: unknown.")
    ] = None,
    heading_sigma: Annotated[float, typer.Option(help="Heading 1-sigma (deg): turns searched.")] = 2.0,
    camera_json: Annotated[Path | None, typer.Option("--camera", help="Camera JSON.")] = None,
    width: Annotated[int, typer.Option(help="Frame width (px) without --camera.")] = 640,
    height: Annotated[int, typer.Option(help="Frame height (px) without --camera.")] = 480,
    hfov: Annotated[float, typer.Option(help="Horizontal field of view (deg) without --camera.")] = 60.0,
    backbone: Annotated[str, typer.Option(help=_BACKBONE_HELP)] = "gradient",
    model: Annotated[Path | None, typer.Option(help="Model file from `correction train`.")] = None,
    size: Annotated[int, typer.Option(help="Frame size for matching (px, long side).")] = 224,
    search_factor: Annotated[float, typer.Option(help="Search region = footprint x this.")] = 1.5,
    plot: Annotated[Path | None, typer.Option(help="PNG: views, heatmap and feature maps.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the fix as JSON.")] = False,
) -> None:
    """Correct one INS prior from one camera frame; print the fix (or why it was rejected)."""
    from orthonav.frames import load_frame
    from orthonav.geo import GeoRaster
    from orthonav.localize import CorrectionConfig, Corrector
    from orthonav.types import Prior

    config = CorrectionConfig(
        backbone="trained" if model else backbone,
        model_path=str(model) if model else None,
        size_px=size,
        search_factor=search_factor,
    )
    camera = camera_from_options(camera_json, width, height, hfov)
    lat, lon = parse_latlon(prior, "--prior")
    prior_pose = Prior(lat, lon, altitude, heading, pitch, roll, heading_sigma_deg=heading_sigma)
    image = load_frame(frame)
    with GeoRaster(ortho) as raster:
        corrector = Corrector(raster, camera, config)
        result = corrector.correct(image, prior_pose)
        if plot:
            from orthonav.viz.correction import plot_correction

            plot_correction(result, corrector.feature_maps(result.views), plot)
    record = result.fix.to_dict()
    if as_json:
        typer.echo(json.dumps(record))
        return
    for key, value in record.items():
        if value not in (None, {}, ""):
            typer.echo(f"{key:>10}: {value}")


@correction_app.command("train")
def correction_train(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")],
    train_dates: Annotated[str, typer.Option(help="Dates to train on, comma-separated (in file names).")],
    out: Annotated[Path, typer.Option(help="Run folder: model.pt, checkpoint, curves (resumes).")],
    backbone: Annotated[str, typer.Option(help="vgg11, resnet18 or mobilenetv2.")] = "resnet18",
    stage: Annotated[int, typer.Option(help="Cut the trunk after this stage.")] = 2,
    epochs: Annotated[int, typer.Option(help="Training epochs.")] = 10,
    samples: Annotated[int, typer.Option(help="Training triplets (over all date pairs).")] = 2000,
    val_samples: Annotated[int, typer.Option(help="Validation triplets.")] = 300,
    train_area: Annotated[
        str, typer.Option(help="Training strip, shares of map width: START,END.")
    ] = "0,0.5",
    val_area: Annotated[str, typer.Option(help="Validation strip (kept apart): START,END.")] = "0.55,1",
    mining: Annotated[str, typer.Option(help="batch-hard or triplets.")] = "batch-hard",
    margin: Annotated[float, typer.Option(help="Triplet loss margin.")] = 0.3,
    batch: Annotated[int, typer.Option(help="Batch size.")] = 16,
    lr: Annotated[float, typer.Option(help="Learning rate (AdamW, cosine schedule).")] = 1e-3,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    threads: Annotated[int | None, typer.Option(help="Torch CPU threads.")] = None,
    flight_frames: Annotated[
        Path | None, typer.Option(help="Real flight: a video, or a folder of frames sorted by name.")
    ] = None,
    flight_log: Annotated[
        Path | None, typer.Option(help="The flight's ArduPilot log (.bin or .tlog).")
    ] = None,
    flight_map: Annotated[
        Path | None, typer.Option(help="Orthophoto (GeoTIFF) of the flown area, of another date.")
    ] = None,
    flight_offset: Annotated[
        float | None, typer.Option(help="Log time (s, on the log's clock) of the first frame.")
    ] = None,
    flight_interval: Annotated[
        float | None, typer.Option(help="Seconds between the frames of an image folder.")
    ] = None,
    flight_every: Annotated[int, typer.Option(help="Use every Nth flight frame.")] = 1,
    flight_gimbal: Annotated[
        bool, typer.Option(help="The camera hangs in a nadir gimbal: ignore the vehicle's pitch/roll.")
    ] = False,
    camera_json: Annotated[Path | None, typer.Option("--camera", help="Flight camera JSON.")] = None,
    width: Annotated[int, typer.Option(help="Flight frame width (px) without --camera.")] = 640,
    height: Annotated[int, typer.Option(help="Flight frame height (px) without --camera.")] = 480,
    hfov: Annotated[float, typer.Option(help="Flight camera horizontal FOV (deg) without --camera.")] = 60.0,
) -> None:
    """Train a correction trunk with the triplet loss on pairs of dates; area-split validation.

    With --flight-frames/--flight-log/--flight-map, triplets from a real flight join the training set.
    """
    import torch

    from orthonav.models.dataset import TripletConfig
    from orthonav.models.train import TrainConfig, dates_in, train_on_dates
    from orthonav.viz.correction import plot_training, plot_triplets

    if threads:
        torch.set_num_threads(threads)
    dates = [d.strip() for d in train_dates.split(",") if d.strip()]
    if len(dates) < 2:
        raise OrthonavError(f"--train-dates {train_dates!r}: expected at least two dates")
    orthos = dates_in(data, dates)
    triplets = TripletConfig(samples=samples, area=parse_area(train_area, "--train-area"), seed=seed)
    flight = FlightOptions(
        flight_frames, flight_log, flight_map, flight_offset, flight_interval, flight_every, flight_gimbal
    )
    extra = flight.triplets(camera_from_options(camera_json, width, height, hfov), triplets)
    if extra is not None:
        typer.echo(f"flight: {len(extra)} triplets from {flight_frames}")
    result = train_on_dates(
        orthos,
        triplets,
        parse_area(val_area, "--val-area"),
        val_samples,
        TrainConfig(backbone, stage, epochs, batch, lr, margin=margin, mining=mining, seed=seed),
        out,
        extra=extra,
        info={"flight": flight.record(extra)} if extra is not None else None,
    )
    preview = result.pop("preview")
    plot_triplets(preview.pop("anchor"), preview, out / "triplets.png")
    plot_training(result["history"], out / "losses.png")
    last = result["history"][-1]
    typer.echo(
        f"trained {len(result['history'])} epochs: val top-1 {last['val_top1']:.3f} (best "
        f"{result['best_val_top1']:.3f}), model {result['model']}, curves {out / 'losses.png'}"
    )


@dataclass(frozen=True)
class FlightOptions:
    """The ``--flight-*`` options of ``correction train``, checked together."""

    frames: Path | None
    log: Path | None
    ortho: Path | None
    offset_s: float | None
    interval_s: float | None
    every: int
    gimbal: bool

    def triplets(self, camera: Camera, config: TripletConfig) -> TripletSet | None:
        """The flight's triplets, or None without flight options."""
        from orthonav.flightlog import read_flight_log
        from orthonav.geo import GeoRaster
        from orthonav.replay.flight_triplets import flight_triplets

        given = {"--flight-frames": self.frames, "--flight-log": self.log, "--flight-map": self.ortho}
        if all(v is None for v in given.values()):
            if self.offset_s is not None or self.interval_s is not None:
                raise OrthonavError(
                    "--flight-offset/--flight-interval: given without --flight-frames, --flight-log "
                    "and --flight-map"
                )
            return None
        missing = [name for name, value in given.items() if value is None]
        if missing:
            raise OrthonavError(
                f"{', '.join(missing)}: missing; --flight-frames, --flight-log and --flight-map go together"
            )
        if self.offset_s is None:
            raise OrthonavError("--flight-offset: missing; give the log time (s) of the first flight frame")
        frames = self._frames()
        flight = read_flight_log(self.log)
        with GeoRaster(self.ortho) as raster:
            return flight_triplets(
                frames,
                flight,
                raster,
                camera,
                config,
                self.offset_s,
                self.every,
                not self.gimbal,
                progress=True,
            )

    def _frames(self) -> FrameSource:
        from orthonav.frames import open_frames

        return open_frames(self.frames, self.interval_s, "--flight-frames", "--flight-interval")

    def record(self, triplets: TripletSet) -> dict:
        """What the run's records keep of the flight."""
        return {
            "frames": str(self.frames),
            "log": str(self.log),
            "map": str(self.ortho),
            "offset_s": self.offset_s,
            "interval_s": self.interval_s,
            "every": self.every,
            "nadir_gimbal": self.gimbal,
            "samples": len(triplets),
        }

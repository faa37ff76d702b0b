"""Training triplets for the correction CNN: anchor frame, positive and negative map patches.

A sample is an anchor (the frame view: a camera frame orthorectified heading-up, from one
date or a real flight) and the map's region view around the TRUE position from another date.
The positive is the region patch under the anchor (the region's centre); the negatives are
patches of the same region shifted by some metres (nearby, hard), among them the patch for
the position ``seconds_earlier`` back along the track (a temporal hard negative).
Patches are cut from the region at training time, so one region serves every negative.

The split is by area: a sample belongs to the strip of the map that holds its whole
search region, and strips are separated by a gap, so no validation pixel is trained on.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.frames.views import Views, make_views, view_geometry
from orthonav.geo import GeoRaster, bright_pixels
from orthonav.types import Prior

MAX_TRIES_PER_SAMPLE = 200


@dataclass(frozen=True)
class TripletConfig:
    """How samples are drawn; frames are 640x480 at ``alt_m`` so the view is ~5 m/px on NAIP."""

    samples: int = 400
    size_px: int = 112
    search_factor: float = 2.0
    alt_m: float = 500.0
    alt_jitter: float = 0.1
    width: int = 640
    height: int = 480
    hfov_deg: float = 60.0
    max_tilt_deg: float = 3.0
    heading_noise_deg: float = 1.0
    photometric: float = 1.0
    speed_mps: float = 15.0
    seconds_earlier: float = 10.0
    area: tuple[float, float] = (0.0, 1.0)  # share of the map's width the regions must lie in
    seed: int = 0

    def __post_init__(self) -> None:
        lo, hi = self.area
        if not 0.0 <= lo < hi <= 1.0:
            raise OrthonavError(
                f"triplet area: expected 0 <= start < end <= 1 (shares of map width), got {self.area}"
            )
        if self.samples < 1:
            raise OrthonavError(f"triplet samples: expected at least 1, got {self.samples}")

    @property
    def camera(self) -> Camera:
        return Camera.from_hfov(self.width, self.height, self.hfov_deg)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TripletSet:
    """Samples of one kind and size: anchors (N, h, w, 3), regions (N, H, W, 3), uint8 RGB.

    ``temporal_px`` (N, 2): where the temporal negative lies relative to the positive (x, y px).
    """

    anchors: np.ndarray
    anchor_masks: np.ndarray
    regions: np.ndarray
    temporal_px: np.ndarray
    gsd_m: float
    sources: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.anchors)

    @property
    def margin_px(self) -> tuple[int, int]:
        """(x, y) margin of the region around the positive patch (it is centred)."""
        return (
            (self.regions.shape[2] - self.anchors.shape[2]) // 2,
            (self.regions.shape[1] - self.anchors.shape[1]) // 2,
        )

    def patch(self, index: int, dx_px: int = 0, dy_px: int = 0) -> np.ndarray:
        """The region patch shifted ``(dx, dy)`` from the positive (0, 0 = the positive)."""
        mx, my = self.margin_px
        h, w = self.anchors.shape[1:3]
        if abs(dx_px) > mx or abs(dy_px) > my:
            raise OrthonavError(
                f"patch shift ({dx_px}, {dy_px}) px is beyond the region's margin ({mx}, {my})"
            )
        return self.regions[index, my + dy_px : my + dy_px + h, mx + dx_px : mx + dx_px + w]

    @staticmethod
    def concatenate(sets: list[TripletSet]) -> TripletSet:
        shapes = {(s.anchors.shape[1:], s.regions.shape[1:]) for s in sets}
        if len(shapes) != 1:
            raise OrthonavError(f"triplet sets of different sizes cannot be mixed: {sorted(shapes)}")
        return TripletSet(
            np.concatenate([s.anchors for s in sets]),
            np.concatenate([s.anchor_masks for s in sets]),
            np.concatenate([s.regions for s in sets]),
            np.concatenate([s.temporal_px for s in sets]),
            sets[0].gsd_m,
            [src for s in sets for src in s.sources],
        )


def build_pair_triplets(
    anchor_ortho: Path, map_ortho: Path, config: TripletConfig, progress: bool = False
) -> TripletSet:
    """Triplets from two co-registered orthophotos of the same area at different dates.

    Anchors are frames rendered from ``anchor_ortho`` (random pose, attitude, photometric
    change), regions come from ``map_ortho``; poses follow random straight tracks, and the
    temporal negative is the position ``seconds_earlier`` back along the track.
    """
    camera = config.camera
    rng = np.random.default_rng([config.seed, *anchor_ortho.stem.encode(), *map_ortho.stem.encode()])
    with GeoRaster(anchor_ortho) as frames, GeoRaster(map_ortho) as ortho:
        views = [
            _pair_sample(frames, ortho, camera, config, rng)
            for _ in _steps(config.samples, progress, map_ortho)
        ]
    earlier_m = config.speed_mps * config.seconds_earlier  # in each sample's own pixels (altitudes differ)
    temporal = [(0.0, earlier_m / v.geometry.gsd_m) for v in views]
    return _to_set(views, temporal, f"{anchor_ortho.name} -> {map_ortho.name}")


def views_to_triplets(views: list[Views], temporal_px: list[tuple[float, float]], source: str) -> TripletSet:
    """Views made at the true positions (e.g. from a flight log) -> a triplet set."""
    if not views:
        raise OrthonavError(f"{source}: no samples to make triplets from")
    return _to_set(views, temporal_px, source)


def _to_set(views: list[Views], temporal_px: list[tuple[float, float]], source: str) -> TripletSet:
    return TripletSet(
        np.stack([v.frame for v in views]),
        np.stack([v.frame_mask for v in views]),
        np.stack([v.region for v in views]),
        np.asarray(temporal_px, np.float32).reshape(-1, 2),
        views[0].geometry.gsd_m,
        [source] * len(views),
    )


def _steps(n: int, progress: bool, path: Path) -> Iterator[int]:
    return iter(tqdm(range(n), desc=f"triplets {path.name}", disable=not progress, leave=False))


def _pair_sample(
    frames: GeoRaster, ortho: GeoRaster, camera: Camera, config: TripletConfig, rng: np.random.Generator
) -> Views:
    for _ in range(MAX_TRIES_PER_SAMPLE):
        truth = _random_pose(ortho, config, rng)
        prior = Prior(
            truth.lat,
            truth.lon,
            truth.alt_agl_m,
            (truth.yaw_deg + rng.normal(0.0, config.heading_noise_deg)) % 360.0,
            truth.pitch_deg,
            truth.roll_deg,
        )
        try:
            geometry = view_geometry(ortho, camera, prior, config.size_px, config.search_factor)
        except OrthonavError:
            continue  # too near the map's edge
        if not _inside_area(ortho, geometry, config.area):
            continue
        frame = render_frame(frames, camera, truth, Photometric.random(rng, config.photometric), rng)
        views = make_views(ortho, camera, frame, prior, config.size_px, config.search_factor)
        if views.region_mask.mean() > 0.99 and bright_pixels(views.frame).mean() > 0.98:
            return views
    raise OrthonavError(
        f"{ortho.path}: found no pose whose search region lies inside the area {config.area} of the map "
        f"(at {config.alt_m:.0f} m the region is too large for it; lower alt_m or widen the area)"
    )


def _random_pose(ortho: GeoRaster, config: TripletConfig, rng: np.random.Generator) -> TruePose:
    lo, hi = config.area
    col = rng.uniform(lo * ortho.width, hi * ortho.width)
    row = rng.uniform(0, ortho.height)
    lat, lon = (float(v) for v in ortho.pixel_to_latlon(col, row))
    tilt = config.max_tilt_deg
    alt = config.alt_m * rng.uniform(1 - config.alt_jitter, 1 + config.alt_jitter)
    return TruePose(lat, lon, alt, rng.uniform(0, 360), rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt))


def _inside_area(ortho: GeoRaster, geometry, area: tuple[float, float]) -> bool:
    """The whole (rotated) region lies between the area's left and right map columns."""
    cols, _ = ortho.latlon_to_pixel(*geometry.region_corners_latlon())
    return bool(cols.min() >= area[0] * ortho.width and cols.max() <= area[1] * ortho.width)


def year_pair_triplets(orthos: list[Path], config: TripletConfig, progress: bool = False) -> TripletSet:
    """Triplets from every ordered pair of different dates: anchors from one, map from the other."""
    orthos = list(dict.fromkeys(orthos))  # a date named twice (e.g. '2018,20180716') counts once
    if len(orthos) < 2:
        names = ", ".join(p.name for p in orthos)
        raise OrthonavError(f"training needs at least two different dates of the same area, got: {names}")
    pairs = [(a, b) for a in orthos for b in orthos if a != b]
    per_pair = max(1, config.samples // len(pairs))
    sets = [build_pair_triplets(a, b, replace(config, samples=per_pair), progress) for a, b in pairs]
    return TripletSet.concatenate(sets)

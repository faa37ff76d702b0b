"""Seeded synthetic aerial orthophoto for the built-in demo.

The demo has to run offline, so instead of downloading imagery we paint a plausible rural
scene - fields, roads, villages, trees and water - and georeference it in the local UTM
zone. Every layer carries fine, high-contrast detail (crop rows, soil grain, bushes, roof
edges, tree crowns) because the navigation pipeline matches ORB keypoints against this map:
large uniform areas would be blind spots. Sizes are given in metres and converted with
the ground sample distance, so the scene keeps its scale at any ``gsd_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from orthonav.errors import OrthonavError
from orthonav.geo import write_geotiff

# Sun from the north-west: shadows fall to the south-east (+x, +y in image coordinates).
_SUN_DIR = np.array([1.0, 1.0]) / math.sqrt(2.0)

_FIELD_COLOURS = np.array(
    [
        (86, 118, 50),  # green crops
        (104, 138, 58),
        (70, 98, 44),
        (122, 148, 72),
        (140, 158, 92),  # grass and pasture
        (96, 124, 66),
        (198, 182, 112),  # wheat and stubble
        (212, 192, 126),
        (180, 164, 96),
        (188, 170, 120),
        (124, 98, 72),  # ploughed soil
        (142, 112, 82),
        (104, 84, 62),
        (158, 132, 100),
    ],
    dtype=np.float32,
)
_ROOF_COLOURS = np.array(
    [
        (152, 72, 56),  # clay tiles
        (170, 96, 62),
        (128, 60, 50),
        (118, 118, 124),  # slate
        (84, 84, 90),  # bitumen
        (196, 196, 192),  # light metal
        (92, 122, 112),  # green metal
        (150, 138, 120),  # concrete
    ],
    dtype=np.float32,
)
_ASPHALT = (92, 92, 96)
_DIRT = (182, 164, 128)
_SHADOW = (36, 40, 32)
_WATER = np.array((34, 66, 82), dtype=np.float32)
_SHORE = (128, 118, 92)


@dataclass(frozen=True)
class TerrainConfig:
    """Size, resolution, georeference and seed of the synthetic orthophoto."""

    size_px: int = 2048  # square image side
    gsd_m: float = 1.0  # metres per pixel
    center_lat: float = 50.45  # WGS84 centre of the image
    center_lon: float = 30.52
    seed: int = 7

    def __post_init__(self) -> None:
        if self.size_px < 64:
            raise OrthonavError(f"terrain size_px must be at least 64, got {self.size_px}")
        if not (math.isfinite(self.gsd_m) and self.gsd_m > 0.0):
            raise OrthonavError(f"terrain gsd_m must be a positive number, got {self.gsd_m}")
        if not -80.0 <= self.center_lat <= 84.0:
            raise OrthonavError(
                f"terrain center_lat {self.center_lat} is outside the UTM range [-80, 84] degrees"
            )
        if not -180.0 <= self.center_lon <= 180.0:
            raise OrthonavError(f"terrain center_lon {self.center_lon} is outside [-180, 180]")


@dataclass(frozen=True)
class _Scene:
    """Shared state of one render: the random stream, image size and metre/pixel scale."""

    rng: np.random.Generator
    size: int
    px_per_m: float

    def px(self, metres: float, minimum: float = 1.0) -> float:
        """Metres -> pixels, never below ``minimum`` so features survive coarse GSDs."""
        return max(metres * self.px_per_m, minimum)

    @property
    def side_km(self) -> float:
        """Ground length of the image side."""
        return self.size / self.px_per_m / 1000.0

    def count(self, per_km2: float, minimum: int = 1) -> int:
        """How many features of a given density fit in the image area."""
        return max(minimum, round(per_km2 * self.side_km**2))


def render_terrain(config: TerrainConfig) -> np.ndarray:
    """Return an (H, W, 3) uint8 RGB image of synthetic terrain, deterministic for a seed."""
    scene = _Scene(np.random.default_rng(config.seed), config.size_px, 1.0 / config.gsd_m)
    polygons, image = _fields(scene)
    _bushes(scene, image)
    _woods(scene, image)
    roads = _roads(scene, image, polygons)  # after the woods: roads cut through them
    _villages(scene, image, roads)
    _farmsteads(scene, image)
    _tree_lines(scene, image, polygons)
    _water(scene, image, roads)
    return _finish(scene, image)


def write_terrain_geotiff(path: Path, config: TerrainConfig = TerrainConfig()) -> Path:
    """Render and write an RGB GeoTIFF in the UTM zone of the centre, atomically.

    Readers never see a half-written map, and a crash leaves the previous file untouched.
    """
    path = Path(path)
    image = render_terrain(config)
    crs = _utm_crs(config.center_lat, config.center_lon)
    east, north = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True).transform(
        config.center_lon, config.center_lat
    )
    half_m = config.size_px * config.gsd_m / 2.0
    profile = {
        "driver": "GTiff",
        "width": config.size_px,
        "height": config.size_px,
        "count": 3,
        "dtype": "uint8",
        "crs": crs,
        # North-up: the origin is the top-left corner, rows run south.
        "transform": Affine(config.gsd_m, 0.0, east - half_m, 0.0, -config.gsd_m, north + half_m),
        "photometric": "RGB",
        "compress": "deflate",
        "predictor": 2,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_geotiff(path, np.moveaxis(image, -1, 0), profile)


def _utm_crs(lat: float, lon: float) -> CRS:
    """The WGS84 UTM CRS whose zone contains (lat, lon), via the PROJ database.

    On a zone boundary two zones qualify: the nearer central meridian wins and a tie goes to
    the lower EPSG code, so the choice is deterministic.
    """
    aoi = AreaOfInterest(lon, lat, lon, lat)
    infos = query_utm_crs_info(datum_name="WGS 84", area_of_interest=aoi)
    if not infos:
        raise OrthonavError(f"no WGS84 UTM zone covers lat {lat}, lon {lon}")
    best = min(
        infos,
        key=lambda i: (abs((i.area_of_use.west + i.area_of_use.east) / 2 - lon), i.code),
    )
    return CRS.from_epsg(int(best.code))


# --- noise ---------------------------------------------------------------------------------


def _value_noise(rng: np.random.Generator, size: int, cell_px: float, octaves: int) -> np.ndarray:
    """Fractal value noise in [0, 1]: cubic-upsampled random grids give organic shapes cheaply."""
    total = np.zeros((size, size), np.float32)
    amplitude = 1.0
    for octave in range(octaves):
        cell = max(cell_px / 2**octave, 2.0)
        cells = math.ceil(size / cell) + 2
        grid = rng.random((cells, cells), dtype=np.float32)
        side = round(cells * cell)
        smooth = cv2.resize(grid, (side, side), interpolation=cv2.INTER_CUBIC)
        total += amplitude * smooth[:size, :size]
        amplitude *= 0.5
    low, high = float(total.min()), float(total.max())
    return (total - low) / max(high - low, 1e-6)


# --- fields --------------------------------------------------------------------------------


def _fields(scene: _Scene) -> tuple[list[np.ndarray], np.ndarray]:
    """Patchwork of fields, each with its own colour and oriented crop rows.

    Fields are Voronoi cells of jittered seeds, stretched along one prevailing direction so
    they come out elongated like real farmland. Returns the field polygons (for tracks and
    hedges along their edges) and the image.
    """
    rng, size = scene.rng, scene.size
    spacing = scene.px(110.0, minimum=16.0)
    heading = rng.uniform(0.0, math.pi)
    stretch = rng.uniform(1.5, 2.2)
    cos, sin = math.cos(heading), math.sin(heading)
    rotation = np.array([[cos, -sin], [sin, cos]])
    to_image = rotation @ np.diag([stretch, 1.0]) @ rotation.T
    # Seeds cover the image's footprint in the unstretched space, plus one cell of margin.
    reach = size * 0.75 + 2 * spacing
    n = math.ceil(2 * reach / spacing)
    grid = (np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2) + 0.5) * spacing
    seeds = grid - reach + rng.uniform(-0.45, 0.45, grid.shape) * spacing
    subdiv = cv2.Subdiv2D((int(-2 * reach), int(-2 * reach), int(4 * reach), int(4 * reach)))
    subdiv.insert([(float(x), float(y)) for x, y in seeds])
    facets, _ = subdiv.getVoronoiFacetList([])
    centre = np.array([size / 2.0, size / 2.0])
    polygons = [np.round(f @ to_image.T + centre).astype(np.int32) for f in facets]
    polygons = [p for p in polygons if _overlaps_image(p, size)]

    labels = np.zeros((size, size), np.int32)
    for index, polygon in enumerate(polygons):
        cv2.fillPoly(labels, [polygon], index)
    return polygons, _field_texture(scene, labels, len(polygons), heading)


def _overlaps_image(polygon: np.ndarray, size: int) -> bool:
    """Whether a polygon's bounding box touches the image (cheap culling of far fields)."""
    low, high = polygon.min(axis=0), polygon.max(axis=0)
    return bool(np.all(high >= 0) and np.all(low < size))


def _field_texture(scene: _Scene, labels: np.ndarray, n_fields: int, heading: float) -> np.ndarray:
    """Per-field colour, crop rows with tramlines, patchy growth and soil grain.

    Rows run along or across the prevailing field direction, as ploughing follows the
    field's long side. The grain and tramlines give corners for keypoint detectors.
    """
    rng, size = scene.rng, scene.size
    colours = _FIELD_COLOURS[rng.integers(0, len(_FIELD_COLOURS), n_fields)]
    brightness = rng.uniform(0.9, 1.1, (n_fields, 1)).astype(np.float32)
    colours = colours * brightness + rng.normal(0.0, 3.0, colours.shape).astype(np.float32)
    angle = heading + rng.choice([0.0, math.pi / 2], n_fields) + rng.normal(0.0, 0.12, n_fields)
    period = np.maximum(rng.uniform(3.0, 9.0, n_fields) * scene.px_per_m, 3.0)
    tramline = np.maximum(rng.uniform(18.0, 24.0, n_fields) * scene.px_per_m, 8.0)
    row_amp = rng.uniform(0.05, 0.16, n_fields).astype(np.float32)
    grain_amp = rng.uniform(9.0, 14.0, n_fields).astype(np.float32)

    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    # Distance across the rows: the coordinate along each field's row normal.
    across = ys * np.cos(angle).astype(np.float32)[labels]
    across -= xs * np.sin(angle).astype(np.float32)[labels]
    rows = np.sin(across * (2.0 * math.pi / period).astype(np.float32)[labels]) * row_amp[labels]
    lanes = np.abs(np.mod(across / tramline.astype(np.float32)[labels], 1.0) - 0.5)
    tracks = (lanes > 0.5 - 0.6 / tramline.astype(np.float32)[labels]) * np.float32(0.12)
    patches = (_value_noise(rng, size, scene.px(30.0, 4.0), 4) - 0.5) * 0.35
    grain = cv2.GaussianBlur(rng.standard_normal((size, size), dtype=np.float32), (0, 0), 1.0)
    # Grain is additive (grey levels, not relative), so dark fields are as textured as light
    # ones for detectors with an absolute contrast threshold such as FAST.
    grain *= grain_amp[labels] / 0.28  # a sigma-1 blur leaves white noise with std ~0.28
    shade = 1.0 + rows + tracks + patches
    image = colours[labels] * shade[..., None] + grain[..., None]
    return np.clip(image, 0, 255).astype(np.uint8)


def _bushes(scene: _Scene, image: np.ndarray) -> None:
    """Solitary bushes scattered over the fields: small landmarks in otherwise open land."""
    rng, size = scene.rng, scene.size
    for _ in range(scene.count(300.0)):
        _tree(scene, image, rng.uniform(0.0, size, 2), rng.uniform(1.2, 2.5))


# --- roads ---------------------------------------------------------------------------------


def _roads(scene: _Scene, image: np.ndarray, polygons: list[np.ndarray]) -> list[np.ndarray]:
    """Asphalt roads (straight and curved) across the area, plus dirt tracks on field edges.

    Returns the asphalt centre lines (dense polylines) for placing villages along them.
    """
    rng = scene.rng
    _field_tracks(scene, image, polygons)
    roads = []
    # Through-roads scale with the side, not the area, or large maps become a road net.
    for index in range(max(2, round(1.5 * scene.side_km))):
        line = _crossing_line(scene, curved=index % 2 == 1)
        width = scene.px(rng.uniform(5.0, 8.0), minimum=2.0)
        _draw_road(image, line, width, verge=scene.px(1.5))
        if width >= 5.0:
            _centre_dashes(scene, image, line)
        roads.append(line)
    return roads


def _crossing_line(scene: _Scene, curved: bool) -> np.ndarray:
    """A dense polyline entering and leaving the image, through its middle region."""
    rng, size = scene.rng, scene.size
    centre = rng.uniform(0.2, 0.8, 2) * size
    heading = rng.uniform(0.0, math.pi)
    direction = np.array([math.cos(heading), math.sin(heading)])
    normal = np.array([-direction[1], direction[0]])
    t = np.linspace(-1.0, 1.0, 400)[:, None] * size
    bend = 0.0
    if curved:
        amp, waves = rng.uniform(0.06, 0.14) * size, rng.uniform(0.8, 1.6)
        bend = amp * np.sin(math.pi * waves * t / size + rng.uniform(0.0, math.pi))
    return centre + t * direction + bend * normal


def _draw_road(image: np.ndarray, line: np.ndarray, width: float, verge: float) -> None:
    """Road surface over a lighter gravel verge, anti-aliased."""
    points = [np.round(line).astype(np.int32)]
    cv2.polylines(image, points, False, (150, 142, 118), round(width + 2 * verge), cv2.LINE_AA)
    cv2.polylines(image, points, False, _ASPHALT, round(width), cv2.LINE_AA)


def _centre_dashes(scene: _Scene, image: np.ndarray, line: np.ndarray) -> None:
    """White dashed centre line: strong, repeatable corners for the feature matcher."""
    step = np.linalg.norm(np.diff(line, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(step)])
    dash, gap = scene.px(3.0, 2.0), scene.px(6.0, 3.0)
    for start in np.arange(0.0, along[-1], dash + gap):
        a = np.interp(start, along, line[:, 0]), np.interp(start, along, line[:, 1])
        b = np.interp(start + dash, along, line[:, 0]), np.interp(start + dash, along, line[:, 1])
        cv2.line(image, _pt(a), _pt(b), (220, 220, 214), 1, cv2.LINE_AA)


def _field_tracks(scene: _Scene, image: np.ndarray, polygons: list[np.ndarray]) -> None:
    """Light dirt tracks and dark hedge margins along field boundaries."""
    rng = scene.rng
    for polygon in polygons:
        cv2.polylines(image, [polygon], True, (74, 86, 50), 1, cv2.LINE_AA)
        if rng.random() < 0.25:
            edge = rng.integers(0, len(polygon))
            a, b = polygon[edge], polygon[(edge + 1) % len(polygon)]
            width = round(scene.px(rng.uniform(3.0, 4.5), minimum=1.0))
            cv2.line(image, _pt(a), _pt(b), _DIRT, width, cv2.LINE_AA)


# --- buildings -----------------------------------------------------------------------------


def _villages(scene: _Scene, image: np.ndarray, roads: list[np.ndarray]) -> None:
    """Rows of houses facing an asphalt road on both sides, like a street village."""
    rng = scene.rng
    for _ in range(scene.count(0.6, minimum=1)):
        line = roads[rng.integers(0, len(roads))]
        # Every crossing line passes through the image, so some of its points are inside.
        inside = np.all((line >= 0) & (line < scene.size), axis=1)
        start = int(rng.choice(np.flatnonzero(inside[: len(line) - 1])))
        step = np.linalg.norm(np.diff(line, axis=0), axis=1)
        along = np.concatenate([[0.0], np.cumsum(step)])
        spacing = scene.px(rng.uniform(20.0, 30.0), 4.0)
        n_houses = int(rng.integers(6, 16))
        for k in range(n_houses):
            s = along[start] + k * spacing + rng.normal(0.0, 2.0)
            index = min(int(np.searchsorted(along, s)), len(line) - 2)
            tangent = line[index + 1] - line[index]
            tangent /= np.linalg.norm(tangent) + 1e-9
            normal = np.array([-tangent[1], tangent[0]])
            point = np.array([np.interp(s, along, line[:, 0]), np.interp(s, along, line[:, 1])])
            for side in (-1.0, 1.0):
                if rng.random() < 0.15:
                    continue
                setback = scene.px(rng.uniform(14.0, 22.0), 3.0)
                centre = point + side * setback * normal
                angle = math.degrees(math.atan2(tangent[1], tangent[0])) + rng.normal(0.0, 4.0)
                _yard(scene, image, centre + side * scene.px(12.0) * normal, angle)
                _building(scene, image, centre, angle)


def _farmsteads(scene: _Scene, image: np.ndarray) -> None:
    """Loose clusters of barns and houses at random orientations away from the roads."""
    rng, size = scene.rng, scene.size
    for _ in range(scene.count(1.2, minimum=2)):
        centre = rng.uniform(0.05, 0.95, 2) * size
        base_angle = rng.uniform(0.0, 180.0)
        for _ in range(int(rng.integers(3, 9))):
            offset = rng.normal(0.0, scene.px(25.0), 2)
            angle = base_angle + rng.choice([0.0, 90.0]) + rng.normal(0.0, 3.0)
            _building(scene, image, centre + offset, angle, large=rng.random() < 0.4)


def _yard(scene: _Scene, image: np.ndarray, centre: np.ndarray, angle: float) -> None:
    """A mown garden plot behind a house, with a few fruit trees."""
    rng = scene.rng
    size = (scene.px(rng.uniform(16.0, 22.0)), scene.px(rng.uniform(28.0, 40.0)))
    box = cv2.boxPoints((tuple(centre), size, angle)).astype(np.int32)
    lawn = np.array((96.0, 126.0, 62.0)) + rng.normal(0.0, 8.0, 3)
    cv2.fillPoly(image, [box], _rgb(lawn), cv2.LINE_AA)
    for _ in range(int(rng.integers(1, 4))):
        _tree(scene, image, centre + rng.normal(0.0, scene.px(6.0), 2), rng.uniform(2.0, 3.5))


def _building(
    scene: _Scene, image: np.ndarray, centre: np.ndarray, angle: float, large: bool = False
) -> None:
    """A rotated rectangular roof with a gable shading split and a cast shadow."""
    rng = scene.rng
    length, depth = (
        (rng.uniform(20.0, 40.0), rng.uniform(10.0, 16.0))
        if large
        else (rng.uniform(9.0, 16.0), rng.uniform(7.0, 11.0))
    )
    height = rng.uniform(4.0, 8.0) if large else rng.uniform(3.0, 6.0)
    rect = (tuple(centre), (scene.px(length, 2.0), scene.px(depth, 2.0)), angle)
    box = cv2.boxPoints(rect)
    shadow = box + _SUN_DIR * scene.px(height * 0.8)
    cv2.fillPoly(image, [np.round(shadow).astype(np.int32)], _SHADOW, cv2.LINE_AA)
    roof = _ROOF_COLOURS[rng.integers(0, len(_ROOF_COLOURS))] + rng.normal(0.0, 6.0, 3)
    cv2.fillPoly(image, [np.round(box).astype(np.int32)], _rgb(roof), cv2.LINE_AA)
    # The half of the gable facing away from the sun is darker; the ridge runs lengthwise.
    half = np.array([box[0], box[1], (box[1] + box[2]) / 2, (box[0] + box[3]) / 2])
    cv2.fillPoly(image, [np.round(half).astype(np.int32)], _rgb(roof * 0.78), cv2.LINE_AA)


# --- trees ---------------------------------------------------------------------------------


def _tree(scene: _Scene, image: np.ndarray, centre: np.ndarray, radius_m: float) -> None:
    """One crown: shadow to the south-east, dark crown, lit highlight towards the sun."""
    rng = scene.rng
    radius = scene.px(radius_m)
    r = max(round(radius), 1)
    shadow = centre + _SUN_DIR * radius * 0.9
    cv2.circle(image, _pt(shadow), r, _SHADOW, -1, cv2.LINE_AA)
    crown = np.array((48, 78, 36)) + rng.normal(0.0, 7.0, 3)
    cv2.circle(image, _pt(centre), r, _rgb(crown), -1, cv2.LINE_AA)
    light = centre - _SUN_DIR * radius * 0.35
    cv2.circle(image, _pt(light), max(round(radius * 0.5), 1), _rgb(crown * 1.35), -1, cv2.LINE_AA)


def _tree_lines(scene: _Scene, image: np.ndarray, polygons: list[np.ndarray]) -> None:
    """Windbreak rows of trees along some field edges."""
    rng = scene.rng
    for polygon in polygons:
        if rng.random() >= 0.2:
            continue
        edge = rng.integers(0, len(polygon))
        a, b = polygon[edge].astype(float), polygon[(edge + 1) % len(polygon)].astype(float)
        n = int(np.linalg.norm(b - a) / scene.px(5.0, 2.0))
        for t in np.linspace(0.0, 1.0, max(n, 2)):
            jitter = rng.normal(0.0, scene.px(0.8, 0.5), 2)
            _tree(scene, image, a + t * (b - a) + jitter, rng.uniform(2.2, 4.0))


def _woods(scene: _Scene, image: np.ndarray) -> None:
    """Small woods: many overlapping crowns inside a blob of thresholded noise."""
    rng, size = scene.rng, scene.size
    noise = _value_noise(rng, size, scene.px(220.0, 16.0), 3)
    mask = noise > np.quantile(noise, 0.93)
    rows, cols = np.nonzero(mask)
    spacing = scene.px(4.0, 2.0)
    n_trees = int(rows.size / spacing**2)
    picks = rng.integers(0, rows.size, n_trees)
    for col, row in zip(cols[picks], rows[picks], strict=True):
        _tree(scene, image, np.array([col, row], float) + rng.random(2), rng.uniform(2.5, 5.0))


# --- water ---------------------------------------------------------------------------------


def _water(scene: _Scene, image: np.ndarray, roads: list[np.ndarray]) -> None:
    """One or two ponds: a noisy radial blob, dark blue-green with ripples and a muddy shore.

    Ponds are painted last (nothing stands in them) and placed clear of the roads where
    possible, so no road simply ends at a shoreline.
    """
    rng, size = scene.rng, scene.size
    road_points = np.concatenate(roads)
    mask = np.zeros((size, size), np.uint8)
    for _ in range(int(rng.integers(1, 3))):
        radius = min(scene.px(rng.uniform(60.0, 160.0)), 0.1 * size)
        candidates = rng.uniform(0.15, 0.85, (20, 2)) * size
        offsets = candidates[:, None, :] - road_points[None, :, :]
        clearance = np.linalg.norm(offsets, axis=2).min(axis=1)
        _pond_mask(scene, mask, candidates[int(np.argmax(clearance))], radius)
    shore = cv2.dilate(mask, np.ones((3, 3), np.uint8), iterations=round(scene.px(2.0))) > 0
    image[shore & (mask == 0)] = _SHORE

    depth = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
    depth = np.clip(depth / scene.px(25.0, 4.0), 0.0, 1.0)[..., None]
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    wavelength = scene.px(7.0, 3.0)
    ripple = np.sin((xs * 0.8 + ys * 0.6) * (2 * math.pi / wavelength)) * 0.5
    ripple += (_value_noise(rng, size, scene.px(4.0, 2.0), 2) - 0.5) * 0.8
    shallow = np.array((70, 92, 84), np.float32)
    water = shallow * (1.0 - depth) + _WATER * depth
    water = water * (1.0 + 0.12 * ripple[..., None])
    inside = mask > 0
    image[inside] = np.clip(water[inside], 0, 255).astype(np.uint8)


def _pond_mask(scene: _Scene, mask: np.ndarray, centre: np.ndarray, radius: float) -> None:
    """Threshold smooth noise minus distance from the centre: an irregular, compact shoreline."""
    rng, size = scene.rng, scene.size
    reach = int(radius * 1.6)
    x0, y0 = (np.maximum(centre.astype(int) - reach, 0)).tolist()
    x1, y1 = (np.minimum(centre.astype(int) + reach, size)).tolist()
    side = max(x1 - x0, y1 - y0)
    noise = _value_noise(rng, side, max(radius / 1.5, 4.0), 3)[: y1 - y0, : x1 - x0]
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    distance = np.hypot(xs - centre[0], ys - centre[1]) / radius
    inside = distance + (noise - 0.5) * 0.9 < 1.0
    mask[y0:y1, x0:x1] |= inside.astype(np.uint8)


# --- finishing -----------------------------------------------------------------------------


def _finish(scene: _Scene, image: np.ndarray) -> np.ndarray:
    """Uneven illumination and sensor noise, so no two patches of a colour are identical."""
    rng, size = scene.rng, scene.size
    light = 1.0 + (_value_noise(rng, size, scene.px(400.0, 32.0), 2) - 0.5) * 0.16
    grain = rng.normal(0.0, 3.0, (size, size, 1)).astype(np.float32)
    out = image.astype(np.float32) * light[..., None] + grain
    return np.clip(out, 0, 255).astype(np.uint8)


def _pt(xy: np.ndarray | tuple[float, float]) -> tuple[int, int]:
    """A point as the int pixel tuple OpenCV's drawing functions want."""
    return round(float(xy[0])), round(float(xy[1]))


def _rgb(colour: np.ndarray) -> tuple[float, float, float]:
    """An RGB colour as a plain tuple for OpenCV, clipped to the 8-bit range."""
    r, g, b = np.clip(colour, 0, 255)
    return float(r), float(g), float(b)

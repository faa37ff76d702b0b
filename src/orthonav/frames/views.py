"""The views of frame and map that matching compares.

The north-up view (:func:`north_up`) is a frame as a map's tiles are matched and indexed: scaled to
the map's ground resolution and turned north-up for a heading.

The two images a correction compares are the frame and the map's search region, made alike.

Both are heading-up views of the ground at one common ground resolution (``gsd_m``):
- the frame view is the camera frame orthorectified with the prior's altitude, heading and
  attitude, covering the nadir footprint w = 2 h tan(hfov / 2) by h = 2 h tan(vfov / 2) around
  the ground point under the image centre: onto the ground plane, or, given the terrain's
  heights, onto the terrain (every view pixel's ground point at its height, projected into the
  frame), so that relief shows where the orthophoto shows it;
- the region view is the orthophoto, ``search_factor`` times that footprint, around where the
  prior says that point is, read through the geo module (pyproj + rasterio), never by linear
  lat/lon interpolation.
An offset of the frame view inside the region view is then the prior's position error.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, pixel_to_ground, project_ground, project_points
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, LocalFrame, bright_pixels
from orthonav.types import Prior

VIEW_GRID = 5
# Terrain heights (m, one vertical datum) at WGS84 (lat, lon) arrays; NaN where unknown.
HeightsAt = Callable[[np.ndarray, np.ndarray], np.ndarray]
MIN_FOOTPRINT_MAP_PX = 16
MAX_TILT_DEG = 30.0
MAX_SEARCH_FACTOR = 4.0


@dataclass(frozen=True)
class ViewGeometry:
    """Where the views lie: heading-up pixels <-> ENU metres around the prior's position."""

    prior_lat: float
    prior_lon: float
    heading_deg: float
    gsd_m: float
    centre_en: tuple[float, float]  # ground point under the image centre, from the vehicle
    frame_size: tuple[int, int]  # (width, height) px
    region_size: tuple[int, int]

    def offset_to_en(self, dx_px: float, dy_px: float) -> tuple[float, float]:
        """A heading-up image offset (x right, y down) -> (east, north) metres."""
        right, forward = dx_px * self.gsd_m, -dy_px * self.gsd_m
        h = math.radians(self.heading_deg)
        return right * math.cos(h) + forward * math.sin(h), -right * math.sin(h) + forward * math.cos(h)

    def en_to_offset(self, east_m: float, north_m: float) -> tuple[float, float]:
        """(east, north) metres -> heading-up image offset (x right, y down): inverse of ``offset_to_en``."""
        h = math.radians(self.heading_deg)
        right = east_m * math.cos(h) - north_m * math.sin(h)
        forward = east_m * math.sin(h) + north_m * math.cos(h)
        return right / self.gsd_m, -forward / self.gsd_m

    def region_to_latlon(self, pts_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) region-view pixels -> WGS84 (lat, lon) of the ground they show."""
        en = self.pixels_to_en(pts_px, self.region_size)
        return LocalFrame.at(self.prior_lat, self.prior_lon).to_latlon(en[:, 0], en[:, 1])

    def region_corners_latlon(self) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 (lat, lon) of the region view's four corners (it is turned to the heading)."""
        w, h = self.region_size
        return self.region_to_latlon(np.array([[0, 0], [w, 0], [w, h], [0, h]], float))

    def pixels_to_en(self, pts_px: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(N, 2) pixels of a view of ``size`` centred on the image-centre ground point -> ENU."""
        pts = np.asarray(pts_px, float).reshape(-1, 2)
        east, north = self.offset_to_en(pts[:, 0] - size[0] / 2.0, pts[:, 1] - size[1] / 2.0)
        return np.column_stack([east + self.centre_en[0], north + self.centre_en[1]])


@dataclass
class Views:
    """Frame and region views (RGB uint8) with the masks of where they hold imagery.

    ``turn_deg``: the frame view is turned as if the heading were the prior's plus this.
    """

    frame: np.ndarray
    frame_mask: np.ndarray
    region: np.ndarray
    region_mask: np.ndarray
    geometry: ViewGeometry
    turn_deg: float = 0.0

    def turned(self, turn_deg: float) -> Views:
        """The same views for a heading ``turn_deg`` clockwise of the prior's (frame view turned)."""
        if turn_deg == 0.0:
            return self
        h, w = self.frame.shape[:2]
        # Assuming a heading further clockwise turns the frame's content further clockwise onto
        # the map; OpenCV's positive angles turn counter-clockwise.
        rot = cv2.getRotationMatrix2D((w / 2.0 - 0.5, h / 2.0 - 0.5), -turn_deg, 1.0)
        frame = cv2.warpAffine(self.frame, rot, (w, h), flags=cv2.INTER_LINEAR)
        mask = cv2.warpAffine(self.frame_mask.astype(np.uint8), rot, (w, h), flags=cv2.INTER_NEAREST) > 0
        return replace(self, frame=frame, frame_mask=mask, turn_deg=turn_deg)


def make_views(
    raster: GeoRaster,
    camera: Camera,
    frame_bgr: np.ndarray,
    prior: Prior,
    size_px: int,
    search_factor: float,
    heights: HeightsAt | None = None,
) -> Views:
    """Cut and resample both views; raise :class:`OrthonavError` for inputs that cannot work.
    ``heights``: the terrain to orthorectify the frame onto (default: flat ground)."""
    views = make_views_each(raster, camera, frame_bgr, [prior], size_px, search_factor, heights)[0]
    if isinstance(views, OrthonavError):
        raise views
    return views


def make_views_each(
    raster: GeoRaster,
    camera: Camera,
    frame_bgr: np.ndarray,
    priors: Sequence[Prior],
    size_px: int,
    search_factor: float,
    heights: HeightsAt | None = None,
) -> list[Views | OrthonavError]:
    """:func:`make_views` for one frame at several priors (a lost frame's places and trial
    headings), the error in the place of a prior whose views cannot be made. What the priors
    share is made once: on flat ground the frame view, which depends on the altitude and
    attitude but not on the place or heading (the views are heading-up); the map read and
    area-averaged once around each place for all its headings (:meth:`GeoRaster.read_views`).
    On terrain the frame view depends on the ground under it, and is made for each prior."""
    views: list[Views | OrthonavError] = []
    frames: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
    places: dict[tuple, list[int]] = {}
    for i, prior in enumerate(priors):
        try:
            geometry = view_geometry(raster, camera, prior, size_px, search_factor)
            shared = (prior.alt_agl_m, _attitude(prior)) if heights is None else (i,)
            if shared not in frames:
                frames[shared] = _frame_view(camera, frame_bgr, prior, geometry, heights)
        except OrthonavError as exc:
            views.append(exc)
            continue
        views.append(Views(*frames[shared], None, None, geometry))
        places.setdefault((prior.lat, prior.lon, geometry.gsd_m), []).append(i)
    for (_, _, gsd_m), members in places.items():
        outputs = [(views[i].geometry.region_to_latlon, *views[i].geometry.region_size) for i in members]
        for i, region in zip(members, raster.read_views(outputs, gsd_m), strict=True):
            mask = bright_pixels(region)
            views[i] = replace(views[i], region=_filled_off_map(region, mask), region_mask=mask)
    return views


def _filled_off_map(region: np.ndarray, on_map: np.ndarray) -> np.ndarray:
    """The region view with what lies off the map (black) at the mean colour of what lies on
    it: black, the map's edge would be the strongest edge to the gradients correlated."""
    if on_map.all() or not on_map.any():
        return region
    mask = on_map.view(np.uint8)
    filled = cv2.add(np.zeros_like(region), cv2.mean(region, mask=mask))  # each band's mean
    cv2.copyTo(region, mask, filled)
    return filled


def view_geometry(
    raster: GeoRaster, camera: Camera, prior: Prior, size_px: int, search_factor: float
) -> ViewGeometry:
    """The views' geometry from the prior; checks the prior and the map can support them."""
    geometry = _unchecked_geometry(raster, camera, prior, size_px, search_factor)
    _check_on_map(raster, geometry)
    return geometry


def region_overhang_m(margin_m: float, heading_deg: float) -> float:
    """How far (metres) a search region may reach past the map's edge: as far as it reaches
    past a frame by the edge at its centre, its ``margin_m`` around the frame view times (|cos|
    + |sin|) of the heading. Kept wholly on the map (moved inwards by that much), the region had
    such a frame on its border even with a perfect prior, and beyond it with a prior's error.
    What lies off the map is masked (``region_mask``) and filled; the correlation counts only
    placements of the frame mostly on the map."""
    turn = math.radians(heading_deg)
    return margin_m * (abs(math.cos(turn)) + abs(math.sin(turn)))


def region_overhang_px(raster: GeoRaster, geometry: ViewGeometry) -> float:
    """:func:`region_overhang_m` of a view's region, in map pixels."""
    margin = min(r - f for r, f in zip(geometry.region_size, geometry.frame_size, strict=True)) / 2.0
    return region_overhang_m(margin * geometry.gsd_m, geometry.heading_deg) / raster.gsd_m


def keep_region_on_map(
    raster: GeoRaster, camera: Camera, prior: Prior, size_px: int, search_factor: float
) -> Prior:
    """The prior moved inwards by as much as its search region reaches past the map's edge
    beyond its overhang (:func:`region_overhang_px`), so a prior near the edge is searched over
    ground the map has. A region wider than the map stays as it is (the views refuse it)."""
    geometry = _unchecked_geometry(raster, camera, prior, size_px, search_factor)
    col, row = raster.latlon_to_pixel(*geometry.region_corners_latlon())
    overhang = region_overhang_px(raster, geometry)
    shift_col = _inwards(float(col.min()), float(col.max()), raster.width, overhang)
    shift_row = _inwards(float(row.min()), float(row.max()), raster.height, overhang)
    if shift_col == shift_row == 0.0:
        return prior
    prior_col, prior_row = raster.latlon_to_pixel(prior.lat, prior.lon)
    lat, lon = raster.pixel_to_latlon(float(prior_col) + shift_col, float(prior_row) + shift_row)
    return replace(prior, lat=float(lat), lon=float(lon))


def _inwards(low: float, high: float, size: int, overhang: float) -> float:
    """Pixels to move a span [low, high] by so that it lies within [-overhang, size + overhang]
    (0 if it cannot)."""
    first, last = 0.01 - overhang, size - 0.01 + overhang
    if high - low > last - first:
        return 0.0
    if low < first:
        return first - low
    return min(0.0, last - high)


def _unchecked_geometry(
    raster: GeoRaster, camera: Camera, prior: Prior, size_px: int, search_factor: float
) -> ViewGeometry:
    _check_prior(prior)
    if not 1.0 < search_factor <= MAX_SEARCH_FACTOR:
        raise OrthonavError(f"search factor: expected 1 < lambda <= {MAX_SEARCH_FACTOR}, got {search_factor}")
    width_m, height_m = camera.nadir_footprint_m(prior.alt_agl_m)
    if min(width_m, height_m) < MIN_FOOTPRINT_MAP_PX * raster.gsd_m:
        raise OrthonavError(
            f"altitude {prior.alt_agl_m:.1f} m: the camera sees only {min(width_m, height_m):.1f} m of "
            f"ground, less than {MIN_FOOTPRINT_MAP_PX} pixels of the {raster.gsd_m:.2f} m/px map "
            f"{raster.path.name}; fly higher or use a finer map"
        )
    gsd = max(width_m, height_m) / size_px
    frame_size = (max(8, round(width_m / gsd)), max(8, round(height_m / gsd)))
    # An even margin: the centred placement of the frame view is a whole pixel.
    region_size = tuple(s + 2 * round((search_factor - 1.0) * s / 2.0) for s in frame_size)
    pose = CameraPose(0.0, 0.0, prior.alt_agl_m, prior.heading_deg, *_attitude(prior))
    centre = pixel_to_ground(camera, pose, np.array([[camera.cx, camera.cy]]))[0]
    return ViewGeometry(
        prior.lat,
        prior.lon,
        prior.heading_deg % 360.0,
        gsd,
        (float(centre[0]), float(centre[1])),
        frame_size,
        region_size,
    )


def _check_prior(prior: Prior) -> None:
    missing = [
        name
        for name, value in (
            ("position", prior.lat),
            ("altitude", prior.alt_agl_m),
            ("heading", prior.heading_deg),
        )
        if value is None
    ]
    if missing:
        raise OrthonavError(
            f"correction prior: needs position, altitude above ground and heading "
            f"(missing: {', '.join(missing)})"
        )
    if prior.has_attitude and max(abs(prior.pitch_deg), abs(prior.roll_deg)) > MAX_TILT_DEG:
        raise OrthonavError(
            f"correction prior: pitch/roll {prior.pitch_deg:.1f}/{prior.roll_deg:.1f} deg; the frame "
            f"must look within {MAX_TILT_DEG:.0f} deg of straight down"
        )


def _attitude(prior: Prior) -> tuple[float, float]:
    return (prior.pitch_deg, prior.roll_deg) if prior.has_attitude else (0.0, 0.0)


def _check_on_map(raster: GeoRaster, geometry: ViewGeometry) -> None:
    w, h = geometry.region_size
    col, row = raster.latlon_to_pixel(*geometry.region_corners_latlon())
    beyond_px = max(-col.min(), -row.min(), col.max() - raster.width, row.max() - raster.height)
    if beyond_px > region_overhang_px(raster, geometry):
        raise OrthonavError(
            f"prior {geometry.prior_lat:.6f}, {geometry.prior_lon:.6f}: the search region "
            f"({w * geometry.gsd_m:.0f} x {h * geometry.gsd_m:.0f} m) reaches "
            f"{beyond_px * raster.gsd_m:.0f} m beyond the edge of the map {raster.path.name}; "
            "the prior is outside the map or too near its edge"
        )


def _frame_view(
    camera: Camera, frame_bgr: np.ndarray, prior: Prior, geometry: ViewGeometry, heights: HeightsAt | None
) -> tuple[np.ndarray, np.ndarray]:
    """Orthorectify the frame onto the heading-up ground grid (mask: seen by the camera)."""
    if not isinstance(frame_bgr, np.ndarray) or frame_bgr.dtype != np.uint8 or frame_bgr.ndim != 3:
        array = isinstance(frame_bgr, np.ndarray)
        got = f"a {frame_bgr.dtype} array of shape {frame_bgr.shape}" if array else type(frame_bgr).__name__
        raise OrthonavError(f"frame: expected an (H, W, 3) uint8 colour image, got {got}")
    if frame_bgr.shape != (camera.height, camera.width, 3):
        raise OrthonavError(
            f"frame: expected a {camera.width}x{camera.height} colour image for this camera, "
            f"got shape {frame_bgr.shape}"
        )
    pose = CameraPose(0.0, 0.0, prior.alt_agl_m, prior.heading_deg, *_attitude(prior))
    # Shrink first with area averaging: the warp below samples, it does not average.
    shrink = min(1.0, camera.nadir_gsd_m(prior.alt_agl_m) / geometry.gsd_m)
    small = cv2.resize(frame_bgr, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA)
    sx, sy = small.shape[1] / camera.width, small.shape[0] / camera.height
    rgb_small = cv2.cvtColor(small, cv2.COLOR_BGR2RGB)
    relief = _relief_sampling(camera, pose, geometry, heights) if heights is not None else None
    if relief is not None:
        # Into the shrunk image with OpenCV's integer pixel centres, as below.
        map_x = (relief[..., 0] * sx - 0.5).astype(np.float32)
        map_y = (relief[..., 1] * sy - 0.5).astype(np.float32)
        rgb = cv2.remap(rgb_small, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        inside = (map_x >= -0.5) & (map_y >= -0.5)
        seen = inside & (map_x <= small.shape[1] - 0.5) & (map_y <= small.shape[0] - 0.5)
        return rgb, seen
    w, h = geometry.frame_size
    gu, gv = np.meshgrid(np.linspace(0, w, VIEW_GRID), np.linspace(0, h, VIEW_GRID))
    grid = np.column_stack([gu.ravel(), gv.ravel()])
    image_px = project_ground(camera, pose, geometry.pixels_to_en(grid, geometry.frame_size))
    # Into the shrunk image, with OpenCV's integer pixel centres; output samples pixel centres.
    small_px = image_px * [sx, sy] - 0.5
    h_view_to_small, _ = cv2.findHomography(grid, small_px, 0)
    centres = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    warp = h_view_to_small @ centres
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    rgb = cv2.warpPerspective(rgb_small, warp, (w, h), flags=flags)
    seen = cv2.warpPerspective(np.full(small.shape[:2], 255, np.uint8), warp, (w, h), flags=flags)
    return rgb, seen > 127


def _relief_sampling(
    camera: Camera, pose: CameraPose, geometry: ViewGeometry, heights: HeightsAt
) -> np.ndarray | None:
    """(h, w, 2) ideal frame pixels that every view pixel's ground point, at its terrain height,
    projects to; None where the terrain knows no height under the view (flat ground then).

    Heights are taken relative to the median height of the ground in view, the level the
    prior's altitude above ground is taken from (as the keypoint pose does: the height at one
    point, a tree or a roof under the drone, would move the whole view); unknown cells are at
    that level."""
    w, h = geometry.frame_size
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    en = geometry.pixels_to_en(np.column_stack([cols.ravel(), rows.ravel()]), geometry.frame_size)
    lat, lon = LocalFrame.at(geometry.prior_lat, geometry.prior_lon).to_latlon(en[:, 0], en[:, 1])
    z = np.asarray(heights(lat, lon), float)
    if not np.isfinite(z).any():
        return None
    up = np.where(np.isfinite(z), z - np.nanmedian(z), 0.0)
    # Nothing the camera sees rises to its height: clip, so no point lands behind it.
    up = np.minimum(up, 0.9 * pose.alt_agl_m)
    return project_points(camera, pose, np.column_stack([en, up])).reshape(h, w, 2)


def region_point_latlon(geometry: ViewGeometry, x_px: float, y_px: float) -> tuple[float, float]:
    """A region-view pixel -> WGS84 (lat, lon) of the ground it shows."""
    lat, lon = geometry.region_to_latlon(np.array([[x_px, y_px]], float))
    return float(lat[0]), float(lon[0])


def vehicle_below(
    camera: Camera,
    centre_lat: float,
    centre_lon: float,
    alt_agl_m: float,
    heading_deg: float,
    pitch_deg: float,
    roll_deg: float,
) -> tuple[float, float]:
    """The vehicle's position from the ground point its image centre sees, and its attitude."""
    pose = CameraPose(0.0, 0.0, alt_agl_m, heading_deg, pitch_deg, roll_deg)
    east, north = pixel_to_ground(camera, pose, np.array([[camera.cx, camera.cy]]))[0]
    lat, lon = LocalFrame(centre_lat, centre_lon).to_latlon(-east, -north)
    return float(lat), float(lon)


@dataclass(frozen=True)
class NorthUp:
    """A frame as a map's tiles are matched: scaled, turned north-up, its valid pixels and the
    3x3 affine from frame pixels to view pixels (to carry keypoints back into the frame)."""

    gray: np.ndarray
    mask: np.ndarray
    affine: np.ndarray


def north_up(
    frame: np.ndarray, camera: Camera, gsd_m: float, alt_agl_m: float, heading_deg: float
) -> NorthUp:
    """``frame`` (gray or BGR) scaled from the camera's ground resolution at ``alt_agl_m`` to
    ``gsd_m`` (shrunk by area averaging first, so that the turn does not alias) and turned
    north-up for ``heading_deg``; the mask's border eroded so that features on the warp's edge
    are not taken for ground."""
    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    scale = float(np.clip(camera.nadir_gsd_m(alt_agl_m) / gsd_m, 0.05, 4.0))
    h, w = gray.shape
    if scale < 1.0:
        gray = cv2.resize(
            gray, (max(8, round(w * scale)), max(8, round(h * scale))), interpolation=cv2.INTER_AREA
        )
    sx, sy = gray.shape[1] / w, gray.shape[0] / h
    # cv2.resize aligns pixel centres: x_resized = (x + 0.5) sx - 0.5 (integers = pixel centres).
    resize = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    remaining = scale / sx
    hs, ws = gray.shape
    # OpenCV turns counter-clockwise for positive angles; north-up needs a clockwise turn.
    rot = cv2.getRotationMatrix2D((ws / 2.0, hs / 2.0), -heading_deg, remaining)
    corners = np.array([[0, 0, 1], [ws, 0, 1], [ws, hs, 1], [0, hs, 1]], float) @ rot.T
    lo, hi = corners.min(0), corners.max(0)
    rot[:, 2] -= lo
    size = (max(8, math.ceil(hi[0] - lo[0])), max(8, math.ceil(hi[1] - lo[1])))
    warped = cv2.warpAffine(gray, rot, size, flags=cv2.INTER_LINEAR, borderValue=0)
    mask = cv2.warpAffine(np.full_like(gray, 255), rot, size, flags=cv2.INTER_NEAREST)
    mask = cv2.erode(mask, np.ones((7, 7), np.uint8))
    affine = np.vstack([rot, [0, 0, 1]]) @ resize
    return NorthUp(warped, mask, affine)

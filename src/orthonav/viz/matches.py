"""A fix's point matches as one picture: the camera frame beside the map's orthophoto where its
inliers fall, a line per pair, and the verdict. It shows at a glance why a fix was accepted or
rejected (matches spread over the view, or a handful clustered on one field edge)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, PixelWindow
from orthonav.mapdb import MapPackage
from orthonav.types import Fix

ACCEPTED_BGR = (80, 200, 60)
REJECTED_BGR = (40, 60, 230)
BANNER_PX = 22
MARGIN_MAP_PX = 40.0  # orthophoto shown around the inliers, in work-grid pixels
FONT = cv2.FONT_HERSHEY_SIMPLEX


def draw_matches(frame: np.ndarray, fix: Fix, package: MapPackage, orthophoto: GeoRaster) -> np.ndarray:
    """(H, W + H, 3) BGR picture of ``fix``'s inliers: the (H, W) frame on the left, on the right
    the square of ``orthophoto`` (the map's own, opened from ``package.source_path``) around the
    inliers' map points, resized to H x H.

    Map points go work-grid pixels -> WGS84 -> orthophoto pixels, so the orthophoto may be in
    any CRS or resolution.
    """
    if fix.inliers_frame_px is None or fix.inliers_map_px is None or not len(fix.inliers_map_px):
        raise OrthonavError("draw_matches: the fix carries no point matches (inliers_frame_px/map_px)")
    left = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    height, width = left.shape[:2]
    right, patch_px = _orthophoto_patch(fix.inliers_map_px, package, orthophoto, height)
    picture = np.hstack([left, right])
    colour = ACCEPTED_BGR if fix.accepted else REJECTED_BGR
    for (fx, fy), (mx, my) in zip(fix.inliers_frame_px, patch_px, strict=True):
        a, b = _point(fx, fy), _point(mx + width, my)
        cv2.line(picture, a, b, colour, 1, cv2.LINE_AA)
        cv2.circle(picture, a, 2, colour, -1, cv2.LINE_AA)
        cv2.circle(picture, b, 2, colour, -1, cv2.LINE_AA)
    cv2.line(picture, (width, 0), (width, height), (255, 255, 255), 1)
    _banner(picture, _verdict(fix), colour)
    return picture


def _orthophoto_patch(
    map_px: np.ndarray, package: MapPackage, orthophoto: GeoRaster, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """(size, size, 3) BGR square around the map points, and their (N, 2) OpenCV pixels in it."""
    lat, lon = package.grid.pixel_to_latlon(map_px[:, 0], map_px[:, 1])
    col, row = orthophoto.latlon_to_pixel(lat, lon)
    margin = MARGIN_MAP_PX * package.gsd_m / orthophoto.gsd_m
    side = max(col.max() - col.min(), row.max() - row.min()) + 2.0 * margin
    col0 = math.floor((col.min() + col.max() - side) / 2.0)
    row0 = math.floor((row.min() + row.max() - side) / 2.0)
    side = math.ceil(side)
    rgb = orthophoto.read_rgb(PixelWindow(col0, row0, side, side), out_shape=(size, size))
    scale = size / side
    # Raster coordinates put pixel centres at +0.5, OpenCV drawing at integers.
    patch_px = np.column_stack([(col - col0) * scale - 0.5, (row - row0) * scale - 0.5])
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), patch_px


def _verdict(fix: Fix) -> str:
    q = fix.quality
    inliers = int(q.get("inliers", len(fix.inliers_map_px) if fix.inliers_map_px is not None else 0))
    matches = int(q.get("matches", 0))
    # A source that matched in stages (the cascade's guided matching) counts no candidate
    # matches: the picture then says how many it kept, not "of 0".
    counts = f"{inliers} inliers of {matches} matches" if matches >= inliers > 0 else f"{inliers} inliers"
    if fix.accepted:
        rmse = q.get("rmse_map_px")
        return f"accepted: {counts}" + (f", RMSE {rmse:.2f} map px" if rmse is not None else "")
    return f"rejected ({counts}): {fix.reason}"


def _banner(picture: np.ndarray, text: str, colour: tuple[int, int, int]) -> None:
    """``text`` on a dark band along the top, cut with '...' where it would not fit."""
    picture[:BANNER_PX] = (picture[:BANNER_PX] * 0.3).astype(np.uint8)
    limit = picture.shape[1] - 12
    while cv2.getTextSize(text, FONT, 0.5, 1)[0][0] > limit and len(text) > 4:
        text = text[:-4] + "..."
    cv2.putText(picture, text, (6, BANNER_PX - 7), FONT, 0.5, colour, 1, cv2.LINE_AA)


def _point(x: float, y: float) -> tuple[int, int]:
    return round(float(x)), round(float(y))

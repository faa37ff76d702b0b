"""A mission's corridor cut out of a map package: small, self-contained, for the drone.

The corridor is every tile that comes within ``width_m / 2`` of the route (a GeoJSON
LineString in WGS84). The new package keeps those tiles' features unchanged, on a work grid
cropped to their bounding box, and carries its own orthophoto crop (``ortho.tif``: the
dense correlation, the preview and the simulator need the imagery, not only features), so it
can be copied to a companion computer alone; a map with terrain gives it the terrain cells
under its grid. It is written in ``OUT.partial/`` and renamed into place when complete.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import shutil
from pathlib import Path

import numpy as np
from affine import Affine

from orthonav.atomic import sha256_file, write_npz_atomic, write_text_atomic
from orthonav.errors import OrthonavError, read_json_file
from orthonav.geo import GEOD, GeoRaster, check_latlon
from orthonav.mapdb.build import write_global_index, write_preview
from orthonav.mapdb.dsm import cut_terrain
from orthonav.mapdb.package import (
    FEATURE_DIR,
    MANIFEST,
    PREVIEW,
    TILES,
    MapPackage,
    check_replaceable,
    chunk_file,
    index_chunks,
    write_chunk,
)

log = logging.getLogger(__name__)

ORTHO = "ortho.tif"


def read_route(path: Path) -> list[tuple[float, float]]:
    """(lat, lon) vertices of a GeoJSON LineString (bare, in a Feature, or the first of a
    FeatureCollection); GeoJSON gives positions as [lon, lat]."""
    geometry = _line_geometry(read_json_file(path, "GeoJSON route file"), path)
    coords = geometry.get("coordinates")
    if not isinstance(coords, list) or len(coords) < 2:
        raise OrthonavError(f"{path}: a route needs a LineString of at least two [lon, lat] positions")
    route = []
    for i, position in enumerate(coords):
        if not (isinstance(position, list) and len(position) >= 2):
            raise OrthonavError(f"{path}: position {i} is {position!r}; expected [lon, lat]")
        lon, lat = float(position[0]), float(position[1])
        check_latlon(lat, lon, f"{path} position {i} (GeoJSON order is [lon, lat])")
        route.append((lat, lon))
    return route


def _line_geometry(data: object, path: Path) -> dict:
    if isinstance(data, dict) and data.get("type") == "FeatureCollection" and data.get("features"):
        data = data["features"][0]
    if isinstance(data, dict) and data.get("type") == "Feature":
        data = data.get("geometry")
    if not (isinstance(data, dict) and data.get("type") == "LineString"):
        raise OrthonavError(f"{path}: expected a GeoJSON LineString (or a Feature holding one)")
    return data


def corridor_tiles(package: MapPackage, route: list[tuple[float, float]], width_m: float) -> np.ndarray:
    """Indices of the tiles within ``width_m / 2`` of the route, sampled densely along it."""
    if not (math.isfinite(width_m) and width_m > 0):
        raise OrthonavError(f"corridor width: expected metres > 0, got {width_m}")
    step_m = max(package.gsd_m, width_m / 4.0)
    found: set[int] = set()
    for lat, lon in _densify(route, step_m):
        found.update(package.tiles_within(lat, lon, width_m / 2.0).tolist())
    if not found:
        raise OrthonavError(
            f"the route lies outside the map {package.path} (no tile within {width_m / 2:.0f} m of it)"
        )
    outside = sum(not package.grid.contains_latlon(lat, lon) for lat, lon in route)
    if outside:
        log.warning("%d of %d route points lie outside the map %s", outside, len(route), package.path)
    return np.array(sorted(found))


def _densify(route: list[tuple[float, float]], step_m: float) -> list[tuple[float, float]]:
    """The route's vertices with geodesic points at most ``step_m`` apart in between."""
    points = [route[0]]
    for (lat1, lon1), (lat2, lon2) in itertools.pairwise(route):
        _, _, dist = GEOD.inv(lon1, lat1, lon2, lat2)
        n = int(dist // step_m)
        points += [(lat, lon) for lon, lat in GEOD.npts(lon1, lat1, lon2, lat2, n)] if n else []
        points.append((lat2, lon2))
    return points


def cut_corridor(
    package: MapPackage,
    route: list[tuple[float, float]],
    width_m: float,
    out_dir: Path,
    overwrite: bool = False,
) -> MapPackage:
    """Write the corridor package to ``out_dir`` and open it."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise OrthonavError(f"{out_dir}: exists; choose another --out or pass --overwrite")
    if out_dir.exists():
        check_replaceable(out_dir)
    if out_dir.resolve() == package.path.resolve():
        raise OrthonavError(f"{out_dir}: is the map being cut; choose another --out")
    keep = corridor_tiles(package, route, width_m)
    partial = out_dir.with_name(out_dir.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    origin = np.floor(package.tiles.box_px[keep, :2].min(axis=0)).astype(int)
    corner = np.ceil(package.tiles.box_px[keep, 2:].max(axis=0)).astype(int)
    _write_features(package, keep, origin, partial / FEATURE_DIR)
    chunks = index_chunks(partial / FEATURE_DIR, len(keep), package.chunk_tiles)
    write_npz_atomic(partial / TILES, **_tiles(package, keep, origin), **chunks)
    transform = package.grid.transform @ Affine.translation(*origin)
    with GeoRaster(package.source_path) as source:
        xs, ys = package.grid.pixel_to_crs([origin[0], corner[0]], [origin[1], corner[1]])
        source.crop_to((float(min(xs)), float(min(ys)), float(max(xs)), float(max(ys))), partial / ORTHO)
    with GeoRaster(partial / ORTHO) as ortho:
        preview = write_preview(partial / PREVIEW, ortho)
        manifest = _manifest(package, ortho, keep, origin, corner, transform, preview, route, width_m)
    manifest["arrays"] = {TILES: sha256_file(partial / TILES)}
    write_text_atomic(partial / MANIFEST, json.dumps(manifest, indent=2))
    if package.global_index is not None:
        config = {k: v for k, v in package.manifest["global_index"].items() if k not in ("file", "sha256")}
        write_global_index(MapPackage(partial), package.global_index.subset(keep), config)
    cut_terrain(package, MapPackage(partial))
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(partial, out_dir)
    return MapPackage(out_dir)


def _tiles(package: MapPackage, keep: np.ndarray, origin: np.ndarray) -> dict[str, np.ndarray]:
    t = package.tiles
    box = t.box_px[keep].copy()
    box[:, [0, 2]] -= origin[0]
    box[:, [1, 3]] -= origin[1]
    grid_rc = t.grid_rc[keep]
    return {
        "box_px": box,
        "grid_rc": grid_rc - grid_rc.min(axis=0),
        "padded": t.padded[keep],
        "corners_latlon": t.corners_latlon[keep],
    }


def _write_features(package: MapPackage, keep: np.ndarray, origin: np.ndarray, directory: Path) -> None:
    """The kept tiles' features unchanged, renumbered and with map pixels moved to the cropped
    grid, re-chunked one chunk at a time."""
    directory.mkdir()
    size = package.chunk_tiles
    for first in range(0, len(keep), size):
        parts = []
        for new, old in enumerate(keep[first : first + size], start=first):
            records = np.array(package.tile_records(int(old)))
            records["tile"] = new
            records["map_px"] -= origin
            parts.append(records)
        write_chunk(chunk_file(directory, first), np.concatenate(parts))


def _manifest(
    package: MapPackage,
    ortho: GeoRaster,
    keep: np.ndarray,
    origin: np.ndarray,
    corner: np.ndarray,
    transform: Affine,
    preview: tuple[int, int],
    route: list[tuple[float, float]],
    width_m: float,
) -> dict:
    m = json.loads(json.dumps(package.manifest))
    m.pop("global_index", None)  # the parent's file; the corridor writes its own
    m.pop("terrain", None)  # likewise
    span = np.ptp(package.tiles.grid_rc[keep], axis=0) + 1
    m["source"] = {
        **m["source"],
        "path": ORTHO,
        "sha256": sha256_file(ortho.path),
        "width": ortho.width,
        "height": ortho.height,
        "transform": list(ortho.transform)[:6],
    }
    m["work"] = {
        **m["work"],
        "transform": list(transform)[:6],
        "width": int(corner[0] - origin[0]),
        "height": int(corner[1] - origin[1]),
    }
    m["tiling_layout"] = {
        **m["tiling_layout"],
        "rows": int(span[0]),
        "cols": int(span[1]),
        "count": len(keep),
    }
    m["preview"] = {"width": preview[1], "height": preview[0]}
    m["corridor"] = {
        "parent": str(package.path.resolve()),
        "parent_tiles": len(package),
        "width_m": width_m,
        "route_latlon": [list(p) for p in route],
    }
    return m

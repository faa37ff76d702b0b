"""Build a map package from an orthophoto: tile, extract features, write atomically.

The build works in ``MAP_DIR.partial/``. Tiles are processed in chunks, each saved as its
own file as soon as it is done; a build that is interrupted and started again with the same
source and settings skips the chunks already there. Only when every array is written is
the directory renamed to ``MAP_DIR``, so a map package is either complete or absent.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from orthonav import __version__
from orthonav.atomic import atomic_path, write_text_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, Runtime, create_backend
from orthonav.geo import GeoGrid, GeoRaster, PixelWindow
from orthonav.mapdb.globalindex import GLOBAL, GlobalIndex, train_index
from orthonav.mapdb.package import (
    FEATURES,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    PREVIEW,
    TILES,
    MapPackage,
    sha256_file,
)
from orthonav.mapdb.tiling import TileLayout, TilingConfig, layout_tiles, work_gsd_m

log = logging.getLogger(__name__)

CHUNK_TILES = 32
PREVIEW_PX = 1024
BUILD_KEY = "build.json"
# Keypoints this close to nodata or padding are dropped: the border itself is a strong edge.
BORDER_PX = 10


def build_map(
    ortho_path: str | Path,
    out_dir: str | Path,
    camera: Camera,
    tiling: TilingConfig | None = None,
    backend: str = "orb",
    backend_conf: dict | None = None,
    overwrite: bool = False,
    progress: bool = True,
    runtime: Runtime | None = None,
) -> MapPackage:
    """Build (or resume building) a map package; returns it opened.

    ``runtime`` (device, threads) only decides where features are computed, so it is not
    part of the package: a map built on a GPU is used on the drone's CPU.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise OrthonavError(f"{out_dir}: already exists (use --overwrite to replace it)")
    tiling = tiling or TilingConfig()
    features = create_backend(backend, runtime, **(backend_conf or {}))
    with GeoRaster(ortho_path) as raster:
        gsd = work_gsd_m(raster.gsd_m, camera, tiling)
        factor = gsd / raster.gsd_m
        grid = raster.scaled(factor)
        layout = layout_tiles(grid.width, grid.height, gsd, camera, tiling)
        key = {
            "source": str(Path(ortho_path).resolve()),
            "source_sha256": sha256_file(raster.path),
            "camera": camera.to_dict(),
            "tiling": tiling.to_dict(),
            "features": {"backend": backend, "config": features.conf},
            "format_version": FORMAT_VERSION,
        }
        partial = _prepare_partial(out_dir, key)
        _extract_chunks(raster, factor, grid, layout, features, partial, progress)
        _write_package(partial, raster, grid, gsd, layout, key)
    _publish(partial, out_dir)
    return MapPackage(out_dir)


def _prepare_partial(out_dir: Path, key: dict) -> Path:
    """The work directory; kept (resume) only when it was started with the same settings."""
    partial = out_dir.with_name(out_dir.name + ".partial")
    key_file = partial / BUILD_KEY
    if partial.exists():
        try:
            same = json.loads(key_file.read_text()) == json.loads(json.dumps(key))
        except (OSError, json.JSONDecodeError):
            same = False
        if same:
            log.info("resuming the interrupted build in %s", partial)
            return partial
        shutil.rmtree(partial)
    (partial / "chunks").mkdir(parents=True)
    write_text_atomic(key_file, json.dumps(key, indent=2))
    return partial


def _extract_chunks(
    raster: GeoRaster,
    factor: float,
    grid: GeoGrid,
    layout: TileLayout,
    features: FeatureBackend,
    partial: Path,
    progress: bool,
) -> None:
    n = len(layout)
    with tqdm(total=n, desc="map build", unit="tile", disable=not progress) as bar:
        for start in range(0, n, CHUNK_TILES):
            stop = min(start + CHUNK_TILES, n)
            chunk_file = partial / "chunks" / f"chunk_{start:07d}.npz"
            if not chunk_file.exists():
                sets = [_tile_features(raster, factor, layout, i, features) for i in range(start, stop)]
                _save_chunk(chunk_file, sets, layout.boxes[start:stop], grid)
            bar.update(stop - start)


def _tile_features(
    raster: GeoRaster, factor: float, layout: TileLayout, index: int, features: FeatureBackend
) -> FeatureSet:
    col0, row0, col1, row1 = layout.boxes[index]
    window = PixelWindow(col0 * factor, row0 * factor, (col1 - col0) * factor, (row1 - row0) * factor)
    rgb = raster.read_rgb(window, out_shape=(row1 - row0, col1 - col0))
    valid = (rgb.max(axis=2) > 0).astype(np.uint8)
    mask = cv2.erode(valid, np.ones((2 * BORDER_PX + 1, 2 * BORDER_PX + 1), np.uint8))
    if not mask.any():
        return features.empty()
    return features.extract(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), mask)


def _save_chunk(file: Path, sets: list[FeatureSet], boxes: np.ndarray, grid: GeoGrid) -> None:
    counts = np.array([len(s) for s in sets], np.int64)
    kp_tile = np.concatenate([s.keypoints for s in sets]).astype(np.float32)
    # Feature backends give OpenCV pixels (centre of pixel 0 at 0); work px put it at 0.5.
    kp_map = kp_tile + 0.5 + np.repeat(boxes[:, :2], counts, axis=0).astype(np.float32)
    x, y = grid.pixel_to_crs(kp_map[:, 0], kp_map[:, 1])
    _atomic_savez(
        file,
        counts=counts,
        keypoints_tile_px=kp_tile,
        keypoints_map_px=kp_map,
        keypoints_crs=np.column_stack([x, y]),
        descriptors=np.concatenate([s.descriptors for s in sets]),
        scores=np.concatenate([s.scores for s in sets]).astype(np.float32),
    )


def _write_package(
    partial: Path, raster: GeoRaster, grid: GeoGrid, gsd: float, layout: TileLayout, key: dict
) -> None:
    chunks = [dict(np.load(f)) for f in sorted((partial / "chunks").glob("chunk_*.npz"))]
    counts = np.concatenate([c["counts"] for c in chunks])
    if len(counts) != len(layout):
        raise OrthonavError(f"{partial}: chunk files cover {len(counts)} of {len(layout)} tiles")
    feature_arrays = {
        name: np.concatenate([c[name] for c in chunks])
        for name in ("keypoints_tile_px", "keypoints_map_px", "keypoints_crs", "descriptors", "scores")
    }
    if len(feature_arrays["scores"]) == 0:
        raise OrthonavError(
            f"{raster.path}: no features found anywhere in the orthophoto; it has no texture to navigate by"
        )
    feature_arrays["offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    _atomic_savez(partial / FEATURES, **feature_arrays)
    _atomic_savez(partial / TILES, **_tile_arrays(grid, layout))
    preview_shape = write_preview(partial / PREVIEW, raster)
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "orthonav_version": __version__,
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "source": {
            "path": key["source"],
            "sha256": key["source_sha256"],
            "width": raster.width,
            "height": raster.height,
            "bands": raster.band_count,
            "dtype": raster.dtype,
            "gsd_m": raster.gsd_m,
            "transform": list(raster.transform)[:6],
        },
        "work": {
            "crs_wkt": grid.crs.to_wkt(),
            "transform": list(grid.transform)[:6],
            "width": grid.width,
            "height": grid.height,
            "gsd_m": gsd,
        },
        "camera": key["camera"],
        "tiling": key["tiling"],
        "tiling_layout": {
            "tile_px": layout.tile_px,
            "stride_px": layout.stride_px,
            "rows": layout.rows,
            "cols": layout.cols,
            "count": len(layout),
        },
        "features": key["features"],
        "preview": {"width": preview_shape[1], "height": preview_shape[0]},
        "arrays": {name: sha256_file(partial / name) for name in (TILES, FEATURES)},
    }
    write_text_atomic(partial / MANIFEST, json.dumps(manifest, indent=2))


def _tile_arrays(grid: GeoGrid, layout: TileLayout) -> dict[str, np.ndarray]:
    boxes = layout.boxes
    cols = np.stack([boxes[:, 0], boxes[:, 2], (boxes[:, 0] + boxes[:, 2]) / 2], 1)
    rows = np.stack([boxes[:, 1], boxes[:, 3], (boxes[:, 1] + boxes[:, 3]) / 2], 1)
    lat, lon = grid.pixel_to_latlon(cols, rows)
    grid_rc = np.stack(np.divmod(np.arange(len(layout)), layout.cols), 1)
    return {
        "box_px": boxes,
        "grid_rc": grid_rc,
        "padded": layout.padded,
        "corners_latlon": np.stack([lat, lon], -1),
    }


def write_preview(file: Path, raster: GeoRaster) -> tuple[int, int]:
    """The orthophoto at <= PREVIEW_PX for plots; returns its (height, width)."""
    scale = max(1.0, max(raster.width, raster.height) / PREVIEW_PX)
    shape = (max(1, round(raster.height / scale)), max(1, round(raster.width / scale)))
    rgb = raster.read_rgb(out_shape=shape)
    with atomic_path(file) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return shape


def _publish(partial: Path, out_dir: Path) -> None:
    """Swap the finished build into place; an old package is removed only after the swap."""
    (partial / BUILD_KEY).unlink()
    shutil.rmtree(partial / "chunks")
    old = out_dir.with_name(out_dir.name + ".old")
    if out_dir.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(out_dir, old)
    os.replace(partial, out_dir)
    if old.exists():
        shutil.rmtree(old)


def _atomic_savez(file: Path, **arrays: np.ndarray) -> None:
    with atomic_path(file) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def build_global_index(package: MapPackage, words: int = 32, seed: int = 0) -> MapPackage:
    """Train the re-localization index on the package's own features, store it, reopen."""
    index = train_index(package.feature_offsets, package.feature_array("descriptors"), words, seed)
    write_global_index(package, index, {"method": "vlad", "words": words, "seed": seed})
    return MapPackage(package.path)


def write_global_index(package: MapPackage, index: GlobalIndex, config: dict) -> None:
    """``global.npz`` and its manifest record, each written atomically."""
    index.write(package.path / GLOBAL)
    record = {**config, "file": GLOBAL, "sha256": sha256_file(package.path / GLOBAL)}
    write_text_atomic(
        package.path / MANIFEST, json.dumps({**package.manifest, "global_index": record}, indent=2)
    )

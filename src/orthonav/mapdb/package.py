"""The map package: a directory with a JSON manifest and compressed arrays.

Layout (format version 1)::

    MAP_DIR/
      manifest.json   format + version, source file + sha256, CRS (WKT), work-grid transform,
                      camera, tiling, feature backend + config, array checksums, counts
      tiles.npz       box_px (T, 4) work px [col0, row0, col1, row1], grid_rc (T, 2),
                      padded (T,), corners_latlon (T, 3, 2): top-left, bottom-right, centre
      features.npz    offsets (T+1,) into the per-keypoint arrays below, which are grouped by
                      tile: keypoints_tile_px (N, 2), keypoints_map_px (N, 2) work px,
                      keypoints_crs (N, 2) map-CRS x/y, descriptors (N, D), scores (N,)
      preview.jpg     the orthophoto at <= 1024 px, for plots

Packages are written by :mod:`orthonav.mapdb.build` and opened read-only here.
"""

from __future__ import annotations

import functools
import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, Runtime, create_backend
from orthonav.geo import GeoGrid
from orthonav.mapdb.globalindex import GLOBAL, GlobalIndex
from orthonav.mapdb.tiling import TilingConfig

FORMAT = "orthonav-map"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
TILES = "tiles.npz"
FEATURES = "features.npz"
PREVIEW = "preview.jpg"
ARRAY_FILES = (TILES, FEATURES)


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class TileTable:
    """Per-tile geometry: boxes in work pixels, padding flags, WGS84 corners."""

    box_px: np.ndarray
    grid_rc: np.ndarray
    padded: np.ndarray
    corners_latlon: np.ndarray

    def __len__(self) -> int:
        return len(self.box_px)


class MapPackage:
    """A validated, read-only map package."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.manifest = _read_manifest(self.path)
        m = self.manifest
        try:
            self.grid = GeoGrid(
                CRS.from_wkt(m["work"]["crs_wkt"]),
                Affine(*m["work"]["transform"]),
                m["work"]["width"],
                m["work"]["height"],
            )
            self.gsd_m = float(m["work"]["gsd_m"])
            self.camera = Camera.from_dict(m["camera"], source=f"{self.path / MANIFEST} camera")
            self.tiling = TilingConfig(**m["tiling"])
            self.backend_name: str = m["features"]["backend"]
            self.backend_conf: dict = dict(m["features"]["config"])
            self.tile_px = int(m["tiling_layout"]["tile_px"])
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, OrthonavError):
                raise
            raise OrthonavError(f"{self.path / MANIFEST}: damaged manifest ({exc!r})") from None
        self.tiles, self._features = _read_arrays(self.path, m)

    def __len__(self) -> int:
        return len(self.tiles)

    def create_backend(self, runtime: Runtime | None = None, **overrides: Any) -> FeatureBackend:
        """The feature backend, with the exact config, that built this map.

        ``overrides`` may only relocate files the config names (e.g. weights moved since the
        build); anything that changes the features themselves would not match the map.
        """
        for key, value in overrides.items():
            if key not in self.backend_conf or not key.endswith("_weights"):
                raise OrthonavError(
                    f"{self.path}: cannot override {key!r}; the map was built with {self.backend_name} "
                    f"{self.backend_conf}"
                )
            if value is None:
                raise OrthonavError(f"{key}: expected a file path")
        return create_backend(self.backend_name, runtime, **{**self.backend_conf, **overrides})

    @functools.cached_property
    def global_index(self) -> GlobalIndex | None:
        """The re-localization index, if one was built (``orthonav map index``); checked on load."""
        record = self.manifest.get("global_index")
        if record is None:
            return None
        file = self.path / GLOBAL
        if not file.exists() or sha256_file(file) != record.get("sha256"):
            raise OrthonavError(f"{file}: missing or damaged; rebuild it with `orthonav map index`")
        index = GlobalIndex.read(file)
        if len(index.tile_vectors) != len(self):
            raise OrthonavError(f"{file}: {len(index.tile_vectors)} tiles, the package has {len(self)}")
        return index

    @property
    def source_path(self) -> Path:
        """The orthophoto the map was built from; a relative path (a corridor package's own
        crop) lies inside the package."""
        source = Path(self.manifest["source"]["path"])
        return source if source.is_absolute() else self.path / source

    @property
    def feature_offsets(self) -> np.ndarray:
        """(T+1,) start of each tile's keypoints in the per-keypoint arrays."""
        return self._features["offsets"]

    def feature_array(self, key: str) -> np.ndarray:
        """One per-keypoint array (``keypoints_map_px``, ``descriptors``...), grouped by tile."""
        return self._features[key]

    def tile_features(self, index: int) -> FeatureSet:
        """Features of one tile, keypoints in tile pixels."""
        s = slice(*self._features["offsets"][index : index + 2])
        return FeatureSet(
            self._features["keypoints_tile_px"][s],
            self._features["descriptors"][s],
            self._features["scores"][s],
            (self.tile_px, self.tile_px),
        )

    def tile_keypoints_map_px(self, index: int) -> np.ndarray:
        """(N, 2) keypoints of one tile in work-grid pixels."""
        s = slice(*self._features["offsets"][index : index + 2])
        return self._features["keypoints_map_px"][s]

    @property
    def keypoint_count(self) -> int:
        return int(self._features["offsets"][-1])

    def tiles_within(self, lat: float, lon: float, radius_m: float) -> np.ndarray:
        """Indices of tiles whose box comes within ``radius_m`` of a WGS84 point."""
        col, row = self.grid.latlon_to_pixel(lat, lon)
        gx, gy = self.grid.gsd_xy_m
        box = self.tiles.box_px
        dx = np.maximum(0.0, np.maximum(box[:, 0] - col, col - box[:, 2])) * gx
        dy = np.maximum(0.0, np.maximum(box[:, 1] - row, row - box[:, 3])) * gy
        return np.flatnonzero(np.hypot(dx, dy) <= radius_m)

    def preview(self) -> tuple[np.ndarray, GeoGrid]:
        """The stored orthophoto preview (RGB) and the grid it lies on."""
        image = cv2.imread(str(self.path / PREVIEW), cv2.IMREAD_COLOR)
        if image is None:
            raise OrthonavError(f"{self.path / PREVIEW}: missing or unreadable preview image")
        factor = self.grid.width / image.shape[1]
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), self.grid.scaled(factor)

    def summary(self) -> dict:
        """The facts a user wants from ``orthonav map info``."""
        m = self.manifest
        lat, lon = self.grid.center_latlon
        return {
            "path": str(self.path),
            "format_version": m["format_version"],
            "source": str(self.source_path),
            "source_sha256": m["source"]["sha256"][:16],
            "crs": self.grid.crs.to_string(),
            "source_gsd_m": m["source"]["gsd_m"],
            "work_gsd_m": self.gsd_m,
            "work_size_px": f"{self.grid.width} x {self.grid.height}",
            "area_km2": round(self.grid.width * self.grid.height * self.gsd_m**2 / 1e6, 3),
            "centre_latlon": f"{lat:.6f}, {lon:.6f}",
            "camera": f"{self.camera.width}x{self.camera.height}, hfov {self.camera.hfov_deg:.1f} deg",
            "nominal_alt_m": self.tiling.nominal_alt_m,
            "tiles": f"{len(self)} ({m['tiling_layout']['rows']} x {m['tiling_layout']['cols']}, "
            f"{m['tiling_layout']['tile_px']} px, stride {m['tiling_layout']['stride_px']} px, "
            f"{int(self.tiles.padded.sum())} padded)",
            "features": f"{self.backend_name} {self.backend_conf}",
            "keypoints": self.keypoint_count,
            "created": m.get("created", "?"),
        }


def _read_manifest(path: Path) -> dict:
    if not path.is_dir():
        raise OrthonavError(f"{path}: not a map package directory (build one with `orthonav map build`)")
    file = path / MANIFEST
    try:
        manifest = json.loads(file.read_text())
    except FileNotFoundError:
        raise OrthonavError(f"{path}: no {MANIFEST}; not a map package (or an unfinished build)") from None
    except json.JSONDecodeError as exc:
        raise OrthonavError(f"{file}: damaged manifest, not valid JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise OrthonavError(f"{file}: not an orthonav map manifest (format field != {FORMAT!r})")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION:
        raise OrthonavError(
            f"{file}: map format version {version}, this orthonav reads version {FORMAT_VERSION}; "
            "rebuild the map with `orthonav map build`"
        )
    return manifest


def _read_arrays(path: Path, manifest: dict) -> tuple[TileTable, dict[str, np.ndarray]]:
    checksums = manifest.get("arrays", {})
    loaded = {}
    for name in ARRAY_FILES:
        file = path / name
        if not file.exists():
            raise OrthonavError(f"{file}: missing; the map package is incomplete")
        if checksums.get(name) != sha256_file(file):
            raise OrthonavError(f"{file}: checksum mismatch; the map package is damaged, rebuild it")
        try:
            with np.load(file, allow_pickle=False) as data:
                loaded[name] = {key: data[key] for key in data.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise OrthonavError(f"{file}: unreadable arrays ({exc}); rebuild the map") from None
    t, f = loaded[TILES], loaded[FEATURES]
    try:
        tiles = TileTable(t["box_px"], t["grid_rc"], t["padded"], t["corners_latlon"])
        n_tiles, n_kp = len(tiles), int(f["offsets"][-1])
        consistent = len(f["offsets"]) == n_tiles + 1 and all(
            len(f[k]) == n_kp
            for k in ("keypoints_tile_px", "keypoints_map_px", "keypoints_crs", "descriptors", "scores")
        )
    except KeyError as exc:
        raise OrthonavError(f"{path}: array {exc.args[0]!r} missing; the map package is damaged") from None
    if not consistent:
        raise OrthonavError(f"{path}: tile and feature arrays disagree in size; the package is damaged")
    return tiles, f

"""The map package: a directory with a JSON manifest, a tile table and feature chunks.

Layout (format version 2)::

    MAP_DIR/
      manifest.json   format + version, source file + sha256, CRS (WKT), work-grid transform,
                      camera, tiling, feature backend + config + chunk size, tile-table checksum
      tiles.npz       box_px (T, 4) work px [col0, row0, col1, row1], grid_rc (T, 2),
                      padded (T,), corners_latlon (T, 3, 2): top-left, bottom-right, centre,
                      feature_offsets (T+1,) into the concatenation of the chunks,
                      chunk_sha256 (C,) one checksum per feature chunk
      features/chunk_<first tile:07d>.npy
                      the keypoints of ``chunk_tiles`` consecutive tiles, grouped by tile, as
                      one structured array (:func:`keypoint_dtype`): tile, tile_px, map_px (work
                      px), crs (map-CRS x/y), score, descriptor
      preview.jpg     the orthophoto at <= 1024 px, for plots
      terrain.tif     optional: heights of the ground (:mod:`orthonav.mapdb.terrain`), named
                      with its checksum by the manifest's ``terrain`` record; without it the
                      ground is flat

Feature chunks are uncompressed ``.npy`` files opened memory-mapped, on first use, and
checked against their checksum then: opening a package reads only the manifest and the tile
table, and the features of a 1000 km² map never have to fit in memory. The chunk files are
the ones the build writes (locally or on Dask workers), so the build never gathers them.

Packages are written by :mod:`orthonav.mapdb.build` and opened read-only here.
"""

from __future__ import annotations

import functools
import json
import threading
import zipfile
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS

from orthonav.atomic import atomic_path, sha256_file
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, Runtime, create_backend
from orthonav.frames import north_up
from orthonav.geo import GeoGrid, distance_m
from orthonav.mapdb.globalindex import GLOBAL, FrameView, GlobalIndex
from orthonav.mapdb.terrain import Terrain
from orthonav.mapdb.tiling import TilingConfig
from orthonav.types import Prior

FORMAT = "orthonav-map"
FORMAT_VERSION = 2
MANIFEST = "manifest.json"
TILES = "tiles.npz"
FEATURE_DIR = "features"
PREVIEW = "preview.jpg"
OPEN_CHUNKS = 256  # memory maps kept open; a chunk is re-mapped (not re-checked) after eviction


def keypoint_dtype(descriptor_dtype: np.dtype | str, descriptor_size: int) -> np.dtype:
    """One keypoint record of a feature chunk; ``tile`` makes every chunk self-describing."""
    return np.dtype(
        [
            ("tile", "<u4"),
            ("tile_px", "<f4", (2,)),
            ("map_px", "<f4", (2,)),
            ("crs", "<f8", (2,)),
            ("score", "<f4"),
            ("descriptor", np.dtype(descriptor_dtype), (descriptor_size,)),
        ]
    )


def chunk_file(directory: Path, first_tile: int) -> Path:
    return directory / f"chunk_{first_tile:07d}.npy"


def write_chunk(file: Path, records: np.ndarray) -> None:
    """One feature chunk, atomically: a resumed build trusts every chunk file it finds."""
    with atomic_path(file) as tmp, open(tmp, "wb") as fh:
        np.save(fh, records, allow_pickle=False)


def index_chunks(directory: Path, n_tiles: int, chunk_tiles: int) -> dict[str, np.ndarray]:
    """Per-tile offsets and per-chunk checksums of a finished set of chunks, for ``tiles.npz``;
    reads one chunk at a time, so memory does not grow with the map."""
    counts = np.zeros(n_tiles, np.int64)
    checksums = []
    for first in range(0, n_tiles, chunk_tiles):
        file = chunk_file(directory, first)
        if not file.exists():
            raise OrthonavError(f"{file}: missing; the feature chunks do not cover all {n_tiles} tiles")
        tiles = np.load(file, mmap_mode="r", allow_pickle=False)["tile"].astype(np.int64)
        last = min(first + chunk_tiles, n_tiles)
        if len(tiles) and (tiles.min() < first or tiles.max() >= last or np.any(np.diff(tiles) < 0)):
            raise OrthonavError(f"{file}: keypoints of tiles outside {first}-{last - 1}, or out of order")
        counts[first:last] = np.bincount(tiles - first, minlength=last - first)
        checksums.append(sha256_file(file))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return {"feature_offsets": offsets, "chunk_sha256": np.array(checksums, dtype="S64")}


def file_problem(file: Path, sha256: str | None) -> str | None:
    """What is wrong with a file of the package against the checksum the build recorded, or None."""
    if not file.is_file():
        return "missing"
    if sha256_file(file) != sha256:
        return "checksum mismatch"
    return None


class _FeatureChunks:
    """The package's feature chunks, memory-mapped on first use and checked then."""

    def __init__(self, path: Path, offsets: np.ndarray, checksums: np.ndarray, chunk_tiles: int) -> None:
        self.directory = path / FEATURE_DIR
        self.offsets = offsets
        self.checksums = checksums
        self.chunk_tiles = chunk_tiles
        self._open: OrderedDict[int, np.ndarray] = OrderedDict()
        self._checked: set[int] = set()
        self._lock = threading.Lock()

    def records(self, tile: int) -> np.ndarray:
        """The keypoint records of one tile (a read-only view into its chunk's memory map)."""
        chunk = tile // self.chunk_tiles
        base = self.offsets[chunk * self.chunk_tiles]
        return self._chunk(chunk)[self.offsets[tile] - base : self.offsets[tile + 1] - base]

    def _chunk(self, chunk: int) -> np.ndarray:
        with self._lock:  # the companion's worker thread and its main loop share one package
            if chunk not in self._open:
                self._open[chunk] = self._map(chunk)
                if len(self._open) > OPEN_CHUNKS:
                    self._open.popitem(last=False)
            self._open.move_to_end(chunk)
            return self._open[chunk]

    def file(self, chunk: int) -> Path:
        return chunk_file(self.directory, chunk * self.chunk_tiles)

    def tiles(self, chunk: int) -> range:
        """The tiles whose keypoints one chunk holds."""
        first = chunk * self.chunk_tiles
        return range(first, min(first + self.chunk_tiles, len(self.offsets) - 1))

    def damaged(self) -> list[tuple[int, str]]:
        """(chunk, problem) for every chunk missing or not as built; the others count as checked,
        so that reading them later hashes nothing again."""
        found = []
        for chunk in range(len(self.checksums)):
            problem = file_problem(self.file(chunk), self.checksums[chunk].decode())
            if problem:
                found.append((chunk, problem))
            else:
                with self._lock:
                    self._checked.add(chunk)
        return found

    def _map(self, chunk: int) -> np.ndarray:
        first = chunk * self.chunk_tiles
        file = chunk_file(self.directory, first)
        if chunk not in self._checked:
            problem = file_problem(file, self.checksums[chunk].decode())
            if problem:
                raise OrthonavError(f"{file}: {problem}; the map package is damaged, rebuild it")
            self._checked.add(chunk)
        try:
            records = np.load(file, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise OrthonavError(f"{file}: unreadable feature chunk ({exc}); rebuild the map") from None
        end = self.offsets[min(first + self.chunk_tiles, len(self.offsets) - 1)]
        if records.dtype.names is None or len(records) != end - self.offsets[first]:
            raise OrthonavError(f"{file}: does not match the tile table; the map package is damaged")
        return records


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
            # Maps from before the frame-size budget were tiled at the camera's own resolution.
            self.tiling = TilingConfig(**{"max_frame_px": 0, **m["tiling"]})
            self.backend_name: str = m["features"]["backend"]
            self.backend_conf: dict = dict(m["features"]["config"])
            self.tile_px = int(m["tiling_layout"]["tile_px"])
            chunk_tiles = int(m["features"]["chunk_tiles"])
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, OrthonavError):
                raise
            raise OrthonavError(f"{self.path / MANIFEST}: damaged manifest ({exc!r})") from None
        self.tiles, offsets, checksums = _read_tile_table(self.path, m, chunk_tiles)
        self._features = _FeatureChunks(self.path, offsets, checksums, chunk_tiles)

    def __len__(self) -> int:
        return len(self.tiles)

    def verify(self) -> list[str]:
        """Every file the build recorded a checksum for, checked against it (the manifest and the
        tile table were at opening): one line per damaged file, naming it, what is wrong, and for a
        feature chunk the tiles and the area it holds; empty when the package is intact. Hashes
        every byte: seconds for a large map, once, as chunks found intact are not hashed again."""
        damaged = [
            f"{self._features.file(chunk)} {problem} ({self._area(self._features.tiles(chunk))})"
            for chunk, problem in self._features.damaged()
        ]
        recorded = []
        if (index := self.manifest.get("global_index")) is not None:
            recorded.append((self.path / GLOBAL, index.get("sha256")))
        if self.terrain is not None:
            recorded.append((self.terrain.file, self.terrain.record.get("sha256")))
        damaged += [f"{file} {problem}" for file, sha in recorded if (problem := file_problem(file, sha))]
        return damaged

    def require_intact(self) -> None:
        """Raise, in one line naming what is damaged and where, unless :meth:`verify` finds nothing:
        a damaged chunk found in flight would leave the vehicle lost over its area."""
        damaged = self.verify()
        if damaged:
            shown = "; ".join(damaged[:3]) + (f"; and {len(damaged) - 3} more" if len(damaged) > 3 else "")
            raise OrthonavError(
                f"{self.path}: map package damaged, {len(damaged)} file(s): {shown}; "
                "copy it again or rebuild it (orthonav map build)"
            )

    def _area(self, tiles: range) -> str:
        """Tiles and the WGS84 box they cover, in words."""
        corners = self.tiles.corners_latlon[tiles.start : tiles.stop]
        lat, lon = corners[..., 0], corners[..., 1]
        return (
            f"tiles {tiles.start}-{tiles.stop - 1}, lat {lat.min():.5f}..{lat.max():.5f}, "
            f"lon {lon.min():.5f}..{lon.max():.5f}"
        )

    def within_reach(self, lat: float, lon: float, sigma_m: float) -> bool:
        """Whether a position known to ``sigma_m`` (1-sigma) may lie on the map: within 3 sigma of it."""
        return self.grid.contains_latlon(lat, lon, margin_px=3.0 * sigma_m / self.gsd_m)

    def extent(self) -> str:
        """The map's area in words: its south-west and north-east corners and its size; what an
        error about a position off the map shows, so that the user sees where the map is."""
        (south, west), (north, east) = self.grid.bounds_latlon()
        return f"south-west {south:.6f}, {west:.6f}, north-east {north:.6f}, {east:.6f}, {self._size()}"

    def away(self, lats: Sequence[float], lons: Sequence[float]) -> str:
        """Where positions that miss the map are, in words: their median, its distance from the
        map's centre, and the map's extent."""
        lat, lon = self.grid.center_latlon
        mid_lat, mid_lon = float(np.median(lats)), float(np.median(lons))
        away_km = float(distance_m(lat, lon, mid_lat, mid_lon)) / 1000.0
        return (
            f"around {mid_lat:.5f}, {mid_lon:.5f}, {away_km:.1f} km from the map's centre {lat:.5f}, "
            f"{lon:.5f} (the map: {self.extent()})"
        )

    def _size(self) -> str:
        gx, gy = self.grid.gsd_xy_m
        return f"{self.grid.width * gx:.0f} x {self.grid.height * gy:.0f} m"

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

    def frame_view(
        self, camera: Camera, frame: np.ndarray, prior: Prior, backend: FeatureBackend | None = None
    ) -> FrameView:
        """``frame`` as this map's tiles are matched and indexed: at the map's ground resolution
        (from its nominal altitude where the prior has none), north-up for the prior's heading (0
        if unknown), with ``backend``'s features (none without one: the cnn global index describes
        the image alone)."""
        alt_agl_m = prior.alt_agl_m or self.tiling.nominal_alt_m
        view = north_up(frame, camera, self.gsd_m, alt_agl_m, prior.heading_deg or 0.0)
        if backend is not None:
            return FrameView(view.gray, view.mask, backend.extract(view.gray, view.mask))
        h, w = view.gray.shape
        none = FeatureSet(
            np.zeros((0, 2), np.float32), np.zeros((0, 0), np.uint8), np.zeros(0, np.float32), (w, h)
        )
        return FrameView(view.gray, view.mask, none)

    @functools.cached_property
    def global_index(self) -> GlobalIndex | None:
        """The re-localization index, if one was built (``orthonav map index``); checked on load."""
        record = self.manifest.get("global_index")
        if record is None:
            return None
        file = self.path / GLOBAL
        if file_problem(file, record.get("sha256")):
            raise OrthonavError(f"{file}: missing or damaged; rebuild it with `orthonav map index`")
        index = GlobalIndex.read(file)
        if len(index.tile_vectors) != len(self):
            raise OrthonavError(f"{file}: {len(index.tile_vectors)} tiles, the package has {len(self)}")
        return index

    @functools.cached_property
    def terrain(self) -> Terrain | None:
        """Heights of the ground (``orthonav map terrain``), or None: flat ground. The file is
        checked and read on the first height asked for."""
        record = self.manifest.get("terrain")
        if record is None:
            return None
        return Terrain(self.path, self.grid, record)

    @property
    def source_path(self) -> Path:
        """The orthophoto the map was built from; a relative path (a corridor package's own
        crop) lies inside the package."""
        source = Path(self.manifest["source"]["path"])
        return source if source.is_absolute() else self.path / source

    @property
    def feature_offsets(self) -> np.ndarray:
        """(T+1,) start of each tile's keypoints in the concatenation of the feature chunks."""
        return self._features.offsets

    @property
    def chunk_tiles(self) -> int:
        """Tiles per feature chunk (the last chunk may hold fewer)."""
        return self._features.chunk_tiles

    def tile_records(self, index: int) -> np.ndarray:
        """All stored fields of one tile's keypoints (:func:`keypoint_dtype`), read-only."""
        return self._features.records(index)

    def tile_features(self, index: int) -> FeatureSet:
        """Features of one tile, keypoints in tile pixels."""
        r = self._features.records(index)
        return FeatureSet(
            np.ascontiguousarray(r["tile_px"]),
            np.ascontiguousarray(r["descriptor"]),
            np.ascontiguousarray(r["score"]),
            (self.tile_px, self.tile_px),
        )

    def tile_keypoints_map_px(self, index: int) -> np.ndarray:
        """(N, 2) keypoints of one tile in work-grid pixels."""
        return np.ascontiguousarray(self._features.records(index)["map_px"])

    @property
    def keypoint_count(self) -> int:
        return int(self._features.offsets[-1])

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
        (south, west), (north, east) = self.grid.bounds_latlon()
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
            "south_west_latlon": f"{south:.6f}, {west:.6f}",
            "north_east_latlon": f"{north:.6f}, {east:.6f}",
            "size_m": self._size(),
            "camera": f"{self.camera.width}x{self.camera.height}, hfov {self.camera.hfov_deg:.1f} deg",
            "nominal_alt_m": self.tiling.nominal_alt_m,
            "frame_budget_px": self.tiling.max_frame_px or "none (the camera's own resolution)",
            "tiles": f"{len(self)} ({m['tiling_layout']['rows']} x {m['tiling_layout']['cols']}, "
            f"{m['tiling_layout']['tile_px']} px, stride {m['tiling_layout']['stride_px']} px, "
            f"{int(self.tiles.padded.sum())} padded)",
            "features": f"{self.backend_name} {self.backend_conf}",
            "keypoints": self.keypoint_count,
            "feature_chunks": f"{len(self._features.checksums)} of {self.chunk_tiles} tiles, "
            f"{sum(f.stat().st_size for f in (self.path / FEATURE_DIR).glob('chunk_*.npy')) / 1e6:.1f} MB",
            "terrain": "none (flat ground)" if self.terrain is None else self.terrain.describe(),
            "created": m.get("created", "?"),
        }


def check_replaceable(out_dir: Path) -> None:
    """An existing ``out_dir`` that ``--overwrite`` may replace: a folder. A file or a device
    given as the output by mistake is refused before any work, never moved aside and removed
    (as root, /dev/full itself)."""
    if not out_dir.is_dir():
        raise OrthonavError(f"{out_dir}: not a folder; a map package is one (give another output)")


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


def _read_tile_table(
    path: Path, manifest: dict, chunk_tiles: int
) -> tuple[TileTable, np.ndarray, np.ndarray]:
    """The tile table with the feature offsets and chunk checksums, checked against the manifest."""
    file = path / TILES
    if not file.exists():
        raise OrthonavError(f"{file}: missing; the map package is incomplete")
    if manifest.get("arrays", {}).get(TILES) != sha256_file(file):
        raise OrthonavError(f"{file}: checksum mismatch; the map package is damaged, rebuild it")
    try:
        with np.load(file, allow_pickle=False) as data:
            t = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise OrthonavError(f"{file}: unreadable arrays ({exc}); rebuild the map") from None
    try:
        tiles = TileTable(t["box_px"], t["grid_rc"], t["padded"], t["corners_latlon"])
        offsets, checksums = t["feature_offsets"], t["chunk_sha256"]
    except KeyError as exc:
        raise OrthonavError(f"{path}: array {exc.args[0]!r} missing; the map package is damaged") from None
    n_chunks = -(-len(tiles) // chunk_tiles)
    if len(offsets) != len(tiles) + 1 or len(checksums) != n_chunks or np.any(np.diff(offsets) < 0):
        raise OrthonavError(f"{path}: tile and feature tables disagree in size; the package is damaged")
    return tiles, offsets, checksums

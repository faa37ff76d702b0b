"""Map packages: tile layout, build, on-disk round trip, resumable atomic builds, damage detection."""

from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from helpers_geotiff import shared_file
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pyproj import CRS, Geod, Transformer

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import create_backend
from orthonav.mapdb import FORMAT_VERSION, MapPackage, TilingConfig, build_map, layout_tiles, work_gsd_m
from orthonav.mapdb import build as build_module
from orthonav.sim.terrain import TerrainConfig, write_terrain_geotiff

GEOD = Geod(ellps="WGS84")
# A small camera so a 512 px synthetic map at 1 m gives several tiles at a coarser work GSD.
SMALL_CAM = Camera.from_hfov(160, 120, 60.0)
SMALL_TILING = TilingConfig(nominal_alt_m=200.0, scale_coef=1.0, overlap=0.5)
BORDER_PX = 10


def cam_gsd(camera_width: int, hfov_deg: float, alt: float) -> float:
    """Nadir ground size of one camera pixel, from the closed form f = (W/2) / tan(hfov/2)."""
    return alt / ((camera_width / 2) / math.tan(math.radians(hfov_deg) / 2))


def source_gsd(path: Path) -> float:
    """True ground size of a source pixel at the raster centre (mean of x and y), via pyproj."""
    with rasterio.open(path) as ds:
        t, crs, w, h = ds.transform, CRS.from_user_input(ds.crs), ds.width, ds.height
    lon, lat = Transformer.from_crs(crs, 4326, always_xy=True).transform(
        *(t @ (np.array([w / 2, w / 2 + 1, w / 2]), np.array([h / 2, h / 2, h / 2 + 1])))
    )
    gx = GEOD.inv(lon[0], lat[0], lon[1], lat[1])[2]
    gy = GEOD.inv(lon[0], lat[0], lon[2], lat[2])[2]
    return (gx + gy) / 2


@pytest.fixture(scope="module")
def small_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 512 x 512 px, 1 m/px synthetic RGB orthophoto in UTM."""
    return write_terrain_geotiff(
        tmp_path_factory.mktemp("terrain") / "terrain.tif", TerrainConfig(size_px=512, gsd_m=1.0)
    )


@pytest.fixture(scope="module")
def package(small_tif: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    """The synthetic map built once with the small camera (16 tiles, work GSD ~1.44 m)."""
    out = tmp_path_factory.mktemp("maps") / "terrain.map"
    return build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False)


# --- tile layout -------------------------------------------------------------------------------


def check_layout(width: int, height: int, gsd: float, camera: Camera, config: TilingConfig) -> None:
    layout = layout_tiles(width, height, gsd, camera, config)
    boxes = layout.boxes
    tile = layout.tile_px
    assert len(layout) == layout.rows * layout.cols == len(boxes) == len(layout.padded)
    assert np.all(boxes[:, 2] - boxes[:, 0] == tile) and np.all(boxes[:, 3] - boxes[:, 1] == tile)
    # Every pixel of the work grid is covered.
    covered = np.zeros((height, width), bool)
    for c0, r0, c1, r1 in boxes:
        covered[r0:r1, c0:c1] = True
    assert covered.all()
    # Every tile starts on the grid, and the last tile is needed (the one before does not reach the edge).
    assert np.all(boxes[:, 0] < width) and np.all(boxes[:, 1] < height)
    if layout.cols > 1:
        assert boxes[:, 2].max() - layout.stride_px < width
    if layout.rows > 1:
        assert boxes[:, 3].max() - layout.stride_px < height
    # Row-major order with the configured stride.
    grid = boxes.reshape(layout.rows, layout.cols, 4)
    assert np.all(np.diff(grid[:, :, 0], axis=1) == layout.stride_px)
    assert np.all(np.diff(grid[:, :, 1], axis=0) == layout.stride_px)
    assert np.all(grid[0, 0, :2] == 0)
    expected_stride = max(8, round(tile * (1 - config.overlap)))
    assert layout.stride_px == expected_stride
    # Padded exactly when part of the tile lies beyond the grid.
    inside = np.array([covered[r0:r1, c0:c1].size for c0, r0, c1, r1 in boxes])
    np.testing.assert_array_equal(layout.padded, inside < tile * tile)


@pytest.mark.parametrize(
    ("width", "height", "gsd", "alt", "scale", "overlap"),
    [
        (355, 355, 1.44, 200.0, 1.0, 0.5),
        (934, 723, 5.0, 300.0, 1.5, 0.5),
        (1000, 40, 0.25, 100.0, 1.2, 0.0),
        (100, 100, 1.0, 50.0, 1.5, 0.5),  # smaller than one tile
        (1200, 900, 2.0, 400.0, 2.0, 0.9),
    ],
)
def test_layout_covers_grid(
    width: int, height: int, gsd: float, alt: float, scale: float, overlap: float
) -> None:
    """Tiles cover every work pixel, with the configured stride, padded flags exactly at the edges."""
    check_layout(width, height, gsd, Camera.from_hfov(640, 480, 60.0), TilingConfig(alt, scale, overlap))


@settings(max_examples=40, deadline=None)
@given(
    width=st.integers(1, 1200),
    height=st.integers(1, 1200),
    gsd=st.floats(0.2, 10.0),
    alt=st.floats(20.0, 2000.0),
    scale=st.floats(1.0, 3.0),
    overlap=st.floats(0.0, 0.9),
)
def test_layout_covers_grid_property(
    width: int, height: int, gsd: float, alt: float, scale: float, overlap: float
) -> None:
    """The layout properties hold for arbitrary grids and settings."""
    camera = Camera.from_hfov(640, 480, 60.0)
    config = TilingConfig(alt, scale, overlap)
    assume(len(layout_tiles(width, height, gsd, camera, config)) <= 600)
    check_layout(width, height, gsd, camera, config)


@pytest.mark.parametrize(("hfov", "alt", "scale", "gsd"), [(60.0, 300.0, 1.5, 0.5), (84.0, 120.0, 1.0, 0.2)])
def test_tile_size_is_footprint_times_scale(hfov: float, alt: float, scale: float, gsd: float) -> None:
    """A tile spans max(2 h tan(hfov/2), 2 h tan(vfov/2)) x scale_coef metres, to half a pixel."""
    camera = Camera.from_hfov(640, 480, hfov)
    half_h = math.radians(hfov) / 2
    half_v = math.atan(math.tan(half_h) * 480 / 640)
    footprint = max(2 * alt * math.tan(half_h), 2 * alt * math.tan(half_v))
    layout = layout_tiles(5000, 5000, gsd, camera, TilingConfig(alt, scale, 0.5))
    assert abs(layout.tile_px * gsd - footprint * scale) <= gsd / 2 + 1e-9


def test_a_fine_map_is_tiled_at_the_frame_size_budget() -> None:
    """A 1600 px camera at 65 m (5.7 cm a pixel) over a 5 cm orthophoto is matched at 800 px:
    the work grid is twice the camera's pixel; a VGA camera and a coarser source are untouched."""
    photo = Camera(1600, 1200, 1147.4, 1147.4, 800.0, 600.0)
    camera_gsd = photo.nadir_gsd_m(65.0)
    at_800 = TilingConfig(65.0, max_frame_px=800)
    assert work_gsd_m(0.05, photo, at_800) == pytest.approx(2.0 * camera_gsd)
    assert work_gsd_m(0.05, photo, TilingConfig(65.0, max_frame_px=0)) == pytest.approx(camera_gsd)
    assert work_gsd_m(0.5, photo, at_800) == 0.5
    vga = Camera.from_hfov(640, 480, 60.0)
    assert work_gsd_m(0.05, vga, at_800) == pytest.approx(vga.nadir_gsd_m(65.0))


def test_the_frame_budget_is_the_backends_unless_the_map_sets_one() -> None:
    """Unset, the budget is the backend's (ORB 800; ALIKED and DISK 512, where installed); a set
    one, 0 included, stays; an unresolved config cannot lay out a map."""
    from orthonav.features import available_backends, backend_class

    assert TilingConfig().max_frame_px is None
    assert TilingConfig().for_backend(backend_class("orb").frame_budget_px).max_frame_px == 800
    assert TilingConfig(max_frame_px=0).for_backend(512).max_frame_px == 0
    assert TilingConfig(max_frame_px=640).for_backend(512).max_frame_px == 640
    for name in {"aliked", "disk"} & set(available_backends()):
        assert backend_class(name).frame_budget_px == 512
    with pytest.raises(OrthonavError, match="frame size budget is unset"):
        work_gsd_m(0.05, Camera.from_hfov(640, 480, 60.0), TilingConfig(65.0))


@pytest.mark.parametrize(
    "bad",
    [
        {"nominal_alt_m": 0.0},
        {"scale_coef": 0.5},
        {"overlap": 0.95},
        {"overlap": math.nan},
        {"max_frame_px": 32},
    ],
)
def test_tiling_config_validation(bad: dict) -> None:
    """Impossible tiling settings are OrthonavErrors."""
    with pytest.raises(OrthonavError):
        TilingConfig(**bad)


# --- build and round trip ----------------------------------------------------------------------


def test_a_map_from_before_the_frame_budget_reads_as_unlimited(package: MapPackage, tmp_path: Path) -> None:
    """Its tiling record has no max_frame_px: it was tiled at the camera's own resolution."""
    old = tmp_path / "old.map"
    shutil.copytree(package.path, old)
    manifest = json.loads((old / "manifest.json").read_text())
    assert manifest["tiling"].pop("max_frame_px") == 800
    (old / "manifest.json").write_text(json.dumps(manifest))
    assert MapPackage(old).tiling.max_frame_px == 0


def test_manifest_fields(package: MapPackage, small_tif: Path) -> None:
    """Format version, source path and sha256 (hashlib), CRS and work grid are recorded correctly."""
    m = json.loads((package.path / "manifest.json").read_text())
    assert m["format"] == "orthonav-map"
    assert m["format_version"] == FORMAT_VERSION == 2
    assert m["features"]["chunk_tiles"] == build_module.CHUNK_TILES
    assert m["source"]["sha256"] == hashlib.sha256(small_tif.read_bytes()).hexdigest()
    assert Path(m["source"]["path"]) == small_tif.resolve()
    with rasterio.open(small_tif) as ds:
        src_crs, src_t, src_w = CRS.from_user_input(ds.crs), ds.transform, ds.width
    assert CRS.from_wkt(m["work"]["crs_wkt"]) == src_crs
    assert package.grid.crs == src_crs
    # Work GSD: the camera's at the nominal altitude (coarser than the 1 m source here).
    work_gsd = cam_gsd(160, 60.0, 200.0)
    assert package.gsd_m == pytest.approx(work_gsd, rel=1e-9)
    factor = work_gsd / source_gsd(small_tif)
    t = package.grid.transform
    assert (t.c, t.f) == pytest.approx((src_t.c, src_t.f))
    assert (t.a, t.e) == pytest.approx((src_t.a * factor, src_t.e * factor), rel=1e-9)
    assert package.grid.width == round(src_w / factor)
    assert package.camera == SMALL_CAM
    assert package.tiling == SMALL_TILING.for_backend(800)  # ORB's frame budget, recorded
    assert package.backend_name == "orb"
    assert package.create_backend().conf == create_backend("orb").conf
    layout = layout_tiles(package.grid.width, package.grid.height, package.gsd_m, SMALL_CAM, package.tiling)
    assert len(package) == len(layout) == m["tiling_layout"]["count"] == 16
    np.testing.assert_array_equal(package.tiles.box_px, layout.boxes)
    np.testing.assert_array_equal(package.tiles.padded, layout.padded)


def test_keypoint_arrays_are_consistent(package: MapPackage) -> None:
    """map px = tile px + 0.5 + box origin; CRS x/y = work transform of map px; counts add up."""
    total = 0
    transform = package.grid.transform
    for i in range(len(package)):
        tile = package.tile_features(i)
        map_px = package.tile_keypoints_map_px(i)
        assert len(tile) > 50, f"tile {i} of a textured map has no features"
        assert tile.descriptors.shape == (len(tile), 32) and tile.descriptors.dtype == np.uint8
        # Tile keypoints are OpenCV pixels (centre of the first pixel at 0); work-grid pixels follow
        # rasterio (centre at 0.5): map px = tile px + 0.5 + box origin.
        np.testing.assert_allclose(map_px, tile.keypoints + 0.5 + package.tiles.box_px[i, :2], atol=1e-3)
        assert np.all(tile.keypoints >= 0) and np.all(
            tile.keypoints < package.manifest["tiling_layout"]["tile_px"]
        )
        total += len(tile)
    assert total == package.keypoint_count
    f = all_records(package.path)
    assert len(f) == total
    np.testing.assert_array_equal(
        f["tile"], np.repeat(np.arange(len(package)), np.diff(package.feature_offsets))
    )
    xs, ys = transform @ (f["map_px"][:, 0].astype(float), f["map_px"][:, 1].astype(float))
    np.testing.assert_allclose(f["crs"][:, 0], xs, atol=1e-3)
    np.testing.assert_allclose(f["crs"][:, 1], ys, atol=1e-3)


def test_features_are_memory_mapped_chunks_loaded_on_first_use(package: MapPackage) -> None:
    """Opening reads no feature chunk; a tile's features come from its chunk's memory map, checked once."""
    reopened = MapPackage(package.path)
    chunks = reopened._features
    assert not chunks._open and not chunks._checked
    last = len(reopened) - 1
    records = reopened.tile_records(last)
    assert isinstance(records.base, np.memmap) or isinstance(records, np.memmap)
    assert not records.flags.writeable
    assert set(chunks._open) == {last // reopened.chunk_tiles}
    np.testing.assert_array_equal(
        reopened.tile_features(last).keypoints, package.tile_features(last).keypoints
    )


def test_corners_latlon_match_pyproj(package: MapPackage) -> None:
    """Tile corners (TL, BR, centre) in WGS84 equal pyproj applied to the work transform."""
    boxes = package.tiles.box_px.astype(float)
    cols = np.stack([boxes[:, 0], boxes[:, 2], (boxes[:, 0] + boxes[:, 2]) / 2], 1)
    rows = np.stack([boxes[:, 1], boxes[:, 3], (boxes[:, 1] + boxes[:, 3]) / 2], 1)
    xs, ys = package.grid.transform @ (cols, rows)
    lon, lat = Transformer.from_crs(package.grid.crs, 4326, always_xy=True).transform(xs, ys)
    corners = package.tiles.corners_latlon
    assert corners.shape == (len(package), 3, 2)
    np.testing.assert_allclose(corners[..., 0], lat, atol=1e-9)
    np.testing.assert_allclose(corners[..., 1], lon, atol=1e-9)
    g_lat, g_lon = package.grid.pixel_to_latlon(cols, rows)
    np.testing.assert_allclose(corners[..., 0], g_lat, atol=1e-9)
    np.testing.assert_allclose(corners[..., 1], g_lon, atol=1e-9)


def test_no_keypoints_near_padding(package: MapPackage) -> None:
    """Padding beyond the map edge is a strong edge: no keypoint lies within 10 px of it."""
    w, h = package.grid.width, package.grid.height
    padded = np.flatnonzero(package.tiles.padded)
    assert len(padded) > 0
    for i in padded:
        kp = package.tile_keypoints_map_px(i)
        assert len(kp) > 0
        assert np.all(w - kp[:, 0] >= BORDER_PX) and np.all(h - kp[:, 1] >= BORDER_PX)


def test_padding_guard_is_what_keeps_edges_clean(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Control for the test above: without the border guard, keypoints do appear at the padding edge."""
    monkeypatch.setattr(build_module, "BORDER_PX", 0)
    pkg = build_map(small_tif, tmp_path / "noguard.map", SMALL_CAM, SMALL_TILING, progress=False)
    w, h = pkg.grid.width, pkg.grid.height
    kp = np.concatenate([pkg.tile_keypoints_map_px(i) for i in np.flatnonzero(pkg.tiles.padded)])
    near = (w - kp[:, 0] < BORDER_PX) | (h - kp[:, 1] < BORDER_PX)
    assert near.sum() > 5


def test_tiles_within(package: MapPackage) -> None:
    """Tiles within r of a point are found, tiles clearly farther are not (distances via pyproj)."""
    box = package.tiles.box_px[5].astype(float)
    col = box[0] + 0.3 * (box[2] - box[0])
    row = box[1] + 0.6 * (box[3] - box[1])
    x, y = package.grid.transform @ (col, row)
    lon, lat = Transformer.from_crs(package.grid.crs, 4326, always_xy=True).transform(x, y)
    boxes = package.tiles.box_px
    # Radius well below a pixel: exactly the tiles whose box contains the point.
    containing = np.flatnonzero(
        (boxes[:, 0] <= col) & (col <= boxes[:, 2]) & (boxes[:, 1] <= row) & (row <= boxes[:, 3])
    )
    np.testing.assert_array_equal(package.tiles_within(lat, lon, 0.1), containing)
    assert 5 in containing
    # Radius 150 m: box distance measured on the ground (pixel offsets times the work GSD).
    dx = np.maximum(0, np.maximum(boxes[:, 0] - col, col - boxes[:, 2]))
    dy = np.maximum(0, np.maximum(boxes[:, 1] - row, row - boxes[:, 3]))
    dist_m = np.hypot(dx, dy) * package.gsd_m
    found = set(package.tiles_within(lat, lon, 150.0).tolist())
    assert set(np.flatnonzero(dist_m < 145.0).tolist()) <= found
    assert not found & set(np.flatnonzero(dist_m > 155.0).tolist())
    assert len(found) < len(package)
    # A point 5 km away is near no tile.
    far_lon, far_lat, _ = GEOD.fwd(lon, lat, 45.0, 5000.0)
    assert len(package.tiles_within(far_lat, far_lon, 500.0)) == 0


def test_preview_image_and_grid(package: MapPackage, small_tif: Path) -> None:
    """The preview is the orthophoto, downsampled, on a grid with the map's extent."""
    image, grid = package.preview()
    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    assert (grid.width, grid.height) == (image.shape[1], image.shape[0])
    assert grid.crs == package.grid.crs
    px = abs(grid.transform.a)
    x0, y0 = grid.pixel_to_crs(0, 0)
    x1, y1 = grid.pixel_to_crs(grid.width, grid.height)
    with rasterio.open(small_tif) as ds:
        sx0, sy0 = ds.transform @ (0, 0)
        sx1, sy1 = ds.transform @ (ds.width, ds.height)
        source = np.moveaxis(ds.read([1, 2, 3]), 0, -1)
    assert abs(float(x0) - sx0) < 1e-6 and abs(float(y0) - sy0) < 1e-6
    assert abs(float(x1) - sx1) <= px and abs(float(y1) - sy1) <= px
    small = cv2.resize(source, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_AREA)
    assert np.abs(small.astype(float) - image).mean() < 6.0


def test_summary_reports_the_package(package: MapPackage) -> None:
    """summary() states the tile count, keypoints, CRS and format version of this package."""
    s = package.summary()
    assert s["format_version"] == FORMAT_VERSION
    assert s["keypoints"] == package.keypoint_count > 0
    assert s["tiles"].startswith(f"{len(package)} (")
    assert s["crs"] == package.grid.crs.to_string()
    assert s["frame_budget_px"] == 800  # ORB's, recorded when it was built


def test_build_into_existing_dir_needs_overwrite(
    package: MapPackage, small_tif: Path, tmp_path: Path
) -> None:
    """An existing output is never silently replaced; with overwrite it is, leaving no leftovers."""
    out = tmp_path / "existing.map"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    with pytest.raises(OrthonavError, match="already exists") as exc:
        build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False)
    assert str(out) in str(exc.value)
    assert (out / "keep.txt").exists()
    rebuilt = build_map(small_tif, out, SMALL_CAM, SMALL_TILING, overwrite=True, progress=False)
    assert not (out / "keep.txt").exists()
    assert rebuilt.keypoint_count == package.keypoint_count
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.map"]


def test_overwrite_refuses_a_file_given_as_the_output_before_any_tile(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file (or a device such as /dev/full) is not a package to replace: refused at once, left
    as it was, with nothing beside it."""
    out = tmp_path / "notes.txt"
    out.write_text("user data")
    state = count_extracts(monkeypatch)
    with pytest.raises(OrthonavError, match=r"notes\.txt: not a folder; a map package is one"):
        build_map(small_tif, out, SMALL_CAM, SMALL_TILING, overwrite=True, progress=False)
    assert state["calls"] == 0
    assert out.read_text() == "user data" and sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


# --- atomic, resumable builds ------------------------------------------------------------------

BIG_CAM = Camera.from_hfov(640, 480, 60.0)
MANY_TILES = TilingConfig(nominal_alt_m=50.0)  # 11 x 11 = 121 tiles on the 512 px map: 4 chunks


class Interrupted(Exception):
    """Stands in for a crash or Ctrl-C in the middle of a build."""


def count_extracts(
    monkeypatch: pytest.MonkeyPatch, fail_after: int | None = None, watch: Path | None = None
) -> dict[str, int | bool]:
    """Wrap the ORB backend's extract: count calls, optionally raise after some, record out-dir state."""
    cls = type(create_backend("orb"))
    original = cls.extract
    state = {"calls": 0, "out_seen": False}

    def extract(self, gray, mask=None):
        if watch is not None and watch.exists():
            state["out_seen"] = True
        if fail_after is not None and state["calls"] >= fail_after:
            raise Interrupted
        state["calls"] += 1
        return original(self, gray, mask)

    monkeypatch.setattr(cls, "extract", extract)
    return state


def load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def chunk_files(path: Path) -> list[Path]:
    return sorted((path / "features").glob("chunk_*.npy"))


def all_records(path: Path) -> np.ndarray:
    """Every keypoint record of a package (or build directory), in tile order."""
    return np.concatenate([np.load(f) for f in chunk_files(path)])


@pytest.mark.skipif(sys.platform == "win32", reason="no flock on Windows: builds are not locked there")
def test_a_second_build_of_one_map_is_refused_while_the_first_lives(small_tif: Path, tmp_path: Path) -> None:
    """Two builds of one map would share its work directory; the second is refused at once,
    naming the first's process, and builds once that process is gone, even killed outright
    (its lock file left behind is taken over and removed)."""
    out = tmp_path / "shared.map"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from pathlib import Path\n"
            "from orthonav.mapdb.build import _sole_builder\n"
            "with _sole_builder(Path(sys.argv[1])):\n"
            "    print('held', flush=True)\n"
            "    time.sleep(120)\n",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(OrthonavError, match=rf"another build \(pid {holder.pid}\) is writing it"):
            build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False)
        assert not out.exists() and not out.with_name(out.name + ".partial").exists()
    finally:
        holder.kill()
        holder.wait(timeout=30)
    package = build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False)
    assert len(package.tiles) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "shared.map"
    ]  # the killed one's lock taken and removed


def test_interrupted_build_resumes_and_equals_clean_build(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A crash leaves no package but keeps finished chunks and the tiles of the chunk it was in; a
    rerun extracts only the rest, same result."""
    out = tmp_path / "resume.map"
    partial = tmp_path / "resume.map.partial"
    chunk = build_module.CHUNK_TILES
    state = count_extracts(monkeypatch, fail_after=2 * chunk + 5, watch=out)
    with pytest.raises(Interrupted):
        build_map(small_tif, out, BIG_CAM, MANY_TILES, progress=False)
    assert not state["out_seen"] and not out.exists()
    chunks = [p.name for p in chunk_files(partial)]
    assert chunks == [f"chunk_{0:07d}.npy", f"chunk_{chunk:07d}.npy"]
    for i, file in enumerate(chunk_files(partial)):
        assert set(np.unique(np.load(file)["tile"])) <= set(range(i * chunk, (i + 1) * chunk))
    monkeypatch.undo()

    state = count_extracts(monkeypatch, watch=out)
    resumed = build_map(small_tif, out, BIG_CAM, MANY_TILES, progress=False)
    n_tiles = len(resumed)
    assert n_tiles > 3 * chunk
    assert state["calls"] == n_tiles - 2 * chunk - 5
    assert not state["out_seen"]
    assert out.is_dir() and not partial.exists()
    assert sorted(p.name for p in out.iterdir()) == ["features", "manifest.json", "preview.jpg", "tiles.npz"]
    assert len(chunk_files(out)) == -(-n_tiles // chunk)
    monkeypatch.undo()

    clean = build_map(small_tif, tmp_path / "clean.map", BIG_CAM, MANY_TILES, progress=False)
    a, b = load_npz(out / "tiles.npz"), load_npz(clean.path / "tiles.npz")
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    # Chunk files carry no write times: byte-identical.
    assert [f.read_bytes() for f in chunk_files(out)] == [f.read_bytes() for f in chunk_files(clean.path)]
    # The arrays are equal (above); their zip files carry write times, so skip those checksums.
    ma, mb = dict(resumed.manifest), dict(clean.manifest)
    for key in ("created", "arrays"):
        ma.pop(key), mb.pop(key)
    assert ma == mb


def assert_same_package(a: Path, b: Path) -> None:
    """Same tile table arrays and byte-identical feature chunks (the zip files and the manifest
    carry write times)."""
    ta, tb = load_npz(a / "tiles.npz"), load_npz(b / "tiles.npz")
    assert ta.keys() == tb.keys()
    for key in ta:
        np.testing.assert_array_equal(ta[key], tb[key], err_msg=key)
    assert [f.read_bytes() for f in chunk_files(a)] == [f.read_bytes() for f in chunk_files(b)]


@pytest.mark.parametrize("built_first", [1, 7])
def test_build_smaller_than_a_chunk_resumes_at_the_tile_it_reached(
    small_tif: Path, package: MapPackage, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, built_first: int
) -> None:
    """Progress is saved per tile: a map of fewer tiles than a chunk, interrupted after k tiles,
    resumes at tile k, says so, counts only what it built, and gives the uninterrupted package."""
    n_tiles = len(package)
    assert n_tiles < build_module.CHUNK_TILES
    out = tmp_path / "small.map"
    count_extracts(monkeypatch, fail_after=built_first)
    with pytest.raises(Interrupted):
        build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False)
    monkeypatch.undo()

    state = count_extracts(monkeypatch)
    said: list[str] = []
    report = build_module.BuildReport(say=said.append)
    resumed = build_map(small_tif, out, SMALL_CAM, SMALL_TILING, progress=False, report=report)
    assert said == [f"resuming: {built_first} of {n_tiles} tiles already built (in {out}.partial)"]
    assert (report.reused, report.built) == (built_first, n_tiles - built_first)
    assert state["calls"] == n_tiles - built_first
    assert sorted(p.name for p in out.iterdir()) == ["features", "manifest.json", "preview.jpg", "tiles.npz"]
    assert_same_package(resumed.path, package.path)


def test_damaged_saved_parts_are_built_again_and_said(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A chunk and a tile saved by the interrupted build, each with one byte changed, are found
    at the start of the rerun (not after every other tile), named in one line and built again:
    the package is the same as a clean build's."""
    out = tmp_path / "damaged.map"
    partial = tmp_path / "damaged.map.partial"
    chunk = build_module.CHUNK_TILES
    count_extracts(monkeypatch, fail_after=chunk + 4)
    with pytest.raises(Interrupted):
        build_map(small_tif, out, BIG_CAM, MANY_TILES, progress=False)
    monkeypatch.undo()
    flip_one_bit(partial / "features" / f"chunk_{0:07d}.npy")
    flip_one_bit(partial / "progress" / f"tile_{chunk + 2:07d}.npy")

    state = count_extracts(monkeypatch)
    said: list[str] = []
    report = build_module.BuildReport(say=said.append)
    resumed = build_map(small_tif, out, BIG_CAM, MANY_TILES, progress=False, report=report)
    n_tiles = len(resumed)
    assert len(said) == 2, said
    damage, resuming = said
    for fragment in (f"chunk_{0:07d}.npy checksum mismatch", f"tile_{chunk + 2:07d}.npy checksum mismatch"):
        assert fragment in damage
    assert f"building their {chunk + 1} tile(s) again" in damage
    assert resuming.startswith(f"resuming: 3 of {n_tiles} tiles already built")
    assert state["calls"] == report.built == n_tiles - 3
    monkeypatch.undo()
    clean = build_map(small_tif, tmp_path / "clean.map", BIG_CAM, MANY_TILES, progress=False)
    assert_same_package(resumed.path, clean.path)


def write_bad_dsm(like: Path, out: Path, damage: str) -> Path:
    """A DSM over the whole map: only nodata there, or real heights in tiles whose compressed data
    are partly zeroed (a damaged copy)."""
    with rasterio.open(like) as ds:
        profile = {"driver": "GTiff", "width": ds.width, "height": ds.height, "count": 1}
        profile.update(dtype="float32", crs=ds.crs, transform=ds.transform, nodata=-9999.0)
    profile.update(tiled=True, blockxsize=128, blockysize=128, compress="deflate")
    shape = (1, profile["height"], profile["width"])
    heights = np.random.default_rng(0).uniform(100.0, 110.0, shape).astype(np.float32)
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(np.full(shape, -9999.0, np.float32) if damage == "nodata" else heights)
    if damage == "damaged":
        data = bytearray(out.read_bytes())
        data[len(data) // 2 : len(data) // 2 + 5000] = bytes(5000)
        out.write_bytes(bytes(data))
    return out


@pytest.mark.parametrize(
    ("damage", "message"), [("nodata", "has no heights"), ("damaged", "heights unreadable over the map")]
)
def test_a_bad_dsm_fails_before_any_tile(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage: str, message: str
) -> None:
    """A DSM that covers the map but cannot give its heights is refused in one line naming it,
    before a tile is built and before a work directory exists."""
    dsm = write_bad_dsm(small_tif, tmp_path / "bad_dsm.tif", damage)
    state = count_extracts(monkeypatch)
    with pytest.raises(OrthonavError, match=rf"bad_dsm\.tif: {message}"):
        build_map(small_tif, tmp_path / "m.map", SMALL_CAM, SMALL_TILING, progress=False, dsm=dsm)
    assert state["calls"] == 0
    assert not (tmp_path / "m.map.partial").exists()


def test_stale_partial_with_other_settings_is_discarded(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Chunks from an interrupted build with different settings are not reused."""
    out = tmp_path / "stale.map"
    count_extracts(monkeypatch, fail_after=40)
    with pytest.raises(Interrupted):
        build_map(small_tif, out, BIG_CAM, MANY_TILES, progress=False)
    monkeypatch.undo()
    state = count_extracts(monkeypatch)
    other = TilingConfig(nominal_alt_m=50.0, overlap=0.4)
    said: list[str] = []
    report = build_module.BuildReport(say=said.append)
    pkg = build_map(small_tif, out, BIG_CAM, other, progress=False, report=report)
    assert said == [
        f"map build: {out}.partial was started with other settings or another source; starting again"
    ]
    assert state["calls"] == len(pkg) == report.built
    assert pkg.tiling == other.for_backend(800)


# --- damaged packages --------------------------------------------------------------------------


def damaged_copy(package: MapPackage, tmp_path: Path) -> Path:
    copy = tmp_path / "copy.map"
    shutil.copytree(package.path, copy)
    return copy


def rewrite_manifest(path: Path, change) -> None:
    file = path / "manifest.json"
    manifest = json.loads(file.read_text())
    change(manifest)
    file.write_text(json.dumps(manifest))


def tamper_chunk(path: Path) -> None:
    file = chunk_files(path)[-1]
    data = np.load(file)
    data["crs"][0, 0] += 1.0
    np.save(file, data)


def rewrite_tiles(path: Path, change) -> None:
    """Change the tile table and re-seal it in the manifest, as a bad writer would."""
    data = load_npz(path / "tiles.npz")
    change(data)
    np.savez_compressed(path / "tiles.npz", **data)
    digest = hashlib.sha256((path / "tiles.npz").read_bytes()).hexdigest()
    rewrite_manifest(path, lambda m: m["arrays"].__setitem__("tiles.npz", digest))


def read_last_tile(path: Path) -> None:
    """Damage in a chunk shows when its tiles are first read (opening reads no chunk)."""
    package = MapPackage(path)
    package.tile_features(len(package) - 1)


DAMAGE = {
    "tampered_chunk": (tamper_chunk, r"chunk_\d+\.npy: checksum mismatch"),
    "missing_chunk": (lambda p: chunk_files(p)[-1].unlink(), r"chunk_\d+\.npy: missing"),
    "tampered_tiles": (
        lambda p: (p / "tiles.npz").write_bytes(b"x" + (p / "tiles.npz").read_bytes()),
        r"tiles\.npz: checksum mismatch",
    ),
    "missing_manifest": (lambda p: (p / "manifest.json").unlink(), r"no manifest\.json"),
    "invalid_json": (lambda p: (p / "manifest.json").write_text("{not json"), r"not valid JSON"),
    "other_version": (
        lambda p: rewrite_manifest(p, lambda m: m.update(format_version=FORMAT_VERSION + 1)),
        rf"map format version {FORMAT_VERSION + 1}, this orthonav reads version {FORMAT_VERSION}",
    ),
    "not_a_manifest": (
        lambda p: rewrite_manifest(p, lambda m: m.update(format="something-else")),
        r"not an orthonav map manifest",
    ),
    "manifest_missing_work": (lambda p: rewrite_manifest(p, lambda m: m.pop("work")), r"damaged manifest"),
    "missing_array_file": (lambda p: (p / "tiles.npz").unlink(), r"tiles\.npz: missing"),
    "missing_array": (
        lambda p: rewrite_tiles(p, lambda t: t.pop("chunk_sha256")),
        r"array 'chunk_sha256' missing",
    ),
    "offsets_disagree": (
        lambda p: rewrite_tiles(p, lambda t: t.update(feature_offsets=t["feature_offsets"][:-1])),
        r"tile and feature tables disagree",
    ),
    "manifest_missing_chunk_size": (
        lambda p: rewrite_manifest(p, lambda m: m["features"].pop("chunk_tiles")),
        r"damaged manifest",
    ),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_damaged_package_is_refused(package: MapPackage, tmp_path: Path, damage: str) -> None:
    """Each kind of damage is an OrthonavError naming the package and the problem."""
    path = damaged_copy(package, tmp_path)
    read_last_tile(path)  # the undamaged copy opens and reads
    apply, pattern = DAMAGE[damage]
    apply(path)
    with pytest.raises(Exception) as exc:
        read_last_tile(path)
    assert type(exc.value) is OrthonavError, repr(exc.value)
    assert str(path) in str(exc.value)
    assert re.search(pattern, str(exc.value)), str(exc.value)


def flip_one_bit(file: Path) -> None:
    """The damage a bad card or copy does: one bit in the middle of the file."""
    data = bytearray(file.read_bytes())
    data[len(data) // 2] ^= 0x10
    file.write_bytes(bytes(data))


def test_verify_names_each_damaged_chunk_with_its_tiles_and_area(
    small_tif: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(build_module, "CHUNK_TILES", 4)  # the 16 tiles in 4 chunks
    path = build_map(small_tif, tmp_path / "chunked.map", SMALL_CAM, SMALL_TILING, progress=False).path
    assert MapPackage(path).verify() == []
    files = chunk_files(path)
    assert len(files) == 4
    flip_one_bit(files[0])
    files[-1].unlink()
    copy = MapPackage(path)  # opens: chunks are read only when their tiles are asked for
    damaged = copy.verify()
    assert len(damaged) == 2
    last = len(copy) - 1
    assert damaged[0].startswith(f"{files[0]} checksum mismatch (tiles 0-{copy.chunk_tiles - 1}, lat ")
    assert damaged[1].startswith(
        f"{files[-1]} missing (tiles {last // copy.chunk_tiles * copy.chunk_tiles}-{last},"
    )
    # The area named holds the centre of every tile of the chunk.
    lat0, lat1, lon0, lon1 = map(float, re.findall(r"-?\d+\.\d+", damaged[0].split("lat ")[1]))
    centres = copy.tiles.corners_latlon[: copy.chunk_tiles, 2]
    assert np.all((lat0 <= centres[:, 0]) & (centres[:, 0] <= lat1))
    assert np.all((lon0 <= centres[:, 1]) & (centres[:, 1] <= lon1))
    with pytest.raises(OrthonavError, match="map package damaged, 2 file") as err:
        copy.require_intact()
    assert "\n" not in str(err.value) and files[0].name in str(err.value)


def test_not_a_directory_is_refused(tmp_path: Path) -> None:
    """Opening a file or nothing as a map says it is not a map package."""
    with pytest.raises(OrthonavError, match="not a map package directory"):
        MapPackage(tmp_path / "nothing.map")


# --- real data ---------------------------------------------------------------------------------


def test_build_real_naip_map(tmp_path: Path) -> None:
    """The real 5 m NAIP orthophoto builds in < 20 s into tiles that nearly all carry keypoints."""
    path = shared_file("naip/m_4709963_se_14_1_20200831.tif")
    start = time.perf_counter()
    pkg = build_map(path, tmp_path / "naip.map", BIG_CAM, TilingConfig(nominal_alt_m=300.0), progress=False)
    elapsed = time.perf_counter() - start
    assert elapsed < 20.0
    assert pkg.grid.crs.to_epsg() == 26914
    assert pkg.gsd_m == pytest.approx(source_gsd(path), rel=1e-6)  # the camera at 300 m sees 0.54 m/px
    counts = np.diff(pkg.feature_offsets)
    assert len(counts) == len(pkg) > 50
    assert np.mean(counts > 20) > 0.8
    reopened = MapPackage(pkg.path)
    assert reopened.keypoint_count == pkg.keypoint_count

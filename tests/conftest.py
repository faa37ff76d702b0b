"""Shared fixtures: a synthetic terrain map and the real NAIP 2020 map, built once per session.

Helpers for the localizer, simulation and CLI tests live here too: the true ground point
under the image centre (from the camera model, independently of the localizer), random
true poses whose footprint stays on the map, and priors with realistic sensor noise.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import struct
import subprocess
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from orthonav.camera import Camera, CameraPose, footprint_enu, ground_to_image_homography
from orthonav.features import Runtime
from orthonav.frames.render import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame, PixelWindow, destination, distance_m
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage, TilingConfig, attach_terrain, build_map
from orthonav.models.onnx import files as onnx_files
from orthonav.models.onnx import runtime as onnx_runtime
from orthonav.sim.terrain import TerrainConfig, write_terrain_geotiff
from orthonav.types import Fix, Prior

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NAIP_DIR = SHARED_DATA / "naip"
NAIP_YEARS = ("20090818", "20120731", "20150926", "20180716", "20200831")

CAMERA = Camera.from_hfov(640, 480, 60.0)
TERRAIN = TerrainConfig(size_px=1024, gsd_m=1.0)
TERRAIN_ALT_M = 300.0
NAIP_ALT_M = 1000.0
# The attitude (pitch/roll) error of the autopilot's AHRS given to the localizer as a prior.
AHRS_SIGMA_DEG = 0.3


def naip_path(year: str) -> Path:
    """The NAIP quarter-quad of one year, read in place; skip when ../shared/data is absent."""
    path = NAIP_DIR / f"m_4709963_se_14_1_{year}.tif"
    if not path.is_file():
        pytest.skip(f"real NAIP data not available: {path} is missing")
    return path


def zeroed_middle(data: bytes, size: int = 5000) -> bytes:
    """A file's bytes with ``size`` bytes zeroed in the middle (a JPEG's entropy-coded data): the
    damage a bad card or link does, which leaves the start and end markers in place."""
    start = len(data) // 2
    return data[:start] + bytes(size) + data[start + size :]


def damage_video_frame(video: Path, out: Path, frame: int) -> Path:
    """A copy of a Motion JPEG video with a quarter of one frame's JPEG data zeroed in its
    middle: the container and every other frame intact, as a bad card or link leaves them."""
    data = bytearray(video.read_bytes())
    starts = [m.start() for m in re.finditer(b"\xff\xd8\xff", data)] + [len(data)]
    start, end = starts[frame], starts[frame + 1]
    size = (end - start) // 4
    middle = (start + end) // 2
    data[middle : middle + size] = bytes(size)
    out.write_bytes(bytes(data))
    return out


def png_declaring(width: int, height: int) -> bytes:
    """A small grey PNG whose header declares ``width`` x ``height`` pixels."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(bytes(100)))
        + chunk(b"IEND", b"")
    )


# Workers beyond this hold a copy of every session map and model each, for little gain: the
# longest test file alone sets the suite's time once the rest is spread over a few cores.
MAX_WORKERS = 4


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker per physical core (its affinity, a container's quota), at most
    ``MAX_WORKERS``."""
    return min(MAX_WORKERS, onnx_runtime.physical_cores())


def pytest_configure(config: pytest.Config) -> None:
    """A worker of several takes its share of the cores for torch: torch's OpenMP threads spin
    while they wait, so workers each running torch on every core slow each other far more than
    sharing the cores costs."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        with contextlib.suppress(ImportError):
            import torch

            torch.set_num_threads(max(1, onnx_runtime.physical_cores() // workers))


@pytest.fixture(scope="session", autouse=True)
def private_export_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Graphs exported at first use (ALIKED's on a CPU) go to a cache of the test session's own:
    the user's cache is never written by the tests."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("ORTHONAV_CACHE_DIR", str(tmp_path_factory.mktemp("orthonav-cache")))
        yield


@contextlib.contextmanager
def module_export_cache(tmp_path_factory: pytest.TempPathFactory, name: str) -> Iterator[Path]:
    """A cache of exported graphs for one test module's fixtures, the engine left to the auto
    choice; yields its ``onnx`` folder (where the graphs are written)."""
    root = tmp_path_factory.mktemp(name)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("ORTHONAV_CACHE_DIR", str(root))
        patch.delenv("ORTHONAV_RUNTIME", raising=False)
        yield root / "onnx"


@pytest.fixture(scope="session")
def camera() -> Camera:
    return CAMERA


@pytest.fixture(scope="session")
def terrain_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1024 x 1024 px, 1 m/px synthetic orthophoto (UTM)."""
    return write_terrain_geotiff(tmp_path_factory.mktemp("terrain") / "terrain.tif", TERRAIN)


@pytest.fixture(scope="session")
def terrain_map(terrain_tif: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    out = tmp_path_factory.mktemp("terrain_map") / "map"
    return build_map(terrain_tif, out, CAMERA, TilingConfig(nominal_alt_m=TERRAIN_ALT_M), progress=False)


@pytest.fixture(scope="session")
def terrain_raster(terrain_tif: Path) -> Iterator[GeoRaster]:
    with GeoRaster(terrain_tif) as raster:
        yield raster


@pytest.fixture(scope="session")
def naip2020_tif() -> Path:
    return naip_path("20200831")


@pytest.fixture(scope="session")
def naip_map(naip2020_tif: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    out = tmp_path_factory.mktemp("naip_map") / "map"
    return build_map(naip2020_tif, out, CAMERA, TilingConfig(nominal_alt_m=NAIP_ALT_M), progress=False)


@pytest.fixture(scope="session")
def naip_raster(naip2020_tif: Path) -> Iterator[GeoRaster]:
    with GeoRaster(naip2020_tif) as raster:
        yield raster


@pytest.fixture(scope="session")
def seneca_dataset() -> Path:
    """The real Seneca flight (photos, reference poses, orthophoto, DSM), read in place."""
    queries = SHARED_DATA / "real" / "seneca" / "queries.csv"
    if not queries.is_file():
        pytest.skip(f"../shared/data not present: {queries} is missing (real-data test)")
    return queries.parent


@pytest.fixture(scope="session")
def seneca_camera(seneca_dataset: Path) -> Camera:
    return Camera.from_json(seneca_dataset / "camera.json")


@pytest.fixture(scope="session")
def seneca_walkthrough_priors(seneca_dataset: Path) -> dict[str, Prior]:
    """Per photo, the getting-started guide's prior: the EXIF position (15 m sigma) and altitude
    above the field (216 m above sea level); no heading, no roll or pitch."""
    import csv

    with (seneca_dataset / "queries.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {
        row["name"]: Prior(float(row["lat"]), float(row["lon"]), float(row["alt_amsl"]) - 216.0, sigma_m=15.0)
        for row in rows
    }


@pytest.fixture(scope="session")
def seneca_map(
    seneca_dataset: Path, seneca_camera: Camera, tmp_path_factory: pytest.TempPathFactory
) -> MapPackage:
    """Seneca's whole orthophoto at 65 m with ORB, its DSM attached: built once per session."""
    out = tmp_path_factory.mktemp("seneca") / "map"
    package = build_map(
        seneca_dataset / "ortho.tif", out, seneca_camera, TilingConfig(65.0), "orb", {}, progress=False
    )
    return attach_terrain(package, seneca_dataset / "dsm.tif")


@pytest.fixture(scope="module")
def torch_one_thread() -> Iterator[None]:
    """One torch thread for a module of learned-backend tests: on 2 shared cores OpenMP's
    spinning barriers make these small networks several times slower."""
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# --- helpers -----------------------------------------------------------------------------


def naip_gray(year: str, col: int, row: int, width: int, height: int) -> np.ndarray:
    """A (col, row, width, height) window of one NAIP year as a gray uint8 image."""
    with GeoRaster(naip_path(year)) as raster:
        return cv2.cvtColor(raster.read_rgb(PixelWindow(col, row, width, height)), cv2.COLOR_RGB2GRAY)


def write_naip_crop(year: str, window: tuple[int, int, int, int], out: Path) -> Path:
    """A (col, row, width, height) window of one NAIP year as its own GeoTIFF, georeferencing
    kept: a small real map that learned backends build quickly."""
    import rasterio
    from rasterio.windows import Window

    col, row, width, height = window
    with rasterio.open(naip_path(year)) as src:
        win = Window(col, row, width, height)
        profile = src.profile.copy()
        profile.update(width=width, height=height, transform=src.window_transform(win))
        data = src.read(window=win)
        colorinterp = src.colorinterp
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(data)
        dst.colorinterp = colorinterp
    return out


def true_centre_latlon(camera: Camera, pose: TruePose) -> tuple[float, float]:
    """The ground point under the image centre (cx, cy) at ``pose``, from the camera model."""
    cam_pose = CameraPose(0.0, 0.0, pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    h = np.linalg.inv(ground_to_image_homography(camera, cam_pose))
    p = h @ np.array([camera.cx, camera.cy, 1.0])
    lat, lon = LocalFrame(pose.lat, pose.lon).to_latlon(p[0] / p[2], p[1] / p[2])
    return float(lat), float(lon)


def footprint_on_map(raster: GeoRaster, camera: Camera, pose: TruePose, margin_px: float = 4.0) -> bool:
    """Whether every corner of the camera's ground footprint lies on the raster."""
    corners = footprint_enu(
        camera, CameraPose(0.0, 0.0, pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    )
    lat, lon = LocalFrame(pose.lat, pose.lon).to_latlon(corners[:, 0], corners[:, 1])
    col, row = raster.latlon_to_pixel(lat, lon)
    return bool(
        np.all((col >= margin_px) & (col <= raster.width - margin_px))
        and np.all((row >= margin_px) & (row <= raster.height - margin_px))
    )


def random_pose(
    rng: np.random.Generator,
    raster: GeoRaster,
    camera: Camera,
    nominal_alt_m: float,
    max_tilt_deg: float = 5.0,
) -> TruePose:
    """A random true pose (alt +-20 %, any yaw, pitch/roll up to ``max_tilt_deg``) seeing only the map."""
    for _ in range(1000):
        col, row = rng.uniform(0, raster.width), rng.uniform(0, raster.height)
        lat, lon = raster.pixel_to_latlon(col, row)
        pose = TruePose(
            float(lat),
            float(lon),
            nominal_alt_m * float(rng.uniform(0.8, 1.2)),
            float(rng.uniform(0.0, 360.0)),
            float(rng.uniform(-max_tilt_deg, max_tilt_deg)),
            float(rng.uniform(-max_tilt_deg, max_tilt_deg)),
        )
        if footprint_on_map(raster, camera, pose):
            return pose
    raise AssertionError("no pose with its footprint on the map: the map is too small for the camera")


@dataclass(frozen=True)
class NoisyPrior:
    """A prior as the vehicle's sensors would give it, and the attitude error it carries."""

    prior: Prior
    attitude_error_deg: float  # |(pitch, roll) error| of the AHRS prior


def noisy_prior(
    rng: np.random.Generator, pose: TruePose, position: bool = True, heading: bool = True
) -> NoisyPrior:
    """Position within 200 m, heading within 10 deg, altitude within 3 %, pitch/roll + 0.3 deg noise."""
    lat = lon = head = None
    if position:
        lat, lon = destination(pose.lat, pose.lon, rng.uniform(0, 360), 200.0 * math.sqrt(rng.uniform()))
    if heading:
        head = (pose.yaw_deg + rng.uniform(-10.0, 10.0)) % 360.0
    d_pitch, d_roll = rng.normal(0.0, AHRS_SIGMA_DEG, 2)
    prior = Prior(
        lat,
        lon,
        pose.alt_agl_m * float(rng.uniform(0.97, 1.03)),
        head,
        pose.pitch_deg + float(d_pitch),
        pose.roll_deg + float(d_roll),
        sigma_m=200.0,
        heading_sigma_deg=10.0,
        attitude_sigma_deg=AHRS_SIGMA_DEG,
    )
    return NoisyPrior(prior, math.hypot(d_pitch, d_roll))


def rendered_frames(
    rng: np.random.Generator, raster: GeoRaster, count: int
) -> Iterator[tuple[TruePose, np.ndarray, Prior]]:
    """``count`` frames of :data:`CAMERA` rendered over ``raster`` at random poses near
    :data:`NAIP_ALT_M` (tilt up to 3 deg, varied light), each with its noisy prior."""
    for _ in range(count):
        pose = random_pose(rng, raster, CAMERA, NAIP_ALT_M, max_tilt_deg=3.0)
        frame = render_frame(raster, CAMERA, pose, Photometric.random(rng, 0.5), rng)
        yield pose, frame, noisy_prior(rng, pose).prior


def angle_diff_deg(a: float, b: float) -> float:
    """Smallest absolute difference of two angles in degrees."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


def fixed_with_its_heading(fix: Fix, truth: TruePose, wrong_m: float, heading_tol_deg: float = 3.0) -> bool:
    """Whether a fix of a frame localized without a heading was accepted; an accepted one must be
    within ``wrong_m`` of the truth with the heading found to ``heading_tol_deg``, a rejected
    one must say why."""
    if not fix.accepted:
        assert fix.reason, "a rejection says why"
        return False
    assert distance_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon) <= wrong_m
    turn = angle_diff_deg(fix.pose.heading_deg, truth.yaw_deg)
    assert turn <= heading_tol_deg, f"heading found {fix.pose.heading_deg:.1f}, true {truth.yaw_deg:.1f}"
    return True


# (col, row, width, height) of the 2020 NAIP orthophoto that the ONNX engine tests map
ENGINE_MAP_WINDOW = (150, 100, 640, 520)


def torch_built_naip_map(tmp_path_factory: pytest.TempPathFactory, backend: str) -> MapPackage:
    """A map of ENGINE_MAP_WINDOW of NAIP 2020 for ``backend``, its features extracted under
    torch on one thread: the reference that the ONNX engine's frames are localized against."""
    tif = write_naip_crop("20200831", ENGINE_MAP_WINDOW, tmp_path_factory.mktemp("crop") / "naip2020.tif")
    out = tmp_path_factory.mktemp(f"{backend}_map") / "map"
    tiling = TilingConfig(nominal_alt_m=NAIP_ALT_M)
    torch = Runtime(threads=1, engine="torch")
    return build_map(tif, out, CAMERA, tiling, backend=backend, runtime=torch, progress=False)


def engines_agree(
    package: MapPackage, backends: dict, seed: int, frames: int, agreement_m: float = 1.0
) -> list[tuple[TruePose, Fix]]:
    """Frames rendered at known poses over ``package``, localized with the frame's features from
    the ``torch`` and the ``onnx`` backend: the same decisions, inliers within 5 %, fixes within
    ``agreement_m`` of each other; returns the truth and ONNX Runtime's fix of those accepted."""
    localizers = {
        name: Localizer(package, package.camera, backend=backends[name]) for name in ("torch", "onnx")
    }
    accepted = []
    with GeoRaster(package.source_path) as raster:
        for pose, frame, prior in rendered_frames(np.random.default_rng(seed), raster, frames):
            want, got = (localizers[k].localize(frame, prior) for k in ("torch", "onnx"))
            assert got.accepted == want.accepted, (got.reason, want.reason)
            if want.accepted:
                assert got.quality["inliers"] == pytest.approx(want.quality["inliers"], rel=0.05)
                assert distance_m(got.pose.lat, got.pose.lon, want.pose.lat, want.pose.lon) <= agreement_m
                accepted.append((pose, got))
    return accepted


# As where torch is not installed: the path finder does not find torch (or a submodule), so
# find_spec gives None, importing it fails, and it is not in sys.modules at all (a None there,
# the usual way to block an import, trips libraries that probe sys.modules for torch arrays).
NO_TORCH = """import importlib.machinery, json, sys
class _PathsWithoutTorch(importlib.machinery.PathFinder):
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        return None if name.split(".")[0] == "torch" else super().find_spec(name, path, target)
sys.meta_path = [_PathsWithoutTorch if f is importlib.machinery.PathFinder else f for f in sys.meta_path]
"""


def run_without_torch(body: str, cache_root: Path) -> dict:
    """Run ``body`` in a fresh Python where ``import torch`` fails (a companion with ONNX Runtime
    only), with the export cache under ``cache_root`` and the default engine; ``body`` sets a
    dict ``result``, returned with the torch, torchvision and kornia modules it loaded."""
    script = (
        NO_TORCH
        + body
        + '\nloaded = sorted(m for m, v in sys.modules.items() if v and m.split(".")[0] in '
        + '("torch", "torchvision", "kornia"))\nprint(json.dumps({**result, "torch_modules": loaded}))\n'
    )
    env = {**os.environ, onnx_files.CACHE_ENV: str(cache_root)}
    env.pop(onnx_runtime.RUNTIME_ENV, None)
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def older_graph(cached: Path, info: dict, out: Path) -> Path:
    """A copy of the exported graph ``cached`` (metadata ``info``) that says it is of file
    format 0, as a graph exported by an older orthonav says: it must be refused with the command
    that exports it again."""
    import onnx

    proto = onnx.load(str(cached))
    for entry in proto.metadata_props:
        if entry.key == "orthonav.info":
            entry.value = json.dumps({**info, "graph_version": 0})
    onnx.save_model(proto, str(out))
    return out

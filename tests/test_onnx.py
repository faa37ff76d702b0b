"""ONNX export and runtime of the trained correction trunk and the retrieval network, against torch.

The shipped models are exported into a temporary cache ($ORTHONAV_CACHE_DIR: the user's cache is
never touched), int8 calibrated on crops of a NAIP date that neither the maps nor the frames use.
Agreement is measured where it matters: feature maps (fp32 within 1e-4 relative), descriptors,
and the fixes of the corrector on frames rendered at known poses (torch vs ONNX within 0.5 m;
int8 too: its features are ~3 % off, cosine 0.9995, but the fix comes from the full-resolution
refinement started in the same CNN cell, so on the bench's 32 frames int8 and torch fixes were
identical). The ONNX path is also run in a subprocess where importing torch fails.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import CAMERA, naip_path, run_without_torch
from typer.testing import CliRunner

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, make_views, render_frame
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.models import SHIPPED_RETRIEVAL_MODEL, shipped_model_path
from orthonav.types import Fix, Prior

pytest.importorskip("onnxruntime", reason="the ONNX runtime needs onnxruntime (the 'onnx' extra)")
pytest.importorskip("torch", reason="exporting and the comparison need torch (the 'learned' extra)")
pytest.importorskip("onnxscript", reason="exporting needs onnx and onnxscript (the 'learned' extra)")

from orthonav.models.export import calibration_crops, cell_means, export_onnx
from orthonav.models.onnx import files as onnx_files
from orthonav.models.onnx import graphs as onnx_graphs
from orthonav.models.onnx import loading as onnx_loading
from orthonav.models.onnx import preprocess as onnx_preprocess
from orthonav.models.onnx import runtime as onnx_runtime

FIX_AGREEMENT_M = 0.5
INT8_FIX_AGREEMENT_M = 0.5
FEATURE_RTOL = 1e-4
CASES = 6


# --- fixtures ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory, torch_one_thread) -> Iterator[Path]:
    """A private cache with fp32 exports of both shipped models and an int8 correction trunk."""
    root = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(onnx_files.CACHE_ENV, str(root))
        patch.delenv(onnx_runtime.RUNTIME_ENV, raising=False)
        crops = calibration_crops([naip_path("20120731")], 16)
        export_onnx(shipped_model_path())
        export_onnx(shipped_model_path(SHIPPED_RETRIEVAL_MODEL))
        export_onnx(shipped_model_path(), "int8", calibration=crops)
        export_onnx(shipped_model_path(SHIPPED_RETRIEVAL_MODEL), "int8", calibration=crops)
        yield root / "onnx"


@pytest.fixture(scope="module")
def rasters() -> Iterator[tuple[GeoRaster, GeoRaster]]:
    """The 2018 map and the 2020 imagery the frames are rendered from."""
    with GeoRaster(naip_path("20180716")) as map_raster, GeoRaster(naip_path("20200831")) as frames:
        yield map_raster, frames


def _cases(map_raster: GeoRaster, frames: GeoRaster, n: int, seed: int = 3):
    """(true pose, frame of 2020, prior 10-15 m off with heading and altitude errors) x n."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        lat, lon = map_raster.pixel_to_latlon(rng.uniform(200, 734), rng.uniform(190, 533))
        pose = TruePose(
            float(lat), float(lon), rng.uniform(500, 700), rng.uniform(0, 360), *rng.uniform(-3, 3, 2)
        )
        frame = render_frame(frames, CAMERA, pose, Photometric.random(rng, 0.5), rng)
        lat, lon = destination(pose.lat, pose.lon, rng.uniform(0, 360), rng.uniform(10.0, 15.0))
        heading = (pose.yaw_deg + rng.normal(0.0, 1.5)) % 360.0
        alt = pose.alt_agl_m * rng.uniform(0.97, 1.03)
        yield pose, frame, Prior(lat, lon, alt, heading, pose.pitch_deg, pose.roll_deg, heading_sigma_deg=2.0)


def _apart_m(a: Fix, b: Fix) -> float:
    return float(distance_m(a.pose.lat, a.pose.lon, b.pose.lat, b.pose.lon))


def _rotated_mask(h: int, w: int, angle: float) -> np.ndarray:
    """A frame view's footprint: a rotated rectangle, as a bool mask."""
    box = cv2.boxPoints(((w / 2, h / 2), (0.8 * w, 0.6 * h), angle))
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(box).astype(np.int32), 1)
    return mask.astype(bool)


# --- the numpy copies of the torch pre- and post-processing -----------------------------------


@pytest.mark.parametrize(("h", "w"), [(168, 224), (101, 77), (253, 339)])
def test_numpy_processing_matches_torch(h: int, w: int) -> None:
    import torch
    import torch.nn.functional as F

    from orthonav.models import trunks

    rng = np.random.default_rng(h)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mask = _rotated_mask(h, w, 25.0)
    np.testing.assert_allclose(
        onnx_preprocess.standardise(rgb, mask), trunks.to_tensor(rgb, mask).numpy(), atol=1e-5
    )
    np.testing.assert_allclose(onnx_preprocess.standardise(rgb), trunks.to_tensor(rgb).numpy(), atol=1e-5)
    masks = torch.from_numpy(mask)[None, None]
    for shape in [(h // 8 + 1, w // 8 + 1), (h // 4, w // 4), (7, 5)]:
        want = trunks.valid_cells(masks, shape)[0, 0].numpy()
        np.testing.assert_array_equal(onnx_preprocess.valid_cells(mask, shape), want)
        pooled = F.adaptive_avg_pool2d(masks.float(), shape)
        torch.testing.assert_close(cell_means(masks.float(), *shape), pooled)  # the in-graph copy
    region = rng.standard_normal((1, 16, h // 8 + 9, w // 8 + 6)).astype(np.float32)
    template = rng.standard_normal((1, 16, h // 8, w // 8)).astype(np.float32)
    valid = (rng.uniform(size=(1, 1, h // 8, w // 8)) > 0.3).astype(np.float32)
    want = trunks.correlate(*(torch.from_numpy(a) for a in (region, template, valid)))[0].numpy()
    got = onnx_preprocess.correlate(region[0], template[0], valid[0, 0])
    np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())


# --- agreement with torch ---------------------------------------------------------------------


@pytest.mark.parametrize("size", [224, 448])
def test_feature_maps_agree_fp32(cache: Path, rasters, size: int) -> None:
    """The frame and region views of a correction: ONNX fp32 features within 1e-4 of torch's."""
    from orthonav.models.trunks import load_model

    map_raster, frames = rasters
    net, info = load_model(shipped_model_path())
    onnx_net, onnx_info = onnx_loading.load_onnx_trunk(shipped_model_path(), cache_dir=cache)
    assert (onnx_net.backbone, onnx_net.stage, onnx_net.stride) == (net.backbone, net.stage, net.stride)
    assert onnx_info == json.loads(json.dumps(info))  # the model's record travels in the metadata
    _, frame, prior = next(_cases(map_raster, frames, 1, seed=size))
    views = make_views(map_raster, CAMERA, frame, prior, size, 1.5)
    for rgb, mask in ((views.frame, views.frame_mask), (views.region, views.region_mask)):
        want = net.image_features(rgb, mask).numpy()
        got = onnx_net.image_features(rgb, mask)
        assert got.shape == want.shape
        assert np.linalg.norm(got - want) <= FEATURE_RTOL * np.linalg.norm(want)
        assert np.abs(got - want).max() <= FEATURE_RTOL * np.abs(want).max()
    heat, onnx_heat = (
        n.feature_heatmap(views, n.image_features(views.region, views.region_mask)) for n in (net, onnx_net)
    )
    np.testing.assert_allclose(onnx_heat.values, heat.values, atol=1e-4)


def test_int8_features_and_descriptors_stay_close(cache: Path, rasters) -> None:
    """int8 (static, calibrated on another date): features within 5 % (measured ~3 %), cosine
    per cell > 0.999; descriptors: cosine > 0.999 (measured 0.9999)."""
    from orthonav.models.retrieval import load_retrieval_model
    from orthonav.models.trunks import load_model

    map_raster, _ = rasters
    net, _ = load_model(shipped_model_path())
    int8, _ = onnx_loading.load_onnx_trunk(shipped_model_path(), "int8", cache_dir=cache)
    rgb = map_raster.read_rgb()[200:452, 300:636]
    want, got = net.image_features(rgb, None).numpy(), int8.image_features(rgb)
    assert np.linalg.norm(got - want) <= 0.05 * np.linalg.norm(want)
    assert (got * want).sum(axis=1).mean() > 0.999
    retrieval = shipped_model_path(SHIPPED_RETRIEVAL_MODEL)
    torch_net = load_retrieval_model(retrieval)[0]
    onnx_net = onnx_loading.load_onnx_retrieval(retrieval, "int8", cache_dir=cache)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    mask = np.ones_like(gray)
    assert float(torch_net.describe(gray, mask) @ onnx_net.describe(gray, mask)) > 0.999


def test_retrieval_descriptors_agree_fp32(cache: Path, rasters) -> None:
    """Tiles of any size, partly empty ones and empty ones: the same descriptors as torch."""
    from orthonav.models.retrieval import load_retrieval_model

    map_raster, _ = rasters
    model = shipped_model_path(SHIPPED_RETRIEVAL_MODEL)
    torch_net = load_retrieval_model(model)[0]
    onnx_net = onnx_loading.load_onnx_retrieval(model, cache_dir=cache)
    assert onnx_net.dim == torch_net.dim
    gray = cv2.cvtColor(map_raster.read_rgb(), cv2.COLOR_RGB2GRAY)
    for h, w, angle in [(346, 346, 0.0), (203, 271, 33.0), (97, 131, 70.0)]:
        tile = np.ascontiguousarray(gray[100 : 100 + h, 150 : 150 + w])
        mask = _rotated_mask(h, w, angle).astype(np.uint8) if angle else np.ones((h, w), np.uint8)
        want, got = torch_net.describe(tile * mask, mask), onnx_net.describe(tile * mask, mask)
        assert np.abs(got - want).max() <= FEATURE_RTOL, (h, w)
    empty = np.zeros((120, 160), np.uint8)
    assert not onnx_net.describe(empty, empty).any() and not torch_net.describe(empty, empty).any()


def test_the_index_describes_frames_under_onnx_runtime_where_installed(
    monkeypatch: pytest.MonkeyPatch, torch_one_thread: None
) -> None:
    """``auto`` takes ONNX Runtime for the index's network (faster, the same descriptors), unless
    $ORTHONAV_RUNTIME says torch; a map's index prepares it before the first lost frame."""
    from orthonav.mapdb.globalindex import GlobalIndex, load_retrieval_network
    from orthonav.models.retrieval import RetrievalNet

    model = shipped_model_path(SHIPPED_RETRIEVAL_MODEL)
    monkeypatch.delenv("ORTHONAV_RUNTIME", raising=False)
    assert isinstance(load_retrieval_network(str(model), sha256_file(model)), onnx_graphs.OnnxRetrieval)
    monkeypatch.setenv("ORTHONAV_RUNTIME", "torch")
    assert isinstance(load_retrieval_network(str(model), sha256_file(model)), RetrievalNet)
    index = GlobalIndex(
        np.zeros((0, 0), np.float32), np.eye(2, 128, dtype=np.float32), "cnn", str(model), sha256_file(model)
    )
    assert "network" not in vars(index)
    index.prepare()
    assert isinstance(vars(index)["network"], RetrievalNet)


def test_fixes_agree_between_torch_and_onnx(cache: Path, rasters) -> None:
    """Cross-date frames at known poses: the same decisions, fixes within 0.5 m (fp32 and int8)."""
    map_raster, frames = rasters
    common = {"backbone": "trained"}
    torch_corrector = Corrector(map_raster, CAMERA, CorrectionConfig(**common, runtime="torch"))
    fp32 = Corrector(map_raster, CAMERA, CorrectionConfig(**common, runtime="onnx"))
    int8 = Corrector(map_raster, CAMERA, CorrectionConfig(**common, runtime="onnx", onnx_precision="int8"))
    assert isinstance(fp32.network, onnx_graphs.OnnxTrunk) and fp32.network.record.precision == "fp32"
    assert fp32.network.path == onnx_files.beside_onnx_path(shipped_model_path())
    assert int8.network.path.parent == cache and int8.network.record.precision == "int8"
    errors = []
    for pose, frame, prior in _cases(map_raster, frames, CASES):
        want = torch_corrector.correct(frame, prior).fix
        for corrector, limit in ((fp32, FIX_AGREEMENT_M), (int8, INT8_FIX_AGREEMENT_M)):
            got = corrector.correct(frame, prior).fix
            assert got.accepted == want.accepted, (got.reason, want.reason)
            if want.accepted:
                assert _apart_m(got, want) <= limit
                assert got.quality["peak_ratio"] == pytest.approx(want.quality["peak_ratio"], rel=0.05)
        errors.append(
            float(distance_m(want.pose.lat, want.pose.lon, pose.lat, pose.lon)) if want.accepted else math.inf
        )
    assert sum(e < 10.0 for e in errors) >= CASES // 2, errors  # the frames do correct
    views = torch_corrector.correct(frame, prior).views
    for a, b in zip(torch_corrector.feature_maps(views), fp32.feature_maps(views), strict=True):
        assert isinstance(b, np.ndarray) and a.shape == b.shape


def test_the_trained_correlation_takes_onnx_runtime_where_installed(
    cache: Path, rasters, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``auto`` (the default) correlates with the trunk's shipped export wherever ONNX Runtime
    is installed (faster on a CPU, the same fixes: above); $ORTHONAV_RUNTIME=torch takes torch."""
    map_raster, _ = rasters
    auto = Corrector(map_raster, CAMERA, CorrectionConfig(backbone="trained"))
    assert isinstance(auto.network, onnx_graphs.OnnxTrunk)
    assert auto.network.path == onnx_files.beside_onnx_path(shipped_model_path())
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "torch")
    forced = Corrector(map_raster, CAMERA, CorrectionConfig(backbone="trained"))
    assert not isinstance(forced.network, onnx_graphs.OnnxTrunk)


def test_the_onnx_path_runs_without_torch(cache: Path, rasters) -> None:
    """A companion without torch and with an empty cache: `auto` picks ONNX Runtime and the
    graphs that ship beside the models, torch is never imported, and the fix and the index
    descriptor are torch's. A model without a graph beside it cannot be exported there: the
    error says how."""
    map_raster, frames = rasters
    _, frame, prior = next(_cases(map_raster, frames, 1, seed=11))
    want = Corrector(map_raster, CAMERA, CorrectionConfig(backbone="trained", runtime="torch")).correct(
        frame, prior
    )
    np.save(cache.parent / "frame.npy", frame)
    fields = {k: None if v is None else float(v) for k, v in dataclasses.asdict(prior).items()}
    copy = cache.parent / "copy" / "model.pt"  # the shipped model without its graph beside it
    copy.parent.mkdir(exist_ok=True)
    shutil.copy(shipped_model_path(), copy)
    empty = cache.parent / "empty"
    empty.mkdir(exist_ok=True)
    body = f"""
import numpy as np
from orthonav.camera import Camera
from orthonav.geo import GeoRaster
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.mapdb.globalindex import load_retrieval_network
from orthonav.atomic import sha256_file
from orthonav.models import shipped_model_path
from orthonav.types import Prior
frame = np.load({str(cache.parent / "frame.npy")!r})
with GeoRaster({str(naip_path("20180716"))!r}) as raster:
    corrector = Corrector(raster, Camera.from_hfov(640, 480, 60.0), CorrectionConfig(backbone="trained"))
    fix = corrector.correct(frame, Prior(**json.loads({json.dumps(fields)!r}))).fix
model = shipped_model_path("retrieval_naip.pt")
network = load_retrieval_network(str(model), sha256_file(model))
vector = network.describe(np.full((200, 240), 90, np.uint8), np.ones((200, 240), np.uint8))
from orthonav.errors import OrthonavError
from orthonav.models.onnx.loading import load_onnx_trunk
try:
    load_onnx_trunk({str(copy)!r})
    missing = ""
except OrthonavError as exc:
    missing = str(exc)
result = {{"network": type(corrector.network).__name__, "accepted": fix.accepted, "lat": fix.pose.lat,
          "lon": fix.pose.lon, "norm": float(np.linalg.norm(vector)), "missing": missing,
          "graphs": [corrector.network.path.name, network.path.name]}}
"""
    got = run_without_torch(body, empty)
    assert got["network"] == "OnnxTrunk" and got["torch_modules"] == []
    assert got["graphs"] == ["resnet18_naip.onnx", "retrieval_naip.onnx"] and not any(empty.iterdir())
    assert got["accepted"] == want.fix.accepted and want.fix.accepted
    assert distance_m(got["lat"], got["lon"], want.fix.pose.lat, want.fix.pose.lon) <= FIX_AGREEMENT_M
    assert got["norm"] == pytest.approx(1.0, abs=1e-4)
    # Without torch a missing export cannot be made here: the error says how to make it.
    assert "no such exported ONNX file" in got["missing"] and "orthonav models export" in got["missing"]


# --- files: re-export, stale, missing, corrupt ------------------------------------------------


@pytest.mark.parametrize(
    ("name", "kind"), [("resnet18_naip.pt", "correction"), ("retrieval_naip.pt", "retrieval")]
)
def test_the_shipped_graphs_are_their_models_exports(name: str, kind: str, cache: Path) -> None:
    """The graph beside each shipped model was made from that very file (a retrained model
    without a new export fails here) and computes what a fresh export computes."""
    model = shipped_model_path(name)
    shipped = onnx_files.beside_onnx_path(model)
    session, record = onnx_files.open_session(shipped)
    assert (record.kind, record.precision, record.source_name) == (kind, "fp32", name)
    assert record.source_sha256 == _sha(model)
    fresh, _ = onnx_files.open_session(onnx_files.cached_onnx_path(_sha(model), cache_dir=cache))
    rng = np.random.default_rng(5)
    feeds = {
        i.name: rng.normal(size=(1, 3 if i.name == "image" else 1, 96, 128)).astype(np.float32)
        for i in session.get_inputs()
    }
    if "mask" in feeds:
        feeds["mask"] = np.ones_like(feeds["mask"])
    for got, want in zip(session.run(None, feeds), fresh.run(None, feeds), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_a_graph_beside_the_model_is_found_and_a_stale_one_passed_over(tmp_path: Path) -> None:
    """``model.onnx`` beside ``model.pt`` is used without being named; once the model changes it
    is left alone and the cache's export (made here, where torch is installed) used instead."""
    from orthonav.models.trunks import load_model, save_model

    model = tmp_path / "model.pt"
    shutil.copy(shipped_model_path(), model)
    beside = onnx_files.beside_onnx_path(model)
    assert (
        beside.name == "model.onnx" and onnx_files.beside_onnx_path(model, "int8").name == "model.int8.onnx"
    )
    export_onnx(model, out=beside)
    trunk, _ = onnx_loading.load_onnx_trunk(model, cache_dir=tmp_path / "cache")
    assert trunk.path == beside and not (tmp_path / "cache").exists()
    net, info = load_model(model)
    save_model(net, model, {**info, "note": "retrained"})
    stamp = beside.stat().st_mtime_ns
    trunk, info = onnx_loading.load_onnx_trunk(model, cache_dir=tmp_path / "cache")
    assert trunk.path == onnx_files.cached_onnx_path(_sha(model), cache_dir=tmp_path / "cache")
    assert info["note"] == "retrained" and beside.stat().st_mtime_ns == stamp


def test_a_changed_model_is_exported_again(cache: Path, tmp_path: Path) -> None:
    from orthonav.models.trunks import load_model, save_model

    model = tmp_path / "model.pt"
    shutil.copy(shipped_model_path(), model)
    out = tmp_path / "trunk.onnx"
    export_onnx(model, out=out)
    stamp = out.stat().st_mtime_ns
    assert export_onnx(model, out=out) == out and out.stat().st_mtime_ns == stamp  # current: kept
    net, info = load_model(model)
    save_model(net, model, {**info, "note": "retrained"})  # same weights, another file
    with pytest.raises(OrthonavError, match="exported from another model file") as error:
        onnx_loading.load_onnx_trunk(model, onnx_path=out)
    assert "orthonav models export" in str(error.value)
    export_onnx(model, out=out)  # stale: made again
    _, record = onnx_files.open_session(out)
    assert record.source_sha256 == sha256_file(model) and record.info["note"] == "retrained"
    trunk, info = onnx_loading.load_onnx_trunk(model, onnx_path=out)
    assert info["note"] == "retrained" and trunk.stride == 8
    # The cache: a file per model content; a damaged one is made again where torch is installed.
    cached = onnx_files.cached_onnx_path(sha256_file(model), cache_dir=tmp_path / "cache")
    onnx_loading.load_onnx_trunk(model, cache_dir=tmp_path / "cache")
    assert cached.is_file()
    cached.write_bytes(b"damaged")
    trunk, _ = onnx_loading.load_onnx_trunk(model, cache_dir=tmp_path / "cache")
    assert trunk.path == cached and cached.stat().st_size > 1_000_000


def test_missing_corrupt_or_foreign_files_are_clear_errors(cache: Path, tmp_path: Path) -> None:
    model = shipped_model_path()
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x08\x01not a graph")
    retrieval = onnx_files.cached_onnx_path(
        sha256_file(shipped_model_path(SHIPPED_RETRIEVAL_MODEL)), cache_dir=cache
    )
    cases = {
        tmp_path / "missing.onnx": "no such exported ONNX file",
        junk: "not a readable ONNX file",
        retrieval: "an exported retrieval model, expected a correction model",
    }
    for path, fragment in cases.items():
        with pytest.raises(OrthonavError, match=fragment) as error:
            onnx_loading.load_onnx_trunk(model, onnx_path=path)
        assert str(path) in str(error.value) and "orthonav models export" in str(error.value)
    with pytest.raises(OrthonavError, match="a fp32 export, expected int8"):
        onnx_loading.load_onnx_trunk(
            model, "int8", onnx_path=onnx_files.cached_onnx_path(_sha(model), cache_dir=cache)
        )
    with pytest.raises(OrthonavError, match="--int8 --calibration"):  # int8 is never made implicitly
        onnx_loading.load_onnx_trunk(model, "int8", cache_dir=tmp_path / "empty")
    with pytest.raises(OrthonavError, match="no such model file"):
        onnx_loading.load_onnx_trunk(tmp_path / "nothing.pt")
    with pytest.raises(OrthonavError, match="needs calibration imagery"):
        export_onnx(model, "int8", out=tmp_path / "int8.onnx")
    with pytest.raises(OrthonavError, match="not a readable model file"):
        export_onnx(junk)
    # through the corrector
    config = CorrectionConfig(backbone="trained", runtime="onnx", onnx_path=str(junk))
    with pytest.raises(OrthonavError, match="not a readable ONNX file"):
        Corrector(None, CAMERA, config)


def _sha(path: Path) -> str:
    return sha256_file(path)


def test_plain_onnx_without_our_metadata_is_refused(cache: Path, tmp_path: Path) -> None:
    import onnx

    proto = onnx.load(str(onnx_files.cached_onnx_path(_sha(shipped_model_path()), cache_dir=cache)))
    del proto.metadata_props[:]
    onnx.save_model(proto, str(tmp_path / "plain.onnx"))
    with pytest.raises(OrthonavError, match="not an ONNX file exported by orthonav"):
        onnx_loading.load_onnx_trunk(shipped_model_path(), onnx_path=tmp_path / "plain.onnx")


# --- configuration, threads, the command ------------------------------------------------------


def test_runtime_choice_and_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(onnx_runtime.RUNTIME_ENV, raising=False)
    assert onnx_runtime.resolve_runtime("auto") == "torch"  # torch is installed: as before
    assert onnx_runtime.resolve_runtime("onnx") == "onnx"
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "onnx")
    assert onnx_runtime.resolve_runtime("auto") == "onnx" and onnx_runtime.resolve_runtime("torch") == "torch"
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "tpu")
    with pytest.raises(OrthonavError, match="expected torch or onnx"):
        onnx_runtime.resolve_runtime("auto")
    with pytest.raises(OrthonavError, match="runtime 'tpu'"):
        CorrectionConfig(backbone="trained", runtime="tpu")
    with pytest.raises(OrthonavError, match="only for the trained backbone"):
        CorrectionConfig(backbone="resnet18", runtime="onnx")
    with pytest.raises(OrthonavError, match="precision 'int4'"):
        CorrectionConfig(backbone="trained", onnx_precision="int4")
    cores = onnx_runtime.physical_cores()
    assert 1 <= cores <= (os.cpu_count() or 1)
    assert onnx_runtime.session_options().intra_op_num_threads == cores
    assert onnx_runtime.session_options(1).intra_op_num_threads == 1


def test_cli_models_export(tmp_path: Path) -> None:
    from orthonav.cli.models import models_app

    runner = CliRunner()
    out = tmp_path / "retrieval.onnx"
    result = runner.invoke(
        models_app, ["export", str(shipped_model_path(SHIPPED_RETRIEVAL_MODEL)), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    _, record = onnx_files.open_session(out)
    assert record.kind == "retrieval" and record.precision == "fp32"
    result = runner.invoke(models_app, ["export", "--int8", "--out", str(tmp_path / "int8.onnx")])
    assert isinstance(result.exception, OrthonavError) and "calibration" in str(result.exception)
    result = runner.invoke(models_app, ["export", "--int8", "--calibration", str(tmp_path / "no.tif")])
    assert isinstance(result.exception, OrthonavError) and "no such calibration" in str(result.exception)


def test_runtime_bench_smoke(tmp_path: Path) -> None:
    """One frame, one size: rows for every runtime, JSON and PNG written."""
    from orthonav.bench.runtime import RuntimeBenchConfig, run_runtime_benchmark

    naip_path("20120731")  # skips without the data
    config = RuntimeBenchConfig(
        frames=1,
        sizes=(224,),
        repeats=1,
        tiles=2,
        calibration_crops=4,
        threads=1,
        parts=("corrections", "index"),
    )
    out = tmp_path / "bench_runtime.json"
    result = run_runtime_benchmark(naip_path("20200831").parent, out, config, progress=False)
    assert [r["runtime"] for r in result["corrections"]] == ["torch", "onnx-fp32", "onnx-int8"]
    assert all(r["median_ms"] > 0 and r["same_decision"] == "1/1" for r in result["corrections"])
    assert [r["runtime"] for r in result["index"]] == ["torch", "onnx-fp32", "onnx-int8"]
    assert result["index"][1]["min_cosine_to_torch"] > 0.9999
    assert json.loads(out.read_text())["machine"]["threads"] == 1
    assert out.with_suffix(".png").stat().st_size > 0
    with pytest.raises(OrthonavError, match="torch included"):
        RuntimeBenchConfig(runtimes=("onnx-fp32",))

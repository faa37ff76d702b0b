"""Small synthetic GeoTIFFs for unit tests, written with rasterio into a temp directory."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.errors import NotGeoreferencedWarning

# NAIP quarter-quad in North Dakota, NAD83 / UTM 14N: a plausible place for a UTM test map.
UTM14_CRS = "EPSG:26914"
UTM14_ORIGIN = (485899.0, 5209246.0)
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_file(relative: str) -> Path:
    """A file under ../shared/data, or skip the test with the reason when it is absent."""
    path = SHARED_DATA / relative
    if not path.is_file():
        pytest.skip(f"../shared/data not present: {path} is missing (real-data test)")
    return path


def textured(height: int, width: int, bands: int = 3, seed: int = 0) -> np.ndarray:
    """(bands, H, W) uint8 smooth random texture with blobs: plenty of corners for ORB/SIFT."""
    rng = np.random.default_rng(seed)
    out = np.empty((bands, height, width), np.uint8)
    for b in range(bands):
        total = np.zeros((height, width), np.float32)
        for sigma, weight in ((1.0, 0.3), (3.0, 0.5), (8.0, 1.0)):
            noise = rng.standard_normal((height, width)).astype(np.float32)
            total += weight * cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
        total = (total - total.min()) / (total.max() - total.min())
        out[b] = np.clip(20 + 215 * total, 0, 255).astype(np.uint8)
    return out


def write_geotiff(
    path: Path,
    data: np.ndarray,
    crs: Any = UTM14_CRS,
    transform: Affine | None = None,
    nodata: float | None = None,
    driver: str = "GTiff",
) -> Path:
    """Write (bands, H, W) ``data``; default transform: 1 m north-up pixels at UTM14_ORIGIN."""
    if transform is None:
        transform = Affine(1.0, 0.0, UTM14_ORIGIN[0], 0.0, -1.0, UTM14_ORIGIN[1])
    profile: dict[str, Any] = {
        "driver": driver,
        "width": data.shape[2],
        "height": data.shape[1],
        "count": data.shape[0],
        "dtype": data.dtype.name,
        "transform": transform,
    }
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(data)
    return path

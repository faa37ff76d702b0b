"""Validating an uploaded orthophoto at a cost bounded by its size.

Reading every block of a file costs what its pixels take decoded, which its header declares and
its size does not bound: a sparse GeoTIFF (blocks without data) or an extremely compressed one
declares far more than it holds. So the declared size is checked against the file's bytes
before any block is read, the blocks are then read through GDAL's bounded block cache, and the
memory they took is handed back to the system afterwards.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import rasterio
from fastapi import HTTPException
from rasterio.errors import NotGeoreferencedWarning

from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.geo.raster import bounded_block_cache
from orthonav.web.memory import release_memory

# Small files are read whatever they declare: reading this much costs a fraction of a second.
DECODED_FLOOR_BYTES = 64 << 20


def validate_geotiff(path: Path, name: str, max_decoded_ratio: float) -> None:
    """Open it as orthonav opens every orthophoto (CRS, north-up, bands, pixel type) and read
    every block, once its declared size has been found proportionate to its bytes (else 413)."""
    try:
        _check_declared_size(path, name, max_decoded_ratio)
        with bounded_block_cache(), GeoRaster(path) as raster:
            raster.check_readable()  # every block: a truncated upload is refused now, not at build
    except HTTPException:
        raise
    except Exception as exc:  # any failure here is the file's, and the user's to fix
        reason = str(exc) if isinstance(exc, OrthonavError) else f"not a readable GeoTIFF ({exc})"
        reason = reason.replace(f"{path}: ", "").replace(str(path), name)  # no server paths
        raise OrthonavError(f"upload {name}: {reason}") from None
    finally:
        release_memory()


def _check_declared_size(path: Path, name: str, max_decoded_ratio: float) -> None:
    """From the header alone (opening a GeoTIFF reads no block)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # GeoRaster refuses it, in words
        with rasterio.open(path) as ds:
            width, height, bands = ds.width, ds.height, ds.count
            decoded = width * height * bands * np.dtype(ds.dtypes[0]).itemsize
    size = path.stat().st_size
    if decoded > max(DECODED_FLOOR_BYTES, max_decoded_ratio * size):
        raise HTTPException(
            413,
            f"upload {name}: declares {width} x {height} px in {bands} bands, {decoded / 1e9:.1f} GB "
            f"of pixels in a file of {size / 1e6:.1f} MB, more than {max_decoded_ratio:g} times its "
            "size: a sparse or extremely compressed GeoTIFF is refused (crop it to where it has "
            "imagery, e.g. with gdal_translate -projwin)",
        )

"""Pre- and post-processing of the correction and retrieval networks in numpy (standardisation,
valid cells, correlation): copies of the torch code in :mod:`orthonav.models.trunks`, checked
against it in the tests."""

from __future__ import annotations

import cv2
import numpy as np
import scipy.fft

VALID_CELL_FRACTION = 0.99  # as trunks.valid_cells: a cell holds imagery when 99 % of its pixels do


def standardise(rgb: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H, W) float32 standardised per channel over the valid pixels,
    invalid pixels 0: as :func:`orthonav.models.trunks.to_tensor`. The statistics by OpenCV and
    each channel scaled in place, without temporaries: a lost frame's index describes a dozen such
    views, so this runs often."""
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

    By FFT, summed over channels in the frequency domain: at correction sizes far cheaper on a CPU
    than a direct convolution. A circular correlation of the region's size is exact
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

"""Correlation heatmaps and their peaks: where the frame view sits in the region view.

A :class:`Heatmap` scores every placement of the frame view inside the region view;
``values[i, j]`` is the placement whose top-left corner is region pixel
(``j * stride``, ``i * stride``). The classical scorer is normalised cross-correlation of
gradient-magnitude images (OpenCV, FFT inside): gradients survive the changes of colour,
season and sensor between dates far better than intensities. Their orientation survives more
(:func:`orientation_field`): a field's edge keeps its direction when its crop turns it from
brighter than the road to darker, or fades it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

GRADIENT_BLUR_SIGMA_PX = 1.0


@dataclass
class Heatmap:
    values: np.ndarray  # (rows, cols) float32
    stride: int
    # Where the frame placed lies on the map (None: everywhere); elsewhere ``values`` hold the
    # median of those on it, so no peak is found there and the background is the map's own.
    on_map: np.ndarray | None = None

    def placement_px(self, row: float, col: float) -> tuple[float, float]:
        """Heatmap cell (row, col) -> region pixel (x, y) of the frame view's top-left corner."""
        return col * self.stride, row * self.stride

    def on_border(self, row: float, col: float) -> bool:
        """Whether the placement (row, col) lies within half a cell of the heatmap's border or
        next to a placement off the map: the best one may lie beyond it."""
        rows, cols = self.values.shape
        if not (0.5 <= row <= rows - 1.5 and 0.5 <= col <= cols - 1.5):
            return True
        if self.on_map is None:
            return False
        r, c = round(row), round(col)
        return not self.on_map[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2].all()

    def keep_on_map(self, on_map: np.ndarray) -> Heatmap:
        """This heatmap with only the placements where ``on_map`` (their cells') count."""
        if on_map.all():
            return self
        values = self.values.copy()
        values[~on_map] = np.median(values[on_map]) if on_map.any() else values.min()
        return Heatmap(values, self.stride, on_map)


@dataclass(frozen=True)
class Peak:
    """The best placement (sub-cell), its score and how much it stands out."""

    row: float
    col: float
    score: float
    second: float
    ratio: float


def gradient_magnitude(rgb: np.ndarray) -> np.ndarray:
    """Square-root gradient magnitude of the blurred gray image, float32."""
    return root_gradient(_blurred_gray(rgb))


def orientation_field(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32: the blurred gray image's gradient orientation as a doubled angle
    (cos 2a, sin 2a), weighted by the square root of the gradient magnitude (as
    :func:`gradient_magnitude`). Doubling the angle makes an edge the same whichever side is
    brighter, so an edge whose contrast reversed between dates still correlates, and the
    magnitude counts only as its square root: a faint edge of a hazy year weighs nearly as much
    as the sharp one of another. On NAIP frames at 1000 m with a 200 m prior (five pairs with
    2009, two without), the correlation peak put 93 % of frame centres within 25 m, the
    magnitude's 73 %."""
    return root_orientation(_blurred_gray(rgb))


def _blurred_gray(rgb: np.ndarray) -> np.ndarray:
    """The float32 gray image, blurred as every gradient image here is."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return cv2.GaussianBlur(gray, (0, 0), GRADIENT_BLUR_SIGMA_PX)


def root_orientation(image: np.ndarray) -> np.ndarray:
    """:func:`orientation_field` of a float32 gray image as it is (blurred by the caller)."""
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3)
    squared = gx * gx + gy * gy
    # weight / |g|^2 = |g|^(1/2 - 2); zero where there is no gradient (float noise of a blur).
    scale = np.zeros_like(squared)
    np.power(squared, -0.75, out=scale, where=squared > 1e-6)  # under a thousandth of a gray level
    return np.dstack([(gx * gx - gy * gy) * scale, 2.0 * gx * gy * scale])


def root_gradient(image: np.ndarray) -> np.ndarray:
    """Square root of the Sobel gradient magnitude of a float32 image: the square root keeps
    strong edges (roads, shores) from drowning every other structure. The magnitude by numpy,
    not ``cv2.magnitude``, whose threads round a last bit differently from run to run: enough
    to swap near-equal peaks of a lost frame's search between two runs of the same frame."""
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3)
    return np.sqrt(np.sqrt(gx * gx + gy * gy))


def ncc_heatmap(region: np.ndarray, template: np.ndarray, template_mask: np.ndarray | None = None) -> Heatmap:
    """Normalised cross-correlation of two single-channel float32 images (stride 1).

    Template pixels outside ``template_mask`` are set to the template's mean so they add
    nothing to the zero-mean correlation.
    """
    filled = _filled(template, template_mask)
    values = cv2.matchTemplate(region.astype(np.float32), filled, cv2.TM_CCOEFF_NORMED)
    return Heatmap(np.nan_to_num(values, copy=False, nan=-1.0), 1)


def ncc_score(image: np.ndarray, template: np.ndarray, template_mask: np.ndarray | None = None) -> float:
    """:func:`ncc_heatmap`'s one value for a template of the image's own size, summed directly in
    float64 (OpenCV would transform both images for that one value)."""
    if image.shape != template.shape:
        raise ValueError(f"image {image.shape} and template {template.shape}: expected the same size")
    filled = _filled(template, template_mask).astype(np.float64).ravel()
    filled -= filled.mean()
    window = image.astype(np.float64).ravel()
    window -= window.mean()
    # Products summed by numpy, not np.dot: OpenBLAS's threads spin on after a call and take
    # their cores from the ONNX Runtime extraction that follows in the cascade on a small CPU.
    filled_sq, window_sq = float(np.square(filled).sum()), float(np.square(window).sum())
    if filled_sq < np.finfo(float).eps:  # a flat template: 1, as OpenCV has it
        return 1.0
    if window_sq == 0.0:  # a flat image: 0
        return 0.0
    return float((filled * window).sum()) / math.sqrt(filled_sq * window_sq)


def _filled(template: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """A float32 copy of ``template`` with the pixels outside ``mask`` at the mean of those inside."""
    filled = template.astype(np.float32, copy=True)
    if mask is not None and not mask.all():
        filled[~mask] = filled[mask].mean(axis=0) if mask.any() else 0.0
    return filled


class Template:
    """A template for :class:`Correlator`, prepared once: pixels outside its mask at the mean of
    those inside (as :func:`ncc_heatmap`), zero mean, its norm, and its spectrum per FFT size.
    An (h, w, C) image is C channels correlated together, as ``matchTemplate`` correlates a
    colour image: each channel's own mean, the sums over all of them."""

    def __init__(self, image: np.ndarray, mask: np.ndarray | None = None) -> None:
        template = _filled(image, mask).reshape(*image.shape[:2], -1)
        template -= template.mean(axis=(0, 1), dtype=np.float64).astype(np.float32)
        self.image = template
        self.norm = float(np.sqrt(np.square(template, dtype=np.float64).sum()))
        self._spectra: dict[tuple[int, int], np.ndarray] = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]

    @property
    def channels(self) -> int:
        return self.image.shape[2]

    def spectrum(self, fft_shape: tuple[int, int]) -> np.ndarray:
        """The conjugate spectrum, (C, rows, cols // 2 + 1): channel first, as :class:`Correlator`
        sums the channels' products (contiguous planes added, not a reduction over a short axis)."""
        if fft_shape not in self._spectra:
            planes = np.ascontiguousarray(np.moveaxis(self.image, 2, 0))
            self._spectra[fft_shape] = np.conj(scipy.fft.rfft2(planes, fft_shape, axes=(1, 2)))
        return self._spectra[fft_shape]


class Correlator:
    """:func:`ncc_heatmap` of one region with many templates of one size, by FFT: the region's
    spectrum and its sums under the template's window are computed once for every template,
    each template's spectrum once for every region. A lost frame's search correlates each region
    with seven turns of the frame view, and each turn with dozens of regions; OpenCV's
    ``matchTemplate`` transforms both images for every pair. The same values as
    ``matchTemplate``'s TM_CCOEFF_NORMED (its rule for flat windows included) to float precision,
    for one channel or several (an (H, W, C) region; templates of as many channels). Channels
    cost their forward transforms only: their products are summed before the one inverse.
    """

    def __init__(self, region: np.ndarray, template_shape: tuple[int, int]) -> None:
        rows, cols = region.shape[:2]
        h, w = template_shape
        if h > rows or w > cols:
            raise ValueError(f"template {w}x{h} larger than the region {cols}x{rows}")
        self.template_shape = (h, w)
        self.fft_shape = (scipy.fft.next_fast_len(rows, True), scipy.fft.next_fast_len(cols, True))
        # Sums under the window at every placement, from integral images in float64 (the variance
        # is a difference of two large sums), each channel's own, added over the channels.
        region32 = region.astype(np.float32, copy=False).reshape(rows, cols, -1)
        squares = np.zeros((rows - h + 1, cols - w + 1))
        for channel in np.moveaxis(region32, 2, 0):
            integral, squared = cv2.integral2(
                np.ascontiguousarray(channel), sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F
            )
            sums = _window_sums(integral, h, w)
            sums *= sums  # in place, as the rest: the arithmetic of sqrt(squares - sums**2 / hw)
            sums /= h * w
            squares += _window_sums(squared, h, w)
            squares -= sums
        norm = np.sqrt(np.maximum(squares, 0.0, out=squares), out=squares)
        # 0 for a flat window: its correlation is 0, as OpenCV makes it.
        self._inverse_norm = np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0.0).astype(
            np.float32
        )
        self.channels = region32.shape[2]
        planes = np.ascontiguousarray(np.moveaxis(region32, 2, 0))
        self._spectrum = scipy.fft.rfft2(planes, self.fft_shape, axes=(1, 2))  # (C, rows, cols // 2 + 1)
        self._out = (rows - h + 1, cols - w + 1)

    def heatmap(self, template: Template) -> Heatmap:
        if template.shape != self.template_shape or template.channels != self.channels:
            raise ValueError(
                f"template {template.shape} of {template.channels} channels, the correlator's is "
                f"{self.template_shape} of {self.channels}"
            )
        rows, cols = self._out
        if template.norm < np.finfo(float).eps:  # a flat template: 1 everywhere, as OpenCV has it
            return Heatmap(np.ones(self._out, np.float32), 1)
        spectra = template.spectrum(self.fft_shape)
        product = self._spectrum[0] * spectra[0]
        for channel in range(1, self.channels):
            product += self._spectrum[channel] * spectra[channel]
        values = scipy.fft.irfft2(product, self.fft_shape)[:rows, :cols]
        values *= self._inverse_norm
        values *= np.float32(1.0 / template.norm)
        # OpenCV's rule beyond the norm (rounding): just beyond it +-1, far beyond 0.
        if values.max() >= 1.0 or values.min() <= -1.0:
            beyond = np.abs(values) >= 1.0
            values[beyond] = np.where(np.abs(values[beyond]) < 1.125, np.sign(values[beyond]), 0.0)
        return Heatmap(values, 1)


def _window_sums(integral: np.ndarray, h: int, w: int) -> np.ndarray:
    """Sums under an ``h`` x ``w`` window at every placement, from an integral image."""
    sums = integral[h:, w:] - integral[:-h, w:]
    sums -= integral[h:, :-w]
    sums += integral[:-h, :-w]
    return sums


def find_peak(heatmap: Heatmap, exclusion_cells: float) -> Peak:
    """The maximum with a sub-cell quadratic fit, and its ratio to the best peak elsewhere.

    The ratio is taken above the heatmap's median (a background level), so a map that
    scores high everywhere does not pass for a distinct peak: (p1 - med) / (p2 - med).
    "Elsewhere" is outside ``exclusion_cells`` of the maximum: the same peak's flanks do
    not count as a rival.
    """
    values = heatmap.values
    row, col = np.unravel_index(int(np.argmax(values)), values.shape)
    score = float(values[row, col])
    rows, cols = np.ogrid[: values.shape[0], : values.shape[1]]
    outside = (rows - row) ** 2 + (cols - col) ** 2 > exclusion_cells**2
    second = float(values[outside].max()) if outside.any() else float(values.min())
    floor = float(np.median(values))
    ratio = (score - floor) / max(second - floor, 1e-6)
    sub_row, sub_col = _quadratic_offset(values, row, col)
    return Peak(row + sub_row, col + sub_col, score, second, float(min(ratio, 1e3)))


def rival_peaks(heatmap: Heatmap, peak: Peak, exclusion_cells: float) -> np.ndarray:
    """(N, 3) row, col and relative height of the heatmap's other modes: each local maximum (the
    highest of the square reaching ``exclusion_cells`` around it) outside ``exclusion_cells`` of
    ``peak``, its height above the median as a share of the peak's, as :func:`find_peak` measures
    the ratio. The flanks of one hump are not its rivals; separate humps are the places the frame
    might also be."""
    values = heatmap.values.astype(np.float32)
    radius = max(1, math.ceil(exclusion_cells))
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    highest = cv2.dilate(values, kernel, borderType=cv2.BORDER_REPLICATE)
    floor = float(np.median(values))
    rows, cols = np.nonzero((values >= highest) & (values > floor))
    apart = (rows - peak.row) ** 2 + (cols - peak.col) ** 2 > exclusion_cells**2
    rows, cols = rows[apart], cols[apart]
    height = (values[rows, cols] - floor) / max(peak.score - floor, 1e-6)
    return np.column_stack([rows, cols, height]).astype(float)


def _quadratic_offset(values: np.ndarray, row: int, col: int) -> tuple[float, float]:
    """Sub-cell position of a maximum from a parabola through it and its two neighbours, per axis."""

    def axis(minus: float, centre: float, plus: float) -> float:
        denom = minus - 2.0 * centre + plus
        return (
            0.0
            if denom >= 0 or not math.isfinite(denom)
            else float(np.clip(0.5 * (minus - plus) / denom, -0.5, 0.5))
        )

    d_row = (
        axis(values[row - 1, col], values[row, col], values[row + 1, col])
        if 0 < row < values.shape[0] - 1
        else 0.0
    )
    d_col = (
        axis(values[row, col - 1], values[row, col], values[row, col + 1])
        if 0 < col < values.shape[1] - 1
        else 0.0
    )
    return d_row, d_col

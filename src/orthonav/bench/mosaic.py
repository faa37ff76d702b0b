"""Large test maps made from real imagery: blocks of several dates laid out side by side.

The shared data holds one NAIP quarter-quad (~17 km^2) in five years; scale benchmarks need
maps of 100 km^2 and more. A mosaic cuts each year into four non-overlapping quarter blocks
(~4.2 km^2) and lays blocks of all years on a grid (then mirrored copies, when more are
asked for), georeferenced in the source CRS and resolution. The same ground thus appears
once per year: places that look alike but are not the same, as repetitive farmland does.
The same layout drawn with every block taken from one date that the mosaic does not use
(``every_block_from``) gives the cross-date frames for that mosaic: were that date in the
mosaic, a cross-date frame would find its own imagery, same-date, at another block.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window

from orthonav.errors import OrthonavError
from orthonav.geo import write_geotiff


@dataclass(frozen=True)
class Block:
    """One quarter of source ``date`` (index into the sources), mirrored left-right or not."""

    date: int
    quarter: int
    mirror: bool


@dataclass(frozen=True)
class Mosaic:
    """Blocks of ``block_px`` (width, height) on a near-square grid."""

    sources: tuple[Path, ...]
    blocks: tuple[Block, ...]
    block_px: tuple[int, int]

    @property
    def per_row(self) -> int:
        return math.ceil(math.sqrt(len(self.blocks)))

    def area_km2(self, gsd_m: float) -> float:
        """Ground covered by imagery (the grid's empty cells do not count)."""
        return len(self.blocks) * self.block_px[0] * self.block_px[1] * gsd_m**2 / 1e6

    def origin_px(self, index: int) -> tuple[int, int]:
        """Top-left (col, row) of block ``index`` in the mosaic."""
        row, col = divmod(index, self.per_row)
        return col * self.block_px[0], row * self.block_px[1]


def mosaic_layout(sources: list[Path], blocks: int, repeat: bool = False) -> Mosaic:
    """``blocks`` distinct blocks: every quarter of every date, then their mirror images; with
    ``repeat`` the same sequence again for more (fine for build timing and memory, not for
    re-localization, where a repeated block has two right answers)."""
    if not sources:
        raise OrthonavError("mosaic: no source GeoTIFFs")
    sizes = set()
    for source in sources:
        with rasterio.open(source) as src:
            sizes.add((src.width, src.height))
    # Dates of one area differ by a pixel or so; the smallest common size bounds the quarters.
    width, height = min(w for w, _ in sizes), min(h for _, h in sizes)
    variants = [
        Block(date, quarter, mirror)
        for mirror, quarter, date in itertools.product((False, True), range(4), range(len(sources)))
    ]
    if blocks < 1 or (blocks > len(variants) and not repeat):
        raise OrthonavError(
            f"mosaic: 1 to {len(variants)} distinct blocks from {len(sources)} dates, asked for {blocks}"
        )
    chosen = tuple(itertools.islice(itertools.cycle(variants), blocks))
    return Mosaic(tuple(sources), chosen, (width // 2, height // 2))


def write_mosaic(mosaic: Mosaic, out: Path, every_block_from: Path | None = None) -> Path:
    """The mosaic as one GeoTIFF (atomically); ``every_block_from`` draws every block from
    that one source instead of its own date (same grid and size: another date of the area)."""
    bw, bh = mosaic.block_px
    rows = math.ceil(len(mosaic.blocks) / mosaic.per_row)
    image = None
    for i, block in enumerate(mosaic.blocks):
        source = every_block_from or mosaic.sources[block.date]
        with rasterio.open(source) as src:
            qr, qc = divmod(block.quarter, 2)
            data = src.read(window=Window(qc * bw, qr * bh, bw, bh))
            if image is None:
                image = np.zeros((src.count, rows * bh, mosaic.per_row * bw), src.dtypes[0])
                profile, colorinterp = src.profile, src.colorinterp
        col, row = mosaic.origin_px(i)
        image[:, row : row + bh, col : col + bw] = data[:, :, ::-1] if block.mirror else data
    t = profile["transform"]
    profile = {
        **profile,
        "driver": "GTiff",
        "width": image.shape[2],
        "height": image.shape[1],
        "transform": Affine(t.a, 0.0, t.c, 0.0, t.e, t.f),
        "compress": "deflate",
    }
    return write_geotiff(out, image, profile, colorinterp)

"""Several orthophotos as one: a GDAL VRT mosaic on one grid, other CRSs reprojected first.

A map may come as a folder of GeoTIFFs (or COGs) in different CRSs and resolutions. The
mosaic's grid takes the CRS of the first file (or the one given) and the finest resolution
among them: a file in another CRS counts by its ground resolution turned into the target
CRS's units where it lies (pyproj's scale factors: a Web Mercator metre is 1/cos(lat) ground
metres). Files already on that CRS and
resolution are referenced as they are; the others are reprojected with GDAL's warper
(rasterio ``WarpedVRT``) into a tiled GeoTIFF, block by block, so memory stays bounded
whatever their size. The VRT then places every file at its offset; where files overlap, the
later one (by name) is on top. Gaps are nodata (0), which the map build ignores.
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import escape

import rasterio
from affine import Affine
from pyproj import CRS, Proj
from rasterio.vrt import WarpedVRT
from rasterio.warp import calculate_default_transform
from rasterio.windows import Window

from orthonav.atomic import atomic_path, write_text_atomic
from orthonav.errors import OrthonavError
from orthonav.geo.raster import GeoRaster

BLOCK_PX = 1024
SUFFIXES = (".tif", ".tiff")


def mosaic_sources(folder: Path) -> list[Path]:
    """The GeoTIFFs of a folder, by name."""
    if not folder.is_dir():
        raise OrthonavError(f"{folder}: not a folder of GeoTIFFs")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in SUFFIXES)
    if not files:
        raise OrthonavError(f"{folder}: no GeoTIFF (.tif, .tiff) in it")
    return files


def build_vrt(sources: list[Path], out_vrt: Path, crs: str | None = None) -> Path:
    """Write ``out_vrt`` (and reprojected copies beside it) mosaicking ``sources``."""
    rasters = [GeoRaster(p) for p in sources]  # validates every file, naming the bad one
    try:
        target = CRS.from_user_input(crs) if crs else rasters[0].crs
        if not target.is_projected:
            raise OrthonavError(
                f"mosaic CRS {target.to_string()}: expected a projected CRS (metres), e.g. UTM"
            )
        _check_bands(rasters)
        res = min(
            abs(r.transform.a) if r.crs == target else r.gsd_m * crs_units_per_metre(target, r)
            for r in rasters
        )
        out_vrt.parent.mkdir(parents=True, exist_ok=True)
        placed = [
            _on_grid(r, target, res, out_vrt.parent / f"{out_vrt.stem}.{i:03d}.tif")
            for i, r in enumerate(rasters)
        ]
    finally:
        for raster in rasters:
            raster.close()
    write_text_atomic(out_vrt, _vrt_xml(placed, target, res))
    return out_vrt


def crs_units_per_metre(crs: CRS, raster: GeoRaster) -> float:
    """Target-CRS units that cover one ground metre at the centre of ``raster``: the map
    projection's scale factor there (the mean of its meridional and parallel scales, equal for
    conformal projections such as UTM and Web Mercator), over the CRS's unit in metres."""
    lat, lon = raster.center_latlon
    factors = Proj(crs).get_factors(lon, lat)
    scale = (factors.meridional_scale + factors.parallel_scale) / 2.0
    return scale / crs.axis_info[0].unit_conversion_factor


def _check_bands(rasters: list[GeoRaster]) -> None:
    first = rasters[0]
    for raster in rasters[1:]:
        if (raster.band_count, raster.dtype) != (first.band_count, first.dtype):
            raise OrthonavError(
                f"{raster.path}: {raster.band_count} bands of {raster.dtype}, but {first.path.name} has "
                f"{first.band_count} of {first.dtype}; a mosaic needs one band layout"
            )


def _on_grid(raster: GeoRaster, crs: CRS, res: float, copy: Path) -> Path:
    """The file itself when it already has the CRS and resolution, else a reprojected copy."""
    same_res = math.isclose(abs(raster.transform.a), res, rel_tol=1e-6) and math.isclose(
        abs(raster.transform.e), res, rel_tol=1e-6
    )
    if raster.crs == crs and same_res:
        return raster.path.resolve()
    with rasterio.open(raster.path) as src:
        transform, width, height = calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds, resolution=res
        )
        profile = {
            **src.profile,
            "driver": "GTiff",
            "crs": crs,
            "transform": transform,
            "width": width,
            "height": height,
            "tiled": True,
            "blockxsize": 256,
            "blockysize": 256,
            "compress": "deflate",
            "nodata": 0,
        }
        with (
            WarpedVRT(src, crs=crs, transform=transform, width=width, height=height, nodata=0) as warped,
            atomic_path(copy) as tmp,
            rasterio.open(tmp, "w", **profile) as dst,
        ):
            for window in _blocks(width, height):
                dst.write(warped.read(window=window), window=window)
    return copy.resolve()


def _blocks(width: int, height: int) -> list[Window]:
    return [
        Window(col, row, min(BLOCK_PX, width - col), min(BLOCK_PX, height - row))
        for row in range(0, height, BLOCK_PX)
        for col in range(0, width, BLOCK_PX)
    ]


def _vrt_xml(files: list[Path], crs: CRS, res: float) -> str:
    """A VRT over the union of the files' bounds; each file a source at its pixel offset."""
    infos = []
    for path in files:
        with rasterio.open(path) as ds:
            infos.append((path, ds.bounds, ds.width, ds.height, ds.count, ds.dtypes[0]))
    left = min(b.left for _, b, *_ in infos)
    top = max(b.top for _, b, *_ in infos)
    width = math.ceil((max(b.right for _, b, *_ in infos) - left) / res)
    height = math.ceil((top - min(b.bottom for _, b, *_ in infos)) / res)
    transform = Affine(res, 0.0, left, 0.0, -res, top)
    bands, dtype = infos[0][4], infos[0][5]
    gdal_type = {"uint8": "Byte", "uint16": "UInt16", "int16": "Int16", "float32": "Float32"}.get(dtype)
    if gdal_type is None:
        raise OrthonavError(f"mosaic: data type {dtype} is not supported (uint8, uint16, int16, float32)")
    lines = [
        f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">',
        f"  <SRS>{escape(crs.to_wkt())}</SRS>",
        "  <GeoTransform>" + ", ".join(repr(v) for v in transform.to_gdal()) + "</GeoTransform>",
    ]
    for band in range(1, bands + 1):
        lines += [
            f'  <VRTRasterBand dataType="{gdal_type}" band="{band}">',
            "    <NoDataValue>0</NoDataValue>",
        ]
        for path, bounds, w, h, *_ in infos:
            x = (bounds.left - left) / res
            y = (top - bounds.top) / res
            lines += [
                "    <ComplexSource>",
                f'      <SourceFilename relativeToVRT="0">{escape(str(path))}</SourceFilename>',
                f"      <SourceBand>{band}</SourceBand>",
                f'      <SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>',
                f'      <DstRect xOff="{x!r}" yOff="{y!r}" xSize="{w}" ySize="{h}"/>',
                "      <NODATA>0</NODATA>",
                "    </ComplexSource>",
            ]
        lines.append("  </VRTRasterBand>")
    lines.append("</VRTDataset>")
    return "\n".join(lines) + "\n"

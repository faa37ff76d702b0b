"""Map packages: tiling an orthophoto, extracting features, the on-disk format, queries."""

from orthonav.mapdb.build import build_global_index, build_map
from orthonav.mapdb.corridor import corridor_tiles, cut_corridor, read_route
from orthonav.mapdb.globalindex import GlobalIndex
from orthonav.mapdb.package import FORMAT_VERSION, MapPackage, TileTable
from orthonav.mapdb.tiling import TileLayout, TilingConfig, layout_tiles, work_gsd_m

__all__ = [
    "FORMAT_VERSION",
    "GlobalIndex",
    "MapPackage",
    "TileLayout",
    "TileTable",
    "TilingConfig",
    "build_global_index",
    "build_map",
    "corridor_tiles",
    "cut_corridor",
    "layout_tiles",
    "read_route",
    "work_gsd_m",
]

"""Map packages: tiling an orthophoto, extracting features, terrain heights, the format, queries."""

from orthonav.mapdb.build import build_global_index, build_map
from orthonav.mapdb.corridor import corridor_tiles, cut_corridor, read_route
from orthonav.mapdb.dsm import attach_terrain
from orthonav.mapdb.globalindex import METHODS as INDEX_METHODS
from orthonav.mapdb.globalindex import GlobalIndex
from orthonav.mapdb.package import FORMAT_VERSION, MapPackage, TileTable
from orthonav.mapdb.terrain import Terrain
from orthonav.mapdb.tiling import TileLayout, TilingConfig, check_max_frame_px, layout_tiles, work_gsd_m

__all__ = [
    "FORMAT_VERSION",
    "INDEX_METHODS",
    "GlobalIndex",
    "MapPackage",
    "Terrain",
    "TileLayout",
    "TileTable",
    "TilingConfig",
    "attach_terrain",
    "build_global_index",
    "build_map",
    "check_max_frame_px",
    "corridor_tiles",
    "cut_corridor",
    "layout_tiles",
    "read_route",
    "work_gsd_m",
]

"""Pictures of results: trajectories over the map, benchmark plots, a fix's matches."""

from orthonav.viz.matches import draw_matches
from orthonav.viz.plots import (
    plot_error_cdf,
    plot_fixes,
    plot_mapbuild_bench,
    plot_mission,
    plot_mission_bench,
    plot_pair_matrix,
    plot_relocalize_bench,
    plot_speed_bench,
)

__all__ = [
    "draw_matches",
    "plot_error_cdf",
    "plot_fixes",
    "plot_mapbuild_bench",
    "plot_mission",
    "plot_mission_bench",
    "plot_pair_matrix",
    "plot_relocalize_bench",
    "plot_speed_bench",
]

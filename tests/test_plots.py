"""The pictures read at a glance: the mission plot and ``localize --plot`` over a real map package.

The inputs are synthetic flights and fixes over the terrain map (the plot functions only draw),
and each test asks what a reader would: is any marker under the legend, is the view the flight
and not the whole map, can the error axis be read, are rejected frames shown, do names collide.
"""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.colors import to_rgba
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from orthonav.camera import Camera
from orthonav.fusion.consistency import consistency_line
from orthonav.geo import GeoRaster, destination
from orthonav.mapdb import MapPackage
from orthonav.types import Fix, Pose, Prior
from orthonav.viz.axes import MIN_MARGIN, ZOOM_MARGIN, view_box
from orthonav.viz.fixes import _marker_boxes, fixes_figure, plot_fixes
from orthonav.viz.mission import mission_figure, plot_mission

PNG = b"\x89PNG\r\n\x1a\n"


def _latlon(package: MapPackage, fx: float, fy: float) -> tuple[float, float]:
    lat, lon = package.grid.pixel_to_latlon(fx * package.grid.width, fy * package.grid.height)
    return float(lat), float(lon)


@pytest.fixture(scope="module")
def flight(terrain_map: MapPackage) -> dict:
    """A straight flight over the middle third of the map: the filter 15 m north of the truth,
    the INS drifting east; every 5 s a frame (one rejected, one fix gated out), 1 Hz navigation."""
    start, target = _latlon(terrain_map, 0.35, 0.35), _latlon(terrain_map, 0.6, 0.62)
    times = np.arange(0.0, 61.0)
    nav = []
    for t in times:
        f = t / times[-1]
        lat, lon = start[0] + f * (target[0] - start[0]), start[1] + f * (target[1] - start[1])
        nav_lat, nav_lon = destination(lat, lon, 0.0, 15.0)
        ins_lat, ins_lon = destination(lat, lon, 90.0, 2.0 + 0.05 * t**2)
        nav.append(
            {
                "time_s": float(t), "true_lat": lat, "true_lon": lon, "nav_lat": float(nav_lat),
                "nav_lon": float(nav_lon), "nav_error_m": 15.0, "nav_sigma_m": 8.0 + 0.1 * (t % 5),
                "ins_lat": float(ins_lat), "ins_lon": float(ins_lon), "ins_error_m": 2.0 + 0.05 * t**2,
            }
        )  # fmt: skip
    steps = []
    for i, record in enumerate(nav[::5]):
        accepted = i != 3
        est = destination(record["true_lat"], record["true_lon"], 45.0, 0.5 + i) if accepted else None
        steps.append(
            {
                "time_s": record["time_s"], "true_lat": record["true_lat"], "true_lon": record["true_lon"],
                "est_lat": est and float(est[0]), "est_lon": est and float(est[1]),
                "error_m": 0.5 + i if accepted else None, "accepted": accepted, "fused": accepted and i != 6,
            }
        )  # fmt: skip
    return {"steps": steps, "nav": nav, "start": start, "target": target}


@pytest.fixture
def mission(terrain_map: MapPackage, flight: dict):
    fig = mission_figure(
        terrain_map, flight["steps"], flight["nav"], flight["start"], flight["target"], 40.0, "an outcome"
    )
    fig.canvas.draw()
    yield fig
    plt.close(fig)


def _marker_points(ax) -> np.ndarray:
    """Display coordinates of every marker drawn in ``ax``."""
    lines = [line for line in ax.get_lines() if line.get_marker() not in (None, "", "None", " ")]
    return np.concatenate([ax.transData.transform(line.get_xydata()) for line in lines])


def test_mission_legends_cover_no_marker(mission) -> None:
    for ax in mission.axes:
        box = ax.get_legend().get_window_extent()
        points = _marker_points(ax)
        assert len(points) > 0
        covered = [p for p in points if box.contains(*p)]
        assert not covered, (ax.get_title(), covered)


def test_mission_map_is_zoomed_to_the_flight(mission, terrain_map: MapPackage) -> None:
    ax = mission.axes[0]
    lines = [line.get_xydata() for line in ax.get_lines()]
    cols, rows = np.concatenate(lines).T
    (left, right), (bottom, top) = ax.get_xlim(), ax.get_ylim()
    assert left <= cols.min() and cols.max() <= right and top <= rows.min() and rows.max() <= bottom
    image, _ = terrain_map.preview()
    extent = max(np.ptp(cols), np.ptp(rows))
    margin = max(ZOOM_MARGIN * extent, MIN_MARGIN * max(image.shape[:2]))
    assert right - left <= extent + 2 * margin + 1e-6 and bottom - top <= extent + 2 * margin + 1e-6
    assert right - left < 0.6 * image.shape[1], "the whole map, not the flight"


def test_mission_map_true_track_over_the_filter_and_in_metres(mission) -> None:
    ax = mission.axes[0]
    lines = {line.get_label().split(" (")[0]: line for line in ax.get_lines()}
    truth, nav = lines["true track"], lines["navigation filter"]
    assert truth.get_zorder() > nav.get_zorder() and truth.get_linestyle() == "--"
    assert any(isinstance(artist, AnchoredSizeBar) for artist in ax.artists), "no scale bar"
    assert "east" in ax.get_xlabel() and "north" in ax.get_ylabel()
    labels = [t.get_text() for t in ax.get_xticklabels() + ax.get_yticklabels()]
    assert len(labels) >= 4 and all(np.isfinite([float(text) for text in labels]))
    assert "0" in labels  # metres from the start zone centre, which is on the map


def test_mission_error_axis_is_log_with_minor_ticks_and_plain_labels(mission) -> None:
    ax = mission.axes[1]
    assert ax.get_yscale() == "log"
    low, high = ax.get_ylim()
    minor = [v for v in ax.yaxis.get_minorticklocs() if low <= v <= high]
    assert len(minor) >= 5
    labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
    values = [float(text) for text in labels]  # plain numbers, no 10^n mathtext
    assert {2.0, 5.0, 20.0} <= set(values), labels
    assert low > 0 and high >= 3 * 2.0 + 0.05 * 60**2  # the INS's worst error is on the axis


def test_mission_map_says_how_far_each_estimate_ended_from_the_truth(mission) -> None:
    """At the map's scale a filter metres off is drawn on the true track: the legend says how far
    each estimate ended from the truth (the flight's own last errors), and the INS's end is named
    on the map, inside the view, however near its edge the track ends."""
    ax = mission.axes[0]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    ins_end = 2.0 + 0.05 * 60**2
    assert f"INS alone ({ins_end:.0f} m from the truth at the end)" in legend, legend
    assert "navigation filter (15 m from the truth at the end)" in legend, legend
    named = [t for t in ax.texts if t.get_text() == f"INS alone: {ins_end:.0f} m off"]
    assert len(named) == 1, [t.get_text() for t in ax.texts]
    box, inside = named[0].get_window_extent(), ax.get_window_extent()
    assert inside.x0 <= box.x0 and box.x1 <= inside.x1 and inside.y0 <= box.y0 and box.y1 <= inside.y1


def test_mission_error_lines_are_named_at_their_ends(mission) -> None:
    """Each error line carries its name and last value at its right end, in its own colour, and
    the INS's line is dotted where the filter's is solid: which is which reads without the legend."""
    ax = mission.axes[1]
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert lines["INS alone"].get_linestyle() == ":" and lines["filter error"].get_linestyle() == "-"
    names = {t.get_text(): t for t in ax.texts}
    for text, label, value in (
        ("filter: 15 m", "filter error", 15.0),
        ("INS alone: 182 m", "INS alone", 182.0),
    ):
        assert text in names, list(names)
        assert names[text].xy == pytest.approx((60.0, value))
        assert to_rgba(names[text].get_color()) == to_rgba(lines[label].get_color())


def test_plot_mission_writes_a_png(terrain_map: MapPackage, flight: dict, tmp_path: Path) -> None:
    out = plot_mission(
        terrain_map, flight["steps"], flight["nav"], flight["start"], flight["target"], tmp_path / "m.png"
    )
    assert out.read_bytes()[:8] == PNG


def test_view_box_frames_points_and_keeps_the_map_edges() -> None:
    left, right, bottom, top = view_box([100, 200], [300, 310], (1000, 1000))
    assert left < 100 and right > 200 and top < 300 and bottom > 310
    assert (bottom - top) >= 0.6 * (right - left) - 1e-9  # a line along x is not a sliver
    left, right, bottom, top = view_box([2, 50], [3, 40], (1000, 1000))
    assert left == 0.0 and top == 0.0  # the margin is not blank space beyond the map
    left, right, bottom, top = view_box([-50, 50], [10, 40], (1000, 1000))
    assert left < -50  # a vehicle that left the map stays in view


# --- localize --plot ------------------------------------------------------------------------------


def _fixes(package: MapPackage) -> tuple[list[tuple[str, Fix]], dict[str, Prior]]:
    """Ten fixes 8 m apart (their names would pile up), three rejected frames with a prior
    position (two reasons), one without."""
    lat0, lon0 = _latlon(package, 0.5, 0.5)
    fixes, priors = [], {}
    for i in range(10):
        lat, lon = destination(lat0, lon0, 100.0, 8.0 * i)
        pose = Pose(float(lat), float(lon), 300.0, 30.0, 0.0, 0.0, float(lat), float(lon))
        covariance = np.eye(2) * (9.0 if i == 5 else 1.0)  # one fix less sure than the others
        fixes.append((f"IMG_{i:04d}.JPG", Fix(True, pose=pose, covariance_enu_m2=covariance)))
    for i, reason in enumerate(("only 7 inliers (need 12)", "only 3 inliers (need 12)", "no homography")):
        lat, lon = destination(lat0, lon0, 200.0, 150.0 + 40.0 * i)
        name = f"REJ_{i}.JPG"
        fixes.append((name, Fix(False, reason=reason)))
        priors[name] = Prior(float(lat), float(lon), 300.0)
    fixes.append(("NOPRIOR.JPG", Fix(False, reason="no homography")))
    return fixes, priors


@pytest.fixture
def fixes_plot(terrain_map: MapPackage, camera: Camera):
    fixes, priors = _fixes(terrain_map)
    fig = fixes_figure(terrain_map, fixes, camera, priors)
    fig.canvas.draw()
    yield fig, fixes
    plt.close(fig)


def test_plot_fixes_draws_rejected_frames_with_their_reason(fixes_plot) -> None:
    fig, _ = fixes_plot
    ax = fig.axes[0]
    rejected = [line for line in ax.get_lines() if line.get_marker() == "x"]
    assert sum(len(line.get_xdata()) for line in rejected) == 3
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(
        text.replace("\n", " ") == "rejected (2), drawn at the prior: only 3-7 inliers (need 12)"
        for text in legend
    ), legend
    assert any("(1), drawn at the prior: no homography" in text.replace("\n", " ") for text in legend), legend
    assert "1 rejected frame(s) without a prior position" in ax.get_title()


def test_plot_fixes_legend_has_no_placeholder_and_no_cut_text(fixes_plot) -> None:
    """A legend says what happened in the frames' own numbers, whole (wrapped, not cut)."""
    fig, _ = fixes_plot
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    for text in legend:
        assert not re.search(r"\bn\b", text) and "..." not in text and "…" not in text, text


def test_plot_fixes_rings_the_least_sure_fix(fixes_plot) -> None:
    fig, _ = fixes_plot
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "least sure fix: IMG_0005.JPG (sigma 3.0 m)" in legend, legend
    # localize knows no reference position: nothing may claim an error or a worst fix.
    words = " ".join([*legend, fig.axes[0].get_title()]).lower()
    assert "worst" not in words and "error" not in words, words


def test_maps_have_a_north_arrow_and_the_origin_in_degrees(fixes_plot, mission) -> None:
    for ax in (fixes_plot[0].axes[0], mission.axes[0]):
        assert any(t.get_text() == "N" for t in ax.texts), "no north arrow"
        assert re.search(r"\(\d+\.\d{5}° [NS], \d+\.\d{5}° [EW]\)", ax.get_xlabel()), ax.get_xlabel()


def test_plot_fixes_outlines_footprints_and_keeps_the_legend_off_the_data(fixes_plot) -> None:
    fig, _ = fixes_plot
    ax = fig.axes[0]
    assert not ax.patches and not ax.collections, "footprints filled"
    outlines = [line for line in ax.get_lines() if len(line.get_xdata()) == 5]
    assert len(outlines) == 10
    box = ax.get_legend().get_window_extent()
    assert not [p for p in _marker_points(ax) if box.contains(*p)]


def test_plot_fixes_labels_do_not_overlap(fixes_plot) -> None:
    fig, _ = fixes_plot
    ax = fig.axes[0]
    renderer = fig.canvas.get_renderer()
    labels = [t for t in ax.texts if t.get_text().startswith("IMG_")]
    assert 1 < len(labels) < 10  # some names placed, the ones that would pile up left out
    boxes = [t.get_window_extent(renderer) for t in labels]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            assert not a.overlaps(b)
    markers = _marker_boxes(ax)
    assert not [
        (t.get_text(), m) for t, box in zip(labels, boxes, strict=True) for m in markers if box.overlaps(m)
    ]


def test_plot_fixes_writes_a_png_without_priors(terrain_map: MapPackage, camera: Camera, tmp_path) -> None:
    fixes, _ = _fixes(terrain_map)
    assert plot_fixes(terrain_map, fixes, camera, tmp_path / "f.png").read_bytes()[:8] == PNG


def test_the_interactive_map_is_one_offline_file(terrain_map, camera, tmp_path) -> None:
    """localize --plot's HTML: Leaflet inlined, the map's preview embedded, every fix a footprint
    and every rejected frame a point at its prior with its reason; nothing fetched from a server."""
    import json
    import re

    from orthonav.types import Fix, Pose, Prior
    from orthonav.viz.html import write_fixes_html

    lat, lon = (float(v) for v in terrain_map.grid.center_latlon)
    pose = Pose(lat, lon, 300.0, 30.0, 0.0, 0.0, lat, lon)
    fixes = [
        ("a.png", Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * 4.0, quality={"inliers": 50})),
        ("b.png", Fix(False, "only 3 inliers (need 12)")),
        ("c.png", Fix(False, "no prior to place it at")),
    ]
    out = write_fixes_html(terrain_map, fixes, camera, tmp_path / "fixes.html", {"b.png": Prior(lat, lon)})
    page = out.read_text()
    assert "L.map(" in page and "data:image/jpeg;base64," in page
    assert not re.search(r'(src|href)="https?://', page.replace('href="https://leafletjs.com"', ""))
    frames = json.loads(re.search(r"const frames = (\{.*?\});\n", page).group(1))["features"]
    assert [f["properties"]["name"] for f in frames] == ["a.png", "b.png"]
    assert frames[0]["geometry"]["type"] == "Polygon" and frames[0]["properties"]["sigma_m"] == 2.0
    assert frames[1]["properties"]["reason"] == "only 3 inliers (need 12)"


def test_the_filter_leaving_its_three_sigma_shows(terrain_map: MapPackage, flight: dict) -> None:
    """The 3-sigma bound is drawn in a colour of its own, not the filter error's, and where the
    error is above it the excess is filled: leaving the bound must be seen."""
    nav = [dict(r, nav_error_m=40.0) if 20 <= r["time_s"] <= 30 else r for r in flight["nav"]]
    fig = mission_figure(terrain_map, flight["steps"], nav, flight["start"], flight["target"])
    err_ax = fig.axes[1]
    lines = {line.get_label(): line for line in err_ax.get_lines()}
    error_colour = to_rgba(lines["filter error"].get_color())
    assert to_rgba(lines["filter 3-sigma"].get_color()) != error_colour
    for band in err_ax.collections:
        assert to_rgba(band.get_facecolor()[0], 1.0) != error_colour
    above = [c for c in err_ax.collections if c.get_label() == "error above 3-sigma"]
    assert above and above[0].get_paths(), "the error above its 3-sigma is not drawn"
    plt.close(fig)


def test_the_error_plot_says_how_consistent_the_filter_was(terrain_map: MapPackage, flight: dict) -> None:
    line = consistency_line(
        {"nav_beyond_1sigma_share": 0.4, "nav_beyond_2sigma_share": 0.25, "nav_beyond_3sigma_share": 0.2}
        | {"nav_nees_mean": 14.2}
    )
    fig = mission_figure(
        terrain_map, flight["steps"], flight["nav"], flight["start"], flight["target"], consistency=line
    )
    title = fig.axes[1].get_title()
    assert "1, 2, 3 sigma: 40%, 25%, 20%" in title and "NEES 14.2" in title, title
    fig.canvas.draw()
    heading, panel = fig.axes[1].title.get_window_extent(), fig.axes[1].get_window_extent()
    assert heading.width <= panel.width, "the title runs past its panel"
    plt.close(fig)


# --- bench real ---------------------------------------------------------------------------------


def _real_result(raster: GeoRaster, runs: int) -> dict:
    """Six photos over one corner of the orthophoto, ``runs`` runs of them."""
    cols, rows = np.linspace(100.0, 220.0, 6), np.linspace(120.0, 200.0, 6)
    lat, lon = raster.pixel_to_latlon(cols, rows)
    photos = [
        {"accepted": i % 3 != 0, "reference": [float(a), float(o)], "error_m": 0.5 * i}
        for i, (a, o) in enumerate(zip(lat, lon, strict=True))
    ]
    footprints = []
    for col, row in zip(cols, rows, strict=True):
        c, r = (
            np.array([col - 20, col + 20, col + 20, col - 20]),
            np.array([row - 15, row - 15, row + 15, row + 15]),
        )
        flat, flon = raster.pixel_to_latlon(c, r)
        footprints.append(np.column_stack([flat, flon]).tolist())
    per_photo = {f"run {i}": photos for i in range(runs)}
    return {"photos": 6, "dataset": "corner", "per_photo": per_photo, "footprints": footprints}


@pytest.mark.parametrize("runs", [1, 4])
def test_bench_real_picture_titles_apart_and_the_map_zoomed(
    terrain_tif: Path, terrain_raster, runs, monkeypatch
):
    """Suptitle, the map's title, the outcome legend and the colour bar never overlap (their
    bounding boxes), and the photos fill the map panel instead of a speck of the orthophoto."""
    from orthonav.viz import real

    figures = []
    monkeypatch.setattr(real, "save_figure", lambda fig, out: figures.append(fig) or out)
    real.plot_real_bench(_real_result(terrain_raster, runs), terrain_tif, Path("unused.png"))
    fig = figures[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    grid_ax, map_ax = fig.axes[:2]
    boxes = {
        "suptitle": fig._suptitle.get_window_extent(renderer),
        "map title": map_ax.title.get_window_extent(renderer),
        "legend": grid_ax.get_legend().get_window_extent(renderer),
        "colour bar": fig.axes[2].get_tightbbox(renderer),
    }
    names = list(boxes)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not boxes[a].overlaps(boxes[b]), (a, b)
    dots = map_ax.collections[0].get_offsets()
    spread = np.ptp(map_ax.transLimits.transform(dots), axis=0)
    assert spread.max() > 0.5, f"the photos span {spread} of the map panel"
    plt.close(fig)


def test_the_picture_of_a_result_sent_to_a_device_is_not_drawn_beside_it(tmp_path: Path) -> None:
    """``bench ... --out /dev/null`` puts its picture at ``/dev/null.png``: nothing is written
    there (a file in /dev, for whoever runs as root), while an ordinary result's picture is."""
    from orthonav.viz.axes import save_figure

    beside_device = Path("/dev/null.png")
    assert not beside_device.exists()
    save_figure(plt.figure(), beside_device)
    assert not beside_device.exists()
    ordinary = tmp_path / "result.png"
    save_figure(plt.figure(), ordinary)
    assert ordinary.stat().st_size > 0

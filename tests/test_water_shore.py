"""Lakes whose shore moved between the map's year and the frame's: over the prairie potholes of
the NAIP area a lake's water level changes between years and its shore moves by tens of metres.
A frame that sees little besides that shore is slid onto the map's shore, a pose tens of metres
off; the verification's land check finds where the frame's land fits best instead, and the fix's
sigma reaches that place: such a fix is refused, or within 3 sigma of the truth. The less the
frame's land agrees at the pose than the whole frame, the more the shore alone holds the pose, and
the more of the land search's reach the sigma claims (all of it where the land agrees far less)."""

from __future__ import annotations

from contextlib import ExitStack

import cv2
import numpy as np
import pytest
from conftest import CAMERA, write_naip_crop

from orthonav.errors import OrthonavError
from orthonav.frames import TruePose, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize.sources import open_fix_sources
from orthonav.localize.verify import VerifyConfig, shore_hold
from orthonav.mapdb import build_map
from orthonav.mapdb.tiling import TilingConfig
from orthonav.types import Prior

MAP_YEAR, FRAMES_YEAR = "20180716", "20200831"
# A plane's cruise over the lakes (the SITL plane's): the frame sees a few hundred metres.
ALT_M = 300.0
# Map pixels of the quarter-quad: a block of lakes whose shores moved between the two years.
WINDOW = (430, 130, 280, 260)
FRAMES = 48
# The SITL benchmark's wrong message: more than this many sigma, or metres, off.
WRONG_SIGMAS, WRONG_M = 3.0, 50.0
# Over the moved shores no fix claims less than half its error (a right fix's error is well within 2
# sigma; a pose the shore holds is off by what the shore moved, tens of metres).
CLAIMED_SIGMAS = 2.0
# A fix this many metres sure: one a moved shore has not widened.
SURE_M = 20.0
# A shore counts as moved where the two years' water differs this many map pixels from it.
MOVED_PX = 4
# Points this many map pixels from the crop's edges at least: a frame's footprint half.
EDGE_PX = 40


def _moved_shore_points(
    rng: np.random.Generator, raster: GeoRaster, other: GeoRaster
) -> list[tuple[float, float]]:
    """(lat, lon) of points on the frame year's shore where the map year's water differs
    around them: where a frame's shore and the map's are apart."""
    water, _ = raster.water_mask() or (None, 1.0)
    others, _ = other.water_mask() or (None, 1.0)
    assert water is not None and others is not None, "no water found in the NAIP crops"
    h = min(water.shape[0], others.shape[0])
    w = min(water.shape[1], others.shape[1])
    water, others = water[:h, :w].astype(np.uint8), others[:h, :w].astype(np.uint8)
    shore = cv2.morphologyEx(others, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    kernel = np.ones((2 * MOVED_PX + 1, 2 * MOVED_PX + 1), np.uint8)
    differs = cv2.dilate((water != others).astype(np.uint8), kernel) > 0
    stable = cv2.erode((water == others).astype(np.uint8), kernel) > 0
    rows, cols = np.nonzero(shore & differs & ~stable)
    keep = (rows > EDGE_PX) & (rows < h - EDGE_PX) & (cols > EDGE_PX) & (cols < w - EDGE_PX)
    rows, cols = rows[keep], cols[keep]
    assert len(rows) >= FRAMES, f"only {len(rows)} points on moved shores"
    chosen = rng.choice(len(rows), FRAMES, replace=False)
    return [tuple(map(float, other.pixel_to_latlon(cols[i] + 0.5, rows[i] + 0.5))) for i in chosen]


@pytest.fixture(scope="module")
def shore_fixes(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[float, float]]:
    """(error, sigma) in metres of each fix accepted over the moved shores, localized as fly does
    with the prior at the truth."""
    tmp_path = tmp_path_factory.mktemp("shores")
    map_tif = write_naip_crop(MAP_YEAR, WINDOW, tmp_path / "map.tif")
    frames_tif = write_naip_crop(FRAMES_YEAR, WINDOW, tmp_path / "frames.tif")
    package = build_map(map_tif, tmp_path / "map", CAMERA, TilingConfig(nominal_alt_m=ALT_M), progress=False)
    rng = np.random.default_rng(3)
    fixes: list[tuple[float, float]] = []
    with ExitStack() as stack:
        raster = stack.enter_context(GeoRaster(map_tif))
        frames = stack.enter_context(GeoRaster(frames_tif))
        source = open_fix_sources(stack, package, CAMERA).source
        for lat, lon in _moved_shore_points(rng, raster, frames):
            yaw = float(rng.uniform(0.0, 360.0))
            frame = render_frame(frames, CAMERA, TruePose(lat, lon, ALT_M, yaw, 0.0, 0.0))
            prior = Prior(
                lat, lon, ALT_M, yaw, 0.0, 0.0, sigma_m=15.0, heading_sigma_deg=3.0, attitude_sigma_deg=1.0
            )
            fix = source.localize(frame, prior)
            if fix.accepted:
                fixes.append((float(distance_m(lat, lon, fix.pose.lat, fix.pose.lon)), fix.sigma_m))
    return fixes


def test_frames_over_moved_lake_shores_are_rejected_or_within_their_sigma(
    shore_fixes: list[tuple[float, float]],
) -> None:
    """Every fix accepted is within 3 sigma (and 50 m) of the truth; some frames are fixed (the
    ground around the lakes is not refused)."""
    wrong = [(e, s) for e, s in shore_fixes if e > WRONG_SIGMAS * s or e > WRONG_M]
    assert not wrong, f"wrong fixes (error, sigma) over moved shores: {wrong}"
    assert len(shore_fixes) >= FRAMES // 4, f"only {len(shore_fixes)} of {FRAMES} frames fixed"


def test_fixes_a_moved_shore_holds_claim_no_less_than_half_their_error(
    shore_fixes: list[tuple[float, float]],
) -> None:
    """A frame whose shore, not its land, holds the pose claims the land search's reach as far as
    its land falls short: every fix is within 2 sigma of the truth; and the fixes its land holds
    keep a narrow sigma (a quarter of the frames are fixed within ``SURE_M``)."""
    overclaimed = [(e, s) for e, s in shore_fixes if e > CLAIMED_SIGMAS * s]
    assert not overclaimed, f"fixes (error, sigma) beyond {CLAIMED_SIGMAS} sigma: {overclaimed}"
    sure = [s for _, s in shore_fixes if s < SURE_M]
    assert len(sure) >= FRAMES // 4, f"only {len(sure)} of {FRAMES} frames fixed within {SURE_M} m"


def test_the_reach_a_shore_claims_grows_with_what_the_land_lacks() -> None:
    """Nothing where the land agrees as well as the whole frame, the whole reach at ``land_share``
    of it or less, more the less the land agrees in between (no step); a ``land_share`` that
    leaves no room to grade is refused by name."""
    share = VerifyConfig().land_share
    ratios = np.linspace(share, 1.0, 25)
    held = [shore_hold(0.3 * r, 0.3, share) for r in ratios]
    assert held[0] == 1.0 and held[-1] == 0.0 and shore_hold(0.4, 0.3, share) == 0.0
    assert shore_hold(0.0, 0.3, share) == 1.0 and shore_hold(-0.1, 0.0, share) == 1.0
    steps = np.diff(held)
    assert np.all(steps < 0.0) and np.max(-steps) < 2.0 / len(ratios), held
    with pytest.raises(OrthonavError, match="land_share"):
        VerifyConfig(land_share=1.0)

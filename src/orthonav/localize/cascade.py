"""The cascade fix source: each method where it is strong, then one calibrated decision.

Across dates, keypoints rarely survive (crops, water levels and sensors change) and, when few
do, chance matches can give a confident wrong pose; dense gradient correlation finds the place
robustly but with the prior's attitude and a coarse altitude. So, each stage timed:

1. candidates: the windows to search: the prior's position +- a few sigma, or, lost, around the
   best tiles of the map's global index (no index: around the keypoint localizer's fix over
   every tile, as the keypoint fix source alone would search); without a heading, each window
   at evenly spaced trial headings (the index searched at each, its best tiles at every one),
   and the best placement's heading searched again as a prior's would be (lost, a tile's
   centre region is such a trial at the prior's heading too);
2. coarse: gradient correlation (:class:`Corrector`) over each window -> placement and heading;
   its own gates are off by default: a weak peak is evidence for the acceptance, not a verdict;
3. fine: the keypoint :class:`Localizer` on the tiles under the coarse placement, with a prior
   centred there, which gives the full pose (on the map's DSM when it has one); where the coarse
   stage had to split a wide window (a low camera) or found nothing, over the window itself;
4. verification (:mod:`orthonav.localize.verify`): the orthophoto rendered at each pose found
   against the frame: the keypoint pose where the two agree, else the one that verifies better;
   a correlation pose taken is then refined to the frame's sub-pixel best place against that
   rendering, compared finer than the map's pixels (the coarse search places it to about one);
   where the acceptance model weighs it, the trained trunk's features are compared too;
5. acceptance (:mod:`orthonav.localize.acceptance`): every stage's evidence -> P(right) in
   ``quality["p_correct"]``; accepted above the model's threshold (chosen for false fixes).

Every stage is a small class usable alone; :class:`Cascade` chains them and is a ``FixSource``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend
from orthonav.frames import TruePose, check_frame_size, render_frame
from orthonav.frames.views import region_overhang_m
from orthonav.geo import GeoRaster, LocalFrame, distance_m
from orthonav.localize.acceptance import BLOCKS_FEATURE, AcceptanceModel
from orthonav.localize.candidates import tiles_near
from orthonav.localize.dense import (
    BACKBONES,
    GRADIENT,
    ORIENTATION,
    TRAINED,
    CorrectionConfig,
    Corrector,
    clamp,
    largest_search_factor,
    region_half_extents_m,
    trained_trunk,
)
from orthonav.localize.fallback import FALLBACK, Fallback, parse_chain
from orthonav.localize.keypoint import Localizer, LocalizerConfig, north_up_view
from orthonav.localize.verify import Verification, Verifier, VerifyConfig
from orthonav.mapdb import GlobalIndex, MapPackage
from orthonav.models import DenseTrunk
from orthonav.types import Fix, FixSource, Pose, Prior

CASCADE = "cascade"
KEYPOINTS = "keypoints"
CORRELATION = "correlation"
# In a proposal's quality: the P(right) of the model without the trunk, which decided it.
SURE_WITHOUT_TRUNK = "p_without_trunk"
# Every fix source a driver (fly, simulate) or localize can be asked for by name.
FIX_SOURCES = (CASCADE, KEYPOINTS, CORRELATION)
# The cascade's coarse correlations unless asked otherwise: the gradient magnitude's, then the
# gradients' orientation on the frames it rejects (more fixes on every dataset measured, no new
# false fix: docs/benchmarks/localize.md).
DEFAULT_COARSE_BACKBONE = f"{GRADIENT}{FALLBACK}{ORIENTATION}"
# ``--trunk-check`` by name: CascadeConfig.trunk_check's values.
TRUNK_CHECKS: dict[str, bool | None] = {"auto": None, "on": True, "off": False}


# --- 1. candidates -------------------------------------------------------------------------
@dataclass(frozen=True)
class CandidatesConfig:
    """Where the coarse stage searches."""

    # With a position prior: its position +- this many sigma (2.5: 95 % of a 2-D Gaussian).
    window_sigmas: float = 2.5
    # Lost (no position prior): windows around this many of the global index's best tiles, each
    # searched as a trial (over its centre region, without the alignment: lost_trial_regions), at
    # the prior's heading or at every trial heading, and the best trial again over its whole
    # window at the heading it found. A trial costs little, and the index's shortlist often
    # misses the frame's tile: the tile holding the frame's centre was among the 3 best for
    # 80-85 % of 2012-2020 frames on the 2020 map, among the 10 best for 95-100 %. bench
    # localize, ORB, cnn index, 400 cross-date frames, 3 tiles -> 10: no prior 51.0 -> 71.8 % of
    # centres within 25 m (1.6-2.0 -> 2.07 s a frame), the same one fix more than 25 m off;
    # with the compass heading (3 tiles searched over all their regions before, 1.01 s) 68.2 ->
    # 79.5 % in 0.62 s, one fix more than 25 m off (none before).
    index_candidates: int = 10
    # No heading in the prior: every window at this many evenly spaced headings, each searched
    # +- the correlation's turn range (9 deg); the best is searched again at the heading found,
    # with ECC. NAIP 2015 frames on the 2020 map, 200 m prior: 12 trials found the heading to
    # 1.5 deg and the place to 6 m for 8 of 8 frames; 8 trials for 6 of 8.
    heading_trials: int = 12
    # Lost, each of the index's best tiles is searched (at every trial heading without one) over
    # at most this many of its window's regions (the nearest its centre): the best tiles
    # overlap (by half a tile), and the heading found is then searched over the whole window.
    # NAIP, 2015 and 2020 maps, 10 frames of each other year without a heading: 33 of 80 fixed
    # with one region or all of them, in 3.4 instead of 6.1 s a frame.
    lost_trial_regions: int = 1
    # The heading the trials found is searched again with this sigma, as a prior's heading
    # (the bench's and the acceptance model's priors: 10 deg, sigma 5).
    found_heading_sigma_deg: float = 5.0

    def __post_init__(self) -> None:
        if self.window_sigmas <= 0 or self.index_candidates < 1:
            raise OrthonavError("cascade candidates: expected window_sigmas > 0 and index_candidates >= 1")
        if self.heading_trials < 1 or self.found_heading_sigma_deg <= 0 or self.lost_trial_regions < 1:
            raise OrthonavError(
                "cascade candidates: expected heading_trials >= 1, found_heading_sigma_deg > 0 and "
                "lost_trial_regions >= 1"
            )

    def trial_headings(self, prior: Prior) -> list[Prior]:
        """The prior itself where it has a heading, else one prior per trial heading, its heading
        sigma half the trials' spacing."""
        if prior.heading_deg is not None:
            return [prior]
        spacing = 360.0 / self.heading_trials
        return [
            replace(prior, heading_deg=k * spacing, heading_sigma_deg=0.5 * spacing)
            for k in range(self.heading_trials)
        ]


@dataclass(frozen=True)
class Window:
    """One search window: the prior moved to its centre with its sigma, and its radius."""

    prior: Prior
    radius_m: float
    source: str
    # Searched as a trial (without the alignment), and the best trial again over its whole
    # window at the heading it found: the trial headings of a prior without one, and a lost
    # frame's tile windows (at the prior's heading where it has one).
    heading_trial: bool = False
    # At most this many of its regions searched (the nearest its centre); None: all.
    max_regions: int | None = None
    # Its regions scouted and only the best correlated in full (CoarseConfig.region_shortlist):
    # a prior's window. Not a lost frame's tile windows: searched at the heading the trials found,
    # scouted they fixed 3 of the lost benchmark's 400 frames fewer.
    scout_regions: bool = False


class CandidatesStage:
    """The prior's window, or without a position the global index's best tiles, or without an
    index the place the keypoint ``localizer`` (if given) finds over every tile."""

    def __init__(
        self,
        camera: Camera,
        config: CandidatesConfig | None = None,
        package: MapPackage | None = None,
        backend: FeatureBackend | None = None,
        localizer: Localizer | None = None,
    ) -> None:
        self.camera = camera
        self.config = config or CandidatesConfig()
        self.package = package
        self.backend = backend
        self.localizer = localizer
        # The last lost frame (the array, a sample of its pixels: a capture buffer refilled in
        # place is another frame), its prior and its index windows: a chain's cascades share
        # this stage, and the frame one rejects is searched by the next over the same tiles
        # without describing it for the index again (about 0.2 s a frame).
        self._last_lost: tuple[np.ndarray, bytes, Prior, list[Window]] | None = None

    def windows(self, frame: np.ndarray, prior: Prior) -> list[Window]:
        """Windows to search; raises :class:`OrthonavError` with the reason there are none."""
        if prior.alt_agl_m is None:
            raise OrthonavError("the cascade needs the altitude above ground in the prior")
        if prior.has_position:
            radius_m = self.config.window_sigmas * prior.sigma_m
            trials = self.config.trial_headings(prior)
            windows = [Window(trial, radius_m, "prior", scout_regions=True) for trial in trials]
            return [_trial_window(window, prior) for window in windows]
        index = self.package.global_index if self.package is not None else None
        if index is None and self.localizer is not None:
            return [self._keypoint_window(frame, prior)]
        if index is None:
            raise OrthonavError(
                "lost (no position prior) and the map package has no global index to search "
                "(orthonav map index --method cnn)"
            )
        last, pixels = self._last_lost, frame[::8, ::8].tobytes()
        if last is not None and last[0] is frame and last[1] == pixels and last[2] == prior:
            return last[3]
        backend = self.backend if index.method == "vlad" else None
        if index.method == "vlad" and backend is None:
            backend = self.backend = self.package.create_backend()
        windows = self._index_windows(frame, prior, index, backend)
        self._last_lost = (frame, pixels, prior, windows)
        return windows

    def _index_windows(
        self, frame: np.ndarray, prior: Prior, index: GlobalIndex, backend: FeatureBackend | None
    ) -> list[Window]:
        """Windows over the index's best tiles, the frame described at each trial heading (or the
        prior's) and a tile ranked by its best score; each tile is then searched as a trial at
        every trial heading. The index finds the tile but not its heading: the heading a
        cross-date frame's own tile scored best at was within 15 deg of the truth for 1 to 3
        NAIP frames in 10."""
        trials = self.config.trial_headings(prior)
        count = self.config.index_candidates
        found: list[tuple[float, int]] = []
        for trial in trials:
            view = north_up_view(self.package, self.camera, frame, trial, backend)
            tiles, scores = index.search(view, count)
            found += [(float(score), int(tile)) for tile, score in zip(tiles, scores, strict=True)]
        chosen = list(dict.fromkeys(tile for _, tile in sorted(found, key=lambda item: -item[0])))
        as_trial = {"heading_trial": True, "max_regions": self.config.lost_trial_regions}
        return [
            replace(_trial_window(self._tile_window(heading, tile), prior), **as_trial)
            for tile in chosen[:count]
            for heading in trials
        ]

    def _tile_window(self, prior: Prior, tile: int) -> Window:
        """A window over one tile: centred on it, its radius the tile's half diagonal."""
        box = self.package.tiles.box_px[tile]
        lat, lon = self.package.grid.pixel_to_latlon(0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3]))
        radius_m = 0.5 * math.hypot(box[2] - box[0], box[3] - box[1]) * self.package.gsd_m
        return self._window(prior, float(lat), float(lon), radius_m, f"index tile {tile}")

    def _keypoint_window(self, frame: np.ndarray, prior: Prior) -> Window:
        """Lost on a map without a global index: a tile-sized window around the keypoint
        localizer's fix over every tile (slow on a large map, rare across dates, but what the
        keypoint fix source alone would do), so the later stages check what it found."""
        fix = self.localizer.localize(frame, prior)
        if not fix.accepted:
            raise OrthonavError(
                f"lost (no position prior), the map package has no global index (orthonav map index "
                f"--method cnn) and keypoints over every tile found no place: {fix.reason}"
            )
        radius_m = 0.5 * math.hypot(self.package.tile_px, self.package.tile_px) * self.package.gsd_m
        if prior.heading_deg is None:  # the keypoints' heading (their own rotation trials found it)
            prior = replace(prior, heading_deg=fix.pose.heading_deg)
        return self._window(prior, fix.pose.lat, fix.pose.lon, radius_m, "keypoints over every tile")

    def _window(self, prior: Prior, lat: float, lon: float, radius_m: float, source: str) -> Window:
        """A window of ``radius_m`` centred on (lat, lon), its sigma as a prior's window would have."""
        centred = replace(prior, lat=lat, lon=lon, sigma_m=radius_m / self.config.window_sigmas)
        return Window(centred, radius_m, source)


def _trial_window(window: Window, prior: Prior) -> Window:
    """``window`` marked as a heading trial (and named so) where ``prior`` had no heading."""
    if prior.heading_deg is not None:
        return window
    source = f"{window.source}, heading trial {window.prior.heading_deg:.0f} deg"
    return replace(window, source=source, heading_trial=True)


# --- 2. coarse -----------------------------------------------------------------------------
def _ungated() -> CorrectionConfig:
    """The Corrector with its peak-ratio and match-score gates open: the acceptance weighs them."""
    return CorrectionConfig(min_peak_ratio=1.0, min_match_score=-1.0)


@dataclass(frozen=True)
class CoarseConfig:
    """The Corrector's settings (gates open by default) and how far a window may stretch it."""

    correction: CorrectionConfig = field(default_factory=_ungated)
    # Never narrower: a region barely larger than the frame leaves no room for a rival peak,
    # the peak ratio saturates (1000) and the acceptance model, fitted on 200 m priors, takes
    # it for certainty (a filter's 30 m prior made it accept fixes 40-100 m off across dates).
    min_search_factor: float = 1.5
    # Beyond this the search region outgrows most maps and the correlation its peak.
    max_search_factor: float = 3.0
    # A window wider than one search region (a low camera, a vague prior) is searched as several
    # overlapping regions, at most this many (the nearest to the window's centre).
    max_regions: int = 9
    # More than twice ``trial_shortlist`` heading-trial windows (a lost frame without a heading:
    # the index's best tiles x the trial headings): every trial is first scouted at
    # ``scout_px`` (a quarter of the area, about 40 % of the time with its views),
    # and only the shortlisted trials with the best peaks are correlated at full size; fewer (a
    # prior's 12 trials) save too little to be worth a scout. None: no scouting. NAIP, 2015 and
    # 2020 maps, 10 lost frames of each other year: 32 of 80 fixed in 1.8 s a frame, against 33
    # in 3.4 s unscouted (160 px, 4 kept: 33 in 2.2 s; a 200 m prior's 12 trials scouted to 4:
    # 51 instead of 52, 325 instead of 409 ms).
    scout_px: int | None = 112
    trial_shortlist: int = 8
    # Likewise a window of more than ``region_shortlist`` regions (a low camera under a vague
    # prior: the drone-scale maps' frames at 50-150 m with a 200 m prior, 8-9 regions) has them
    # scouted, and only the shortlisted ones correlated at full size and aligned (a scout costs
    # about a third of a region's correlation and alignment: from 3 regions up it saves). bench
    # localize, ORB, drone-scale same-date frames: all 40 within 10 m either way, median 197
    # instead of 402 ms a frame; NAIP with a 200 m prior (one region a window) unchanged.
    region_shortlist: int = 2

    def __post_init__(self) -> None:
        if not 1.0 < self.min_search_factor <= self.max_search_factor <= 4.0 or self.max_regions < 1:
            raise OrthonavError(
                "cascade coarse: expected 1 < min_search_factor <= max_search_factor <= 4 and "
                "max_regions >= 1"
            )
        scout_ok = self.scout_px is None or 32 <= self.scout_px < self.correction.size_px
        if not scout_ok or min(self.trial_shortlist, self.region_shortlist) < 1:
            raise OrthonavError(
                f"cascade coarse: expected scout_px in 32..{self.correction.size_px - 1} (or None) "
                "and trial_shortlist, region_shortlist >= 1"
            )


class CoarseStage:
    """Dense gradient correlation over a window -> placement and heading (the Corrector).

    The window is searched as one region where one reaches it, else as a grid of overlapping
    regions; each fits on the map (a window reaching past the map's edge is searched over the
    ground the map has), and the placement whose peak stands out most wins. A heading trial's
    window is searched without the ECC alignment: trials are only ranked by their peaks, and the
    winner is searched again with it (NAIP cross-date frames, 12 trials: the same headings found,
    in 650 instead of 1070 ms).
    """

    def __init__(self, raster: GeoRaster, camera: Camera, config: CoarseConfig | None = None) -> None:
        self.camera = camera
        self.raster = raster
        self.config = config or CoarseConfig()
        self.corrector = Corrector(raster, camera, self.config.correction)

    @cached_property
    def trial_corrector(self) -> Corrector:
        """The Corrector of heading trials: no ECC alignment (its network shared)."""
        return self.corrector.variant(refine="none")

    @cached_property
    def scout_corrector(self) -> Corrector:
        """The Corrector of heading trials and regions at the scouting size (see CoarseConfig)."""
        return self.corrector.variant(size_px=self.config.scout_px, refine="none")

    def shortlist(self, frame: np.ndarray, windows: list[Window]) -> list[Window]:
        """The heading trials among ``windows`` worth a full-size correlation: all of them where
        they are few (see CoarseConfig), else those whose scouted peaks stand out most."""
        keep = self.config.trial_shortlist
        if self.config.scout_px is None or len(windows) <= 2 * keep or not windows[0].heading_trial:
            return windows
        return _best_scouted(windows, self.localize_each(frame, windows, self.scout_corrector), keep)

    def shortlist_regions(self, frame: np.ndarray, regions: list[Prior], factor: float) -> list[Prior]:
        """The regions of one window worth a full-size correlation: all of them where they are
        few (see CoarseConfig) or where no scout placed the frame (the scouts say nothing: at
        full size a region may still place it), else those whose scouted peaks stand out most."""
        keep = self.config.region_shortlist
        if self.config.scout_px is None or len(regions) <= keep:
            return regions
        scouted = self.scout_corrector.fixes_each(frame, regions, factor, "scouted")
        if all(fix.pose is None for fix in scouted):
            return regions
        return _best_scouted(regions, scouted, keep)

    def search_factor(self, window: Window) -> float:
        """The region must reach the window's radius (plus a pixel or two) along the footprint's
        short side, or the truth falls on the region's border and is rejected there; no
        narrower than the configured minimum, no wider than the maximum and than the map can
        hold."""
        short_m = min(self.camera.nadir_footprint_m(window.prior.alt_agl_m))
        reach_m = window.radius_m + 2.0 * self.raster.gsd_m
        wanted = max(self.config.min_search_factor, 1.0 + 2.0 * reach_m / short_m)
        return min(
            wanted,
            self.config.max_search_factor,
            largest_search_factor(self.raster, self.camera, window.prior),
        )

    def regions(self, window: Window) -> list[Prior]:
        """The centres (as priors) of the regions that cover ``window`` at its search factor (the
        nearest its centre first, as many as the window and the config allow)."""
        factor = self.search_factor(window)
        if factor <= 1.0:
            raise OrthonavError(
                f"the map {self.raster.path.name} is smaller than the camera's view at "
                f"{window.prior.alt_agl_m:.0f} m: nothing to search"
            )
        short_m = min(self.camera.nadir_footprint_m(window.prior.alt_agl_m))
        reach_m = 0.5 * (factor - 1.0) * short_m - 2.0 * self.raster.gsd_m
        if reach_m >= window.radius_m:
            return [self._onto_map(window.prior, window.prior.lat, window.prior.lon)]
        # Discs of radius ``reach`` on a square grid of side reach * sqrt(2) cover the plane.
        step = max(reach_m, self.raster.gsd_m) * math.sqrt(2.0)
        k = math.ceil(window.radius_m / step)
        offsets = [(e * step, n * step) for e in range(-k, k + 1) for n in range(-k, k + 1)]
        offsets = sorted(
            (o for o in offsets if math.hypot(*o) <= window.radius_m + reach_m), key=lambda o: math.hypot(*o)
        )
        local = LocalFrame.at(window.prior.lat, window.prior.lon)
        # Inside the map by the region's extents, less what it may reach past the edge.
        overhang_m = region_overhang_m(0.5 * (factor - 1.0) * short_m, window.prior.heading_deg or 0.0)
        extents_m = region_half_extents_m(self.raster, self.camera, window.prior, factor)
        inset_m = tuple(max(0.0, extent - overhang_m) for extent in extents_m)
        wanted = min(self.config.max_regions, window.max_regions or self.config.max_regions)
        centres: list[Prior] = []
        for east, north in offsets:
            if len(centres) == wanted:  # the offsets go outwards: the rest would be cut off
                break
            lat, lon = local.to_latlon(east, north)
            centre = self._onto_map(window.prior, float(lat), float(lon), inset_m)
            if all(distance_m(centre.lat, centre.lon, c.lat, c.lon) > 0.5 * reach_m for c in centres):
                centres.append(centre)
        return centres

    def localize(self, frame: np.ndarray, window: Window, corrector: Corrector | None = None) -> Fix:
        """The Corrector's best fix over ``window``; inputs it cannot work with are a rejection.
        ``corrector``: another than the stage's own (the default's, or its trials')."""
        return self.localize_each(frame, [window], corrector)[0]

    def localize_each(
        self, frame: np.ndarray, windows: Sequence[Window], corrector: Corrector | None = None
    ) -> list[Fix]:
        """:meth:`localize` of each window, their regions corrected together where they share a
        corrector and search factor (:meth:`Corrector.correct_each`: a lost frame's places at
        every trial heading share the frame view and the map read around each place)."""
        fixes: list[list[Fix]] = [[] for _ in windows]
        unsearched: dict[int, Fix] = {}
        searched: dict[int, int] = {}  # the regions each window was split into
        jobs: dict[tuple[Corrector, float], list[tuple[int, Prior]]] = {}
        for i, window in enumerate(windows):
            try:
                factor, regions = self.search_factor(window), self.regions(window)
            except OrthonavError as exc:
                unsearched[i] = Fix(False, f"no correlation: {exc}", method=self.corrector.method)
                continue
            chosen = corrector or (self.trial_corrector if window.heading_trial else self.corrector)
            searched[i] = len(regions)
            if chosen is self.corrector and window.scout_regions:
                regions = self.shortlist_regions(frame, regions, factor)
            jobs.setdefault((chosen, factor), []).extend((i, region) for region in regions)
        for (chosen, factor), regions in jobs.items():
            done = chosen.fixes_each(frame, [region for _, region in regions], factor, "no correlation")
            for (i, _), fix in zip(regions, done, strict=True):
                fixes[i].append(fix)
        return [
            unsearched[i] if i in unsearched else _best_region(found, searched[i])
            for i, found in enumerate(fixes)
        ]

    def _onto_map(
        self, prior: Prior, lat: float, lon: float, inset_m: tuple[float, float] = (0.0, 0.0)
    ) -> Prior:
        """``prior`` moved to (lat, lon), at least ``inset_m`` (east-west, north-south) inside the
        map (at least onto its pixels: the Corrector moves a region on the map inwards until it
        fits, it leaves one centred off the map where it is)."""
        col, row = self.raster.latlon_to_pixel(lat, lon)
        inset_col, inset_row = (max(0.5, inset / self.raster.gsd_m) for inset in inset_m)
        col = clamp(float(col), inset_col, self.raster.width - inset_col)
        row = clamp(float(row), inset_row, self.raster.height - inset_row)
        lat, lon = self.raster.pixel_to_latlon(col, row)
        return replace(prior, lat=float(lat), lon=float(lon))


def _best_scouted(scouted: list, fixes: list[Fix], keep: int) -> list:
    """The ``keep`` of ``scouted`` whose scouting ``fixes`` have the peaks that stand out most;
    of equal ones (none placed the frame) the first, as given (regions: the nearest the centre)."""
    peaks = [-fix.quality["peak_ratio"] if fix.pose is not None else 0.0 for fix in fixes]
    return [scouted[i] for i in np.argsort(peaks, kind="stable")[:keep]]


def _best_region(fixes: list[Fix], regions: int) -> Fix:
    """Of one window's regions (``regions`` of them, ``fixes`` those correlated), the placement
    whose peak stands out most (the first rejection where none placed the frame)."""
    placed = [fix for fix in fixes if fix.pose is not None]
    best = max(placed, key=lambda fix: fix.quality["peak_ratio"]) if placed else fixes[0]
    best.quality["regions"] = float(regions)
    return best


# --- 3. fine -------------------------------------------------------------------------------
LEARNED_KEYPOINT_DENSITY = 10.0  # frame keypoints per 1000 view pixels


@dataclass(frozen=True)
class FineConfig:
    """The keypoint localizer's settings and how it is pointed at the coarse placement."""

    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    # Tiles matched, the nearest to the coarse image centre first. None: one for a LightGlue-type
    # matcher (a pass costs the product of the two keypoint sets; the tile under a placement good
    # to a few map pixels holds the view), four for a classical one. Across NAIP dates (ALIKED,
    # 2020 map, 16 frames of each other year) one tile fixed as many frames as four, in 0.6 s
    # instead of 1.1 s.
    max_tiles: int | None = None
    # The frame's strongest keypoints matched there, per 1000 view pixels. None: 10 for a
    # LightGlue-type matcher, all for a classical one; the localizer's own density, where set,
    # wins. A NAIP view at 1000 m (about 40 000 pixels) keeps about 400 of ALIKED's 1024: over
    # the 20 NAIP year pairs, 64.7 against 65.7 % fixed, in 0.46 instead of 0.6 s a frame. A
    # Seneca photo's view (about 500 000 pixels) keeps all: a fixed 384 there cost 3 of 52
    # photos within 3 m.
    frame_keypoint_density: float | None = None
    # Guided matching (LocalizerConfig.guided) instead of the backend's matcher. None: for a
    # LightGlue-type matcher, whose attention over every pair of keypoints is mostly spent ruling
    # out places the coarse placement already excludes. ALIKED, 2020 map, 16 frames each of
    # 2009, 2012, 2015 and 2018 (and 2015 on the 2009 map): the same frames fixed give or take
    # one, the drone within 10 m as often or more, the fine stage in 120-150 ms instead of
    # 290-320 ms. ORB gains nothing and loses time (its binary descriptors are many and far apart).
    guided: bool | None = None
    # The localizer's prior around the coarse placement: sigma (at least) and heading sigma.
    min_sigma_m: float = 15.0
    heading_sigma_deg: float = 3.0
    # Keypoint and coarse poses this close (image centre and point under the drone) agree: the
    # keypoint pose is taken; farther apart, the one that verifies better.
    agree_m: float = 25.0
    # Where keypoints around the coarse placement find no pose and the map does not confirm the
    # placement either (its verification score under this), the keypoints search the prior's
    # window too, as for a window searched as several regions: a placement scoring about 0 is
    # another place, where keypoints cannot find the frame. Seneca's real photos, ORB: 40 -> 42
    # of 52 fixed with the attitude prior (two 70-76 m coarse misses, now within 0.8 m), 39 -> 41
    # without; ALIKED the same photos; none wrong. NAIP, 200 m prior, 400 cross-date frames: ORB
    # the same fixes, ALIKED one more (2009's map with 2012's frames to 90 %). 0.1 did the same.
    # Searching only the prior's window, not around such a placement first, cost ALIKED a Seneca
    # photo that keypoints near the placement had fixed.
    min_coarse_verify: float = 0.05

    def __post_init__(self) -> None:
        tiles_ok = self.max_tiles is None or self.max_tiles >= 1
        if not tiles_ok or self.min_sigma_m <= 0 or self.heading_sigma_deg <= 0 or self.agree_m <= 0:
            raise OrthonavError("cascade fine: expected max_tiles >= 1 and positive sigmas and agree_m")
        if not -1.0 <= self.min_coarse_verify <= 1.0:
            raise OrthonavError(
                "cascade fine: min_coarse_verify is a verification score in [-1, 1], "
                f"got {self.min_coarse_verify}"
            )


class FineStage:
    """The keypoint localizer restricted to the tiles under a coarse placement."""

    def __init__(
        self,
        package: MapPackage,
        camera: Camera,
        config: FineConfig | None = None,
        backend: FeatureBackend | None = None,
    ) -> None:
        self.package = package
        self.config = config or FineConfig()
        backend = backend or package.create_backend()
        learned = backend.padded_batching  # LightGlue-type matchers batch tiles
        # Tiles matched around a coarse placement (see FineConfig).
        self.max_tiles = self.config.max_tiles or (1 if learned else 4)
        localizer = self.config.localizer
        if localizer.frame_keypoint_density is None:
            density = self.config.frame_keypoint_density or (LEARNED_KEYPOINT_DENSITY if learned else None)
            localizer = replace(localizer, frame_keypoint_density=density)
        guided = learned if self.config.guided is None else self.config.guided
        localizer = replace(localizer, guided=localizer.guided or guided)
        self.localizer = Localizer(package, camera, localizer, backend)

    def localize(
        self, frame: np.ndarray, prior: Prior, coarse: Fix | None = None, candidates: np.ndarray | None = None
    ) -> Fix:
        """The keypoint fix around a coarse placement (its pose, altitude, heading and sigma), or
        without one (None) around the prior, as the localizer alone would search."""
        if coarse is None or coarse.pose is None:
            return self._localize(frame, prior, candidates)
        pose = coarse.pose
        sigma_m = max(self.config.min_sigma_m, coarse.sigma_m or 0.0)
        centred = replace(
            prior,
            lat=pose.lat,
            lon=pose.lon,
            alt_agl_m=pose.alt_agl_m,
            heading_deg=pose.heading_deg,
            sigma_m=sigma_m,
            heading_sigma_deg=self.config.heading_sigma_deg,
        )
        if candidates is None:
            near = tiles_near(self.package, pose.centre_lat, pose.centre_lon, 3.0 * sigma_m)
            candidates = near[: self.max_tiles]
        return self._localize(frame, centred, candidates)

    def _localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None) -> Fix:
        try:
            return self.localizer.localize(frame, prior, candidates=candidates)
        except OrthonavError as exc:
            return Fix(False, f"no keypoint fix: {exc}", method=self.package.backend_name)


# --- the cascade ---------------------------------------------------------------------------
@dataclass(frozen=True)
class CascadeConfig:
    """Every stage's config, and the decision's model and threshold."""

    candidates: CandidatesConfig = field(default_factory=CandidatesConfig)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    fine: FineConfig = field(default_factory=FineConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)
    # The acceptance model's JSON; None: the NAIP model shipped with orthonav for the map's
    # backend (ALIKED's own, ORB's for the others).
    acceptance_path: str | None = None
    # P(right) needed to accept; None: the model's own (chosen for < 0.5 % false fixes).
    threshold: float | None = None
    # Measure the trained trunk's agreement of frame and map at the pose taken (about 40 ms a
    # frame); None: where the acceptance model uses it, except where the backend's model without
    # it is already this sure (P(right) >= ``sure_without_trunk``): the shipped models' records
    # (both halves, ORB and ALIKED) have the same fixes and false fixes either way at 0.99, and
    # the trunk measured on about half of the cross-date frames instead of all. True: always.
    trunk_check: bool | None = None
    sure_without_trunk: float = 0.99
    # Measure the frame's blocks at the pose (Verification.blocks_at_pose, 2-5 ms a frame at
    # NAIP's scale); None: where a model that may decide weighs it. True: always (records to fit
    # a model on); False: never.
    blocks_check: bool | None = None
    # The shipped models that weigh the trunk were fitted on NAIP (5 m pixels, frames at 1000 m);
    # on orthophotos finer than this they are not used: on Seneca's real photos over a 5 cm map
    # they fixed 35 and 36 of 52 against 36 and 38 without them (none wrong either way).
    trunk_min_map_gsd_m: float = 1.0

    def __post_init__(self) -> None:
        if self.threshold is not None and not 0.0 < self.threshold < 1.0:
            raise OrthonavError(f"cascade threshold: expected a probability in (0, 1), got {self.threshold}")
        if not 0.0 < self.sure_without_trunk <= 1.0:
            raise OrthonavError(
                f"cascade sure_without_trunk: expected a probability in (0, 1], got {self.sure_without_trunk}"
            )
        if not self.trunk_min_map_gsd_m >= 0.0:
            raise OrthonavError(
                f"cascade trunk_min_map_gsd_m: expected metres >= 0, got {self.trunk_min_map_gsd_m}"
            )

    def to_dict(self) -> dict:
        return asdict(self)


class Cascade:
    """candidates -> coarse -> fine -> verification -> acceptance, for one camera and one map.

    ``raster`` is the orthophoto the map package was built from (opened by the caller; the
    coarse stage and the verification read it); ``backend`` as for :class:`Localizer`.
    """

    def __init__(
        self,
        package: MapPackage,
        raster: GeoRaster,
        camera: Camera,
        config: CascadeConfig | None = None,
        acceptance: AcceptanceModel | None = None,
        backend: FeatureBackend | None = None,
        candidates: CandidatesStage | None = None,
    ) -> None:
        """``candidates``: another cascade's stage over the same map and with the same config (a
        chain's first), shared; by default its own."""
        self.camera = camera
        self.config = config or CascadeConfig()
        self.fine = FineStage(package, camera, self.config.fine, backend)
        localizer = self.fine.localizer
        if candidates is not None and candidates.config != self.config.candidates:
            raise OrthonavError("cascade: a shared candidates stage needs the cascade's candidates config")
        self.candidates = candidates or CandidatesStage(
            camera, self.config.candidates, package, localizer.backend, localizer
        )
        self.coarse = CoarseStage(raster, camera, self.config.coarse)
        self.verifier = Verifier(raster, camera, self.config.verify)
        self._acceptance = acceptance
        self.backend_name = package.backend_name
        self.method = f"{CASCADE}:{package.backend_name}"
        # Why the fine stage's LightGlue-type matcher could not load at the warm-up (no torch);
        # None where it did, or was not tried.
        self.matcher_failure: str | None = None

    def localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        """A FixSource: frame (BGR uint8 of this camera) + prior -> accepted or rejected Fix.

        ``candidates``: tiles for the keypoint stage instead of those under the coarse placement.
        """
        return self.accept(self.propose(frame, prior, candidates))

    @property
    def acceptance(self) -> AcceptanceModel:
        """The decision's model, loaded on first use (proposals alone, as when fitting it, need none)."""
        if self._acceptance is None:
            self._acceptance = AcceptanceModel.load(
                self.config.acceptance_path,
                self.backend_name,
                trunk=self._trunk_loads(),
                coarse_backbone=self.config.coarse.correction.backbone,
            )
        return self._acceptance

    def propose(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        """Every stage but the decision: a not-yet-accepted Fix with its pose (if any stage found
        one) and all the evidence in its quality; ``reason`` says why there is no pose."""
        check_frame_size(frame, self.camera, "frame")
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        try:
            windows = self.candidates.windows(frame, prior)
        except OrthonavError as exc:
            return self._no_pose(str(exc), {}, timings, t0)
        timings["candidates_ms"] = _ms(t0)
        t = time.perf_counter()
        window, coarse = self._coarse(frame, windows)
        if window.heading_trial and coarse.pose is not None:
            window, coarse = self._at_found_heading(frame, window, coarse)
        timings["coarse_ms"] = _ms(t)
        quality = _coarse_evidence(coarse, len(windows))
        t = time.perf_counter()
        checks: dict[str, Verification] = {}
        if coarse.pose is not None:
            checks["coarse"] = self.verifier.verify(frame, coarse.pose, self.checks_blocks)
        timings["verify_ms"] = _ms(t)
        t = time.perf_counter()
        # A wide window split into regions: the coarse winner is less sure; keypoints search it all.
        single = coarse.pose is not None and coarse.quality.get("regions", 1.0) <= 1.0
        fine = self.fine.localize(frame, prior, coarse if single else None, candidates)
        if single and not fine.accepted and self._unconfirmed(prior, checks["coarse"]):
            fine = self.fine.localize(frame, prior, None, candidates)
        timings["fine_ms"] = _ms(t)
        quality.update(_fine_evidence(fine, coarse))
        found = {"coarse": coarse} if coarse.pose is not None else {}
        if fine.accepted:
            found["fine"] = fine
        if not found:
            # As the keypoint localizer's own rejections: the matches it found and rejected.
            quality["inliers"] = quality["fine_inliers"]
            rejected = self._no_pose(f"{coarse.reason}; {fine.reason}", quality, timings, t0)
            rejected.inliers_frame_px, rejected.inliers_map_px = fine.inliers_frame_px, fine.inliers_map_px
            return rejected
        t = time.perf_counter()
        if fine.accepted:
            checks["fine"] = self.verifier.verify(frame, fine.pose, self.checks_blocks)
        timings["verify_ms"] += _ms(t)
        fix = self._choose(found, checks, window, quality)
        if self.checks_trunk and not self._sure_without_trunk(quality):
            t = time.perf_counter()
            quality.update(self.verifier.trunk_agreement(frame, fix.pose, self.trunk))
            timings["trunk_ms"] = _ms(t)
        if not quality["fine_used"]:
            # Only the pose moves: the evidence stays the coarse pose's, as the acceptance was fitted.
            t = time.perf_counter()
            fix.pose = self.verifier.refine(frame, fix.pose)
            timings["refine_ms"] = _ms(t)
        timings["total_ms"] = _ms(t0)
        fix.timings_ms = timings
        return fix

    def accept(self, proposal: Fix) -> Fix:
        """The acceptance model's decision on a proposal (its probability in the quality)."""
        if proposal.pose is None:
            return proposal
        t = time.perf_counter()
        q = proposal.quality
        model = self.without_trunk if SURE_WITHOUT_TRUNK in q else self.acceptance
        p = model.probability(q)
        threshold = self.config.threshold or model.threshold
        proposal.quality["p_correct"] = p
        proposal.accepted = p >= threshold
        if not proposal.accepted:
            q = proposal.quality
            taken = "keypoint" if q["fine_used"] else "correlation"
            proposal.reason = (
                f"P(right) {p:.3f} below {threshold:.3f} ({taken} pose, verification "
                f"{q['verify_score']:.2f}, peak ratio {q.get('coarse_peak_ratio', 0.0):.2f})"
            )
        proposal.timings_ms["accept_ms"] = _ms(t)
        proposal.timings_ms["total_ms"] = proposal.timings_ms.get("total_ms", 0.0) + _ms(t)
        return proposal

    @cached_property
    def without_trunk(self) -> AcceptanceModel:
        """The backend's shipped model that does not weigh the trunk: it decides the proposals
        it is sure of before the trunk is measured."""
        return AcceptanceModel.load(None, self.backend_name)

    def _sure_without_trunk(self, quality: dict) -> bool:
        """Whether the model without the trunk accepts ``quality`` surely enough to decide (only
        for the shipped models, the check left to them: ``trunk_check`` None); marked in it.
        Never after the trained correlation: the models without the trunk were fitted on the
        gradient one's evidence (on the trained one's records the shortcut passed one false fix
        more), so there the model fitted on its own evidence decides every proposal."""
        if not self._may_decide_without_trunk:
            return False
        p = self.without_trunk.probability(quality)
        if p < self.config.sure_without_trunk:
            return False
        quality[SURE_WITHOUT_TRUNK] = p
        return True

    @cached_property
    def _may_decide_without_trunk(self) -> bool:
        """Whether the model without the trunk may decide proposals it is sure of
        (:meth:`_sure_without_trunk`)."""
        config = self.config
        if config.trunk_check is not None or config.acceptance_path is not None:
            return False
        return config.coarse.correction.backbone != TRAINED

    @cached_property
    def checks_blocks(self) -> bool:
        """Whether proposals carry the frame's blocks at the pose (``config.blocks_check``): by
        default where a model that may decide weighs them; so not after the gradient
        correlation, nor on maps finer than the trunk's models were fitted on."""
        if self.config.blocks_check is not None:
            return self.config.blocks_check
        deciding = [self.acceptance]
        if self.checks_trunk and self._may_decide_without_trunk:
            deciding.append(self.without_trunk)
        return any(BLOCKS_FEATURE in model.features for model in deciding)

    def _trunk_loads(self) -> bool:
        """Whether the shipped model that weighs the trained trunk's agreement decides: not
        turned off, a map as coarse as those it was fitted on, and the trunk loads (torch, or
        ONNX Runtime with the trunk's shipped or cached graph). Where not, the model without it
        does."""
        if self.config.acceptance_path is not None or self.config.trunk_check is False:
            return False
        if self.verifier.raster.gsd_m < self.config.trunk_min_map_gsd_m:
            return False
        return self.trunk_failure() is None

    def trunk_failure(self) -> str | None:
        """Why the trained trunk does not load (torch, or ONNX Runtime with its graph);
        None where it does. Loaded here, once, shared by every cascade of the process."""
        try:
            self.trunk  # noqa: B018
        except (OrthonavError, ImportError) as exc:
            return str(exc)
        return None

    @cached_property
    def checks_trunk(self) -> bool:
        """Whether proposals carry the trained trunk's agreement (``config.trunk_check``)."""
        asked, uses = self.config.trunk_check, self.acceptance.uses_trunk
        if asked is False and uses:
            raise OrthonavError(
                f"cascade: trunk_check is off but the acceptance model {self.config.acceptance_path} "
                "weighs the trained trunk's agreement; turn it on or choose a model without it"
            )
        return uses if asked is None else asked

    @cached_property
    def trunk(self) -> DenseTrunk:
        """The trained trunk the trunk agreement compares with, loaded on first use."""
        return trained_trunk(self.coarse.corrector.config.runtime)

    # --- steps ---------------------------------------------------------------------------
    def _coarse(self, frame: np.ndarray, windows: list[Window]) -> tuple[Window, Fix]:
        """The window whose correlation peak stands out most (of those that gave a placement;
        heading trials among the shortlisted)."""
        shortlisted = self.coarse.shortlist(frame, windows)
        results = list(zip(shortlisted, self.coarse.localize_each(frame, shortlisted), strict=True))
        placed = [r for r in results if r[1].pose is not None]
        if not placed:
            return results[0]
        return max(placed, key=lambda r: r[1].quality["peak_ratio"])

    def _unconfirmed(self, prior: Prior, coarse: Verification) -> bool:
        """Whether the map does not confirm a coarse placement (``FineConfig.min_coarse_verify``),
        so that keypoints which found nothing around it search the prior's window too. Not for a
        lost frame: its keypoints would search the whole map (slow on a large one)."""
        return prior.has_position and coarse.score < self.config.fine.min_coarse_verify

    def _at_found_heading(self, frame: np.ndarray, window: Window, coarse: Fix) -> tuple[Window, Fix]:
        """Trial headings placed the frame: its window searched again at the heading found, as a
        prior's heading would be, so the evidence is what the acceptance was fitted on (a trial
        up to half its spacing off correlates more weakly); the trial's where that finds none."""
        sigma = self.config.candidates.found_heading_sigma_deg
        found = replace(window.prior, heading_deg=coarse.pose.heading_deg, heading_sigma_deg=sigma)
        source = f"{window.source}, found {coarse.pose.heading_deg:.0f} deg"
        again = replace(window, prior=found, source=source, heading_trial=False, max_regions=None)
        fix = self.coarse.localize(frame, again)
        return (again, fix) if fix.pose is not None else (window, coarse)

    def _choose(
        self, found: dict[str, Fix], checks: dict[str, Verification], window: Window, quality: dict
    ) -> Fix:
        """The keypoint pose where it agrees with the coarse one (it is the full pose), else the
        pose that verifies better; the evidence of both, for the decision."""
        agree = quality.get("agreement_m", math.inf) <= self.config.fine.agree_m
        disagree = len(found) == 2 and not agree
        name = _pick(checks, agree)
        best, check = found[name], checks[name]
        used = name == "fine"
        quality.update(
            fine_used=float(used),
            fine_disagrees=float(disagree),
            verify_score=check.score,
            verify_valid=check.valid,
            verify_margin=check.margin,
            verify_offset_px=check.offset_px,
            verify_offset_m=check.offset_m,
            verify_orientation_score=check.orientation_score,
            verify_orientation_margin=check.orientation_margin,
            verify_blocks_at_pose=check.blocks_at_pose,
        )
        if len(found) == 2:
            other = checks["coarse" if used else "fine"]
            quality["verify_other_score"] = other.score
        # Under the names Fix.to_dict shows: the point matches behind the pose taken (none
        # behind a correlation pose: no picture of matches pretends to support it).
        quality["inliers"] = quality["fine_inliers"] if used else 0.0
        if used:
            quality["rmse_px"] = quality["fine_rmse_px"]
        offset_m = float(distance_m(window.prior.lat, window.prior.lon, best.pose.lat, best.pose.lon))
        quality.update(prior_offset_m=offset_m, prior_offset_sigma=offset_m / window.prior.sigma_m)
        covariance = best.covariance_enu_m2
        fix = Fix(False, pose=best.pose, covariance_enu_m2=covariance, quality=quality, method=self.method)
        if used:
            fix.inliers_frame_px, fix.inliers_map_px = best.inliers_frame_px, best.inliers_map_px
        return fix

    def _no_pose(self, reason: str, quality: dict, timings: dict, t0: float) -> Fix:
        timings["total_ms"] = _ms(t0)
        return Fix(False, reason, quality=quality, timings_ms=timings, method=self.method)


def _pick(checks: dict[str, Verification], agree: bool) -> str:
    """Which pose: the only one, the keypoint one where both agree, else the better verified."""
    if len(checks) == 1:
        return next(iter(checks))
    if agree:
        return "fine"
    return "fine" if checks["fine"].score >= checks["coarse"].score else "coarse"


def _coarse_evidence(coarse: Fix, windows: int) -> dict[str, float]:
    q = coarse.quality
    keys = ("peak_ratio", "peak_score", "match_score", "ecc_score", "heading_change_deg", "scale", "regions")
    evidence = {f"coarse_{k}": float(q[k]) for k in keys if k in q}
    return {"windows": float(windows), "coarse_pose": float(coarse.pose is not None), **evidence}


def _fine_evidence(fine: Fix, coarse: Fix) -> dict[str, float]:
    """The keypoint stage's numbers; where it found a pose, its agreement with the coarse one:
    the larger distance of the two image centres and of the two points under the drone (a
    keypoint pose with the right centre and a wrong tilt puts the drone far off at 1000 m)."""
    q = fine.quality
    out = {
        "fine_pose": float(fine.pose is not None),
        "fine_accepted": float(fine.accepted),
        "fine_matches": float(q.get("matches", 0)),
        "fine_inliers": float(q.get("inliers", 0)),
        "fine_inlier_ratio": float(q.get("inlier_ratio", 0.0)),
        "fine_tiles": float(q.get("tiles", 0)),
        "fine_keypoints": float(q.get("keypoints", 0)),
        "fine_quick": float(q.get("quick", 0.0)),  # matched by descriptors alone (LocalizerConfig.quick)
    }
    if fine.pose is not None:
        out["fine_rmse_px"] = float(q["rmse_px"])
    if fine.pose is not None and coarse.pose is not None:
        a, b = fine.pose, coarse.pose
        centres = float(distance_m(a.centre_lat, a.centre_lon, b.centre_lat, b.centre_lon))
        out["agreement_m"] = max(centres, float(distance_m(a.lat, a.lon, b.lat, b.lon)))
    return out


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


# --- the fix source by name ----------------------------------------------------------------
def map_orthophoto(package: MapPackage) -> Path:
    """The orthophoto ``package`` was built from, where its manifest records it, checked to be
    that raster (size and georeference as recorded); raises :class:`OrthonavError` saying why
    it cannot serve. Its checksum is not recomputed: hashing a large orthophoto at every start
    of a flight would cost more than a changed file that kept its size and georeference."""
    path, recorded = package.source_path, package.manifest["source"]
    if not path.is_file():
        raise OrthonavError(f"the map's orthophoto {path} (recorded in {package.path}) is not there")
    with GeoRaster(path) as raster:
        found = (raster.width, raster.height, [round(v, 6) for v in list(raster.transform)[:6]])
    expected = (recorded["width"], recorded["height"], [round(v, 6) for v in recorded["transform"]])
    if found != expected:
        raise OrthonavError(
            f"{path} is not the orthophoto {package.path} was built from: size and georeference "
            f"{found[:2]} {found[2]}, the map recorded {expected[:2]} {expected[2]}"
        )
    return path


@dataclass(frozen=True)
class ChosenFixSource:
    """The fix source a driver runs, its name, and what it should say once about it."""

    source: FixSource
    name: str
    # Why it is not the one asked for (the default's fallback), else "".
    fallback: str = ""
    # What the user should know about how it searches (e.g. frames without a position prior).
    note: str = ""
    # The orthophoto it reads (None for keypoints alone): what :func:`warm_up` renders from.
    raster: GeoRaster | None = None


def open_fix_source(
    stack: ExitStack,
    package: MapPackage,
    camera: Camera,
    name: str | None = None,
    orthophoto: Path | None = None,
    localizer: LocalizerConfig | None = None,
    backend: FeatureBackend | None = None,
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    rasters: dict[Path, GeoRaster] | None = None,
    trunk_check: bool | None = None,
) -> ChosenFixSource:
    """The fix source ``name`` over ``package``: the cascade, the keypoint localizer alone, or
    dense gradient correlation; None: the cascade where the map's orthophoto is there, else
    keypoints (``fallback`` says why). Correlation and the cascade read ``orthophoto`` (default:
    the map's own, :func:`map_orthophoto`), opened on ``stack``; ``localizer`` configures the
    keypoint matching (alone or as the cascade's fine stage), ``coarse_backbone`` the cascade's
    correlation, ``trunk_check`` its :attr:`CascadeConfig.trunk_check`. ``rasters``:
    orthophotos already open, by resolved path, shared by the maps of one flight (their
    in-memory views are built once); one opened here is added."""
    if name is not None and name not in FIX_SOURCES:
        raise OrthonavError(f"--fix-source {name!r}: expected one of {', '.join(FIX_SOURCES)}")
    fallback = ""
    if name != KEYPOINTS and orthophoto is None:
        try:
            orthophoto = map_orthophoto(package)
        except OrthonavError as exc:
            if name is not None:
                raise OrthonavError(f"--fix-source {name}: {exc}") from None
            fallback = f"fix source keypoints instead of the cascade: {exc}"
    if name is None:
        name = CASCADE if not fallback else KEYPOINTS
    raster = None if name == KEYPOINTS else _open_shared(stack, orthophoto, rasters)
    source = make_fix_source(name, package, camera, raster, localizer, backend, coarse_backbone, trunk_check)
    if name == KEYPOINTS:
        return ChosenFixSource(source, name, fallback)
    return ChosenFixSource(source, name, note=_lost_note(package, name), raster=raster)


def _open_shared(stack: ExitStack, path: Path, rasters: dict[Path, GeoRaster] | None) -> GeoRaster:
    """The orthophoto at ``path``: the one in ``rasters`` already open there, else opened on
    ``stack`` (and added to ``rasters`` where given)."""
    if rasters is None:
        return stack.enter_context(GeoRaster(path))
    key = Path(path).resolve()
    if key not in rasters:
        rasters[key] = stack.enter_context(GeoRaster(path))
    return rasters[key]


def warm_up(source: FixSource, raster: GeoRaster, camera: Camera, alt_agl_m: float) -> Fix:
    """``source``'s fix of a frame rendered from ``raster`` at its centre, straight down from
    ``alt_agl_m``, heading north: what the first frame of a flight would otherwise pay for is
    paid at start-up instead (the map's in-memory views, its tiles and terrain, a learned
    backend's sessions: on a Seneca photo, 1.0 s against 0.2 s for the next with ORB, 4 s more
    than the next with ALIKED). The fix is of the map's own picture: information, not a check of the
    flight's camera. Every source of a :class:`Fallback` is warmed (the later ones answer only
    frames the first rejects, and the first such frame should not pay for them); the first
    source's fix is returned."""
    lat, lon = raster.center_latlon
    frame = render_frame(raster, camera, TruePose(lat, lon, alt_agl_m, 0.0))
    prior = Prior(lat, lon, alt_agl_m, 0.0, sigma_m=10.0, heading_sigma_deg=5.0)
    sources = _leaves(source)
    fixes = [each.localize(frame, prior) for each in sources]
    for each in sources:
        if isinstance(each, Cascade):
            _warm_matcher(each, frame)
            each.verifier.warm(Pose(lat, lon, alt_agl_m, 0.0, 0.0, 0.0, lat, lon))
    return fixes[0]


def _leaves(source: FixSource) -> list[FixSource]:
    """The fix sources a :class:`Fallback` asks in turn, through nested ones (``fly --fallback``
    over maps whose fix source is itself a chain of cascades)."""
    if isinstance(source, Fallback):
        return [leaf for each in source.sources for leaf in _leaves(each)]
    return [source]


def _warm_matcher(cascade: Cascade, frame: np.ndarray) -> None:
    """A LightGlue-type matcher loads on its first match (torch and its weights: 4.1 s against
    0.7 s for the next, ALIKED's LightGlue on a 2-core CPU). The warm-up frame, placed surely
    enough for guided matching, never asks for it; the first frame with a wide prior (a flight's
    start, a window split into regions) would. Matched once here, a corner of the frame with
    itself (the load is the cost). Where it cannot load (no torch), such frames go without a
    keypoint pose and say why, as before; ``cascade.matcher_failure`` says it at start-up."""
    backend = cascade.fine.localizer.backend
    if not backend.padded_batching:
        return
    features = backend.extract(cv2.cvtColor(frame[:256, :256], cv2.COLOR_BGR2GRAY))
    try:
        backend.match(features, features)
    except OrthonavError as exc:
        cascade.matcher_failure = str(exc)


def learned_parts(source: FixSource) -> list[str]:
    """Where each cascade of a flight's fix source computes what, after :func:`warm_up`: its
    keypoints, its LightGlue, the trained trunk's check and the global index's network, and
    what a part that cannot load costs. A companion without torch learns it at start-up, not
    from its first rejected frames."""
    lines = [line for each in _leaves(source) if isinstance(each, Cascade) for line in _parts(each)]
    return list(dict.fromkeys(lines))  # the cascades of a chain share their parts: said once


def _parts(cascade: Cascade) -> list[str]:
    backend = cascade.fine.localizer.backend
    lines = [f"{cascade.method}: keypoints on {backend.engine}"]
    if backend.matcher_engine is not None:
        lines.append(f"{cascade.method}: LightGlue on {backend.matcher_engine}")
    if backend.padded_batching and cascade.matcher_failure is not None:
        fallback = "get no keypoint pose"
        if cascade.fine.localizer.descriptors_first:
            fallback = "are matched by mutual nearest descriptors alone (no keypoint pose where rejected)"
        lines.append(
            f"{cascade.method}: no LightGlue ({cascade.matcher_failure}); frames whose search "
            f"splits into regions, or whose placement is too loose for guided matching, {fallback}"
        )
    lines.append(f"{cascade.method}: trained trunk's check {_trunk_part(cascade)}")
    index = cascade.candidates.package.global_index
    if index is not None and index.method == "cnn":
        lines.append(f"{cascade.method}: global index's network on {_runs_on(index.network)}")
    return lines


def _trunk_part(cascade: Cascade) -> str:
    config = cascade.config
    if not cascade.checks_trunk:
        if config.trunk_check is False:
            return "off (--trunk-check off)"
        if config.acceptance_path is not None:
            return "off (the acceptance model given does not weigh it)"
        gsd_m = cascade.verifier.raster.gsd_m
        if gsd_m < config.trunk_min_map_gsd_m:
            return f"off (the map's {gsd_m:.2f} m pixels: finer than its models were fitted on)"
    failure = cascade.trunk_failure()
    if failure is not None:
        return f"off: the trunk does not load ({failure})"
    return f"on {_runs_on(cascade.trunk)}"


def _runs_on(network: object) -> str:
    """ONNX Runtime and the graph's file, or torch."""
    path = getattr(network, "path", None)
    return f"ONNX Runtime ({path.name})" if isinstance(path, Path) else "torch"


def make_fix_source(
    name: str,
    package: MapPackage,
    camera: Camera,
    raster: GeoRaster | None = None,
    localizer: LocalizerConfig | None = None,
    backend: FeatureBackend | None = None,
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    trunk_check: bool | None = None,
) -> FixSource:
    """The fix source ``name`` over ``package``, built the one way every driver and benchmark
    builds it: the keypoint localizer, gradient correlation (a lost frame searched around the
    map's global index) or the cascade with ``localizer`` as its fine stage and
    ``coarse_backbone`` as its correlation's (``trained``: seed 003's CNN correlation, the trunk
    shipped with orthonav; ``gradient>trained``: a cascade with each, the second asked only
    where the first rejects the frame, :class:`Fallback`) and ``trunk_check`` as its
    :attr:`CascadeConfig.trunk_check`. Correlation and the cascade read ``raster``, the map's
    orthophoto opened by the caller."""
    if name == KEYPOINTS:
        return Localizer(package, camera, localizer, backend)
    if name not in FIX_SOURCES:
        raise OrthonavError(f"fix source {name!r}: expected one of {', '.join(FIX_SOURCES)}")
    if raster is None:
        raise OrthonavError(f"fix source {name}: needs the map's orthophoto")
    if name == CORRELATION:
        use_terrain = (localizer or LocalizerConfig()).use_terrain
        correction = CorrectionConfig(backbone="gradient", use_terrain=use_terrain)
        return Corrector(raster, camera, correction, package=package)
    backbones = coarse_backbones(coarse_backbone)
    fine = FineConfig(localizer=localizer or LocalizerConfig())
    backend = backend or package.create_backend()  # one for every cascade of a chain
    cascades: list[Cascade] = []
    for backbone in backbones:  # one candidates stage: a lost frame described for the index once
        shared = cascades[0].candidates if cascades else None
        config = cascade_config(backbone, trunk_check, fine)
        cascades.append(Cascade(package, raster, camera, config, backend=backend, candidates=shared))
    failure = cascades[0].trunk_failure() if trunk_check else None
    if failure:
        # Asked to measure it on every proposal: fail now rather than on a flight's first frame.
        raise OrthonavError(
            f"--trunk-check on: the trained trunk does not load ({failure}); --trunk-check auto "
            "measures it only where it loads"
        )
    if len(cascades) == 1:
        return cascades[0]
    return Fallback(cascades, [f"{CASCADE}-{backbone}" for backbone in backbones])


def coarse_backbones(spec: str) -> list[str]:
    """``"gradient>trained"`` -> ``["gradient", "trained"]``: the cascade's coarse correlations,
    tried in order on the frames the one before rejects; each name checked."""
    backbones = parse_chain(spec, "coarse backbone")
    unknown = [name for name in backbones if name not in BACKBONES]
    if unknown:
        raise OrthonavError(
            f"coarse backbone {spec!r}: expected one of {', '.join(BACKBONES)}, or several joined "
            f"by '{FALLBACK}' (e.g. gradient{FALLBACK}trained)"
        )
    return backbones


def trunk_check_option(value: str) -> bool | None:
    """``--trunk-check`` (auto, on, off) as :attr:`CascadeConfig.trunk_check`."""
    if value not in TRUNK_CHECKS:
        raise OrthonavError(f"--trunk-check {value!r}: expected one of {', '.join(TRUNK_CHECKS)}")
    return TRUNK_CHECKS[value]


def cascade_config(
    backbone: str = GRADIENT, trunk_check: bool | None = None, fine: FineConfig | None = None
) -> CascadeConfig:
    """The cascade's config with ``backbone`` as its coarse correlation (its gates open, as
    every cascade's) and ``trunk_check`` as :attr:`CascadeConfig.trunk_check`."""
    coarse = CoarseConfig(correction=replace(_ungated(), backbone=backbone))
    return CascadeConfig(coarse=coarse, fine=fine or FineConfig(), trunk_check=trunk_check)


def _lost_note(package: MapPackage, name: str) -> str:
    """How the fix source ``name`` answers a frame without a position prior on this map."""
    if package.manifest.get("global_index") is not None:
        return "frames without a position prior are searched around the map's global index"
    how = "searched by keypoints over every tile" if name == CASCADE else "rejected"
    return (
        f"the map has no global index: frames without a position prior are {how} "
        "(orthonav map index --method cnn: fast, and robust across dates)"
    )

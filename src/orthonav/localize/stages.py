"""The cascade's search stages, each a small class usable alone (:mod:`orthonav.localize.cascade`
chains them, verifies and decides):

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
   stage had to split a wide window (a low camera) or found nothing, over the window itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend
from orthonav.frames.views import region_overhang_m
from orthonav.geo import GeoRaster, LocalFrame, distance_m
from orthonav.localize.candidates import tiles_near
from orthonav.localize.dense import (
    CorrectionConfig,
    Corrector,
    clamp,
    largest_search_factor,
    region_half_extents_m,
)
from orthonav.localize.keypoint import Localizer
from orthonav.localize.keypoint_config import LocalizerConfig
from orthonav.localize.timing import FrameDeadline
from orthonav.mapdb import GlobalIndex, MapPackage
from orthonav.types import Fix, Prior


# --- 1. candidates -------------------------------------------------------------------------
@dataclass(frozen=True)
class CandidatesConfig:
    """Where the coarse stage searches."""

    # With a position prior: its position +- this many sigma (2.5: the chi-square 0.95 quantile
    # of two degrees of freedom).
    window_sigmas: float = 2.5
    # Lost (no position prior): windows around this many of the global index's best tiles, each
    # searched as a trial (over its centre region, without the alignment: lost_trial_regions), at
    # the prior's heading or at every trial heading, and the best trial again over its whole
    # window at the heading it found. A trial costs little, and the index's shortlist often
    # misses the frame's tile among its first few but rarely among its first ten: ten fix many
    # more lost frames than three, at about the same cost (CHANGELOG, 2026-12-06).
    index_candidates: int = 10
    # No heading in the prior: every window at this many evenly spaced headings, each searched
    # +- the correlation's turn range (9 deg); the best is searched again at the heading found,
    # with ECC. Twelve trials overlap their turn ranges enough to find every frame's heading
    # where fewer missed some.
    heading_trials: int = 12
    # Lost, each of the index's best tiles is searched (at every trial heading without one) over
    # at most this many of its window's regions (the nearest its centre): the best tiles
    # overlap (by half a tile), and the heading found is then searched over the whole window:
    # one region a tile fixes as many lost frames as all of them, in about half the time.
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
        # without describing it for the index again.
        self._last_lost: tuple[np.ndarray, bytes, Prior, list[Window]] | None = None

    def windows(self, frame: np.ndarray, prior: Prior, deadline: FrameDeadline | None = None) -> list[Window]:
        """Windows to search; raises :class:`OrthonavError` with the reason there are none (a
        lost frame's index search stopped by ``deadline``: :class:`DeadlineSpent`)."""
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
        windows = self._index_windows(frame, prior, index, backend, deadline)
        self._last_lost = (frame, pixels, prior, windows)
        return windows

    def _index_windows(
        self,
        frame: np.ndarray,
        prior: Prior,
        index: GlobalIndex,
        backend: FeatureBackend | None,
        deadline: FrameDeadline | None = None,
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
            if deadline is not None:
                deadline.check("the global index's search")
            view = self.package.frame_view(self.camera, frame, trial, backend)
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
def ungated() -> CorrectionConfig:
    """The Corrector with its peak-ratio and match-score gates open and its rival humps out of
    the covariance: the acceptance weighs them, and takes a correlation pose only where it is
    sure of the place."""
    return CorrectionConfig(min_peak_ratio=1.0, min_match_score=-1.0, rival_weight=None)


@dataclass(frozen=True)
class CoarseConfig:
    """The Corrector's settings (gates open by default) and how far a window may stretch it."""

    correction: CorrectionConfig = field(default_factory=ungated)
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
    # ``scout_px`` (a quarter of the area, so a fraction of the time with its views),
    # and only the shortlisted trials with the best peaks are correlated at full size; fewer (a
    # prior's 12 trials) save too little to be worth a scout. None: no scouting. Scouted, a lost
    # frame costs less and the same frames are fixed (measured: docs/benchmarks/localize.md).
    scout_px: int | None = 112
    trial_shortlist: int = 8
    # Likewise a window of more than ``region_shortlist`` regions (a low camera under a vague
    # prior: the drone-scale maps' frames at 50-150 m with a 200 m prior, 8-9 regions) has them
    # scouted, and only the shortlisted ones correlated at full size and aligned (a scout costs
    # about a third of a region's correlation and alignment: from 3 regions up it saves); the
    # drone-scale frames are placed as well either way, in about half the time.
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
    window is searched without the ECC alignment: trials are only ranked by their peaks, which the
    alignment hardly moves, and the winner is searched again with it, so the search pays for one
    alignment instead of one per trial.
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

    def shortlist(
        self, frame: np.ndarray, windows: list[Window], deadline: FrameDeadline | None = None
    ) -> list[Window]:
        """The heading trials among ``windows`` worth a full-size correlation: all of them where
        they are few (see CoarseConfig), else those whose scouted peaks stand out most."""
        keep = self.config.trial_shortlist
        if self.config.scout_px is None or len(windows) <= 2 * keep or not windows[0].heading_trial:
            return windows
        scouted = self.localize_each(frame, windows, self.scout_corrector, deadline)
        return _best_scouted(windows, scouted, keep)

    def shortlist_regions(
        self, frame: np.ndarray, regions: list[Prior], factor: float, deadline: FrameDeadline | None = None
    ) -> list[Prior]:
        """The regions of one window worth a full-size correlation: all of them where they are
        few (see CoarseConfig) or where no scout placed the frame (the scouts say nothing: at
        full size a region may still place it), else those whose scouted peaks stand out most.
        The scouting first checks ``deadline`` (:class:`DeadlineSpent` where it is spent)."""
        keep = self.config.region_shortlist
        if self.config.scout_px is None or len(regions) <= keep:
            return regions
        if deadline is not None:
            deadline.check("the scouting of the coarse regions")
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
        self,
        frame: np.ndarray,
        windows: Sequence[Window],
        corrector: Corrector | None = None,
        deadline: FrameDeadline | None = None,
    ) -> list[Fix]:
        """:meth:`localize` of each window, their regions corrected together where they share a
        corrector and search factor (:meth:`Corrector.correct_each`: a lost frame's places at
        every trial heading share the frame view and the map read around each place). Each
        such batch first checks ``deadline`` (:class:`DeadlineSpent` where it is spent)."""
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
                regions = self.shortlist_regions(frame, regions, factor, deadline)
            jobs.setdefault((chosen, factor), []).extend((i, region) for region in regions)
        for (chosen, factor), regions in jobs.items():
            if deadline is not None:
                deadline.check("the coarse correlation")
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
    # to a few map pixels holds the view), four for a classical one. Across dates one tile
    # fixed as many frames as four with ALIKED, in about half the time.
    max_tiles: int | None = None
    # The frame's strongest keypoints matched there, per 1000 view pixels. None: 10 for a
    # LightGlue-type matcher, all for a classical one; the localizer's own density, where set,
    # wins. A density, not a count: a small view (NAIP's at 1000 m) keeps a few hundred of
    # ALIKED's keypoints, about as many fixes in less time; a large one (a Seneca photo's) keeps
    # them all, where a fixed count cost photos placed within 3 m.
    frame_keypoint_density: float | None = None
    # Guided matching (LocalizerConfig.guided) instead of the backend's matcher. None: for a
    # LightGlue-type matcher, whose attention over every pair of keypoints is mostly spent ruling
    # out places the coarse placement already excludes: with ALIKED across dates the same frames
    # are fixed, give or take one, the drone within 10 m as often or more, the fine stage in
    # about half the time. ORB gains nothing and loses time (its binary descriptors are many and
    # far apart).
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
    # another place, where keypoints cannot find the frame (on the real photos, coarse misses
    # tens of metres off were then fixed by keypoints; no fix went wrong). Searching only the
    # prior's window, not around such a placement first, cost photos that keypoints near the
    # placement had fixed.
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
        self,
        frame: np.ndarray,
        prior: Prior,
        coarse: Fix | None = None,
        candidates: np.ndarray | None = None,
        deadline: FrameDeadline | None = None,
    ) -> Fix:
        """The keypoint fix around a coarse placement (its pose, altitude, heading and sigma), or
        without one (None) around the prior, as the localizer alone would search; ``deadline``
        the frame's, which the localizer keeps to (:meth:`Localizer.localize`)."""
        if coarse is None or coarse.pose is None:
            return self._localize(frame, prior, candidates, deadline)
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
        return self._localize(frame, centred, candidates, deadline)

    def _localize(
        self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None, deadline: FrameDeadline | None
    ) -> Fix:
        try:
            return self.localizer.localize(frame, prior, candidates, deadline)
        except OrthonavError as exc:
            return Fix(False, f"no keypoint fix: {exc}", method=self.package.backend_name)

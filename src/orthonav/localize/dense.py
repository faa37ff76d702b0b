"""INS drift correction: find the camera frame inside the map around the prior -> ``Fix``.

Steps (each timed): cut and resample the frame and search-region views
(:mod:`orthonav.frames.views`); score every placement of the frame inside the region
(a correlation heatmap of gradient images or of CNN features) at a few headings around the
prior's; take the best peak with a sub-pixel fit; for a CNN's coarse stride, refine with
gradient correlation at full resolution; align with ECC, which also measures the heading and
altitude errors; offset in pixels -> metres -> corrected latitude/longitude.

A peak that does not stand out from the rest of the heatmap (peak-to-second-peak ratio), that
lies on the border of the search region (the truth may be outside it), or where the frame
does not look like the map (gradient correlation at the final placement) is rejected with
its reason, never applied.

Without a position prior (the vehicle is lost), a corrector given a map package with a global
index (``orthonav map index --method cnn`` works across dates) describes the frame north-up as
the keypoint localizer does, takes the index's few best tiles, corrects around each tile's
centre over a region wide enough to cover the tile, and keeps the candidate whose peak stands
out most among those that pass every check.
"""

from __future__ import annotations

import copy
import functools
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError, beyond
from orthonav.frames import check_frame_size
from orthonav.frames.views import (
    HeightsAt,
    ViewGeometry,
    Views,
    keep_region_on_map,
    make_views_each,
    region_point_latlon,
    vehicle_below,
)
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize.refine import Alignment, ecc_align
from orthonav.localize.timing import elapsed_ms
from orthonav.localize.uncertainty import FlatGroundModel
from orthonav.mapdb import MapPackage
from orthonav.models import DenseTrunk, shipped_model_path
from orthonav.models.heatmap import (
    Correlator,
    Heatmap,
    Peak,
    Template,
    find_peak,
    gradient_magnitude,
    ncc_heatmap,
    ncc_score,
    orientation_field,
    rival_peaks,
)
from orthonav.models.onnx.files import PRECISIONS, default_cache_dir
from orthonav.models.onnx.runtime import RUNTIMES, prefer_onnx
from orthonav.types import Fix, Pose, Prior

GRADIENT = "gradient"
ORIENTATION = "orientation"
TRAINED = "trained"
UNTRAINED = ("vgg11", "resnet18", "mobilenetv2")
BACKBONES = (GRADIENT, ORIENTATION, TRAINED, *UNTRAINED)
# Correlated without a network: the image -> the (H, W) or (H, W, C) float32 image correlated.
CLASSICAL = {GRADIENT: gradient_magnitude, ORIENTATION: orientation_field}
REFINEMENTS = ("none", "ncc", "ecc")


@dataclass(frozen=True)
class CorrectionConfig:
    """What decides a correction; every rejection names the threshold that failed.

    ``backbone``: ``gradient`` (the gradient magnitude; no learning), ``orientation`` (the
    gradient's orientation, which an edge keeps when its contrast reverses between dates: see
    :func:`orthonav.models.heatmap.orientation_field`), ``trained`` (the model shipped with
    orthonav, or ``model_path``), or an untrained torchvision trunk (``vgg11``, ``resnet18``,
    ``mobilenetv2``: random weights, as no pretrained download is possible).

    ``runtime`` of the trained trunk: ``torch``, ``onnx`` (ONNX Runtime, no torch needed: the
    model's export, ``onnx_path`` or the cache, see :mod:`orthonav.models.onnx`) or ``auto``
    ($ORTHONAV_RUNTIME, else ONNX Runtime where installed, else torch). ``onnx_precision``: ``fp32``, or
    ``int8`` (faster, slightly less exact; exported with calibration imagery beforehand).
    ``onnx_threads``: default one per physical core.
    """

    backbone: str = GRADIENT
    stage: int | None = None
    model_path: str | None = None
    size_px: int = 224
    search_factor: float = 1.5
    refine: str = "ecc"
    turn_step_deg: float = 3.0
    max_turn_deg: float = 9.0
    max_rotation_deg: float = 15.0
    max_scale_change: float = 0.2
    min_peak_ratio: float = 1.25
    # Gradient correlation of the frame view with the map where it was placed (any backbone):
    # the peak ratio alone passes most frames of other places and of noise.
    min_match_score: float = 0.25
    exclusion: float = 0.15
    sigma_px: float = 1.5
    # Each other hump of the heatmap shares the position with the peak, weighted
    # exp(-rival_weight x its shortfall below the peak) (heights above the background, the peak's
    # 1): the covariance holds the humps' spread, so a peak that barely stands out carries the
    # places it barely beat; the peak-ratio gate alone lets such a peak through. Calibrated on half
    # the real photos' placements and on NAIP's same-date frames, where more doubt would outgrow
    # the errors (docs/benchmarks/real.md). None: left out, for a caller whose own decision weighs
    # the rivals and accepts only the placements it is sure of (the cascade).
    rival_weight: float | None = 7.0
    # A prior without roll/pitch: the camera is taken as level, so the point under the drone is
    # only known to height x tan(this) (a gimbal-less fixed wing banks 20 deg and more; at 65 m a
    # level assumption put real photos up to 15 m off while their sigma claimed 0.9 m).
    unknown_tilt_sigma_deg: float = 10.0
    # Lost (no position prior): tiles of the map's global index tried, and the search factor
    # around each tile's centre (3 x the footprint reaches the edges of a tile 1.5 footprints wide).
    index_candidates: int = 5
    relocalize_search_factor: float = 3.0
    # Another place accepted with a peak ratio within this factor of the best's: ambiguous.
    ambiguity_ratio: float = 1.2
    # Orthorectify the frame onto the map package's terrain model where it has one (and the
    # corrector is given the package); else onto flat ground.
    use_terrain: bool = True
    runtime: str = "auto"
    onnx_precision: str = "fp32"
    onnx_path: str | None = None
    onnx_threads: int | None = None

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise OrthonavError(
                f"correction backbone {self.backbone!r}: expected one of {', '.join(BACKBONES)}"
            )
        if self.refine not in REFINEMENTS:
            raise OrthonavError(
                f"correction refine {self.refine!r}: expected one of {', '.join(REFINEMENTS)}"
            )
        if not 32 <= self.size_px <= 2048:
            raise OrthonavError(f"correction size: expected 32..2048 px, got {self.size_px}")
        if not 0 < self.exclusion < 1 or self.min_peak_ratio < 1 or self.sigma_px <= 0:
            raise OrthonavError(
                "correction thresholds: expected 0 < exclusion < 1, min_peak_ratio >= 1 and sigma_px > 0"
            )
        if self.rival_weight is not None and not self.rival_weight > 0:
            raise OrthonavError(f"correction rival_weight: expected > 0, got {self.rival_weight}")
        if not 0.0 <= self.unknown_tilt_sigma_deg < 45.0:
            raise OrthonavError(
                f"correction unknown_tilt_sigma_deg: expected 0..45 deg, got {self.unknown_tilt_sigma_deg}"
            )
        if self.index_candidates < 1:
            raise OrthonavError(f"correction index_candidates: expected >= 1, got {self.index_candidates}")
        if self.runtime not in RUNTIMES or self.onnx_precision not in PRECISIONS:
            raise OrthonavError(
                f"correction runtime {self.runtime!r} / precision {self.onnx_precision!r}: expected one "
                f"of {', '.join(RUNTIMES)} / {', '.join(PRECISIONS)}"
            )
        if self.runtime == "onnx" and self.backbone != TRAINED:
            raise OrthonavError(
                f"correction runtime onnx: only for the trained backbone, not {self.backbone!r}"
            )

    @property
    def name(self) -> str:
        return f"{self.backbone}-{self.size_px}"

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Correction:
    """A correction's fix, with what it was computed from (for pictures and diagnosis)."""

    fix: Fix
    views: Views
    heatmap: Heatmap
    peak: Peak
    alignment: Alignment


class Corrector:
    """Corrects priors of one camera against one orthophoto (the map, opened once).

    ``package``: a map package of the same ground whose global index re-localizes a frame
    without a position prior (optional; without it such a frame is rejected) and whose terrain
    model, if it has one, the frame is orthorectified onto.
    """

    def __init__(
        self,
        raster: GeoRaster,
        camera: Camera,
        config: CorrectionConfig | None = None,
        package: MapPackage | None = None,
    ) -> None:
        self.raster = raster
        self.camera = camera
        self.config = config or CorrectionConfig()
        self.package = package
        self._index_backend = None
        self._heights = _terrain_heights(package) if self.config.use_terrain else None
        self.network, self.model_info = (
            (None, {}) if self.config.backbone in CLASSICAL else _network(self.config)
        )

    def variant(self, size_px: int | None = None, refine: str | None = None) -> Corrector:
        """This corrector at another view size or refinement, sharing its loaded network (which
        neither changes) instead of loading the model again."""
        config = replace(
            self.config,
            size_px=self.config.size_px if size_px is None else size_px,
            refine=self.config.refine if refine is None else refine,
        )
        twin = copy.copy(self)
        twin.config = config
        return twin

    def correct(self, frame_bgr: np.ndarray, prior: Prior, search_factor: float | None = None) -> Correction:
        """One correction of ``prior`` from ``frame_bgr`` (BGR uint8 of this camera's size)."""
        correction = self.correct_each(frame_bgr, [prior], search_factor)[0]
        if isinstance(correction, OrthonavError):
            raise correction
        return correction

    def correct_each(
        self, frame_bgr: np.ndarray, priors: Sequence[Prior], search_factor: float | None = None
    ) -> list[Correction | OrthonavError]:
        """:meth:`correct` of one frame at each of ``priors`` (a lost frame's places and trial
        headings), the error in the place of a prior that cannot be corrected. Their common work
        is done once (:func:`make_views_each`; the frame view's turns, where it is shared); each
        correction's ``views_ms`` is its share of the views made together."""
        t0 = time.perf_counter()
        factor = search_factor or self.config.search_factor
        regions: list[Prior | OrthonavError] = []
        for prior in priors:
            try:
                regions.append(self._region_prior(prior, factor))
            except OrthonavError as exc:
                regions.append(exc)
        valid = [i for i, region in enumerate(regions) if isinstance(region, Prior)]
        size = self.config.size_px
        made = make_views_each(
            self.raster, self.camera, frame_bgr, [regions[i] for i in valid], size, factor, self._heights
        )
        views_ms = elapsed_ms(t0) / max(1, len(valid))
        corrections: list[Correction | OrthonavError] = list(regions)
        turns: dict[tuple[int, float], tuple] = {}
        for i, views in zip(valid, made, strict=True):
            corrections[i] = (
                views
                if isinstance(views, OrthonavError)
                else self._correct_views(views, priors[i], views_ms, turns)
            )
        return corrections

    def fixes_each(
        self, frame_bgr: np.ndarray, priors: Sequence[Prior], search_factor: float, failed: str
    ) -> list[Fix]:
        """The fixes of :meth:`correct_each`; a prior that cannot be corrected is a rejection
        whose reason starts with ``failed``."""
        return [
            each.fix if isinstance(each, Correction) else Fix(False, f"{failed}: {each}", method=self.method)
            for each in self.correct_each(frame_bgr, priors, search_factor)
        ]

    def _region_prior(self, prior: Prior, factor: float) -> Prior:
        """Where the search region is centred: the prior, moved onto the map near its edge."""
        if prior.has_position and self.raster.contains_latlon(prior.lat, prior.lon):
            return keep_region_on_map(self.raster, self.camera, prior, self.config.size_px, factor)
        return prior

    def _correct_views(self, views: Views, prior: Prior, views_ms: float, turns: dict) -> Correction:
        t = time.perf_counter()
        views, heatmap, peak, gradients = self._best_turn(views, prior, turns)
        timings = {"views_ms": views_ms, "correlate_ms": elapsed_ms(t)}
        t = time.perf_counter()
        gradients = gradients or _Gradients.of(views)
        alignment = self._align(views, heatmap.placement_px(peak.row, peak.col), heatmap.stride, gradients)
        timings["refine_ms"] = elapsed_ms(t)
        fix = self._fix(views, heatmap, peak, alignment, prior, _match_score(views, alignment, gradients))
        timings["total_ms"] = sum(timings.values())
        fix.timings_ms = timings
        return Correction(fix, views, heatmap, peak, alignment)

    @property
    def method(self) -> str:
        return f"correction:{self.config.name}"

    def localize(self, frame_bgr: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        """The keypoint localizer's interface, so the mission and companion loops take either.

        Correlation is local: without a position prior it searches the global index of its map
        package (:meth:`relocalize`), and without one it rejects the frame; a search region the
        map cannot supply (off its edge) is a rejection, not an error. Candidate tiles do not
        apply. A frame of the wrong size is still an error: it is another camera.
        """
        check_frame_size(frame_bgr, self.camera, "frame")
        if not prior.has_position:
            if self.package is None or self.package.global_index is None:
                reason = (
                    "dense correlation needs a position prior (the filter is lost) or a map package "
                    "with a global index to search (orthonav map index --method cnn)"
                )
                return Fix(False, reason, method=self.method)
            return self.relocalize(frame_bgr, prior)
        try:
            return self.correct(frame_bgr, prior).fix
        except OrthonavError as exc:
            return Fix(False, f"no correction: {exc}", method=self.method)

    def relocalize(self, frame_bgr: np.ndarray, prior: Prior) -> Fix:
        """A lost frame (no position; altitude and heading known): correct around each of the
        global index's best tiles, keep the accepted candidate whose peak stands out most."""
        t0 = time.perf_counter()
        method = f"{self.method}+index"
        if prior.alt_agl_m is None or prior.heading_deg is None:
            return Fix(False, "lost: searching the index needs the altitude and heading", method=method)
        index = self.package.global_index
        if index.method == "vlad" and self._index_backend is None:
            self._index_backend = self.package.create_backend()  # VLAD describes the map's own features
        view = self.package.frame_view(self.camera, frame_bgr, prior, self._index_backend)
        tiles, _ = index.search(view, self.config.index_candidates)
        timings = {"index_ms": elapsed_ms(t0)}
        fixes = self._correct_around_tiles(frame_bgr, prior, tiles)
        timings["total_ms"] = elapsed_ms(t0)
        accepted = [(rank, fix) for rank, fix in fixes.items() if fix.accepted]
        if not accepted:
            reasons = "; ".join(f"tile {tiles[rank]}: {fix.reason}" for rank, fix in fixes.items())
            return Fix(
                False, f"lost: no index candidate correlated: {reasons}", timings_ms=timings, method=method
            )
        rank, best = max(accepted, key=lambda item: item[1].quality["peak_ratio"])
        best.quality.update(index_rank=rank, index_tile=int(tiles[rank]), index_accepted=len(accepted))
        best.timings_ms = timings
        best.method = method
        rival = self._rival(best, [fix for _, fix in accepted])
        if rival is not None:
            reason = (
                f"lost: ambiguous, two places {rival[0]:.0f} m apart correlate alike "
                f"(peak ratio {best.quality['peak_ratio']:.2f} vs {rival[1]:.2f})"
            )
            return Fix(False, reason, pose=best.pose, quality=best.quality, timings_ms=timings, method=method)
        return best

    def _correct_around_tiles(self, frame_bgr: np.ndarray, prior: Prior, tiles: np.ndarray) -> dict[int, Fix]:
        """Corrections around each tile, by rank; a tile whose search centre (moved onto the
        map) is near one already searched is skipped: its region is nearly the same. Tiles of
        one search factor are corrected together (:meth:`correct_each`: one frame view)."""
        near_m = 0.25 * min(self.camera.nadir_footprint_m(prior.alt_agl_m))
        searched: list[tuple[float, float]] = []
        by_factor: dict[float, list[tuple[int, Prior]]] = {}
        for rank, tile in enumerate(tiles):
            factor, centred = self._tile_prior(prior, int(tile))
            if any(distance_m(centred.lat, centred.lon, *done) < near_m for done in searched):
                continue
            searched.append((centred.lat, centred.lon))
            by_factor.setdefault(factor, []).append((rank, centred))
        fixes = {}
        for factor, centres in by_factor.items():
            done = self.fixes_each(frame_bgr, [centred for _, centred in centres], factor, "no correction")
            fixes.update((rank, fix) for (rank, _), fix in zip(centres, done, strict=True))
        return dict(sorted(fixes.items()))

    def _rival(self, best: Fix, accepted: list[Fix]) -> tuple[float, float] | None:
        """(distance, peak ratio) of an accepted candidate at another place whose peak stands out
        almost as much as the best's: look-alike ground, no way to tell which is right. Apart is
        beyond the peak's own sigma, not its rivals' spread: that spread is the doubt asked about."""
        apart_m = 3.0 * best.quality["peak_sigma_m"] + 10.0
        for fix in accepted:
            offset = float(distance_m(fix.pose.lat, fix.pose.lon, best.pose.lat, best.pose.lon))
            ratio = fix.quality["peak_ratio"]
            if offset > apart_m and ratio * self.config.ambiguity_ratio >= best.quality["peak_ratio"]:
                return offset, ratio
        return None

    def _tile_prior(self, prior: Prior, tile: int) -> tuple[float, Prior]:
        """The search factor and prior around a tile's centre, its sigma covering the tile."""
        box = self.package.tiles.box_px[tile]
        lat, lon = self.package.grid.pixel_to_latlon(0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3]))
        half_diagonal_m = 0.5 * math.hypot(box[2] - box[0], box[3] - box[1]) * self.package.gsd_m
        centre = replace(prior, lat=float(lat), lon=float(lon), sigma_m=half_diagonal_m)
        return self._fit_on_map(centre, self.config.relocalize_search_factor)

    def _fit_on_map(self, prior: Prior, wanted_factor: float) -> tuple[float, Prior]:
        """The search factor and centre for a search region on the orthophoto: the wanted
        factor, smaller if the map is narrower than that region turned to the heading; the
        centre moved inwards until the region fits (a prior near the map's edge, or a tile on
        it, is still searched, over ground the map has)."""
        factor = min(wanted_factor, largest_search_factor(self.raster, self.camera, prior))
        half_x, half_y = (
            h / self.raster.gsd_m for h in region_half_extents_m(self.raster, self.camera, prior, factor)
        )
        col, row = self.raster.latlon_to_pixel(prior.lat, prior.lon)
        col = clamp(float(col), half_x, self.raster.width - half_x)
        row = clamp(float(row), half_y, self.raster.height - half_y)
        lat, lon = self.raster.pixel_to_latlon(col, row)
        return factor, replace(prior, lat=float(lat), lon=float(lon))

    def _best_turn(
        self, views: Views, prior: Prior, made: dict[tuple[int, float], tuple] | None = None
    ) -> tuple[Views, Heatmap, Peak, _Gradients | None]:
        """Correlate at headings around the prior's (a translation-only peak is biased by a
        heading error of a few degrees); keep the turn whose peak scores highest. Only that
        turn's peak is measured (sub-cell, rival, background): a lost frame's search correlates
        hundreds of turns, and measuring the others would not change which one wins.
        ``made``: turns of frame views already made (see :meth:`_turned`). With gradient
        (magnitude) correlation, the best turn's gradient images come too (for the ECC alignment
        and the match score)."""
        step = self.config.turn_step_deg
        turns = int(min(self.config.max_turn_deg, 2.0 * prior.heading_sigma_deg) // step) if step > 0 else 0
        region = self._region_features(views)
        correlator = Correlator(region, views.frame.shape[:2]) if self.network is None else None
        made = {} if made is None else made
        best: tuple[Views, Heatmap, _Gradients | None] | None = None
        best_score = -math.inf
        on_map = None
        for k in sorted(range(-turns, turns + 1), key=abs):
            turned, template, correlated = self._turned(views, k * step, made)
            if correlator is None:
                heatmap = self.network.feature_heatmap(turned, region)
            else:
                heatmap = correlator.heatmap(template)
            # The unturned view's mask for every turn: theirs differ only at the corners.
            on_map = _placements_on_map(views, heatmap) if on_map is None else on_map
            heatmap = heatmap.keep_on_map(on_map)
            gradients = _Gradients(region, correlated) if self.config.backbone == GRADIENT else None
            score = float(heatmap.values.max())
            if best is None or score > best_score:
                best, best_score = (turned, heatmap, gradients), score
        turned, heatmap, gradients = best
        return turned, heatmap, find_peak(heatmap, self._exclusion_cells(views, heatmap)), gradients

    def _exclusion_cells(self, views: Views, heatmap: Heatmap) -> float:
        """How far around a peak its own flanks reach, in heatmap cells: no rival within."""
        return max(2.0, self.config.exclusion * min(views.geometry.frame_size) / heatmap.stride)

    def _region_features(self, views: Views):
        """The region's image as correlated (gradient, orientation) or CNN features: computed
        once for every turn."""
        if self.network is None:
            return CLASSICAL[self.config.backbone](views.region)
        return self.network.image_features(views.region, views.region_mask)

    def _turned(
        self, views: Views, turn_deg: float, made: dict[tuple[int, float], tuple]
    ) -> tuple[Views, Template | None, np.ndarray | None]:
        """``views`` with the frame view turned, its image as correlated (gradient, orientation)
        and that image as a correlation template (classical correlation). A frame view shared by
        several places and headings (:func:`make_views_each`) turns alike for each of them: its
        turns and their templates (with their spectra) are made once, kept in ``made`` by the
        view's identity."""
        key = (id(views.frame), turn_deg)
        if key not in made:
            turned = views.turned(turn_deg)
            template = correlated = None
            if self.network is None:
                correlated = CLASSICAL[self.config.backbone](turned.frame)
                template = Template(correlated, turned.frame_mask)
            made[key] = (turned.frame, turned.frame_mask, template, correlated)
        frame, mask, template, correlated = made[key]
        return replace(views, frame=frame, frame_mask=mask, turn_deg=turn_deg), template, correlated

    def feature_maps(self, views: Views) -> tuple[np.ndarray, np.ndarray]:
        """(C, h, w) frame and region features as correlated (gradient images: C = 1, orientation
        C = 2), for pictures."""
        if self.network is None:
            frame, region = (
                np.atleast_3d(CLASSICAL[self.config.backbone](image)) for image in (views.frame, views.region)
            )
            return np.moveaxis(frame, 2, 0), np.moveaxis(region, 2, 0)
        frame = self.network.image_features(views.frame, views.frame_mask)
        return self.network.as_array(frame), self.network.as_array(self._region_features(views))

    def _align(
        self, views: Views, placement: tuple[float, float], stride: int, gradients: _Gradients
    ) -> Alignment:
        """Peak placement -> full-resolution translation (CNN strides) -> ECC similarity."""
        if stride > 1 and self.config.refine != "none":
            placement = _refine_ncc(views, placement, stride, gradients.frame)
        w, h = views.geometry.frame_size
        aligned = Alignment(placement[0] + w / 2.0, placement[1] + h / 2.0, 0.0, 1.0, 0.0)
        if self.config.refine == "ecc":
            ecc = ecc_align(
                gradients.frame,
                views.frame_mask,
                gradients.region,
                views.region_mask,
                placement,
                max_shift_px=2.0 * stride + 3.0,
                max_rotation_deg=self.config.max_rotation_deg,
                max_scale_change=self.config.max_scale_change,
            )
            aligned = ecc or aligned
        return aligned

    def _fix(
        self, views: Views, heatmap: Heatmap, peak: Peak, aligned: Alignment, prior: Prior, match_score: float
    ) -> Fix:
        geometry = views.geometry
        region_w, region_h = geometry.region_size
        offset_px = (aligned.centre_x - region_w / 2.0, aligned.centre_y - region_h / 2.0)
        quality = {
            "peak_ratio": peak.ratio,
            "peak_score": peak.score,
            "offset_m": math.hypot(*offset_px) * geometry.gsd_m,
            "gsd_m": geometry.gsd_m,
            "ecc_score": aligned.score,
            "heading_change_deg": views.turn_deg + aligned.rotation_deg,
            "scale": aligned.scale,
            "match_score": match_score,
            "terrain": float(self._heights is not None),
            "inliers": 0.0,  # no keypoints pin a correlation pose (Fix.unpinned)
        }
        method = self.method
        if peak.ratio < self.config.min_peak_ratio:
            ratio, limit = beyond(peak.ratio, self.config.min_peak_ratio, 2), self.config.min_peak_ratio
            reason = f"peak ratio {ratio} below {limit:g}: no distinct match"
            return Fix(False, reason, quality=quality, method=method)
        if heatmap.on_border(peak.row, peak.col):
            reason = "peak on the border of the search region: the position may lie outside it"
            return Fix(False, reason, quality=quality, method=method)
        if quality["match_score"] < self.config.min_match_score:
            reason = (
                f"match score {beyond(quality['match_score'], self.config.min_match_score, 2)} below "
                f"{self.config.min_match_score:g}: "
                "the frame does not look like the map where it was placed"
            )
            return Fix(False, reason, quality=quality, method=method)
        pitch, roll = (prior.pitch_deg, prior.roll_deg) if prior.has_attitude else (0.0, 0.0)
        heading = (geometry.heading_deg + views.turn_deg + aligned.rotation_deg) % 360.0
        alt = prior.alt_agl_m * aligned.scale
        centre_lat, centre_lon = region_point_latlon(geometry, aligned.centre_x, aligned.centre_y)
        lat, lon = vehicle_below(self.camera, centre_lat, centre_lon, alt, heading, pitch, roll)
        pose = Pose(lat, lon, alt, heading, pitch, roll, centre_lat, centre_lon)
        # Sharper peaks (higher ratio) localise better; the floor is the pixel model's sigma.
        sigma_m = (
            self.config.sigma_px * geometry.gsd_m * max(1.0, 2.0 * self.config.min_peak_ratio / peak.ratio)
        )
        # On flat ground (no terrain to orthorectify on), the relief it cannot see: the keypoint
        # pose's floor, as the correlation has no inliers to measure more from.
        flat_m = FlatGroundModel().slope * alt if self._heights is None else 0.0
        own_m2 = sigma_m**2 + self._attitude_m(prior, alt) ** 2 + flat_m**2
        quality["peak_sigma_m"] = math.sqrt(own_m2)
        rivals = np.zeros((2, 2))
        if self.config.rival_weight is not None:
            exclusion = self._exclusion_cells(views, heatmap)
            rivals = rivals_covariance_m2(geometry, heatmap, peak, exclusion, self.config.rival_weight)
            quality["rivals_m"] = math.sqrt(float(np.trace(rivals)))
        covariance = np.eye(2) * own_m2 + rivals
        return Fix(True, pose=pose, covariance_enu_m2=covariance, quality=quality, method=method)

    def _attitude_m(self, prior: Prior, alt_m: float) -> float:
        """How far the attitude's error moves the point under the drone from the one placed below
        the image centre: height x tan(the prior's attitude sigma, or an unknown tilt's)."""
        tilt = prior.attitude_sigma_deg if prior.has_attitude else self.config.unknown_tilt_sigma_deg
        return alt_m * math.tan(math.radians(tilt))


def rivals_covariance_m2(
    geometry: ViewGeometry, heatmap: Heatmap, peak: Peak, exclusion_cells: float, rival_weight: float
) -> np.ndarray:
    """(2, 2) east-north covariance of the position shared between the peak and the heatmap's
    other humps (:func:`rival_peaks`), about the peak: each weighs exp(-``rival_weight`` x its
    shortfall below the peak), the peak 1 (``CorrectionConfig.rival_weight``)."""
    rivals = rival_peaks(heatmap, peak, exclusion_cells)
    weights = np.exp(-rival_weight * (1.0 - rivals[:, 2]))
    offsets = np.array(
        [
            geometry.offset_to_en((col - peak.col) * heatmap.stride, (row - peak.row) * heatmap.stride)
            for row, col, _ in rivals
        ]
    ).reshape(-1, 2)
    return (weights[:, None] * offsets).T @ offsets / (1.0 + weights.sum())


# --- search-region geometry (shared with the cascade's coarse stage) -----------------------------
# A placement counts where this share of what the frame view sees lies on the map: a window
# mostly over the flat fill off it would be normalised over little ground. Not much more: real
# orthophotos end where their flights did, and at 0.98 a Seneca photo half over its
# orthophoto's edge had no placement at all.
MIN_ON_MAP = 0.5


def _placements_on_map(views: Views, heatmap: Heatmap) -> np.ndarray:
    """Per heatmap cell: whether the frame view placed there sees the map (``MIN_ON_MAP``); a
    region may reach past the map's edge (:func:`region_overhang_px`)."""
    rows, cols = heatmap.values.shape
    if views.region_mask.all():
        return np.ones((rows, cols), bool)
    seen = views.frame_mask.astype(np.float32)
    on_map = cv2.matchTemplate(views.region_mask.astype(np.float32), seen, cv2.TM_CCORR)
    stride = heatmap.stride
    cells = on_map[::stride, ::stride][:rows, :cols]
    # A network's feature grid may hold a row or column more than the pixels' placements.
    cells = np.pad(cells, ((0, rows - cells.shape[0]), (0, cols - cells.shape[1])), mode="edge")
    return cells >= MIN_ON_MAP * max(float(seen.sum()), 1.0)


def footprint_extents_m(camera: Camera, prior: Prior) -> tuple[float, float]:
    """East-west and north-south extents of the camera's footprint turned to the heading."""
    width_m, height_m = camera.nadir_footprint_m(prior.alt_agl_m)
    turn = math.radians(prior.heading_deg)
    cos, sin = abs(math.cos(turn)), abs(math.sin(turn))
    return width_m * cos + height_m * sin, width_m * sin + height_m * cos


def look_ahead_m(raster: GeoRaster, prior: Prior) -> float:
    """Room a region keeps for a tilted camera's look-ahead (with the attitude's 2 sigma)."""
    tilt = max(abs(prior.pitch_deg or 0.0), abs(prior.roll_deg or 0.0)) + 2.0 * prior.attitude_sigma_deg
    return prior.alt_agl_m * math.tan(math.radians(tilt)) + 2.0 * raster.gsd_m


def largest_search_factor(raster: GeoRaster, camera: Camera, prior: Prior) -> float:
    """The largest search factor whose region, turned to the heading, fits on the map."""
    extent_x, extent_y = footprint_extents_m(camera, prior)
    slack_m = look_ahead_m(raster, prior)
    map_x, map_y = raster.width * raster.gsd_m, raster.height * raster.gsd_m
    return 0.98 * min((map_x - 2.0 * slack_m) / extent_x, (map_y - 2.0 * slack_m) / extent_y)


def region_half_extents_m(
    raster: GeoRaster, camera: Camera, prior: Prior, factor: float
) -> tuple[float, float]:
    """How far a region at ``factor`` reaches east-west and north-south of its centre."""
    extent_x, extent_y = footprint_extents_m(camera, prior)
    slack_m = look_ahead_m(raster, prior)
    return 0.5 * factor * extent_x + slack_m, 0.5 * factor * extent_y + slack_m


def clamp(value: float, low: float, high: float) -> float:
    """``value`` within [low, high]; the middle when the interval is empty."""
    return 0.5 * (low + high) if low > high else min(max(value, low), high)


class _Gradients(NamedTuple):
    """The gradient images of a region view and of the frame view as correlated: made by the
    gradient correlation, else once for the ECC alignment and the match score."""

    region: np.ndarray
    frame: np.ndarray

    @classmethod
    def of(cls, views: Views) -> _Gradients:
        return cls(gradient_magnitude(views.region), gradient_magnitude(views.frame))


def _match_score(views: Views, aligned: Alignment, gradients: _Gradients) -> float:
    """Gradient correlation of the frame view with the region under its final placement."""
    w, h = views.geometry.frame_size
    region_h, region_w = views.region.shape[:2]
    x0 = int(np.clip(round(aligned.centre_x - w / 2.0), 0, region_w - w))
    y0 = int(np.clip(round(aligned.centre_y - h / 2.0), 0, region_h - h))
    patch = gradients.region[y0 : y0 + h, x0 : x0 + w]
    return ncc_score(patch, gradients.frame, views.frame_mask)


def _refine_ncc(
    views: Views, placement: tuple[float, float], stride: int, frame_gradient: np.ndarray
) -> tuple[float, float]:
    """Gradient correlation at full resolution within one CNN cell around ``placement``."""
    pad = stride + 2
    frame_w, frame_h = views.geometry.frame_size
    region_h, region_w = views.region.shape[:2]
    x0 = int(np.clip(round(placement[0]) - pad, 0, region_w - frame_w))
    y0 = int(np.clip(round(placement[1]) - pad, 0, region_h - frame_h))
    x1 = min(region_w, x0 + frame_w + 2 * pad)
    y1 = min(region_h, y0 + frame_h + 2 * pad)
    local = ncc_heatmap(gradient_magnitude(views.region[y0:y1, x0:x1]), frame_gradient, views.frame_mask)
    peak = find_peak(local, 2.0)
    return x0 + peak.col, y0 + peak.row


def trained_trunk(runtime: str = "auto") -> DenseTrunk:
    """The trained correction trunk shipped with orthonav, for checks that compare features
    without correlating (the verification); ``auto``: under ONNX Runtime wherever it is
    installed (its two passes a frame run faster than under torch). The same network as every
    corrector's of the shipped model under that runtime (:func:`_network`)."""
    return _network(CorrectionConfig(backbone=TRAINED, runtime=runtime))[0]


def _network(config: CorrectionConfig) -> tuple[DenseTrunk, dict]:
    """(network, recorded model info). The trained model runs under torch or ONNX Runtime
    (``config.runtime``); torch is imported only on the torch path, so a companion without it
    corrects with the model's ONNX export. The shipped model is loaded once per process and
    runtime settings, shared by every corrector and the verification's check (a session for
    each map's cascade would hold threads that slow ALIKED's extraction beside them).

    Untrained trunks draw their random weights from a fixed seed, so runs are comparable.
    """
    if config.backbone == TRAINED:
        runtime = prefer_onnx(config.runtime)
        # The exports' folder too: a session is the file it was loaded from.
        cache = str(default_cache_dir()) if runtime == "onnx" else None
        settings = (runtime, config.onnx_precision, config.onnx_path, cache, config.onnx_threads)
        if config.model_path is None:
            network, info = _shipped_network(*settings)
            return network, dict(info)
        return _trained_network(config.model_path, *settings)
    import torch

    from orthonav.models.trunks import DenseFeatures

    with torch.random.fork_rng():
        torch.manual_seed(0)
        return DenseFeatures(config.backbone, config.stage).eval(), {}


@functools.cache
def _shipped_network(
    runtime: str, precision: str, onnx_path: str | None, cache: str | None, threads: int | None
) -> tuple[DenseTrunk, dict]:
    return _trained_network(shipped_model_path(), runtime, precision, onnx_path, cache, threads)


def _trained_network(
    model: str | Path,
    runtime: str,
    precision: str,
    onnx_path: str | None,
    cache: str | None,
    threads: int | None,
) -> tuple[DenseTrunk, dict]:
    if runtime == "onnx":
        from orthonav.models.onnx.loading import load_onnx_trunk

        return load_onnx_trunk(model, precision, onnx_path, cache, threads)
    from orthonav.models.trunks import load_model

    return load_model(model)


def _terrain_heights(package: MapPackage | None) -> HeightsAt | None:
    """The package's terrain heights at (lat, lon) arrays, or None without a terrain model."""
    if package is None or package.terrain is None:
        return None
    return package.terrain.heights_at_latlon

"""INS drift correction: find the camera frame inside the map around the prior -> ``Fix``.

Steps (each timed): cut and resample the frame and search-region views
(:mod:`orthonav.correction.views`); score every placement of the frame inside the region
(a correlation heatmap of gradient images or of CNN features) at a few headings around the
prior's; take the best peak with a sub-pixel fit; for a CNN's coarse stride, refine with
gradient correlation at full resolution; align with ECC, which also measures the heading and
altitude errors; offset in pixels -> metres -> corrected latitude/longitude.

A peak that does not stand out from the rest of the heatmap (peak-to-second-peak ratio), that
lies on the border of the search region (the truth may be outside it), or where the frame
does not look like the map (gradient correlation at the final placement) is rejected with
its reason, never applied.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from orthonav.camera import Camera
from orthonav.correction.heatmap import Heatmap, Peak, find_peak, gradient_magnitude, ncc_heatmap
from orthonav.correction.refine import Alignment, ecc_align
from orthonav.correction.views import Views, make_views, region_point_latlon, vehicle_below
from orthonav.errors import OrthonavError
from orthonav.frames import check_frame_size
from orthonav.geo import GeoRaster
from orthonav.localize import Fix, Pose, Prior

GRADIENT = "gradient"
TRAINED = "trained"
UNTRAINED = ("vgg11", "resnet18", "mobilenetv2")
BACKBONES = (GRADIENT, TRAINED, *UNTRAINED)
SHIPPED_MODEL = "resnet18_naip.pt"
REFINEMENTS = ("none", "ncc", "ecc")


@dataclass(frozen=True)
class CorrectionConfig:
    """What decides a correction; every rejection names the threshold that failed.

    ``backbone``: ``gradient`` (no learning), ``trained`` (the model shipped with orthonav,
    or ``model_path``), or an untrained torchvision trunk (``vgg11``, ``resnet18``,
    ``mobilenetv2``: random weights, as no pretrained download is possible).
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
    """Corrects priors of one camera against one orthophoto (the map, opened once)."""

    def __init__(self, raster: GeoRaster, camera: Camera, config: CorrectionConfig | None = None) -> None:
        self.raster = raster
        self.camera = camera
        self.config = config or CorrectionConfig()
        self.network, self.model_info = (
            (None, {}) if self.config.backbone == GRADIENT else _network(self.config)
        )

    def correct(self, frame_bgr: np.ndarray, prior: Prior) -> Correction:
        """One correction of ``prior`` from ``frame_bgr`` (BGR uint8 of this camera's size)."""
        t0 = time.perf_counter()
        config = self.config
        views = make_views(self.raster, self.camera, frame_bgr, prior, config.size_px, config.search_factor)
        timings = {"views_ms": _ms(t0)}
        t = time.perf_counter()
        views, heatmap, peak = self._best_turn(views, prior)
        timings["correlate_ms"] = _ms(t)
        t = time.perf_counter()
        alignment = self._align(views, heatmap.placement_px(peak.row, peak.col), heatmap.stride)
        timings["refine_ms"] = _ms(t)
        fix = self._fix(views, heatmap, peak, alignment, prior)
        timings["total_ms"] = _ms(t0)
        fix.timings_ms = timings
        return Correction(fix, views, heatmap, peak, alignment)

    @property
    def method(self) -> str:
        return f"correction:{self.config.name}"

    def localize(self, frame_bgr: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        """The keypoint localizer's interface, so the mission and companion loops take either.

        Correlation is local: without a position prior it rejects the frame, and a search
        region the map cannot supply (off its edge) is a rejection, not an error. Candidate
        tiles do not apply. A frame of the wrong size is still an error: it is another camera.
        """
        if not prior.has_position:
            return Fix(
                False, "dense correlation needs a position prior (the filter is lost)", method=self.method
            )
        check_frame_size(frame_bgr, self.camera, "frame")
        try:
            return self.correct(frame_bgr, prior).fix
        except OrthonavError as exc:
            return Fix(False, f"no correction: {exc}", method=self.method)

    def _best_turn(self, views: Views, prior: Prior) -> tuple[Views, Heatmap, Peak]:
        """Correlate at headings around the prior's (a translation-only peak is biased by a
        heading error of a few degrees); keep the turn whose peak scores highest."""
        step = self.config.turn_step_deg
        turns = int(min(self.config.max_turn_deg, 2.0 * prior.heading_sigma_deg) // step) if step > 0 else 0
        region = self._region_features(views)
        best = None
        for k in sorted(range(-turns, turns + 1), key=abs):
            turned = views.turned(k * step)
            heatmap = self._heatmap(turned, region)
            exclusion = self.config.exclusion * min(views.geometry.frame_size) / heatmap.stride
            peak = find_peak(heatmap, max(2.0, exclusion))
            if best is None or peak.score > best[2].score:
                best = (turned, heatmap, peak)
        return best

    def _region_features(self, views: Views):
        """Gradient image or CNN features of the region: computed once for every turn."""
        if self.network is None:
            return gradient_magnitude(views.region)
        from orthonav.correction.trunks import image_features

        return image_features(self.network, views.region, views.region_mask)

    def _heatmap(self, views: Views, region) -> Heatmap:
        if self.network is None:
            return ncc_heatmap(region, gradient_magnitude(views.frame), views.frame_mask)
        from orthonav.correction.trunks import feature_heatmap

        return feature_heatmap(self.network, views, region)

    def feature_maps(self, views: Views) -> tuple[np.ndarray, np.ndarray]:
        """(C, h, w) frame and region features as correlated (gradient images: C = 1), for pictures."""
        if self.network is None:
            return gradient_magnitude(views.frame)[None], gradient_magnitude(views.region)[None]
        from orthonav.correction.trunks import image_features

        frame = image_features(self.network, views.frame, views.frame_mask)[0].numpy()
        return frame, self._region_features(views)[0].numpy()

    def _align(self, views: Views, placement: tuple[float, float], stride: int) -> Alignment:
        """Peak placement -> full-resolution translation (CNN strides) -> ECC similarity."""
        if stride > 1 and self.config.refine != "none":
            placement = _refine_ncc(views, placement, stride)
        w, h = views.geometry.frame_size
        aligned = Alignment(placement[0] + w / 2.0, placement[1] + h / 2.0, 0.0, 1.0, 0.0)
        if self.config.refine == "ecc":
            ecc = ecc_align(
                views.frame,
                views.frame_mask,
                views.region,
                views.region_mask,
                placement,
                max_shift_px=2.0 * stride + 3.0,
                max_rotation_deg=self.config.max_rotation_deg,
                max_scale_change=self.config.max_scale_change,
            )
            aligned = ecc or aligned
        return aligned

    def _fix(self, views: Views, heatmap: Heatmap, peak: Peak, aligned: Alignment, prior: Prior) -> Fix:
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
            "match_score": _match_score(views, aligned),
        }
        method = self.method
        rows, cols = heatmap.values.shape
        if peak.ratio < self.config.min_peak_ratio:
            reason = f"peak ratio {peak.ratio:.2f} below {self.config.min_peak_ratio:.2f}: no distinct match"
            return Fix(False, reason, quality=quality, method=method)
        if not (0.5 <= peak.row <= rows - 1.5 and 0.5 <= peak.col <= cols - 1.5):
            reason = "peak on the border of the search region: the position may lie outside it"
            return Fix(False, reason, quality=quality, method=method)
        if quality["match_score"] < self.config.min_match_score:
            reason = (
                f"match score {quality['match_score']:.2f} below {self.config.min_match_score:.2f}: "
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
        return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * sigma_m**2, quality=quality, method=method)


def _match_score(views: Views, aligned: Alignment) -> float:
    """Gradient correlation of the frame view with the region under its final placement."""
    w, h = views.geometry.frame_size
    region_h, region_w = views.region.shape[:2]
    x0 = int(np.clip(round(aligned.centre_x - w / 2.0), 0, region_w - w))
    y0 = int(np.clip(round(aligned.centre_y - h / 2.0), 0, region_h - h))
    patch = gradient_magnitude(views.region)[y0 : y0 + h, x0 : x0 + w]
    return float(ncc_heatmap(patch, gradient_magnitude(views.frame), views.frame_mask).values[0, 0])


def _refine_ncc(views: Views, placement: tuple[float, float], stride: int) -> tuple[float, float]:
    """Gradient correlation at full resolution within one CNN cell around ``placement``."""
    pad = stride + 2
    frame_w, frame_h = views.geometry.frame_size
    region_h, region_w = views.region.shape[:2]
    x0 = int(np.clip(round(placement[0]) - pad, 0, region_w - frame_w))
    y0 = int(np.clip(round(placement[1]) - pad, 0, region_h - frame_h))
    x1 = min(region_w, x0 + frame_w + 2 * pad)
    y1 = min(region_h, y0 + frame_h + 2 * pad)
    local = ncc_heatmap(
        gradient_magnitude(views.region[y0:y1, x0:x1]), gradient_magnitude(views.frame), views.frame_mask
    )
    peak = find_peak(local, 2.0)
    return x0 + peak.col, y0 + peak.row


def _network(config: CorrectionConfig) -> tuple:
    """(network, recorded model info): torch is imported only for CNN backbones.

    Untrained trunks draw their random weights from a fixed seed, so runs are comparable.
    """
    import torch

    from orthonav.correction.trunks import DenseFeatures, load_model

    if config.backbone == TRAINED:
        return load_model(config.model_path or shipped_model_path())
    with torch.random.fork_rng():
        torch.manual_seed(0)
        return DenseFeatures(config.backbone, config.stage).eval(), {}


def shipped_model_path() -> Path:
    """The trained model that comes with orthonav (see its ``.json`` for data and scores)."""
    return Path(str(resources.files("orthonav.correction") / "models" / SHIPPED_MODEL))


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0

"""The keypoint localizer: frame + prior -> matches on map tiles -> homography -> Fix.

Steps (each timed): warp the frame to the map's ground resolution and north-up orientation
when altitude and heading are known; extract features; match against each candidate tile
(ratio test, N best per tile), merge in map pixels and de-duplicate on a grid; robust
homography (MAGSAC++); the homography from frame pixels to the local ENU ground plane is
decomposed with the intrinsics into the full camera pose; quality checks decide between
a fix and a rejection with its reason.

Rotation: with a heading prior the frame is de-rotated north-up before extraction. Without
one, a backend that is not rotation-invariant (the learned ones except aliked-n16rot) is
tried at ``rotation_trials`` evenly spaced headings; the first that passes every check wins.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from orthonav.camera import (
    AttitudePrior,
    Camera,
    CameraPose,
    apply_homography,
    footprint_enu,
    pixel_to_ground,
    planar_pose_candidates,
    pose_from_homography,
    project_points,
    refine_pose,
    rotation_enu_from_camera,
)
from orthonav.errors import OrthonavError, beyond
from orthonav.features import FeatureBackend, FeatureSet, Matches, mutual_nearest
from orthonav.frames import NorthUp, north_up
from orthonav.geo import LocalFrame, distance_m
from orthonav.localize import candidates as cand
from orthonav.localize.guided import guided_matches
from orthonav.localize.timing import DEADLINE, FrameDeadline, StageCost, elapsed_ms
from orthonav.localize.uncertainty import FlatGroundModel, unexplained_m
from orthonav.mapdb import MapPackage
from orthonav.mapdb.globalindex import FrameView
from orthonav.mapdb.terrain import Terrain
from orthonav.mapdb.tiling import check_footprint
from orthonav.types import Fix, Pose, Prior

_RANSAC_METHODS = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}
MAX_KEPT_INLIERS = 300  # inlier pairs a Fix carries for pictures of the match
POSE_UNKNOWNS = 6  # a camera pose: position and attitude, so at least this many points to refine it on
# A second pose fit counts as a rival minimum when it explains the points about as well.
TILT_RIVAL_RMSE_RATIO = 1.5


@dataclass(frozen=True)
class LocalizerConfig:
    """Matching and acceptance thresholds; every rejection names the one that failed."""

    ransac: str = "magsac"
    ransac_threshold_px: float = 3.0
    ransac_iterations: int = 2000
    dedup_cell_px: float = 1.5
    max_prior_candidates: int = 4
    # With a position prior: the candidate tiles' keypoints where the frame can lie (the prior's
    # 2 sigma plus the footprint), one per place where tiles overlap, matched in one pass instead
    # of tile by tile. None: for learned matchers (a pass costs the product of the two sets'
    # sizes, and the tiles' overlap and far corners are most of them).
    mosaic: bool | None = None
    mosaic_merge_px: float = 2.0
    # With a position and heading prior: match each frame keypoint only with the map keypoints
    # near where the prior's pose puts it (orthonav.localize.guided), instead of the backend's
    # matcher. The radius is how far the prior may misplace the frame's far corners (see
    # Localizer._guided_radius_px), with the altitude off by up to ``guided_altitude_fraction``,
    # and at least ``guided_min_radius_px``: wide enough that chance pairs rarely agree with
    # each other to the RANSAC threshold (about (3 / 20)^2 of them). Where the radius would hold
    # more than ``guided_max_candidates`` map keypoints on average (a prior loose for the map's
    # resolution: 15 m on a 10 cm map), the backend's matcher is used: it tells them apart
    # better, and nearest descriptors among hundreds cost more than its attention.
    guided: bool = False
    guided_altitude_fraction: float = 0.1
    guided_min_radius_px: float = 20.0
    guided_max_candidates: float = 64.0
    guided_ratio: float = 0.9
    # Where the backend's matcher would match the prior's tiles or their mosaic (unguided), the
    # cheap way first: mutual nearest descriptors (cosine above ``quick_min_cosine``), the pose
    # judged as any; where it is accepted, its homography puts every frame keypoint on the map
    # and a second match searches ``quick_radius_px`` map pixels around each (ratio test
    # ``quick_ratio``). That pose, where accepted, is the fix; otherwise the backend's matcher
    # runs as before. A photo of the map's season mostly needs no more; across dates the quick
    # pose is mostly rejected, at the cost of a descriptor product and a RANSAC. None: for
    # learned matchers (the backend's padded batching); it needs float descriptors.
    quick: bool | None = None
    quick_min_cosine: float = 0.8
    quick_radius_px: float = 12.0
    quick_ratio: float = 0.95
    # Without a position prior: this many tiles from the map's global index (if it has one);
    # 0 matches every tile (brute force).
    global_candidates: int = 10
    batch_tiles: int = 16
    rotation_trials: int = 4
    min_frame_keypoints: int = 30
    # At most this many of the frame's keypoints per 1000 pixels of its view (the warped frame's
    # valid part), the strongest (None: all it has). A LightGlue-type matcher costs the product
    # of the two sets' sizes; the cascade's fine stage, whose placement is already known, keeps
    # 10 (see FineConfig): a budget sized to the view, not a count.
    frame_keypoint_density: float | None = None
    min_inliers: int = 12
    # Inliers the pose is refined on (None: all), spread over the frame and best placed by the
    # homography first: the refinement's cost follows its points, while its weight stops growing
    # at ``effective_inliers``.
    pose_points: int | None = 120
    min_inlier_ratio: float = 0.10
    # Share of the frame the inliers' convex hull must cover where the tilt is the image's own
    # (no roll/pitch prior followed). A small patch pins position but not tilt, and the fit's
    # sigma cannot tell (the cases measured on real photos: docs/how-it-works.md).
    min_inlier_spread: float = 0.08
    # Reprojection RMSE of the refined pose in frame pixels (times the map's pixel size in frame
    # pixels where the map is coarser): what the pose model does not explain.
    max_rmse_px: float = 3.0
    max_anisotropy: float = 1.6
    max_tilt_deg: float = 30.0
    altitude_ratio: float = 1.6
    max_heading_error_deg: float = 30.0
    sigma_floor_px: float = 0.5
    # Covariance model (see Localizer._covariance): inliers beyond which errors stop averaging out,
    # the horizontal error a DSM-based pose keeps, the terrain slope flat ground must allow for.
    effective_inliers: int = 20
    terrain_sigma_m: float = 0.3
    flat_slope: float = 0.03
    # The pose refitted without each fifth of its inliers in turn (the jackknife): where that
    # moves the drone by more than this share of its height, a few matches decide the pose and it
    # is rejected (right and wrong fixes' moves on real photos: docs/how-it-works.md).
    jackknife_folds: int = 5
    max_jackknife_height: float = 0.05
    # The map's terrain (DSM) for the pose, when the package has one; False: flat ground.
    use_terrain: bool = True
    # Pitch/roll prior vs the image's own, a chi-square with 2 dof. Beyond ``conflict`` (99.9 %),
    # where the image also fits clearly worse with the prior (``refit_ratio``), the prior is wrong
    # (a sign error, a mount offset): ignored, the image's own pose taken. Beyond ``doubt`` (95 %)
    # otherwise, either may be wrong (a wrong prior, or a view that cannot tell its tilt): where
    # the two poses put the drone more than ``doubt_shift_m`` apart (a few degrees at 1000 m), the
    # fix is rejected; closer (a low flight), the prior is kept.
    attitude_doubt_chi2: float = 5.99
    attitude_conflict_chi2: float = 13.8
    attitude_doubt_shift_m: float = 20.0
    # The second check, independent of the tilts' chi-square (which a weak view passes with any
    # prior: its own tilt is too loose to contradict one): the prior may move the fix from the
    # image's own pose by at most this much, and that move joins the fix's sigma. Were the prior
    # wrong, the fix would be about that far off: no farther than the 50 m a fix may be, and
    # within its 3 sigma.
    attitude_max_shift_m: float = 50.0
    # Beyond ``conflict``, the prior is ignored only where the image fits worse with it than
    # without by this RMSE ratio (flipped NAIP priors: 1.17-2.5); closer, the image cannot tell its
    # own tilt (a real photo over a flat field: 1.05-1.13, its free tilt 10-22 deg off).
    attitude_refit_ratio: float = 1.15
    # Inliers a view needs to overrule the autopilot's attitude: a weak match that contradicts it
    # is as likely wrong as the prior. Across NAIP dates, wrong poses of 41-67 inliers fitting
    # 1.2-1.6x worse with the prior were 130-350 m off (XFeat, DISK; a SIFT one of 12, 120 m);
    # right ones overruling a flipped prior on Seneca had 100-250, or 52-74 fitting 16-22x worse.
    # So: ``attitude_overrule_inliers``, or ``attitude_overrule_clear_inliers`` where the image
    # fits at least ``attitude_overrule_clear_ratio`` times worse with the prior.
    attitude_overrule_inliers: int = 100
    attitude_overrule_clear_inliers: int = 40
    attitude_overrule_clear_ratio: float = 2.0

    def __post_init__(self) -> None:
        if self.ransac not in _RANSAC_METHODS:
            raise OrthonavError(
                f"localizer ransac: expected one of {sorted(_RANSAC_METHODS)}, got {self.ransac!r}"
            )
        if not 0.0 <= self.guided_altitude_fraction < 1.0:
            raise OrthonavError(
                f"localizer guided_altitude_fraction {self.guided_altitude_fraction}: "
                "expected a share in [0, 1)"
            )
        radii_ok = self.guided_min_radius_px > 0 and self.guided_max_candidates > 0
        if not (radii_ok and 0 < self.guided_ratio <= 1):
            raise OrthonavError(
                "localizer guided matching: expected guided_min_radius_px and guided_max_candidates "
                "above 0 and guided_ratio in (0, 1]"
            )
        quick_ok = (
            -1.0 < self.quick_min_cosine < 1.0 and self.quick_radius_px > 0 and 0 < self.quick_ratio <= 1
        )
        if not quick_ok:
            raise OrthonavError(
                "localizer quick matching: expected quick_min_cosine in (-1, 1), quick_radius_px above 0 "
                "and quick_ratio in (0, 1]"
            )
        if self.batch_tiles < 1 or self.rotation_trials < 1:
            raise OrthonavError("localizer batch_tiles and rotation_trials: expected at least 1")
        if not 0.0 <= self.min_inlier_spread < 1.0:
            raise OrthonavError(
                f"localizer min_inlier_spread {self.min_inlier_spread}: "
                "expected a share of the frame in [0, 1)"
            )
        if self.jackknife_folds < 2 or not self.max_jackknife_height > 0:
            raise OrthonavError(
                f"localizer jackknife_folds {self.jackknife_folds} and max_jackknife_height "
                f"{self.max_jackknife_height}: expected at least 2 folds and a share of the height above 0"
            )
        if not self.attitude_max_shift_m > 0:
            raise OrthonavError(
                f"localizer attitude_max_shift_m {self.attitude_max_shift_m}: expected metres above 0"
            )
        if self.pose_points is not None and self.pose_points < POSE_UNKNOWNS:
            raise OrthonavError(
                f"localizer pose_points {self.pose_points}: expected None or at least "
                f"{POSE_UNKNOWNS} (a pose's unknowns)"
            )
        density = self.frame_keypoint_density
        if density is not None and not (math.isfinite(density) and density > 0):
            raise OrthonavError(
                f"localizer frame_keypoint_density {density}: expected None or keypoints per 1000 "
                "view pixels above 0"
            )

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class _Tile:
    """A tile's features as its backend matches them (tile px) and their map px."""

    features: FeatureSet
    map_px: np.ndarray


@dataclass
class _Correspondences:
    frame_px: np.ndarray  # (M, 2) original frame pixels, undistorted, camera-model coordinates
    map_px: np.ndarray  # (M, 2) work-grid pixels
    warped_px: np.ndarray  # (M, 2) warped frame pixels
    tiles: int
    image_px: np.ndarray  # (M, 2) original frame pixels as in the image (OpenCV coordinates)
    map_keypoints: int  # the map keypoints the frame was matched against


@dataclass
class _Attempt:
    """What one frame is matched on: its features and warp, the tiles (or their mosaic), the
    prior, the frame's deadline; each match judged adds its times to ``timings``."""

    frame_features: FeatureSet
    warp: NorthUp
    tiles: list[_Tile]
    n_tiles: int  # the candidate tiles, before a mosaic merged them
    mosaic: bool
    prior: Prior
    timings: dict[str, float]
    deadline: FrameDeadline


# How a frame's keypoints are matched (the matching steps' costs are kept apart).
GUIDED, QUICK, MATCHER = "guided", "quick", "matcher"


class StepCosts:
    """What the localizer's steps took on recent measured frames (:class:`StageCost`): the
    extraction (warp included) and the pose (RANSAC, refinement, checks) in milliseconds, each
    way of matching per square of the frame and map keypoints together (a LightGlue-type matcher
    attends over both sets at once, its map side alone costing most of a pass where the frame
    keeps few; for the other matchers an overestimate, on the safe side). Once started a step
    cannot be cut short, so a frame's deadline lets one start only where the time left affords
    it and what must follow it, and keeps the frame keypoints matched to those the time left
    affords."""

    def __init__(self) -> None:
        self.extract = StageCost()
        self.pose = StageCost()
        self.match = {kind: StageCost() for kind in (GUIDED, QUICK, MATCHER)}

    def add_match(
        self, kind: str, ms: float, frame_keypoints: int, map_keypoints: int, deadline: FrameDeadline
    ) -> None:
        """A match of ``frame_keypoints`` on ``map_keypoints`` by ``kind`` that took ``ms``."""
        self.match[kind].add(ms / max(frame_keypoints + map_keypoints, 1) ** 2, deadline)

    def match_ms(self, kind: str, frame_keypoints: int, map_keypoints: int | None) -> float:
        """What matching ``frame_keypoints`` on ``map_keypoints`` by ``kind`` is likely to take
        (0 where the map keypoints are not known yet)."""
        if map_keypoints is None:
            return 0.0
        return self.match[kind].likely_ms * (frame_keypoints + map_keypoints) ** 2

    def affordable_keypoints(self, kind: str, left_ms: float, map_keypoints: int | None) -> float:
        """The frame keypoints ``kind`` of matching can match on ``map_keypoints`` in ``left_ms``
        (infinite while its cost or the map keypoints are unknown, or the frame unbounded)."""
        per_square = self.match[kind].likely_ms
        if per_square <= 0.0 or map_keypoints is None or math.isinf(left_ms):
            return math.inf
        return max(0.0, math.sqrt(max(0.0, left_ms) / per_square) - map_keypoints)


class Localizer:
    """Localizes frames of one camera against one map package (loaded once, reused).

    ``backend`` defaults to the one that built the map, on the CPU; pass one made with
    :meth:`MapPackage.create_backend` to choose a device or relocate weight files.
    """

    def __init__(
        self,
        package: MapPackage,
        camera: Camera,
        config: LocalizerConfig | None = None,
        backend: FeatureBackend | None = None,
    ) -> None:
        self.package = package
        self.camera = camera
        self.config = config or LocalizerConfig()
        if backend is not None:
            check_backend(package, backend.name)
        self.backend = backend or package.create_backend()
        if self.config.quick and np.dtype(self.backend.descriptor_dtype).kind != "f":
            raise OrthonavError(
                f"localizer quick matching: {self.backend.name}'s descriptors are binary; "
                "mutual nearest cosines need float descriptors"
            )
        self._tile_cache: dict[int, _Tile] = {}
        self.costs = StepCosts()

    def localize(
        self,
        frame: np.ndarray,
        prior: Prior | None = None,
        candidates: np.ndarray | None = None,
        deadline: FrameDeadline | None = None,
    ) -> Fix:
        """Localize one frame (H, W) gray or (H, W, 3) BGR uint8 of this camera's size.

        ``deadline``: the frame's budget (None: unbounded). A step is started only where the time
        left affords what it takes (:class:`StepCosts`), and the frame keypoints matched are
        those it affords; a frame cut short is a rejection whose reason starts with "deadline",
        never a pose that did not pass every check."""
        prior = prior or Prior()
        self._check_inputs(frame, prior)
        gray = _to_gray(frame)
        deadline = deadline or FrameDeadline(None)
        if prior.heading_deg is not None or self.backend.rotation_invariant:
            return self._localize_at(gray, prior, candidates, prior.heading_deg or 0.0, deadline)
        return self._try_rotations(gray, prior, candidates, deadline)

    def frame_features(self, frame: np.ndarray, prior: Prior) -> FeatureSet:
        """The frame's features as they are matched: at the map's ground resolution, north-up for
        the prior's heading."""
        return self.frame_view(frame, prior).features

    def frame_view(self, frame: np.ndarray, prior: Prior) -> FrameView:
        """The frame as it is matched (warped image, mask, features), e.g. to search the global index."""
        self._check_inputs(frame, prior)
        return self.package.frame_view(self.camera, frame, prior, self.backend)

    def _try_rotations(
        self, gray: np.ndarray, prior: Prior, candidates: np.ndarray | None, deadline: FrameDeadline
    ) -> Fix:
        """No heading and no rotation invariance: try evenly spaced headings until one fixes.

        The trial that fixes may be up to 180/trials deg off; its estimated heading then
        de-rotates the frame exactly, and a second pass at it is as precise as one with a
        heading prior (kept when it passes too). A trial the deadline cut ends the search.
        """
        best: Fix | None = None
        spent = 0.0
        for k in range(self.config.rotation_trials):
            fix = self._localize_at(
                gray, prior, candidates, 360.0 * k / self.config.rotation_trials, deadline
            )
            spent += fix.timings_ms["total_ms"]
            if _cut(fix):
                best = fix
                break
            if best is None or fix.accepted or fix.quality.get("inliers", 0) > best.quality.get("inliers", 0):
                best = fix
            if fix.accepted:
                again = self._localize_at(gray, prior, candidates, fix.pose.heading_deg, deadline)
                spent += again.timings_ms["total_ms"]
                best = again if again.accepted else fix
                break
        best.quality["rotation_trials"] = k + 1
        best.timings_ms["total_ms"] = spent
        return best

    def _localize_at(
        self,
        gray: np.ndarray,
        prior: Prior,
        candidates: np.ndarray | None,
        heading_deg: float,
        deadline: FrameDeadline,
    ) -> Fix:
        """One attempt with the frame rotated north-up for ``heading_deg``."""
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        if prior.alt_agl_m is not None:
            try:  # a frame too small at the map's resolution: the geometry is wrong, not the view
                short_side_m = min(self.camera.nadir_footprint_m(prior.alt_agl_m))
                check_footprint(short_side_m, self.package.gsd_m, prior.alt_agl_m, "prior altitude")
            except OrthonavError as exc:
                return self._reject(str(exc), {}, timings, t0)
        costs, kind = self.costs, self._expected_kind(prior)
        map_keypoints = self._expected_map_keypoints(prior, candidates)
        # The extraction, then at least the fewest keypoints matched and a pose, must fit.
        least_ms = costs.pose.likely_ms + costs.match_ms(kind, self.config.min_frame_keypoints, map_keypoints)
        cut = deadline.unaffordable(costs.extract, "the keypoint extraction", least_ms)
        if cut:
            return self._reject(cut, {}, timings, t0)
        alt_agl_m = prior.alt_agl_m or self.package.tiling.nominal_alt_m
        warp = north_up(gray, self.camera, self.package.gsd_m, alt_agl_m, heading_deg)
        timings["warp_ms"] = elapsed_ms(t0)
        t_extract = time.perf_counter()
        # The keypoints matching affords after the extraction and the pose (never fewer than a
        # view needs: fewer would be judged a blank view); ALIKED describes only those asked for.
        after_ms = deadline.left_ms() - costs.extract.likely_ms - costs.pose.likely_ms
        affordable = costs.affordable_keypoints(kind, after_ms, map_keypoints)
        affordable = max(affordable, self.config.min_frame_keypoints)
        limit = _at_most(self._frame_budget(warp.mask), affordable)
        frame_features = self.backend.extract_strongest(warp.gray, warp.mask, limit)
        timings["extract_ms"] = elapsed_ms(t_extract)
        costs.extract.add(elapsed_ms(t0), deadline)
        quality: dict[str, float] = {"keypoints": len(frame_features)}
        if len(frame_features) < self.config.min_frame_keypoints:
            return self._reject(
                f"only {len(frame_features)} features in the frame (need "
                f"{self.config.min_frame_keypoints}): blank, uniform or blurred view",
                quality,
                timings,
                t0,
            )
        view = FrameView(warp.gray, warp.mask, frame_features)
        tiles = self._candidates(prior, view) if candidates is None else np.asarray(candidates)
        mosaic = prior.has_position and len(tiles) > 1 and self._mosaic_wanted()
        quick = prior.has_position and self.descriptors_first
        attempt = _Attempt(frame_features, warp, [], len(tiles), mosaic, prior, timings, deadline)
        fix = self._match_and_estimate(attempt, tiles, dict(quality), quick)
        if mosaic and not fix.accepted and not _cut(fix):
            # Across dates a learned matcher can find less in the mosaic than tile by tile (ALIKED
            # fixed more NAIP frames tile by tile). The second attempt's quality starts afresh: no
            # flag of the first may judge it.
            retry = {**quality, "mosaic_fallback": 1.0}
            fix = self._match_and_estimate(replace(attempt, mosaic=False), tiles, retry, False)
        timings["total_ms"] = elapsed_ms(t0)
        fix.timings_ms = timings
        fix.method = self.package.backend_name
        return fix

    def _match_and_estimate(self, attempt: _Attempt, tiles: np.ndarray, quality: dict, quick: bool) -> Fix:
        """Match the frame on the tiles (or their mosaic) and judge the pose; the stages' times
        add to ``attempt.timings``. Guided where the prior allows it, else ``quick``ly where that
        is accepted, else by the backend's matcher."""
        t1 = time.perf_counter()
        prior, warp = attempt.prior, attempt.warp
        loaded = [self._tile(int(t)) for t in tiles]
        if attempt.mosaic:
            loaded = [self._mosaic(loaded, prior)]
        radius = self._guided_radius_px(prior, loaded)
        attempt.timings["match_ms"] = attempt.timings.get("match_ms", 0.0) + elapsed_ms(t1)
        attempt = replace(attempt, tiles=loaded)
        if radius is not None:

            def guided(features: FeatureSet) -> list[Matches]:
                predicted = self._predicted_by_prior(features, warp, prior)
                return _guided(features, predicted, loaded, radius, self.config.guided_ratio)

            return self._judge_matches(attempt, quality, GUIDED, guided)[0]
        if quick:
            fix = self._quick(attempt, quality)
            if fix.accepted or _cut(fix):
                return fix
            quality["quick"] = 0.0
        return self._judge_matches(
            attempt, quality, MATCHER, lambda features: self._match_tiles(features, loaded)
        )[0]

    def _quick(self, attempt: _Attempt, quality: dict) -> Fix:
        """Mutual nearest descriptors; where their pose is accepted, the match its homography
        guides, whose verdict is the fix's (see ``LocalizerConfig.quick``)."""
        cfg = self.config
        tiles = attempt.tiles

        def nearest(features: FeatureSet) -> list[Matches]:
            return [mutual_nearest(features, t.features, cfg.quick_min_cosine, len(features)) for t in tiles]

        first, h_warp = self._judge_matches(attempt, {**quality, "quick": 1.0}, QUICK, nearest)
        if not first.accepted or h_warp is None:
            return first

        def around(features: FeatureSet) -> list[Matches]:
            predicted = apply_homography(h_warp, features.keypoints.astype(np.float64))
            return _guided(features, predicted, tiles, cfg.quick_radius_px, cfg.quick_ratio)

        return self._judge_matches(attempt, {**quality, "quick": 1.0}, QUICK, around)[0]

    def _judge_matches(
        self,
        attempt: _Attempt,
        quality: dict,
        kind: str,
        match: Callable[[FeatureSet], list[Matches]],
    ) -> tuple[Fix, np.ndarray | None]:
        """``match``'s matches of the frame keypoints merged and judged (see :meth:`_estimate`),
        timed as match and pose. Of the frame keypoints, the strongest the time left affords
        (after the pose's expected time) are matched; too few of them, or too little time left
        for the pose, is a rejection that says the deadline cut the frame."""
        costs, deadline = self.costs, attempt.deadline
        map_keypoints = sum(len(tile.features) for tile in attempt.tiles)
        affordable = costs.affordable_keypoints(
            kind, deadline.left_ms() - costs.pose.likely_ms, map_keypoints
        )
        if affordable < self.config.min_frame_keypoints:
            need_ms = (
                costs.match_ms(kind, self.config.min_frame_keypoints, map_keypoints) + costs.pose.likely_ms
            )
            costs.match[kind].skipped()
            left = f"{deadline.left_ms():.0f} ms left, it and the pose take about {need_ms:.0f} ms"
            return Fix(False, f"{deadline.why('the keypoint matching')}: {left}", quality=quality), None
        features = attempt.frame_features.strongest(_at_most(None, affordable))
        if len(features) < len(attempt.frame_features):
            quality["deadline_keypoints"] = float(len(features))
        t1 = time.perf_counter()
        corr = self._correspondences(features, attempt.warp, attempt.tiles, match(features), attempt.n_tiles)
        match_ms = elapsed_ms(t1)
        attempt.timings["match_ms"] = attempt.timings.get("match_ms", 0.0) + match_ms
        costs.add_match(kind, match_ms, len(features), map_keypoints, deadline)
        quality.update(
            matches=len(corr.map_px),
            tiles=corr.tiles,
            map_keypoints=corr.map_keypoints,
            mosaic=float(attempt.mosaic),
        )
        cut = deadline.unaffordable(costs.pose, "the keypoint pose")
        if cut:
            return Fix(False, cut, quality=quality), None
        t2 = time.perf_counter()
        verdict = self._estimate(corr, attempt.prior, quality)
        pose_ms = elapsed_ms(t2)
        attempt.timings["pose_ms"] = attempt.timings.get("pose_ms", 0.0) + pose_ms
        costs.pose.add(pose_ms, deadline)
        return verdict

    @property
    def descriptors_first(self) -> bool:
        """Whether frames are matched by mutual nearest descriptors before the backend's matcher
        (``LocalizerConfig.quick``; by default for LightGlue-type matchers)."""
        return self._learned_default(self.config.quick)

    def measure_matching(self, frame: np.ndarray, prior: Prior, deadline: FrameDeadline) -> None:
        """Every way of matching but the guided one timed on ``frame`` at ``prior``'s nearest
        tile (kept where ``deadline`` is measured): a warm-up's frame, placed surely enough for
        guided matching, never asks for them, and a flight's first frame with a wide prior would
        otherwise start one with its cost unknown. A matcher that cannot load is left unmeasured
        (the frames that need it say why)."""
        self._check_inputs(frame, prior)
        warp = north_up(
            _to_gray(frame),
            self.camera,
            self.package.gsd_m,
            self._expected_alt(prior),
            prior.heading_deg or 0.0,
        )
        features = self.backend.extract_strongest(warp.gray, warp.mask, self._frame_budget(warp.mask))
        tiles = [self._tile(int(t)) for t in prior_tiles(self.package, prior, 1)]
        ways: dict[str, Callable[[], list[Matches]]] = {MATCHER: lambda: self._match_tiles(features, tiles)}
        if self.descriptors_first:
            cosine = self.config.quick_min_cosine
            ways[QUICK] = lambda: [mutual_nearest(features, t.features, cosine, len(features)) for t in tiles]
        map_keypoints = sum(len(tile.features) for tile in tiles)
        for kind, match in ways.items():
            start = time.perf_counter()
            try:
                match()
            except (OrthonavError, ImportError):
                continue
            self.costs.add_match(kind, elapsed_ms(start), len(features), map_keypoints, deadline)

    def _expected_map_keypoints(self, prior: Prior, candidates: np.ndarray | None) -> int | None:
        """The map keypoints a frame at ``prior`` will be matched on, where known before its
        extraction (its candidate tiles, or the prior's; a lost frame's: None)."""
        if candidates is None and not prior.has_position:
            return None
        tiles = (
            candidates
            if candidates is not None
            else prior_tiles(self.package, prior, self.config.max_prior_candidates)
        )
        return sum(len(self._tile(int(t)).features) for t in tiles)

    def _expected_kind(self, prior: Prior) -> str:
        """How the frame's keypoints will most likely be matched with ``prior`` (the guided
        radius can still fall back to the matcher where the map is too dense for it)."""
        guided = self.config.guided and prior.has_position and prior.heading_deg is not None
        return GUIDED if guided else MATCHER

    def _learned_default(self, setting: bool | None) -> bool:
        """A setting that, left unset (None), is on for LightGlue-type matchers (padded batching)."""
        return self.backend.padded_batching if setting is None else setting

    # --- steps ---------------------------------------------------------------------------
    def _check_inputs(self, frame: np.ndarray, prior: Prior) -> None:
        if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim not in (2, 3):
            raise OrthonavError("frame: expected an (H, W) or (H, W, 3) uint8 image")
        h, w = frame.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise OrthonavError(
                f"frame: {w}x{h} px but the camera is {self.camera.width}x{self.camera.height}; "
                "pass the matching camera (--camera)"
            )
        # A prior off the map by more than its 3-sigma cannot be matched against it.
        if prior.has_position and not self.package.within_reach(prior.lat, prior.lon, prior.sigma_m):
            raise OrthonavError(
                f"prior position outside the map {self.package.path} by more than 3 x its sigma of "
                f"{prior.sigma_m:.0f} m: it is {self.package.away([prior.lat], [prior.lon])}"
            )

    def _frame_budget(self, mask: np.ndarray) -> int | None:
        """The frame keypoints kept for a view of this valid area (None: all)."""
        density = self.config.frame_keypoint_density
        if density is None:
            return None
        return max(self.config.min_frame_keypoints, round(density * np.count_nonzero(mask) / 1000.0))

    def _expected_alt(self, prior: Prior) -> float:
        return prior.alt_agl_m or self.package.tiling.nominal_alt_m

    def _candidates(self, prior: Prior, view: FrameView) -> np.ndarray:
        if not prior.has_position:
            index = self.package.global_index
            if index is None or self.config.global_candidates <= 0:
                return cand.all_tiles(self.package)
            return index.search(view, self.config.global_candidates)[0]
        return prior_tiles(self.package, prior, self.config.max_prior_candidates)

    def _tile(self, index: int) -> _Tile:
        if index not in self._tile_cache:
            self._tile_cache[index] = _Tile(
                self.package.tile_features(index), self.package.tile_keypoints_map_px(index)
            )
        return self._tile_cache[index]

    def _match_tiles(self, frame_features: FeatureSet, tiles: list[_Tile]) -> list[Matches]:
        """The frame against every tile, ``batch_tiles`` tiles per backend call."""
        step = self.config.batch_tiles
        found: list[Matches] = []
        for start in range(0, len(tiles), step):
            chunk = [t.features for t in tiles[start : start + step]]
            found += self.backend.match_many(frame_features, chunk)
        return found

    def _correspondences(
        self,
        frame_features: FeatureSet,
        warp: NorthUp,
        tiles: list[_Tile],
        found: list[Matches],
        n_tiles: int,
    ) -> _Correspondences:
        """Matches on each of ``tiles`` merged in map pixels, duplicates dropped on a grid (best
        distance wins)."""
        q_idx, map_pts, dists = [], [], []
        for tile, m in zip(tiles, found, strict=True):
            if len(m):
                q_idx.append(m.pairs[:, 0])
                map_pts.append(tile.map_px[m.pairs[:, 1]])
                dists.append(m.distances)
        map_keypoints = sum(len(tile.features) for tile in tiles)
        if not q_idx:
            empty = np.zeros((0, 2))
            return _Correspondences(empty, empty, empty, n_tiles, empty, map_keypoints)
        q = np.concatenate(q_idx)
        mp = np.concatenate(map_pts).astype(np.float64)
        d = np.concatenate(dists)
        cells = np.floor(mp / self.config.dedup_cell_px).astype(np.int64)
        keys = np.column_stack([q, cells])
        order = np.argsort(d, kind="stable")
        _, first = np.unique(keys[order], axis=0, return_index=True)
        keep = order[first]
        warped = frame_features.keypoints[q[keep]].astype(np.float64)
        # Back to frame pixels, then from OpenCV's (pixel centre at 0) to the camera model's
        # coordinates (origin at the image corner: pixel centre at 0.5).
        image_px = apply_homography(np.linalg.inv(warp.affine), warped)
        frame_px = self.camera.undistort_points(image_px + 0.5)
        return _Correspondences(frame_px, mp[keep], warped, n_tiles, image_px, map_keypoints)

    def _mosaic_wanted(self) -> bool:
        return self._learned_default(self.config.mosaic)

    def _predicted_by_prior(self, frame_features: FeatureSet, warp: NorthUp, prior: Prior) -> np.ndarray:
        """(N, 2) map pixels where the prior's pose puts each frame keypoint."""
        image_px = apply_homography(np.linalg.inv(warp.affine), frame_features.keypoints.astype(np.float64))
        ideal_px = self.camera.undistort_points(image_px + 0.5)
        ground = pixel_to_ground(self.camera, self._prior_pose(prior), ideal_px)
        return self._map_px(prior, ground)

    def _prior_pose(self, prior: Prior) -> CameraPose:
        """The prior as a camera pose at the origin of its local frame (level if it has no attitude)."""
        pitch, roll = (prior.pitch_deg, prior.roll_deg) if prior.has_attitude else (0.0, 0.0)
        return CameraPose(0.0, 0.0, self._expected_alt(prior), prior.heading_deg, pitch, roll)

    def _map_px(self, prior: Prior, ground_en: np.ndarray) -> np.ndarray:
        """(N, 2) ground offsets (east, north metres) from the prior's position -> map pixels."""
        enu = LocalFrame.around(prior.lat, prior.lon)
        east, north = enu.to_enu(prior.lat, prior.lon)
        lat, lon = enu.to_latlon(ground_en[:, 0] + east, ground_en[:, 1] + north)
        return np.column_stack(self.package.grid.latlon_to_pixel(lat, lon))

    def _guided_radius_px(self, prior: Prior, tiles: list[_Tile]) -> float | None:
        """The guided search radius in map pixels, or None where matching is not guided (not
        asked for, no position or heading, the horizon in view, too many map keypoints within the
        radius): the root sum of squares of the prior's 2-sigma position and of how far a frame
        corner moves for 2 sigma of heading, the altitude's share and 3 sigma of tilt (the whole
        ``max_tilt_deg`` without an attitude)."""
        cfg = self.config
        if not (cfg.guided and prior.has_position and prior.heading_deg is not None):
            return None
        alt = self._expected_alt(prior)
        try:
            corners = footprint_enu(self.camera, self._prior_pose(prior))
        except OrthonavError:
            return None
        reach_m = float(np.hypot(*corners.T).max())
        tilt_deg = 3.0 * prior.attitude_sigma_deg if prior.has_attitude else cfg.max_tilt_deg
        margin_m = math.hypot(
            2.0 * prior.sigma_m,
            reach_m * math.sin(math.radians(min(90.0, 2.0 * prior.heading_sigma_deg))),
            reach_m * cfg.guided_altitude_fraction,
            alt * math.tan(math.radians(tilt_deg)),
        )
        radius_px = max(cfg.guided_min_radius_px, margin_m / self.package.gsd_m)
        area_px = sum(math.prod(t.features.image_size or (0, 0)) for t in tiles)
        density = sum(len(t.features) for t in tiles) / max(area_px, 1)
        return radius_px if density * math.pi * radius_px**2 <= cfg.guided_max_candidates else None

    def _mosaic(self, tiles: list[_Tile], prior: Prior) -> _Tile:
        """The tiles' keypoints within reach of the prior as one feature set, in map pixels less
        their corner; a keypoint that overlapping tiles both found, once."""
        map_px = np.concatenate([t.map_px for t in tiles]).astype(np.float64)
        scores = np.concatenate([t.features.scores for t in tiles])
        descriptors = np.concatenate([t.features.descriptors for t in tiles])
        footprint_m = math.hypot(*self.camera.nadir_footprint_m(self._expected_alt(prior)))
        # The drone within 2 sigma of the prior; the frame's corners up to 0.6 of its nadir
        # diagonal from it (tilt, altitude error).
        reach_px = (2.0 * prior.sigma_m + 0.6 * footprint_m) / self.package.gsd_m
        centre = np.array(self.package.grid.latlon_to_pixel(prior.lat, prior.lon), dtype=np.float64)
        near = np.flatnonzero(np.hypot(*(map_px - centre).T) <= reach_px)
        near = near[np.argsort(-scores[near], kind="stable")]
        # Overlapping tiles found many keypoints twice, a fraction of a pixel apart: the best
        # scored one stays, every weaker one within ``mosaic_merge_px`` of a better one goes.
        pairs = cKDTree(map_px[near]).query_pairs(self.config.mosaic_merge_px, output_type="ndarray")
        weaker = np.zeros(len(near), bool)
        weaker[pairs[:, 1]] = True  # pairs (i, j) with i < j: j scored lower
        keep = np.sort(near[~weaker])
        if len(keep) == 0:
            return _Tile(self.backend.empty(), np.zeros((0, 2)))
        corner = np.floor(map_px[keep].min(0))
        local = (map_px[keep] - corner).astype(np.float32)
        size = tuple(int(v) for v in np.ceil(local.max(0)) + 1)
        return _Tile(FeatureSet(local, descriptors[keep], scores[keep], size), map_px[keep])

    def _estimate(self, corr: _Correspondences, prior: Prior, quality: dict) -> tuple[Fix, np.ndarray | None]:
        """The verdict on the matches, and the RANSAC homography (warped frame px -> map px)
        where one was found."""
        cfg = self.config
        n = len(corr.map_px)
        if n < max(cfg.min_inliers, 4):
            reason = f"only {n} matches (need {cfg.min_inliers}): the view does not match the map"
            return Fix(False, reason, quality=quality), None
        h_warp, inl = cv2.findHomography(
            corr.warped_px,
            corr.map_px,
            _RANSAC_METHODS[cfg.ransac],
            cfg.ransac_threshold_px,
            maxIters=cfg.ransac_iterations,
            confidence=0.999,
        )
        if h_warp is None or inl is None:
            return Fix(False, "no homography found by RANSAC", quality=quality), None
        inliers = inl.ravel().astype(bool)
        quality.update(inliers=int(inliers.sum()), inlier_ratio=float(inliers.mean()))
        fix = self._judge(corr, inliers, h_warp, prior, quality)
        # Kept whatever the verdict: a rejected fix's matches show why it was rejected.
        kept = _even_sample(np.flatnonzero(inliers), MAX_KEPT_INLIERS)
        fix.inliers_frame_px, fix.inliers_map_px = corr.image_px[kept], corr.map_px[kept]
        return fix, h_warp

    def _judge(
        self, corr: _Correspondences, inliers: np.ndarray, h_warp: np.ndarray, prior: Prior, quality: dict
    ) -> Fix:
        """The RANSAC inliers' verdict: enough of them, a plausible homography, then the pose."""
        cfg = self.config
        if inliers.sum() < cfg.min_inliers:
            return Fix(False, f"only {int(inliers.sum())} inliers (need {cfg.min_inliers})", quality=quality)
        if inliers.mean() < cfg.min_inlier_ratio:
            ratio = beyond(inliers.mean(), cfg.min_inlier_ratio, 2)
            return Fix(False, f"inlier ratio {ratio} below {cfg.min_inlier_ratio:g}", quality=quality)
        quality["inlier_spread"] = self._spread(corr.frame_px[inliers])
        anisotropy = _anisotropy(h_warp, corr.warped_px[inliers].mean(0))
        quality["anisotropy"] = anisotropy
        if not anisotropy <= cfg.max_anisotropy:
            return Fix(
                False,
                f"homography is sheared or flipped (anisotropy {anisotropy:.2f} > {cfg.max_anisotropy})",
                quality=quality,
            )
        refined = self._pose_points(corr, inliers, h_warp)
        quality["pose_points"] = len(refined)
        return self._pose(corr.frame_px[inliers], corr.map_px[inliers], prior, quality, refined)

    def _pose_points(self, corr: _Correspondences, inliers: np.ndarray, h_warp: np.ndarray) -> np.ndarray:
        """Which inliers (positions among them) the pose is refined on: at most ``pose_points``,
        on a grid over the frame the one the homography places best in each cell, then the second
        best, and so on."""
        index = np.flatnonzero(inliers)
        limit = self.config.pose_points
        if limit is None or len(index) <= limit:
            return np.arange(len(index))
        placed = apply_homography(h_warp, corr.warped_px[index])
        error = np.hypot(*(placed - corr.map_px[index]).T)
        side = math.ceil(math.sqrt(limit))
        size = np.array([self.camera.width, self.camera.height])
        col, row = np.clip(np.floor(corr.frame_px[index] / size * side), 0, side - 1).astype(int).T
        cell = row * side + col
        by_cell = np.lexsort((error, cell))
        rank = np.empty(len(index), int)
        rank[by_cell] = np.arange(len(index)) - np.searchsorted(cell[by_cell], cell[by_cell])
        return np.sort(np.lexsort((error, rank))[:limit])

    def _spread(self, frame_px: np.ndarray) -> float:
        """The share of the frame the inliers' convex hull covers."""
        hull = cv2.convexHull(np.asarray(frame_px, np.float32))
        return float(cv2.contourArea(hull)) / (self.camera.width * self.camera.height)

    def _pose(
        self, frame_px: np.ndarray, map_px: np.ndarray, prior: Prior, quality: dict, refined: np.ndarray
    ) -> Fix:
        """Frame px <-> ground points: homography -> initial pose, least-squares refinement on the
        terrain (the map's DSM, else flat ground), the attitude prior weighed in, then checks.
        The refinement and its jackknife see the ``refined`` points; the reprojection RMSE and
        what the plane does not explain are measured on every inlier.

        Roll/pitch from the autopilot are a soft prior with their sigma: a homography alone pins
        tilt poorly with a narrow field of view, and at height h a tilt error e moves the point
        under the drone by h tan(e). A prior that the image contradicts (beyond its sigma and the
        image's own precision) is reported in the quality and not followed.
        """
        grid = self.package.grid
        lat_c, lon_c = grid.pixel_to_latlon(*map_px.mean(0))
        enu = LocalFrame.around(float(lat_c), float(lon_c))
        x, y = grid.pixel_to_crs(map_px[:, 0], map_px[:, 1])
        ground = np.column_stack(enu.from_crs(grid.crs, x, y))
        points, datum_m = self._terrain_points(map_px, ground, quality)
        h_img, _ = cv2.findHomography(frame_px, ground, 0)
        if h_img is None:
            return Fix(False, "degenerate inlier geometry (no homography)", quality=quality)
        try:
            initial = pose_from_homography(self.camera, h_img)
        except OrthonavError as exc:
            return Fix(False, str(exc), quality=quality)
        few_px, few_points = frame_px[refined], points[refined]
        cam, cov, _ = self._refine_from_starts(few_px, few_points, initial, prior, quality)
        residuals = project_points(self.camera, cam, points) - frame_px
        rmse = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
        height = self._height_above_terrain(cam, enu, datum_m)
        rmse_map_px = rmse * self.camera.nadir_gsd_m(height) / self.package.gsd_m
        quality.update(rmse_px=rmse, rmse_map_px=rmse_map_px, tilt_deg=cam.tilt_deg, alt_m=height)
        lat, lon = enu.to_latlon(cam.east_m, cam.north_m)
        centre = self._centre_on_ground(cam, points)
        clat, clon = enu.to_latlon(*centre)
        pose = Pose(
            float(lat), float(lon), height, cam.yaw_deg, cam.pitch_deg, cam.roll_deg, float(clat), float(clon)
        )
        if datum_m is not None:
            quality["alt_datum_m"] = cam.alt_agl_m + datum_m
        reason = (
            self._check_pose(cam, rmse, prior, height)
            or self._check_spread(prior, quality)
            or self._check_attitude_agreement(quality)
            or self._check_prior_offset(pose, prior, quality)
        )
        if reason:
            return Fix(False, reason, pose=pose, quality=quality)
        jackknife = self._jackknife(few_px, few_points, cam, prior, quality)
        reason = self._check_stability(height, quality)
        if reason:
            return Fix(False, reason, pose=pose, quality=quality)
        flat_m = None if datum_m is not None else self._flat_ground_m(frame_px, points, cam, prior, quality)
        covariance = self._covariance(cov, jackknife, flat_m, quality)
        return Fix(True, pose=pose, covariance_enu_m2=covariance, quality=quality)

    @property
    def _terrain(self) -> Terrain | None:
        """The map's terrain when the pose is to be solved on it; None: flat ground."""
        return self.package.terrain if self.config.use_terrain else None

    def _terrain_points(
        self, map_px: np.ndarray, ground: np.ndarray, quality: dict
    ) -> tuple[np.ndarray, float | None]:
        """(N, 3) ENU points on the map's terrain, up from the median height of the matched
        points (the datum, returned); the flat (N, 2) ground when there is no terrain."""
        terrain = self._terrain
        heights = terrain.heights_at(map_px) if terrain is not None else None
        known = np.isfinite(heights) if heights is not None else None
        if known is None or known.mean() < 0.5:
            quality["terrain"] = 0.0
            return ground, None
        datum = float(np.median(heights[known]))
        quality.update(terrain=1.0, relief_m=float(np.ptp(heights[known])))
        return np.column_stack([ground, np.where(known, heights - datum, 0.0)]), datum

    def _refine(
        self, frame_px: np.ndarray, points: np.ndarray, initial: CameraPose, prior: Prior, quality: dict
    ) -> tuple[CameraPose, np.ndarray, float]:
        """The image alone first; then with the attitude prior, unless the image contradicts it.

        The image's own tilt can be precise in its covariance and still wrong: over a flat field a
        narrow lens fits a tilt 20 deg off about as well (a real photo at 65 m, 28 m off). So a
        prior the image disagrees with is weighed by how much worse the image fits with it: much
        worse, the prior is wrong and ignored; about as well, the view cannot tell its tilt, and
        where the two poses lie far apart the fix is doubtful (rejected by the checks). However
        well they agree, the prior's pose is kept with the image's own within its 2 sigma, and a
        prior that moves the fix beyond ``attitude_max_shift_m`` makes it doubtful too.
        """
        cfg = self.config
        effective = cfg.effective_inliers
        free = refine_pose(self.camera, frame_px, points, initial, robust=True, effective_points=effective)
        if not prior.has_attitude:
            return free
        att = AttitudePrior(prior.pitch_deg, prior.roll_deg, prior.attitude_sigma_deg)
        cam, cov, rmse = free
        offset = np.array([cam.pitch_deg - att.pitch_deg, cam.roll_deg - att.roll_deg])
        spread = cov[4:6, 4:6] + np.eye(2) * att.sigma_deg**2
        mahalanobis2 = float(offset @ np.linalg.solve(spread, offset))
        held_cam, held_cov, held_rmse = refine_pose(
            self.camera, frame_px, points, cam, attitude_prior=att, robust=True, effective_points=effective
        )
        shift_m = math.hypot(held_cam.east_m - cam.east_m, held_cam.north_m - cam.north_m)
        quality.update(
            attitude_prior_chi2=mahalanobis2,
            attitude_prior_rmse_ratio=held_rmse / max(rmse, 1e-9),
            attitude_prior_shift_m=shift_m,
        )
        if mahalanobis2 > cfg.attitude_conflict_chi2:
            quality["attitude_prior_conflict"] = 1.0
            if held_rmse > cfg.attitude_refit_ratio * rmse:
                quality["attitude_prior_ignored"] = 1.0  # the image contradicts the autopilot's attitude
                return free
        disagree = mahalanobis2 > cfg.attitude_doubt_chi2
        if (disagree and shift_m > cfg.attitude_doubt_shift_m) or shift_m > cfg.attitude_max_shift_m:
            quality["attitude_prior_doubtful"] = 1.0  # rejected by the checks, with its pose
        held_cov = held_cov.copy()
        held_cov[:2, :2] += np.eye(2) * (0.5 * shift_m) ** 2
        return held_cam, held_cov, held_rmse

    def _refine_from_starts(
        self, frame_px: np.ndarray, points: np.ndarray, initial: CameraPose, prior: Prior, quality: dict
    ) -> tuple[CameraPose, np.ndarray, float]:
        """The refinement from the homography's pose and, unless an attitude prior held it, from
        a level camera and from both poses the plane admits; the best fit kept.

        A nearly flat scene seen through a narrow lens pins the tilt poorly: the fit can settle in
        a second minimum about as good as the first, the frame centre in place but the camera
        tilted differently and the point under it metres off (a real photo at 65 m: 18 deg of
        pitch instead of 5, 15 m off, with a sigma of 2.9 m). Which minimum one start finds can
        tip with a CPU's rounding, so both are seeded (``planar_pose_candidates``), and half the
        distance to the farthest rival joins the position covariance: an ambiguous tilt is
        reported, not hidden, on every machine. An attitude prior that the fit followed pins the
        tilt itself, unless that fit explains the points poorly (a start that converged badly:
        60 px on a real photo, where the level start found the pose).
        """
        first_notes: dict = {}
        first = self._refine(frame_px, points, initial, prior, first_notes)
        prior_held = _followed_attitude(prior, first_notes) is not None
        if prior_held and first[2] <= self.config.max_rmse_px:
            quality.update(first_notes)
            return first
        starts = [replace(initial, pitch_deg=0.0, roll_deg=0.0)]
        starts += planar_pose_candidates(self.camera, frame_px, points)
        fits = [(first, first_notes)]
        for start in starts:
            notes: dict = {}
            fits.append((self._refine(frame_px, points, start, prior, notes), notes))
        (cam, cov, rmse), notes = min(fits, key=lambda fit: fit[0][2])
        rivals = [fit for fit, _ in fits if fit[2] <= TILT_RIVAL_RMSE_RATIO * rmse]  # not divergences
        apart_m = max(math.hypot(r.east_m - cam.east_m, r.north_m - cam.north_m) for r, _, _ in rivals)
        quality.update(notes, tilt_ambiguity_m=apart_m)
        cov = cov.copy()
        cov[:2, :2] += np.eye(2) * (0.5 * apart_m) ** 2
        return cam, cov, rmse

    def _height_above_terrain(self, cam: CameraPose, enu: LocalFrame, datum_m: float | None) -> float:
        """The camera's height above the terrain under it (the DSM's), else above the flat ground."""
        terrain = self._terrain
        if datum_m is None or terrain is None:
            return cam.alt_agl_m
        lat, lon = enu.to_latlon(cam.east_m, cam.north_m)
        below = float(terrain.heights_at_latlon(np.atleast_1d(lat), np.atleast_1d(lon))[0])
        return cam.alt_agl_m + datum_m - below if math.isfinite(below) else cam.alt_agl_m

    def _centre_on_ground(self, cam: CameraPose, points: np.ndarray) -> np.ndarray:
        """Where the principal ray meets the ground: the plane at the matched points' median height."""
        ray_cam = np.array([0.0, 0.0, 1.0])
        ray = rotation_enu_from_camera(cam.yaw_deg, cam.pitch_deg, cam.roll_deg) @ ray_cam
        level = float(np.median(points[:, 2])) if points.shape[1] == 3 else 0.0
        scale = (level - cam.alt_agl_m) / min(ray[2], -1e-6)
        return np.array([cam.east_m + ray[0] * scale, cam.north_m + ray[1] * scale])

    def _jackknife(
        self, frame_px: np.ndarray, points: np.ndarray, cam: CameraPose, prior: Prior, quality: dict
    ) -> np.ndarray:
        """The position's covariance by the delete-a-group jackknife: the pose refitted without
        each of ``jackknife_folds`` interleaved groups of inliers in turn (with the attitude prior
        where it was followed).

        The fit's own covariance trusts every match alike; where a few matches decide the pose
        (a weak view whose tilt they pull far off), leaving them out moves it, and this shows
        what the fit's covariance cannot.
        """
        cfg = self.config
        att = _followed_attitude(prior, quality)
        folds = np.arange(len(frame_px)) % cfg.jackknife_folds
        positions = []
        for fold in range(cfg.jackknife_folds):
            keep = folds != fold
            refit, _, _ = refine_pose(
                self.camera,
                frame_px[keep],
                points[keep],
                cam,
                attitude_prior=att,
                robust=True,
                effective_points=cfg.effective_inliers,
            )
            positions.append((refit.east_m, refit.north_m))
        spread = np.array(positions) - np.mean(positions, axis=0)
        covariance = (cfg.jackknife_folds - 1) / cfg.jackknife_folds * spread.T @ spread
        quality["jackknife_m"] = float(math.sqrt(np.trace(covariance)))
        return covariance

    def _check_stability(self, height_m: float, quality: dict) -> str:
        """Why a pose that a few of its matches decide is not trusted, if it is."""
        moved, limit = quality["jackknife_m"], self.config.max_jackknife_height * height_m
        if moved <= limit:
            return ""
        return (
            f"unstable pose: leaving out a fifth of the inliers moves it by {moved:.1f} m (more than "
            f"{limit:.1f} m, {self.config.max_jackknife_height:.0%} of the height): a few matches decide it"
        )

    def _flat_ground_m(
        self, frame_px: np.ndarray, ground: np.ndarray, cam: CameraPose, prior: Prior, quality: dict
    ) -> float:
        """The flat-ground allowance (see :mod:`uncertainty`), its measure in the quality; the
        matcher's noise is a pixel of the coarser of the frame and the map."""
        noise_px = max(1.0, self.package.gsd_m / self.camera.nadir_gsd_m(cam.alt_agl_m))
        residual_m = unexplained_m(self.camera, frame_px, ground, cam, noise_px)
        held = _followed_attitude(prior, quality) is not None
        quality["unexplained_m"] = residual_m
        return FlatGroundModel(slope=self.config.flat_slope).sigma_m(self.camera, cam, residual_m, held)

    def _covariance(
        self, param_cov: np.ndarray, jackknife: np.ndarray, flat_m: float | None, quality: dict
    ) -> np.ndarray:
        """Horizontal covariance that holds on real photos and over relief the model cannot see.

        The fit's own (with correlated pixel errors: no more than ``effective_inliers`` count), or
        the jackknife's where that is the larger, plus what the model leaves out: the map's
        registration, and either the DSM's error or, on flat ground, ``flat_m``: the relief the
        plane cannot see, from what its inliers show of it (relief tilts the fitted plane, which
        moves the camera by about height x tilt). Where the image overruled the autopilot's
        attitude, half the distance to the pose that attitude gives joins it, as a followed prior's
        does: a patch of roofs can fit a wrong tilt better than the right one.
        """
        cfg = self.config
        fit = 0.5 * (param_cov[:2, :2] + param_cov[:2, :2].T)
        if np.trace(jackknife) > np.trace(fit):
            fit = jackknife
        model = cfg.terrain_sigma_m if flat_m is None else flat_m
        overruled = quality.get("attitude_prior_ignored")
        overruled_m = 0.5 * quality["attitude_prior_shift_m"] if overruled else 0.0
        floor = (cfg.sigma_floor_px * self.package.gsd_m) ** 2 + model**2 + overruled_m**2
        return fit + np.eye(2) * floor

    def _check_attitude_agreement(self, quality: dict) -> str:
        """Why a pose whose image and attitude prior disagree is not trusted, if it is: a
        disagreement the image cannot settle that moves the drone far, or a clear one from a view
        too weak to overrule the autopilot."""
        cfg = self.config
        if quality.get("attitude_prior_ignored"):
            inliers, ratio = int(quality.get("inliers", 0)), quality["attitude_prior_rmse_ratio"]
            clear = ratio >= cfg.attitude_overrule_clear_ratio
            needed = cfg.attitude_overrule_clear_inliers if clear else cfg.attitude_overrule_inliers
            if inliers < needed:
                return (
                    f"roll/pitch prior and image disagree (chi-square {quality['attitude_prior_chi2']:.1f} > "
                    f"{cfg.attitude_conflict_chi2:g}, RMSE x{ratio:.2f} with the prior) and the view has "
                    f"only {inliers} inliers (need {needed} to overrule the autopilot): a wrong match "
                    "as likely as a wrong prior"
                )
        if not quality.get("attitude_prior_doubtful"):
            return ""
        chi2, shift = quality["attitude_prior_chi2"], quality["attitude_prior_shift_m"]
        if chi2 <= cfg.attitude_doubt_chi2:
            return (
                f"the roll/pitch prior moves the fix {shift:.0f} m from the image's own pose (more than "
                f"{cfg.attitude_max_shift_m:g} m) and the view's own tilt is too loose to check it "
                f"(chi-square {chi2:.1f}): the fix would be the prior's, not the image's"
            )
        return (
            f"roll/pitch prior and image disagree (chi-square {chi2:.1f} > "
            f"{cfg.attitude_doubt_chi2:g}), the image fits about as well with the prior "
            f"(RMSE x{quality['attitude_prior_rmse_ratio']:.2f}) and their poses lie {shift:.0f} m "
            "apart: a wrong prior or a view too weak to tell its tilt"
        )

    def _check_spread(self, prior: Prior, quality: dict) -> str:
        """Why a pose whose tilt is the image's own rests on too small a patch, if it does: the
        patch pins the position, not the tilt, unless the autopilot's attitude (followed) does."""
        spread, needed = quality["inlier_spread"], self.config.min_inlier_spread
        if spread >= needed or _followed_attitude(prior, quality) is not None:
            return ""
        return (
            f"inliers cover {beyond(spread, needed, 3)} of the frame (need {needed:g} without a "
            "roll/pitch prior to follow): too small a patch to pin the camera's tilt"
        )

    def _check_prior_offset(self, pose: Pose, prior: Prior, quality: dict) -> str:
        if not prior.has_position:
            return ""
        offset = float(distance_m(prior.lat, prior.lon, pose.lat, pose.lon))
        quality["prior_offset_m"] = offset
        limit = 3.0 * prior.sigma_m + 0.5 * math.hypot(*self.camera.nadir_footprint_m(pose.alt_agl_m))
        if offset > limit:
            return f"fix is {offset:.0f} m from the prior, beyond the search radius {limit:.0f} m"
        return ""

    def _check_pose(self, cam: CameraPose, rmse_px: float, prior: Prior, height_m: float) -> str:
        cfg = self.config
        # A map coarser than the frame limits how well its points can be placed in the frame.
        limit = cfg.max_rmse_px * max(1.0, self.package.gsd_m / self.camera.nadir_gsd_m(height_m))
        if rmse_px > limit:
            return f"reprojection RMSE {beyond(rmse_px, limit)} px above {limit:.3g} px"
        tilt = cam.tilt_deg
        if tilt > cfg.max_tilt_deg:
            shown = beyond(tilt, cfg.max_tilt_deg, 0)
            return f"camera tilt {shown} deg above {cfg.max_tilt_deg:g} deg: implausible pose"
        expected = self._expected_alt(prior)
        ratio = height_m / expected
        if not 1.0 / cfg.altitude_ratio <= ratio <= cfg.altitude_ratio:
            return f"altitude {height_m:.0f} m inconsistent with the expected {expected:.0f} m"
        if prior.heading_deg is not None:
            err = abs((cam.yaw_deg - prior.heading_deg + 180.0) % 360.0 - 180.0)
            limit = max(cfg.max_heading_error_deg, 3.0 * prior.heading_sigma_deg)
            if err > limit:
                return f"heading {cam.yaw_deg:.0f} deg is {err:.0f} deg off the prior (limit {limit:.0f})"
        return ""

    def _reject(self, reason: str, quality: dict, timings: dict, t0: float) -> Fix:
        timings["total_ms"] = elapsed_ms(t0)
        return Fix(False, reason, quality=quality, timings_ms=timings, method=self.package.backend_name)


def check_backend(package: MapPackage, name: str) -> None:
    """Features of one backend cannot be matched against a map built with another."""
    if name != package.backend_name:
        raise OrthonavError(
            f"{package.path}: the map was built with the {package.backend_name!r} features; it cannot "
            f"be matched with {name!r} (rebuild it with --features {name})"
        )


def prior_tiles(package: MapPackage, prior: Prior, max_candidates: int) -> np.ndarray:
    """The tiles a frame is matched on with a position prior: those within its 2 sigma, nearest
    first, ``max_candidates`` of them, more where the frame flies above the map's nominal
    altitude (it spans more tiles)."""
    near = cand.tiles_near(package, prior.lat, prior.lon, 2.0 * prior.sigma_m)
    alt = prior.alt_agl_m or package.tiling.nominal_alt_m
    spread = max(1.0, alt / package.tiling.nominal_alt_m) ** 2
    return near[: math.ceil(max_candidates * spread)]


def _followed_attitude(prior: Prior, notes: dict) -> AttitudePrior | None:
    """The autopilot's roll/pitch as the fit followed it: None where the prior has none or the
    image overruled it (``notes`` of the fit)."""
    if not prior.has_attitude or notes.get("attitude_prior_ignored"):
        return None
    return AttitudePrior(prior.pitch_deg, prior.roll_deg, prior.attitude_sigma_deg)


def _guided(
    frame_features: FeatureSet, predicted_px: np.ndarray, tiles: list[_Tile], radius_px: float, ratio: float
) -> list[Matches]:
    """Guided matches of the frame on each tile, within ``radius_px`` of where each frame keypoint
    is predicted on the map (map pixels)."""
    return [
        guided_matches(frame_features, predicted_px, tile.features, tile.map_px, radius_px, ratio)
        for tile in tiles
    ]


def _cut(fix: Fix) -> bool:
    """Whether the frame's deadline cut ``fix`` short (its reason says so)."""
    return fix.reason.startswith(DEADLINE)


def _at_most(limit: int | None, affordable: float) -> int | None:
    """The keypoint limit ``limit`` (None: all) lowered to the ``affordable`` count."""
    if math.isinf(affordable):
        return limit
    return int(affordable) if limit is None else min(limit, int(affordable))


def _to_gray(frame: np.ndarray) -> np.ndarray:
    return frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)


def _even_sample(indices: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` of ``indices``, evenly spread over them."""
    if len(indices) <= limit:
        return indices
    return indices[np.linspace(0, len(indices) - 1, limit).round().astype(int)]


def _anisotropy(h: np.ndarray, at: np.ndarray) -> float:
    """Ratio of the local Jacobian's singular values (inf for a mirror image)."""
    x, y = at
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    jac = (
        np.array(
            [[h[0, 0] - u * h[2, 0], h[0, 1] - u * h[2, 1]], [h[1, 0] - v * h[2, 0], h[1, 1] - v * h[2, 1]]]
        )
        / w
    )
    if np.linalg.det(jac) <= 0:
        return math.inf
    s = np.linalg.svd(jac, compute_uv=False)
    return float(s[0] / s[1])

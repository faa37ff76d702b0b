"""The keypoint localizer: frame + prior -> matches on map tiles -> homography -> Fix.

Steps (each timed): warp the frame to the map's ground resolution and north-up orientation
when altitude and heading are known; extract features; match against each candidate tile
(ratio test, N best per tile), merge in map pixels and de-duplicate on a grid; robust
homography (MAGSAC++); the homography from frame pixels to the local ENU ground plane is
decomposed with the intrinsics into the full camera pose; quality checks decide between
a fix and a rejection with its reason (the pose and its checks:
:mod:`orthonav.localize.keypoint_pose`; the settings: :mod:`orthonav.localize.keypoint_config`).

Rotation: with a heading prior the frame is de-rotated north-up before extraction. Without
one, a backend that is not rotation-invariant (the learned ones except aliked-n16rot) is
tried at ``rotation_trials`` evenly spaced headings; the first that passes every check wins.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from orthonav.camera import (
    Camera,
    CameraPose,
    apply_homography,
    footprint_enu,
    pixel_to_ground,
)
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, Matches, mutual_nearest
from orthonav.frames import NorthUp, north_up
from orthonav.geo import LocalFrame
from orthonav.localize import candidates as cand
from orthonav.localize.guided import guided_matches
from orthonav.localize.keypoint_config import LocalizerConfig
from orthonav.localize.keypoint_pose import Correspondences, PoseJudge
from orthonav.localize.timing import DEADLINE, FrameDeadline, StageCost, elapsed_ms
from orthonav.mapdb import MapPackage
from orthonav.mapdb.globalindex import FrameView
from orthonav.mapdb.tiling import check_footprint
from orthonav.models.onnx.runtime import until_stopped
from orthonav.types import Fix, Prior


@dataclass
class _Tile:
    """A tile's features as its backend matches them (tile px) and their map px."""

    features: FeatureSet
    map_px: np.ndarray


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
    extraction (warp included) per pixel of the north-up view it runs on (a frame turned
    diagonally or tilted gives a view up to twice the size, and the network's pass takes as
    much longer), the pose (RANSAC, refinement, checks) in milliseconds, each
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
        self.judge = PoseJudge(package, camera, self.config)
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
        alt_agl_m = prior.alt_agl_m or self.package.tiling.nominal_alt_m
        warp = north_up(gray, self.camera, self.package.gsd_m, alt_agl_m, heading_deg)
        timings["warp_ms"] = elapsed_ms(t0)
        # The extraction, then at least the fewest keypoints matched and a pose, must fit; the
        # network's pass is over the whole north-up view, whose size follows the heading and tilt.
        pixels = float(warp.gray.size)
        least_ms = costs.pose.kept_ms + costs.match_ms(kind, self.config.min_frame_keypoints, map_keypoints)
        cut = deadline.unaffordable(costs.extract, "the keypoint extraction", least_ms, pixels)
        if cut:
            return self._reject(cut, {}, timings, t0)
        t_extract = time.perf_counter()
        # The keypoints matching affords after the extraction and the pose (never fewer than a
        # view needs: fewer would be judged a blank view); ALIKED describes only those asked for.
        after_ms = deadline.left_ms() - costs.extract.likely_ms * pixels - costs.pose.kept_ms
        affordable = costs.affordable_keypoints(kind, after_ms, map_keypoints)
        affordable = max(affordable, self.config.min_frame_keypoints)
        limit = _at_most(self._frame_budget(warp.mask), affordable)
        # Stopped where the load rises within it, so that the fewest keypoints and a pose still fit.
        frame_features = until_stopped(
            deadline.stop_at(least_ms), self.backend.extract_strongest, warp.gray, warp.mask, limit
        )
        timings["extract_ms"] = elapsed_ms(t_extract)
        costs.extract.add(elapsed_ms(t0) / pixels, deadline)  # stopped: it takes at least this long
        if frame_features is None:
            return self._reject(deadline.why_stopped("the keypoint extraction"), {}, timings, t0)
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
        """``match``'s matches of the frame keypoints merged and judged (see :meth:`PoseJudge.estimate`),
        timed as match and pose. Of the frame keypoints, the strongest the time left affords
        (after the time kept for the pose) are matched; too few of them, too little time left for
        the pose, or a match stopped at the deadline is a rejection that says the deadline cut the
        frame."""
        costs, deadline = self.costs, attempt.deadline
        map_keypoints = sum(len(tile.features) for tile in attempt.tiles)
        affordable = costs.affordable_keypoints(kind, deadline.left_ms() - costs.pose.kept_ms, map_keypoints)
        if affordable < self.config.min_frame_keypoints:
            need_ms = (
                costs.match_ms(kind, self.config.min_frame_keypoints, map_keypoints) + costs.pose.kept_ms
            )
            costs.match[kind].skipped()
            left = f"{deadline.left_ms():.0f} ms left, it and the pose take about {need_ms:.0f} ms"
            return Fix(False, f"{deadline.why('the keypoint matching')}: {left}", quality=quality), None
        features = attempt.frame_features.strongest(_at_most(None, affordable))
        if len(features) < len(attempt.frame_features):
            quality["deadline_keypoints"] = float(len(features))
        t1 = time.perf_counter()
        # LightGlue's exported steps stop between layers and tiles, leaving the pose its time.
        found = until_stopped(deadline.stop_at(costs.pose.kept_ms), match, features)
        match_ms = elapsed_ms(t1)
        attempt.timings["match_ms"] = attempt.timings.get("match_ms", 0.0) + match_ms
        costs.add_match(kind, match_ms, len(features), map_keypoints, deadline)  # stopped: at least this
        if found is None:
            return Fix(False, deadline.why_stopped("the keypoint matching"), quality=quality), None
        corr = self._correspondences(features, attempt.warp, attempt.tiles, found, attempt.n_tiles)
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
        verdict = self.judge.estimate(corr, attempt.prior, quality)
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
            self.judge.expected_alt(prior),
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
    ) -> Correspondences:
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
            return Correspondences(empty, empty, empty, n_tiles, empty, map_keypoints)
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
        return Correspondences(frame_px, mp[keep], warped, n_tiles, image_px, map_keypoints)

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
        return CameraPose(0.0, 0.0, self.judge.expected_alt(prior), prior.heading_deg, pitch, roll)

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
        alt = self.judge.expected_alt(prior)
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
        footprint_m = math.hypot(*self.camera.nadir_footprint_m(self.judge.expected_alt(prior)))
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

"""The keypoint localizer's verdict on a frame's matches: the RANSAC homography, the camera pose
decomposed from it and refined on the map's terrain (the autopilot's attitude weighed in), its
covariance, and the checks that decide between a fix and a rejection with its reason."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from orthonav.camera import (
    AttitudePrior,
    Camera,
    CameraPose,
    apply_homography,
    planar_pose_candidates,
    pose_from_homography,
    project_points,
    refine_pose,
    rotation_enu_from_camera,
)
from orthonav.errors import OrthonavError, beyond
from orthonav.geo import LocalFrame, distance_m
from orthonav.localize.keypoint_config import RANSAC_METHODS, LocalizerConfig
from orthonav.localize.uncertainty import FlatGroundModel, held_tilt_deg, unexplained_m
from orthonav.mapdb import MapPackage
from orthonav.mapdb.terrain import Terrain
from orthonav.types import Fix, Pose, Prior

MAX_KEPT_INLIERS = 300  # inlier pairs a Fix carries for pictures of the match
# A second pose fit counts as a rival minimum when it explains the points about as well.
TILT_RIVAL_RMSE_RATIO = 1.5


@dataclass
class Correspondences:
    """A frame's matches on the map, merged over its tiles: what the pose is judged on."""

    frame_px: np.ndarray  # (M, 2) original frame pixels, undistorted, camera-model coordinates
    map_px: np.ndarray  # (M, 2) work-grid pixels
    warped_px: np.ndarray  # (M, 2) warped frame pixels
    tiles: int
    image_px: np.ndarray  # (M, 2) original frame pixels as in the image (OpenCV coordinates)
    map_keypoints: int  # the map keypoints the frame was matched against


class PoseJudge:
    """The verdict on matched points for one camera and map package under ``config``."""

    def __init__(self, package: MapPackage, camera: Camera, config: LocalizerConfig) -> None:
        self.package = package
        self.camera = camera
        self.config = config

    def expected_alt(self, prior: Prior) -> float:
        """The height the frame is expected from: the prior's, else the map's nominal one."""
        return prior.alt_agl_m or self.package.tiling.nominal_alt_m

    def estimate(self, corr: Correspondences, prior: Prior, quality: dict) -> tuple[Fix, np.ndarray | None]:
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
            RANSAC_METHODS[cfg.ransac],
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
        self, corr: Correspondences, inliers: np.ndarray, h_warp: np.ndarray, prior: Prior, quality: dict
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

    def _pose_points(self, corr: Correspondences, inliers: np.ndarray, h_warp: np.ndarray) -> np.ndarray:
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
            attitude_prior_pull_deg=math.hypot(
                held_cam.pitch_deg - att.pitch_deg, held_cam.roll_deg - att.roll_deg
            ),
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
        matcher's noise is a pixel of the coarser of the frame and the map; a tilt held by the
        autopilot's attitude brings how far the image pulled it from that attitude."""
        noise_px = max(1.0, self.package.gsd_m / self.camera.nadir_gsd_m(cam.alt_agl_m))
        residual_m = unexplained_m(self.camera, frame_px, ground, cam, noise_px)
        held = _followed_attitude(prior, quality)
        tilt_deg = held_tilt_deg(quality["attitude_prior_pull_deg"], held.sigma_deg) if held else None
        quality["unexplained_m"] = residual_m
        return FlatGroundModel(slope=self.config.flat_slope).sigma_m(self.camera, cam, residual_m, tilt_deg)

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
        expected = self.expected_alt(prior)
        ratio = height_m / expected
        if not 1.0 / cfg.altitude_ratio <= ratio <= cfg.altitude_ratio:
            return f"altitude {height_m:.0f} m inconsistent with the expected {expected:.0f} m"
        if prior.heading_deg is not None:
            err = abs((cam.yaw_deg - prior.heading_deg + 180.0) % 360.0 - 180.0)
            limit = max(cfg.max_heading_error_deg, 3.0 * prior.heading_sigma_deg)
            if err > limit:
                return f"heading {cam.yaw_deg:.0f} deg is {err:.0f} deg off the prior (limit {limit:.0f})"
        return ""


def _followed_attitude(prior: Prior, notes: dict) -> AttitudePrior | None:
    """The autopilot's roll/pitch as the fit followed it: None where the prior has none or the
    image overruled it (``notes`` of the fit)."""
    if not prior.has_attitude or notes.get("attitude_prior_ignored"):
        return None
    return AttitudePrior(prior.pitch_deg, prior.roll_deg, prior.attitude_sigma_deg)


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

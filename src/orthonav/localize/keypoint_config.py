"""The keypoint localizer's settings: how frames are matched and which poses are accepted (every
rejection names the setting that failed)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2

from orthonav.errors import OrthonavError

RANSAC_METHODS = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}
POSE_UNKNOWNS = 6  # a camera pose: position and attitude, so at least this many points to refine it on


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
        if self.ransac not in RANSAC_METHODS:
            raise OrthonavError(
                f"localizer ransac: expected one of {sorted(RANSAC_METHODS)}, got {self.ransac!r}"
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

"""A fix's point matches: the keypoint localizer keeps its inlier pairs (accepted or not), the
picture of them puts each map point on the orthophoto where the frame saw it, and a mission
with saved frames writes that picture beside each frame. Also: a mission asked to stop ends
cleanly between frames.

Truth for the inliers comes from the camera model at the pose each frame was rendered at,
not from the localizer.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import NAIP_ALT_M, naip_path, noisy_prior, random_pose

from orthonav.camera import Camera, CameraPose, ground_to_image_homography
from orthonav.errors import OrthonavError
from orthonav.frames.render import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame
from orthonav.localize import Localizer, LocalizerConfig
from orthonav.localize.keypoint_pose import MAX_KEPT_INLIERS
from orthonav.mapdb import MapPackage
from orthonav.sim import MissionConfig, run_mission
from orthonav.sim.mission import CANCELLED
from orthonav.types import Fix
from orthonav.viz.matches import _orthophoto_patch, draw_matches

FRAMES = 6


def _frames(raster: GeoRaster, camera: Camera, seed: int, n: int = FRAMES):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        pose = random_pose(rng, raster, camera, NAIP_ALT_M)
        frame = render_frame(raster, camera, pose, Photometric.random(rng), rng)
        yield pose, frame, noisy_prior(rng, pose).prior


def _true_ground_m(camera: Camera, pose: TruePose, frame_px: np.ndarray) -> np.ndarray:
    """(N, 2) east/north metres from the true position of what frame pixels (OpenCV) see."""
    cam = CameraPose(0.0, 0.0, pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    h = np.linalg.inv(ground_to_image_homography(camera, cam))
    pts = np.column_stack([frame_px + 0.5, np.ones(len(frame_px))]) @ h.T  # camera model: centres at +0.5
    return pts[:, :2] / pts[:, 2:]


def _map_ground_m(package: MapPackage, pose: TruePose, map_px: np.ndarray) -> np.ndarray:
    lat, lon = package.grid.pixel_to_latlon(map_px[:, 0], map_px[:, 1])
    east, north = LocalFrame(pose.lat, pose.lon).to_enu(lat, lon)
    return np.column_stack([east, north])


@pytest.fixture(scope="module")
def localized(naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera) -> list:
    localizer = Localizer(naip_map, camera)
    return [
        (pose, frame, localizer.localize(frame, prior))
        for pose, frame, prior in _frames(naip_raster, camera, 3)
    ]


def test_inliers_pair_frame_pixels_with_the_map_points_they_see(
    localized, naip_map: MapPackage, camera: Camera
) -> None:
    accepted = [(pose, fix) for pose, _, fix in localized if fix.accepted]
    assert len(accepted) >= FRAMES - 1
    for pose, fix in accepted:
        frame_px, map_px = fix.inliers_frame_px, fix.inliers_map_px
        assert frame_px.shape == map_px.shape == (min(int(fix.quality["inliers"]), MAX_KEPT_INLIERS), 2)
        assert np.all((frame_px >= -0.5) & (frame_px <= [camera.width, camera.height]))
        # Where the camera model says each frame pixel looks, the map point lies within a pixel or two.
        gap = np.hypot(*(_true_ground_m(camera, pose, frame_px) - _map_ground_m(naip_map, pose, map_px)).T)
        print(f"\n{len(gap)} inliers: median gap {np.median(gap):.1f} m, 90 % {np.percentile(gap, 90):.1f} m")
        assert np.median(gap) < 1.5 * naip_map.gsd_m and np.percentile(gap, 90) < 4.0 * naip_map.gsd_m


def test_a_rejected_fix_keeps_its_inliers_and_the_record_stays_small(
    naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera
) -> None:
    _, frame, prior = next(_frames(naip_raster, camera, 5, 1))
    fix = Localizer(naip_map, camera, LocalizerConfig(min_inlier_ratio=0.99)).localize(frame, prior)
    assert not fix.accepted and "below 0.99" in fix.reason
    kept = min(int(fix.quality["inliers"]), MAX_KEPT_INLIERS)
    assert fix.quality["inliers"] > 0 and len(fix.inliers_frame_px) == len(fix.inliers_map_px) == kept
    record = fix.to_dict()
    assert not {"inliers_frame_px", "inliers_map_px"} & set(record)
    json.dumps(record)  # still plain JSON

    blank = np.full((camera.height, camera.width, 3), 128, np.uint8)
    no_features = Localizer(naip_map, camera).localize(blank, prior)
    assert not no_features.accepted and no_features.inliers_map_px is None


def test_a_fix_keeps_an_even_sample_of_many_inliers(
    naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera, monkeypatch
) -> None:
    monkeypatch.setattr("orthonav.localize.keypoint_pose.MAX_KEPT_INLIERS", 10)
    _, frame, prior = next(_frames(naip_raster, camera, 3, 1))
    fix = Localizer(naip_map, camera).localize(frame, prior)
    assert fix.quality["inliers"] > 10 and fix.inliers_map_px.shape == fix.inliers_frame_px.shape == (10, 2)
    spread = np.ptp(fix.inliers_map_px, axis=0)
    assert spread.min() > 20, "the sample spans the matched area, not one corner of it"


def test_the_picture_puts_each_map_point_on_what_the_frame_saw(
    localized, naip_map: MapPackage, naip_raster: GeoRaster, camera: Camera
) -> None:
    _, frame, fix = next(item for item in localized if item[2].accepted)
    picture = draw_matches(frame, fix, naip_map, naip_raster)
    assert picture.shape == (camera.height, camera.width + camera.height, 3) and picture.dtype == np.uint8
    left = picture[40:, : camera.width - 1]
    assert np.mean(np.all(left == frame[40:, : camera.width - 1], axis=2)) > 0.7, "the frame, lines over it"
    lines = np.all(picture == (80, 200, 60), axis=2).sum()
    assert lines > 500, "the inlier pairs are drawn in the accepted colour"

    patch, patch_px = _orthophoto_patch(fix.inliers_map_px, naip_map, naip_raster, camera.height)
    # The same ground in the frame and in the orthophoto patch: their brightness agrees.
    frame_gray = cv2.blur(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), (9, 9)).astype(float)
    patch_gray = cv2.blur(cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY), (3, 3)).astype(float)
    fx, fy = np.round(fix.inliers_frame_px).astype(int).T
    px, py = np.clip(np.round(patch_px), 0, camera.height - 1).astype(int).T
    correlation = np.corrcoef(frame_gray[fy, fx], patch_gray[py, px])[0, 1]
    print(f"\nbrightness correlation at {len(fx)} inlier pairs: {correlation:.2f}")
    assert correlation > 0.5
    assert np.all((patch_px > 0) & (patch_px < camera.height)), "the patch holds every inlier"


def test_a_fix_without_point_matches_cannot_be_drawn(naip_map: MapPackage, naip_raster: GeoRaster) -> None:
    frame = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(OrthonavError, match="no point matches"):
        draw_matches(frame, Fix(False, "dense correlation"), naip_map, naip_raster)


# --- missions: the picture beside each saved frame, and a stop between frames ------------


def _mission(package: MapPackage) -> MissionConfig:
    (lat0, lat1), (lon0, lon1) = package.grid.pixel_to_latlon(
        [0.3 * package.grid.width, 0.7 * package.grid.width],
        [0.65 * package.grid.height, 0.35 * package.grid.height],
    )
    return MissionConfig(
        float(lat0),
        float(lon0),
        float(lat1),
        float(lon1),
        alt_agl_m=NAIP_ALT_M,
        speed_mps=30.0,
        seed=1,
        save_frames=True,
    )


@pytest.mark.parametrize("year", ["20200831", "20090818"], ids=["same-date", "cross-date"])
def test_a_stopped_mission_saves_the_matches_beside_each_frame(
    naip_map: MapPackage, camera: Camera, tmp_path: Path, year: str
) -> None:
    asked = []

    def stop_after_four() -> bool:
        asked.append(1)
        return len(asked) > 4

    with GeoRaster(naip_path(year)) as frames:
        result = run_mission(
            naip_map,
            frames,
            camera,
            _mission(naip_map),
            tmp_path,
            progress=False,
            should_stop=stop_after_four,
        )
    assert result.end_reason == CANCELLED and result.steps == 4 and not result.arrived
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["end_reason"] == "cancelled" and summary["steps"] == 4
    assert (tmp_path / "trajectory.png").stat().st_size > 10_000
    steps = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
    assert len(steps) == 4
    for step in steps:
        picture = cv2.imread(str(tmp_path / "frames" / f"matches_{step['step']:05d}.jpg"))
        has_inliers = step["fix"]["quality"].get("inliers", 0) > 0
        assert (picture is not None) == has_inliers, step["reason"]
        if picture is not None:
            assert picture.shape == (camera.height, camera.width + camera.height, 3)
    print(f"\n{year}: " + "; ".join(s["reason"] or "accepted" for s in steps))
    if year == "20090818":
        assert any(not s["accepted"] and s["fix"]["quality"].get("inliers", 0) > 0 for s in steps), (
            "a rejected fix's matches are drawn too"
        )


@pytest.mark.parametrize(
    ("quality", "said"),
    [({"inliers": 17, "matches": 240}, "17 inliers of 240 matches"), ({"inliers": 17}, "17 inliers")],
)
def test_the_verdict_counts_only_what_the_source_counted(quality: dict, said: str) -> None:
    """A fix without a count of candidate matches (the cascade's) is not headed '17 of 0'."""
    from orthonav.viz.matches import _verdict

    fix = Fix(accepted=True, quality=quality, inliers_map_px=np.zeros((17, 2)))
    assert _verdict(fix) == f"accepted: {said}"

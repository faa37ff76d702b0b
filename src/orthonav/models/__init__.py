"""Learned networks, their weights and training: the correlation trunks, the retrieval head and
the triplet training, plus the model files that ship with orthonav. Nothing here knows about map
packages or flights; torch is imported only by the modules that need it."""

from importlib import resources
from pathlib import Path

SHIPPED_MODEL = "resnet18_naip.pt"


def shipped_model_path(name: str = SHIPPED_MODEL) -> Path:
    """A trained model that comes with orthonav, by file name (package data; see its ``.json``
    for data and scores): by default the correction trunk."""
    return Path(str(resources.files("orthonav.models") / "weights" / name))


__all__ = ["SHIPPED_MODEL", "shipped_model_path"]

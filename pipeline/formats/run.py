"""The names of a chain's files: the one table of them. A run's models/ folder holds both chains (`RUN_FILES`,
by pose model: `MODELS`); a weights bundle, or any folder holding one chain, holds one under `BUNDLE_FILES`.
The chain that ships is the robust one (`SHIPPED`); the paper's reproduction rows run on the standard one (`PAPER`).
"""

from __future__ import annotations

from dataclasses import astuple, dataclass

MODELS = ("standard", "robust")  # the pose models: `rpod train` and `rpod train --robust`
PAPER, SHIPPED = MODELS
MODELS_DIR = "models"  # a run's folder of model files (under its working folder)


@dataclass(frozen=True)
class ChainNames:
    """The file names of one chain: its pose checkpoint, its detector (trained on that pose model's SHAP
    values) and its calibrated defense."""

    pose: str
    detector: str
    defense: str

    def __iter__(self):  # noqa: ANN204 - (pose, detector, defense), for unpacking
        return iter(astuple(self))


RUN_FILES = {
    "standard": ChainNames("pose.pt", "detector.pt", "defense_standard.json"),
    "robust": ChainNames("pose_robust.pt", "detector_robust.pt", "defense.json"),
}
BUNDLE_FILES = ChainNames("pose.pt", "detector.pt", "defense.json")

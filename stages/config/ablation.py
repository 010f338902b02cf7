"""The params.yaml section of issue 38's 2 x 2 ablation (`rpod ablation`, optional/dvc.yaml): FGSM as we deliver it
or as the paper's equation prints it, crossed with our strict detector protocol or the paper's."""
from __future__ import annotations

from dataclasses import dataclass

from stages.config.sections import Count, Eps


@dataclass(frozen=True)
class Ablation:
    eps: list[Eps]               # L-inf budgets, pixels in [0, 1]: each cell's detector is trained on all of them
    normal: Count                # clean samples per protocol
    per_eps: Count               # attacked samples per eps and protocol (the two FGSM variants attack the same images)

    def __post_init__(self) -> None:
        if not self.eps:
            raise ValueError("eps must list at least one L-inf budget")

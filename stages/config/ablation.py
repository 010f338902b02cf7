"""The params.yaml section of issue 38's 2 x 2 ablation (`rpod ablation`, optional/dvc.yaml): FGSM as we deliver it
or as the paper's equation prints it, crossed with our strict detector protocol or the paper's."""

from __future__ import annotations

from dataclasses import dataclass

from stages.config.sections import Count, Eps, Probability


@dataclass(frozen=True)
class Ablation:
    eps: list[Eps]  # L-inf budgets, pixels in [0, 1]: each cell's detector is trained on all of them
    normal: Count  # clean samples per protocol
    per_eps: Count  # attacked samples per eps and protocol (the two FGSM variants attack the same images)
    paper_eps: list[Eps]  # the 2 x 2 again, its detectors trained on the paper's eps mix
    paper_per_eps: Count  # its attacked samples per eps and protocol
    fractions: list[Probability]  # learning curve: fractions of a cell's training samples it is refitted on

    def __post_init__(self) -> None:
        if not self.eps or not self.paper_eps:
            raise ValueError("eps and paper_eps must each list at least one L-inf budget")
        if any(not 0 < f < 1 for f in self.fractions):
            raise ValueError(f"fractions must lie in (0, 1), got {self.fractions}")

"""The params.yaml section of issue 40's integrity bound (`rpod bound`, optional/dvc.yaml): the chains, the eps at which
the attacker's capacity is taken, the target frames' stride and the interval-bound certificate's sample."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, Optional

from pipeline.settings import In
from stages.config.sections import Batch, Count, Eps

Frames = Annotated[int, In("[0, 1000000]", "frames")]


@dataclass(frozen=True)
class Bound:
    models: list[Literal["robust", "standard"]]  # the chains: robust (shipped) | standard (the paper's reproduction)
    eps: list[Eps]  # L-inf budgets, pixels in [0, 1]
    stride: Count  # every stride-th frame from the filter's start is a target (and the last)
    trajectories: Optional[Count]  # of the eval_render trajectories, the first N (None: all)
    certify_frames: Frames  # frames of the first trajectory the IBP certificate runs on (0: none)
    batch_size: Batch  # frames per pose-network forward pass

    def __post_init__(self) -> None:
        if not self.eps or not self.models:
            raise ValueError("bound: eps and models must each list at least one value")
        if len(set(self.models)) != len(self.models):
            raise ValueError(f"bound: models must not repeat, got {self.models}")

"""The params.yaml section of the strongest-attack suite (issue 37; pipeline/attacks/strongest.py) on both pose
models: `rpod train --robust` runs it (its members, steps, restarts and starts) for the attacked-error table on test
frames and for the attacker capacity on validation frames (`suite.capacity`); `rpod suite` (optional/dvc.yaml) runs
the full suite (pipeline/attacks/strongest.py FULL's members at the sizes of `suite.full`) on every test frame
beside it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, Optional

from pipeline.settings import In
from stages.config.sections import Batch, Count, Eps, Metres

Steps = Annotated[int, In("[1, 100000]", "attack steps")]


def _increasing(values: list[float], key: str) -> None:
    if not values or any(b <= a for a, b in zip(values, values[1:])):
        raise ValueError(f"{key} must list increasing L-inf budgets (the worst case is nested in eps), got {values}")


@dataclass(frozen=True)
class SuiteCapacity:
    """suite.capacity: the per-frame attacker capacity of each chain on validation frames (the train split's
    validation fraction: never the test split) and its fitted overbound F(eps, range) -> datasets/capacity/."""

    eps: list[Eps]  # L-inf budgets, pixels in [0, 1], increasing
    frames: Optional[Count]  # validation frames attacked (seeded sample); null = every one
    edges: list[Metres]  # range-bin edges of the overbound, metres, increasing
    quantile: Annotated[float, In("(0, 1]", "quantile")]  # of each bin's shifts
    margin: Annotated[float, In("[0, 100]", "relative margin")]  # the overbound is quantile x (1 + margin)
    min_count: Count  # frames a range bin needs (fewer: the stage stops)

    def __post_init__(self) -> None:
        _increasing(self.eps, "suite.capacity.eps")
        if len(self.edges) < 2 or any(b <= a for a, b in zip(self.edges, self.edges[1:])):
            raise ValueError(f"suite.capacity.edges must be >= 2 increasing ranges in metres, got {self.edges}")


@dataclass(frozen=True)
class SuiteFull:
    """suite.full: the full suite (pipeline/attacks/strongest.py FULL's members and starts) at these sizes."""

    steps: Steps  # APGD steps per restart
    restarts: Annotated[int, In("[1, 1000]", "restarts")]
    queries: Annotated[int, In("[1, 1000000]", "queries")]  # Square's, per frame
    square_eps: Eps  # the one eps Square runs at: one of suite.eps
    batch_size: Batch  # frames per attack batch of rpod suite, its full and its lean suite (part of the seeding)


@dataclass(frozen=True)
class Suite:
    eps: list[Eps]  # L-inf budgets, pixels in [0, 1], increasing
    frames: Optional[Count]  # test frames of the attacked-error table (seeded sample); null = every one
    members: list[str]  # method/objective pairs (pipeline/attacks/strongest.py METHODS x OBJECTIVES)
    steps: Steps  # APGD steps per restart
    restarts: Annotated[int, In("[1, 1000]", "restarts")]
    starts: list[Literal["random", "lift"]]  # start kinds the restarts cycle through
    batch_size: Batch  # frames per attack batch (part of the seeding)
    check_frames: Annotated[int, In("[0, 1000000000]", "frames")]  # stability check's subsample (0 = not run)
    full_frames: Annotated[int, In("[0, 1000000000]", "frames")]  # lean-vs-full check's subsample (0 = not run)
    full: SuiteFull
    capacity: SuiteCapacity

    def __post_init__(self) -> None:
        _increasing(self.eps, "suite.eps")
        if not self.members or not self.starts:
            raise ValueError("suite.members and suite.starts must each list at least one")
        if self.full.square_eps not in self.eps:
            raise ValueError(f"suite.full.square_eps ({self.full.square_eps}) must be one of suite.eps {self.eps}")

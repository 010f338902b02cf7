"""The integrity campaign of one chain (what `rpod robustness` runs on the shipped chain and the standard one):
the defended chain flown clean over recorded trajectories, then every chain-level attacker at every eps (the
nested burst on scheduled bursts, the slow drifts in a window of frames), each judged by integrity against the
same trajectories unattacked (pipeline/evaluation/integrity_runs.py), and the nested burst's attacked frames
seen per frame (raw error above the harm threshold and unflagged: pipeline/evaluation/robustness.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.defense.chain import Defended, OnboardChain
from pipeline.defense.integrity import AlertLimitSettings
from pipeline.evaluation.integrity_runs import (
    Flown,
    Track,
    burst_attack,
    clean_row,
    drift_attack,
    fly,
    integrity_row,
    raw_errors,
)
from pipeline.evaluation.robustness import fused_row
from pipeline.stats import Rate, bootstrap_rate

BURST_ROW = "fused chain: burst (nested, worst over lambda and restarts)"   # its per-frame row's name


@dataclass(frozen=True)
class Campaign:
    """What a campaign flies: `eps` (sorted; L-inf, pixels in [0, 1]); the burst attacker (pipeline/attackers/
    burst.py, seeded; None: not flown) on the `bursts` (start, stop) of each track; the drift attackers, each
    (name, e.g. "drift/los", and its DriftSettings), in the frames `window` (first, stop) with `drift_steps` PGD steps
    per frame, seeded `drift_seed`; the alert limit, the batch size of the chain's passes, the harm threshold of
    the per-frame rows (m) and the seed of the rows' bootstrap."""

    eps: list[float]
    burst: Any
    bursts: list[list[tuple[int, int]]]
    drifts: list[tuple[str, Any]]
    window: tuple[int, int]
    drift_steps: int
    drift_seed: int
    limit: AlertLimitSettings
    batch_size: int
    harm_m: float
    seed: int


@dataclass(frozen=True)
class Flights:
    """A campaign's outcome: the clean flights and their false alarms (bootstrap over tracks), every attacked
    run (attacker, eps, its flights, the attacked frames per track), the integrity rows (the burst's with
    `bursts_with_hmi`: per eps [bursts with an HMI frame, bursts] as the attacker judged its own worst cases),
    the clean row, and the nested burst's per-frame rows."""

    clean: list[Flown]
    alarms: Rate
    runs: list[tuple[str, float, list[Flown], list[np.ndarray]]]
    rows: list[dict[str, Any]]
    clean_row: dict[str, Any]
    fused_rows: list[dict[str, Any]]


def fly_campaign(chain: OnboardChain, target: Any, defended: Defended, tracks: Sequence[Track], campaign: Campaign,
                 progress: Callable[[], Any] = lambda: None) -> Flights:
    """The campaign of the module docstring on `chain` (its differentiable copy `target`: a PerFrameChain) with a
    fresh `defended` defense per flight; `progress()` after each attacked track or drift step."""
    c = campaign
    clean = [fly(chain, defended, t, c.limit, c.batch_size) for t in tracks]
    flags = np.concatenate([f.trace.flag for f in clean])
    alarms = bootstrap_rate(flags, np.concatenate([np.full(len(t), g) for g, t in enumerate(tracks)]))
    runs, bursts_hmi = [], {}
    if c.burst is not None:
        masks = [np.isin(np.arange(len(t)), [k for a, b in bs for k in range(a, b)]) for t, bs in zip(tracks, c.bursts)]
        stored, worst = burst_attack(target, defended, tracks, masks, c.burst, c.eps, progress)
        runs += [("burst", e, [fly(chain, defended, t, c.limit, c.batch_size, s, f) for t, s, f in
                               zip(tracks, stored[e], clean)], masks) for e in c.eps]
        bursts_hmi = {e: [sum(int(b.hmi.any()) for bs in worst[e] for b in bs), sum(map(len, worst[e]))] for e in c.eps}
    masks = [(np.arange(len(t)) >= c.window[0]) & (np.arange(len(t)) < c.window[1]) for t in tracks]
    for e in c.eps if c.drifts else []:
        stored = drift_attack(target, defended, tracks, clean, c.window, [s for _, s in c.drifts], e, c.drift_steps,
                              c.drift_seed, progress)
        runs += [(name, e, [fly(chain, defended, t, c.limit, c.batch_size, s, f)
                            for t, s, f in zip(tracks, per, clean)], masks) for (name, _), per in zip(c.drifts, stored)]
    rows = [integrity_row(name, e, flown, clean, masks, seed=c.seed) | ({"bursts_with_hmi": bursts_hmi[e]}
                                                                         if name == "burst" else {})
            for name, e, flown, masks in runs]
    fused = []
    for name, e, flown, masks in runs:
        if name == "burst":
            err, flag, group = raw_errors(flown, tracks, masks)
            fused.append(fused_row(BURST_ROW, e, None, err, flag, group, c.harm_m))
    return Flights(clean, alarms, runs, rows, clean_row(clean, seed=c.seed), fused)

"""The integrity bound's worst fault sequence realised in images (issue 40: why the image attackers reach a small share
of the bound): at one target frame of one trajectory, the sequence of per-frame shifts that `worst_case`
(pipeline/defense/bound.py) found within the capacity F(eps, range) is pursued frame by frame by a targeted attack
(pipeline/attacks/toward.py) of the same eps, and the attacked frames are flown through the real chain.

Three replays of frames 0..target through the real defense separate the bound's two modelling steps:
- `requested`: the program's sequence itself (the estimates moved by exactly the shifts): the bound's feasible
  attack, as `worst_case` replays it;
- `blind`: the attacked images' estimates with the clean detector probabilities: what the images can do against the
  motion checks when the detector is blind, as the bound models it. Well below `requested`: per-frame shifts inside
  F are not all reachable at once (F is a box of separately measured maxima, and a frame's shift must also land
  where the program put it);
- `live`: the attacked images' estimates and detector probabilities: the real chain. Well below `blind`: the
  detector, which the bound takes as blind, is what stops the sequence.
Per attacked frame: the requested shift s and the reached shift r (estimate minus clean estimate, camera frame, m):
the share r.s / |s|^2 reached along the request, and the residual |r - s|. Per replay, what the safety measures of
reports/robustness.md judge: whether the target frame is available (flown, PL <= AL) and the largest error / AL over
the available frames up to it (above 1: the sequence fails the chain).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import Any, Sequence

import numpy as np
import torch

from pipeline.attacks.capacity import Capacity, capacity_at
from pipeline.attacks.toward import toward
from pipeline.defense.bound import record, worst_case
from pipeline.defense.calibration import CleanRun
from pipeline.defense.chain import Defended, OnboardChain
from pipeline.defense.integrity import AlertLimitSettings, alert_limit, defense_frames
from pipeline.evaluation.integrity_runs import Track
from pipeline.evaluation.robustness import pose_estimates

MOVED_M = 1e-6  # a frame whose requested shift is shorter than this (m) is left clean


@dataclass(frozen=True)
class RealizeSettings:
    """The targeted attack per frame: APGD `steps` x `restarts` from `starts` (random | lift), frames per batch, the
    seed of its random starts."""

    steps: int = 100
    restarts: int = 1
    starts: tuple[str, ...] = ("random",)
    batch_size: int = 32
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.steps, self.restarts, self.batch_size) < 1 or not self.starts:
            raise ValueError(f"realize: steps, restarts and batch_size must be >= 1 and starts not empty, got {self}")


def _attack_frames(
    chain: OnboardChain, track: Track, index: np.ndarray, goal: np.ndarray, eps: float, s: RealizeSettings
) -> np.ndarray:
    """Track frames `index` attacked toward the goal poses (len(index), 9) (camera frame, m): uint8 (n, H, W, 3)."""
    generator = torch.Generator().manual_seed(int(s.seed))
    out = np.empty((len(index),) + track.images.shape[1:], np.uint8)
    for lo in range(0, len(index), s.batch_size):
        part = slice(lo, lo + s.batch_size)
        found = toward(
            chain.model,
            track.frames(index[part]),
            torch.as_tensor(goal[part], dtype=torch.float32),
            eps,
            generator=generator,
            steps=s.steps,
            restarts=s.restarts,
            starts=s.starts,
        )
        out[part] = found.images.permute(0, 2, 3, 1).numpy()
    return out


def _reach(s: np.ndarray, r: np.ndarray) -> dict[str, Any]:
    """Requested shifts s and reached shifts r (n, 3) (camera frame, m): the request's median length, the median
    share reached along it, the residual |r - s| (median, 90th percentile)."""
    if not len(s):
        return {
            "requested_length_median_m": 0.0,
            "reached_share_median": None,
            "residual_median_m": 0.0,
            "residual_p90_m": 0.0,
        }
    length, residual = np.linalg.norm(s, axis=1), np.linalg.norm(r - s, axis=1)
    return {
        "requested_length_median_m": float(np.median(length)),
        "reached_share_median": float(np.median(np.einsum("ni,ni->n", r, s) / length**2)),
        "residual_median_m": float(np.median(residual)),
        "residual_p90_m": float(np.percentile(residual, 90)),
    }


def _fly(
    d: Defended,
    track: Track,
    target: int,
    limit: AlertLimitSettings,
    pose: np.ndarray,
    prob: np.ndarray,
    moved: np.ndarray | None = None,
) -> dict[str, Any]:
    """Frames 0..target with estimates `pose` (moved by `moved`, camera frame, m) and detector probabilities `prob`
    through the real defense: the trusted error at the target (m), whether the target frame is available (flown
    and PL <= AL: pipeline/defense/integrity.py) and its PL (m), the largest error / AL over the available frames
    up to it and whether that exceeds 1 (a failure, as reports/robustness.md counts one), and the frames flagged
    (any check; the detector)."""
    m = target + 1
    run = CleanRun(pose, prob, track.R_cam[:m], track.u[:m])
    rec = record(d.settings, d.motion, d.noise, run, moved, partial(alert_limit, settings=limit))
    f = defense_frames(rec.trace, track.truth[:m], track.name, limit)
    ratio = np.where(f.available, f.error / f.alert, 0.0)
    return {
        "error_m": float(f.error[target]),
        "available": bool(f.available[target]),
        "pl_m": None if f.pl is None or not np.isfinite(f.pl[target]) else float(f.pl[target]),
        "max_error_al_available": float(ratio.max()),
        "failed": bool(ratio.max() > 1),
        "flagged": int(rec.trace.flag.sum()),
        "detector_flagged": int(rec.trace.shap_flag.sum()),
    }


def realize_worst(
    chain: OnboardChain,
    defended: Defended,
    track: Track,
    capacities: Sequence[Capacity],
    eps: float,
    limit: AlertLimitSettings,
    target: int,
    settings: RealizeSettings = RealizeSettings(),
) -> dict[str, Any]:
    """The bound's worst sequence at frame `target` of `track` at `eps` (L-inf, pixels in [0, 1]) realised in images
    (module docstring), JSON-ready: the bound (m), the trusted error at the target of the requested, blind and live
    replays and of the clean run (m), AL there (m), the frames attacked, the share of the request reached (median)
    and the residual (median, 90th percentile, m) beside the requested shift's median length (m), and per replay the
    target's availability and PL, the largest error / AL on available frames (`_fly`) and the frames flagged (any
    check; the detector) up to the target."""
    t0 = time.perf_counter()
    d, range_m = defended, np.linalg.norm(track.truth, axis=1)
    est, prob = pose_estimates(chain, track.images, settings.batch_size)
    run, cap = CleanRun(est, prob, track.R_cam, track.u), capacity_at(capacities, float(eps), range_m)
    al = alert_limit(range_m, limit)
    limit_fn = partial(alert_limit, settings=limit)
    w = worst_case(d.settings, d.motion, d.noise, run, track.truth, cap, al, targets=[target], alert_limit=limit_fn)
    out: dict[str, Any] = {"trajectory": track.name, "frame": int(target), "range_m": float(range_m[target])}
    if not np.isfinite(w.upper[0]):
        return {**out, "modelled": False}
    m = target + 1
    shift = w.shift[0, :m]
    index = np.flatnonzero(np.linalg.norm(shift, axis=1) > MOVED_M)
    goal = est[index].copy()
    goal[:, :3] += shift[index]
    images = track.images[:m].copy()
    images[index] = _attack_frames(chain, track, index, goal, float(eps), settings)
    est_a, prob_a = pose_estimates(chain, images, settings.batch_size)
    fly = partial(_fly, d, track, target, limit)
    return {
        **out,
        "modelled": True,
        "eps": float(eps),
        "bound_m": float(w.upper[0]),
        "alert_m": float(al[target]),
        "attacked_frames": int(len(index)),
        **_reach(shift[index], est_a[index, :3] - est[index, :3]),
        "clean": fly(est[:m], prob[:m]),
        "requested": fly(est[:m], prob[:m], shift),
        "blind": fly(est_a, prob[:m]),
        "live": fly(est_a, prob_a),
        "seconds": time.perf_counter() - t0,
    }

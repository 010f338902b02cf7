"""Where the clean availability goes: the protection level's parts, measured (issue 39).

The PL of the trusted estimate (pipeline/defense/protection.py) is, after the trusted frames,
    PL = noise + |b| + offset,   noise = kappa sqrt(lambda_max(P_T + sum_k Q_k)),   b_i = c sum|W| + h TV+(W),
the noise term (the filter's error at T and the execution error's random walk since), the slow ramp c sum|W| (a
drift under the sequential test's reference c that no test of this filter can tell from the noise), the
transients h TV+ (what the test lets through after a start or an alarm) and the offset a restart carried. A frame
is available when the guidance flies on it and PL <= AL (pipeline/defense/integrity.py). `pl_parts` replays a
flight through a fresh defense and gives, per frame, the PL and the PL with parts left out; `availability_parts`
the availability each would give on the same frames, with its bootstrap interval over trajectories: which part
costs how much availability, measured rather than guessed. A PL with a part left out bounds nothing (the part is
there because an attacker can use it): these are diagnostics, never the chain's availability.

`tolerance_availability` asks the other question: what the mission would have to accept for the same PL. The
alert limit falls to the docking tolerance at the goal (pipeline/defense/integrity.py), so the availability of
the same clean frames with the AL of a wider tolerance is what a looser docking requirement would buy, measured.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from pipeline.defense.chain import Defended
from pipeline.defense.integrity import AlertLimitSettings, IntegrityFrames, alert_limit, clean_rates, concat
from pipeline.evaluation.integrity_runs import Flown, Track, as_json
from pipeline.geometry.rotations import sixd_to_matrix

PL = "protection level (as flown)"
TOLERANCES = (1.0, 1.5, 2.0, 3.0, 5.0)  # docking tolerances (m) `tolerance_availability` judges the PL against
PARTS = (PL, "without the slow ramp (c = 0)", "without the transients (h = 0)", "noise term and offset alone")


def pl_parts(defended: Defended, pose: np.ndarray, prob: np.ndarray, R_cam: np.ndarray, u: np.ndarray) -> dict:
    """{part of PARTS: (N,) m} over one flight replayed through `defended.defense()`: pose (N, 9) the chain's
    estimates (camera frame, m, 6-D rotation), prob (N,) the detector's, R_cam (N, 3, 3) camera -> world, u (N, 3)
    the commands (world, m); inf before the filter starts. The first part is the trace's PL exactly."""
    pose = np.asarray(pose, np.float64)
    n = len(pose)
    d = defended.defense()
    R_pred = sixd_to_matrix(pose[:, 3:])
    out = {k: np.full(n, math.inf) for k in PARTS}
    for i in range(n):
        d.step(pose[i, :3], float(prob[i]), R_cam[i], u[i], R_pred[i])
        f = d.filter
        if not math.isfinite(f.protection_level):  # before the start, or a trusted start in doubt
            continue
        pr, noise = f.protection, f.pl_noise_term
        out[PARTS[0]][i] = noise + pr.bias()
        out[PARTS[1]][i] = noise + pr.bias(reference=0.0)
        out[PARTS[2]][i] = noise + pr.bias(threshold=0.0)
        out[PARTS[3]][i] = noise + pr.offset
    return out


def availability_parts(
    frames: Sequence[IntegrityFrames], parts: Sequence[dict[str, np.ndarray]], seed: int = 0
) -> dict[str, dict[str, Any]]:
    """{part: availability as the metrics JSON holds a rate ({"value", "ci", "n", "ci_method"})}: the share of the
    flights' frames (`frames`, each flight's integrity records; `parts`, its `pl_parts`) that would be available
    with that PL, bootstrapped over flights as the clean row is (`seed`: its bootstrap's; the first part is the
    clean row's availability exactly)."""
    if len(frames) != len(parts) or not frames:
        raise ValueError(f"availability_parts: {len(frames)} flights' records for {len(parts)} flights' parts")
    out = {}
    for key in PARTS:
        rates = clean_rates(concat([dataclasses.replace(f, pl=p[key]) for f, p in zip(frames, parts)]), seed=seed)
        out[key] = as_json(rates["availability"], len(frames))
    return out


def clean_availability_parts(
    defended: Defended, clean: Sequence[Flown], tracks: Sequence[Track], seed: int = 0
) -> dict[str, dict[str, Any]]:
    """`availability_parts` of the clean flights `clean` (pipeline/evaluation/integrity_runs.py `Flown`) of
    `tracks` through `defended`, `seed` the clean row's bootstrap seed."""
    parts = [pl_parts(defended, fl.pose, fl.prob, t.R_cam, t.u) for fl, t in zip(clean, tracks)]
    return availability_parts([fl.frames for fl in clean], parts, seed)


def tolerance_availability(
    frames: Sequence[IntegrityFrames],
    alert: AlertLimitSettings,
    tolerances: Sequence[float] = TOLERANCES,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """{f"{t:g}": availability as the metrics JSON holds a rate}: the share of the flights' frames (`frames`, each
    flight's integrity records with its PL) available when the same PL is judged against the alert limit `alert`
    with docking tolerance t (m) instead of its own, at each frame's true range; bootstrapped over flights as the
    clean row is (`seed`). At `alert.tolerance` it is the clean row's availability. {} for a fixed AL (no
    tolerance in it)."""
    if alert.fixed is not None:
        return {}
    if not frames:
        raise ValueError("tolerance_availability: no flights")
    out = {}
    for t in tolerances:
        if not float(t) > 0:
            raise ValueError(f"tolerance_availability: a docking tolerance must be > 0 (metres), got {t!r}")
        s = dataclasses.replace(alert, tolerance=float(t))
        judged = [dataclasses.replace(f, alert=alert_limit(np.linalg.norm(f.truth, axis=1), s)) for f in frames]
        out[f"{t:g}"] = as_json(clean_rates(concat(judged), seed=seed)["availability"], len(frames))
    return out

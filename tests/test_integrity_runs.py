"""The integrity runs of `rpod robustness` (pipeline/evaluation/integrity_runs.py) on a smoke-sized scene:
the nested burst's worst case is monotone in eps through the runner, attacked frames stay within eps
and clean frames untouched (burst and the batched drift), the rows pair each run with its clean
counterpart, a fixed AL and a trace's protection level reach the integrity records. test_burst's tiny
random PoseNet and LSTM on 18 x 32 frames, CPU."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from test_burst import scene  # noqa: F401  (its tiny PoseNet and LSTM)

from pipeline.attackers.burst import BurstAttacker
from pipeline.attackers.drift import DriftSettings
from pipeline.defense.chain import Defended, OnboardChain
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import AlertLimitSettings, defense_frames
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.evaluation.integrity_runs import Track, burst_attack, clean_row, counted, fly, integrity_row, plan_attack

N = 12
NOISE = NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02)


@pytest.fixture(scope="module")
def runs(scene):
    """(OnboardChain, PerFrameChain, Defended, two tracks whose labels are the clean estimates): test_burst's
    tiny PoseNet and LSTM, 12 random frames per track."""
    model, target, _, _ = scene
    tracks, top = [], 0.0
    for k in range(2):
        images = (torch.rand(N, 18, 32, 3, generator=torch.Generator().manual_seed(k)) * 255).to(torch.uint8).numpy()
        with torch.no_grad():
            labels, logit = target(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255)
        tracks.append(Track(f"t{k}", images, labels.double().numpy()))
        top = max(top, float(torch.sigmoid(logit).max()))
    threshold = min(0.99, top + 0.05)
    chain = OnboardChain.from_model(model, target.shap.background_mean.numpy(), target.detector, threshold=threshold)
    return (
        chain,
        target,
        Defended(DefenseSettings(threshold=threshold), MotionSettings(false_alarm=0.01), NOISE),
        tracks,
    )


def _masks(tracks, lo: int, hi: int) -> list[np.ndarray]:
    return [(np.arange(len(t)) >= lo) & (np.arange(len(t)) < hi) for t in tracks]


def test_the_nested_burst_through_the_runner_is_monotone_in_eps_and_within_eps(runs) -> None:
    chain, target, defended, tracks = runs
    masks = _masks(tracks, 6, 10)
    attacker = BurstAttacker(alert_limit=1.0, steps=2, restarts=2, lambdas=(0.0, 10.0))
    eps = [0.01, 0.02, 0.05]
    stored, worst = burst_attack(target, defended, tracks, masks, attacker, eps)
    for i, (t, m) in enumerate(zip(tracks, masks)):
        keys = [worst[e][i][0].key for e in eps]
        assert keys == sorted(keys) and keys[-1][2] > 0  # a trajectory's first burst never weakens as eps grows
        for e in eps:
            delta = np.abs(stored[e][i].astype(int) - t.images.astype(int))
            assert delta[~m].max() == 0 and delta[m].max() <= round(e * 255 + 0.5)
    clean = [fly(chain, defended, t, AlertLimitSettings(), 8) for t in tracks]
    attacked = [fly(chain, defended, t, AlertLimitSettings(), 8, s) for t, s in zip(tracks, stored[0.05])]
    row = integrity_row("burst", 0.05, attacked, clean, masks)
    assert row["frames"] == sum(int(counted(m).sum()) for m in masks) == 2 * (N - 6)
    assert row["attacked_frames"] == 8 and row["trajectories"] == 2
    assert (
        row["hmi"]["value"] <= row["hmi_attacked"]["value"]
        and row["trusted_error_max_m"] >= row["trusted_error_mean_m"]
    )
    assert clean_row(clean)["frames"] == 2 * N


def test_the_batched_plans_change_only_their_frames_within_eps(runs) -> None:
    """Each plan attacks from its own first frame to the end of every track; with the lifting start, BPDA and
    warm starts too (a model without a clamp: the random start and the plain gradient)."""
    from pipeline.attackers.drift import TargetedPGD

    chain, target, defended, tracks = runs
    clean = [fly(chain, defended, t, AlertLimitSettings(), 8) for t in tracks]
    for attack in (TargetedPGD(2), TargetedPGD(2, start="lift", bpda=True)):
        stored = plan_attack(
            target,
            defended,
            tracks,
            clean,
            [(DriftSettings("lateral"), 3), (DriftSettings("los"), 5)],
            0.03,
            seed=0,
            frame_attack=attack,
        )
        assert len(stored) == 2 and all(len(per) == len(tracks) for per in stored)
        for per, first in zip(stored, (3, 5)):
            for t, s, m in zip(tracks, per, _masks(tracks, first, N)):
                delta = np.abs(s.astype(int) - t.images.astype(int))
                assert delta[~m].max() == 0 and 0 < delta[m].max() <= round(0.03 * 255 + 0.5)
    # an attacked flight reads only the changed frames through the chain: the same as reading them all
    again = fly(chain, defended, tracks[0], AlertLimitSettings(), 8, stored[0][0], clean[0])
    full = fly(chain, defended, tracks[0], AlertLimitSettings(), 8, stored[0][0])
    assert np.allclose(again.pose, full.pose, atol=1e-5) and np.array_equal(again.trace.flag, full.trace.flag)


def test_a_fixed_alert_limit_and_a_protection_level_reach_the_records() -> None:
    n = 4
    truth = np.tile([0.0, 0.0, 30.0], (n, 1))
    trace = SimpleNamespace(trusted=truth + [[0, 0, 2.0]], mode=np.array(["track"] * n), pl=None)
    derived = defense_frames(trace, truth, "a", AlertLimitSettings())
    assert derived.pl is None and np.allclose(derived.alert, 11.0) and not derived.hmi.any()
    fixed = defense_frames(trace, truth, "a", AlertLimitSettings(fixed=1.5))
    assert np.allclose(fixed.alert, 1.5) and fixed.hmi.all()
    trace.pl = np.array([1.0, 3.0, np.nan, 20.0])
    with_pl = defense_frames(trace, truth, "a", AlertLimitSettings())
    assert with_pl.mi.tolist() == [True, False, False, False]
    assert with_pl.available.tolist() == [True, True, False, False]  # PL > AL or no PL: not available


def test_a_bootstrap_without_spread_falls_back_to_trajectories_as_trials() -> None:
    from pipeline.evaluation.integrity_runs import as_json
    from pipeline.stats import Rate, wilson

    none = as_json(Rate(0.0, 0.0, 0.0, 1550), trajectories=10)
    assert (
        none["ci"] == pytest.approx([0.0, wilson(0, 10).hi]) and none["ci"][1] > 0.25 and "Wilson" in none["ci_method"]
    )
    every = as_json(Rate(1.0, 1.0, 1.0, 1550), trajectories=10)
    assert every["ci"][0] == pytest.approx(wilson(10, 10).lo) and every["ci"][1] == 1.0
    spread = as_json(Rate(0.2, 0.1, 0.3, 100), trajectories=10)
    assert spread["ci"] == [0.1, 0.3] and spread["ci_method"] == "bootstrap over trajectories"


def _flown(pl: float) -> Any:
    """A 4-frame flight at 20 m, error 0.5 m, every frame tracked, with PL `pl` (m) on every frame."""
    from pipeline.defense.fusion import TRACK
    from pipeline.defense.integrity import IntegrityFrames
    from pipeline.evaluation.integrity_runs import Flown

    truth = np.tile([0.0, 0.0, 20.0], (4, 1))
    frames = IntegrityFrames(
        np.zeros(4, int),
        np.arange(4),
        truth + [0.5, 0.0, 0.0],
        truth,
        np.full(4, TRACK),
        np.full(4, 11.0),
        np.full(4, pl),
    )
    return Flown(np.zeros((4, 9)), np.zeros(4), None, frames)


def test_the_integrity_figure_shows_the_largest_eps_with_an_attacked_frame_on_the_diagram() -> None:
    from pipeline.evaluation.integrity_runs import diagram_eps

    attacked = [np.array([False, True, True, True])]
    runs = [("capture", 0.05, [_flown(2.0)], attacked), ("capture", 0.1, [_flown(3.0)], attacked)]
    lost = [("capture", 0.2, [_flown(np.inf)], attacked)]  # every attacked frame without a PL: nothing to plot
    assert diagram_eps(runs + lost) == 0.1
    assert diagram_eps(lost) == 0.2  # none plotted: the largest flown
    assert diagram_eps([]) is None

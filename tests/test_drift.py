"""The slow drift (pipeline/attackers/drift.py) and the attacker registry (pipeline/attackers/suite.py).

On a toy filter (no network) the drift is fed directly as the measurement error: a drift that keeps
every innovation under the gate (the drift that walked the old filter, with its free drift-velocity
state, past the alert limit unflagged) is caught by the sequential test before its error reaches
the alert limit, and a drift that also keeps under the sequential test stays within the protection
level; a jump of the same final size is flagged by the gate. On a tiny random PoseNet the pixel-level attack moves the estimate
toward its target and stays within eps once stored as 8 bits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.attackers.base import AttackRun
from pipeline.attackers.drift import DriftAttacker, DriftSettings, drift_estimates, targeted_pgd
from pipeline.attackers.suite import get_attacker
from pipeline.attacks.adaptive import PerFrameChain
from pipeline.defense.fusion import Defense, run_defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector
from pipeline.geometry.rotations import matrix_to_6d
from pipeline.pose.model import PoseNet
from pipeline.shap import ExactShap

NOISE = NoiseModel((0.05, 0.05, 0.1), (0.005, 0.005, 0.01), 1.0, 0.0)  # 0.2, 0.2, 0.4 m std at 30 m
MOTION = MotionSettings()
START, FRAMES = 20, 100  # clean frames, then drift frames


def approach(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A chaser closing from 30 m at 5 cm/frame, camera = world axes: true rel (n, 3), clean
    estimates (n, 3) with the noise model's scatter, R_cam (n, 3, 3), commands u (n, 3)."""
    rel = np.stack([np.full(n, 0.5), np.full(n, -0.3), 30 - 0.05 * np.arange(n)], 1)
    std = np.array([NOISE.position_std(float(np.linalg.norm(r))) for r in rel])
    t_clean = rel + np.random.default_rng(seed).normal(size=(n, 3)) * std
    u = np.vstack([np.zeros(3), np.diff(rel, axis=0)])
    return rel, t_clean, np.repeat(np.eye(3)[None], n, 0), u


def drifted(
    direction: str,
    rate: float,
    cusum_fraction: float | None,
    motion: MotionSettings = MOTION,
    seed: int = 0,
    alert_limit: float | None = None,
):
    """The drift planned on the toy approach (START clean frames, then FRAMES attacked) against a
    defense with `motion` settings, and that defense (its availability judged against a constant
    `alert_limit`, m) over what it delivered -> (true rel, clean estimates, the planner's trace, the
    defense's trace)."""
    n = START + FRAMES
    rel, t_clean, R_cam, u = approach(n, seed)
    attacked = np.arange(n) >= START
    defense = Defense(DefenseSettings(), motion, NOISE)
    trace = drift_estimates(
        defense, DriftSettings(direction, 0.5, rate, cusum_fraction), t_clean, np.zeros(n), R_cam, u, attacked
    )
    assert not defense.filter.started  # the caller's defense is left alone
    return (
        rel,
        t_clean,
        trace,
        run_defense(
            DefenseSettings(),
            motion,
            NOISE,
            trace.delivered,
            np.zeros(n),
            R_cam,
            u,
            alert_limit=None if alert_limit is None else lambda _: alert_limit,
        ),
    )


@pytest.mark.parametrize("direction", ["los", "lateral"])
@pytest.mark.parametrize("alert_limit", [3.0, 4.0])
def test_a_drift_under_the_gate_is_caught_or_bounded(direction: str, alert_limit: float) -> None:
    """The drift of issue 26 (every innovation under half the gate, past AL within 100 frames), against
    a filter whose process noise (5 cm per frame) lets the state follow it: with the sequential test
    off it walks the trusted estimate past AL unflagged; with it on, no frame is misleading (error >
    PL) and none is hazardous (available, error > AL): the chain declares itself unavailable (PL >
    AL) before the error passes AL. With a tighter reference value (c = 0.5) the test flags it, and
    the same holds."""
    loose = dataclasses.replace(MOTION, position_noise=0.05)
    rate = 1.25 * alert_limit / FRAMES  # m/frame: past AL within the 100 frames
    rel, t_clean, _, off = drifted(direction, rate, None, dataclasses.replace(loose, cusum_threshold=1e12))
    error = np.linalg.norm(off.trusted - rel, axis=1)
    assert not off.flag.any() and np.nanmax(off.nis_position) <= MOTION.gate
    assert error[:START].max() < alert_limit < error[-1]
    _, _, trace, d = drifted(direction, rate, None, loose, alert_limit=alert_limit)
    error = np.linalg.norm(d.trusted - rel, axis=1)
    assert not d.motion_flag.any()  # the gate still sees nothing
    assert not (d.available & (error > alert_limit)).any()  # no hazardous frame
    assert not (error > d.pl).any()  # no misleading frame
    _, _, _, tight = drifted(
        direction, rate, None, dataclasses.replace(loose, cusum_reference=0.5), alert_limit=alert_limit
    )
    error = np.linalg.norm(tight.trusted - rel, axis=1)
    assert not tight.sequential_flag[:START].any() and tight.sequential_flag[START:].any()
    assert not (tight.available & (error > alert_limit)).any() and not (error > tight.pl).any()
    offset = trace.delivered - t_clean
    jumped = run_defense(
        DefenseSettings(),
        loose,
        NOISE,
        np.where(np.arange(len(rel))[:, None] >= START, t_clean + offset[-1], t_clean),
        np.zeros(len(rel)),
        np.repeat(np.eye(3)[None], len(rel), 0),
        np.vstack([np.zeros(3), np.diff(rel, axis=0)]),
    )
    assert jumped.flag[START]  # the gate catches the same offset as a jump


@pytest.mark.parametrize("direction", ["los", "lateral"])
def test_a_drift_that_keeps_under_both_tests_stays_within_the_protection_level(direction: str) -> None:
    """The drift that also keeps every CUSUM statistic under half its threshold is never flagged,
    but it can only keep up the ramp the filter's process noise allows: the trusted error stays
    within the PL on every frame, far below the 3 m the gate-only drift reached."""
    rel, _, trace, d = drifted(direction, 0.0375, 0.5, seed=2)
    error = np.linalg.norm(d.trusted - rel, axis=1)
    assert not d.flag.any() and d.available[1:].all()
    assert (error <= d.pl).all() and error.max() < 1.5
    np.testing.assert_allclose(d.trusted, trace.trusted)  # the attacker's simulation is the defense
    assert np.abs(trace.bias[-1]) > 0.3  # it did drift


def test_drift_grows_along_its_direction_at_its_rate() -> None:
    n = START + FRAMES
    _, t_clean, R_cam, u = approach(n, seed=1)
    attacked = np.arange(n) >= START
    loose = dataclasses.replace(MOTION, position_noise=0.05, cusum_threshold=1e12)  # a state that follows
    trace = drift_estimates(
        Defense(DefenseSettings(), loose, NOISE),
        DriftSettings("los", 0.5, 0.03, None),
        t_clean,
        np.zeros(n),
        R_cam,
        u,
        attacked,
    )
    assert (trace.bias[~attacked] == 0).all() and (np.diff(trace.bias[attacked]) <= 0.03 + 1e-9).all()
    offset = trace.delivered - t_clean
    along = offset[attacked] @ np.array([0.0, 0.0, 1.0])
    assert along[-1] > 2.5 and np.abs(offset[attacked][:, :2]).max() < 0.2 * along[-1]


def tiny_chain() -> PerFrameChain:
    torch.manual_seed(0)
    model = PoseNet(width=0.125).eval()
    model.set_output_bias((0.0, 0.0, 30.0), tuple(matrix_to_6d(np.eye(3))))
    with torch.no_grad():
        model.head_pos.weight.normal_(0.0, 0.05)  # a pose that responds to the image (m)
        background = model.forward_features(torch.rand(8, 3, 18, 32))
    weight = torch.cat([model.head_pos.weight, model.head_rot.weight]).detach()
    detector = LSTMDetector(LSTMConfig(n_rows=9, n_features=weight.shape[1], hidden=4, dense=[4])).eval()
    return PerFrameChain(model, ExactShap(weight, background.mean(0)), detector)


def frames(n: int) -> torch.Tensor:
    return torch.round(torch.rand(n, 3, 18, 32, generator=torch.Generator().manual_seed(1)) * 255) / 255


def test_targeted_pgd_moves_the_estimate_toward_its_target_within_eps() -> None:
    chain, x, eps = tiny_chain(), frames(2), 0.02
    with torch.no_grad():
        clean = chain(x)[0]
    target = clean.clone()
    target[:, 2] += 1.0  # 1 m farther along the boresight
    stored = targeted_pgd(chain, x, target, eps, 0.0, steps=5, generator=torch.Generator().manual_seed(0))
    assert stored.dtype == torch.uint8
    assert (stored.float() / 255 - x).abs().max() <= eps + 0.5 / 255 + 1e-6
    with torch.no_grad():
        moved = chain(stored.float() / 255)[0]
    assert ((moved[:, :3] - target[:, :3]).norm(dim=1) < (clean[:, :3] - target[:, :3]).norm(dim=1)).all()


def test_drift_attacker_delivers_stored_frames_within_eps() -> None:
    chain, n, eps = tiny_chain(), 6, 0.02
    x = frames(n)
    attacked = np.arange(n) >= 2
    run = AttackRun(x, torch.zeros(n, 9), np.repeat(np.eye(3)[None], n, 0), np.zeros((n, 3)), attacked)
    defense = Defense(DefenseSettings(), MOTION, NOISE)
    stored = get_attacker("drift", steps=3).attack(chain, defense, run, eps)
    assert stored.shape == x.shape and stored.dtype == torch.uint8
    assert torch.equal(stored[~torch.from_numpy(attacked)], run.stored()[~torch.from_numpy(attacked)])
    assert (stored.float() / 255 - x).abs().max() <= eps + 0.5 / 255 + 1e-6
    with torch.no_grad():
        delivered, clean = chain(stored.float() / 255)[0], chain(x)[0]
    assert (delivered[attacked, 2] - clean[attacked, 2]).mean() > 0.1  # pushed away along the line of sight
    assert not defense.filter.started and defense.holding  # the caller's defense is left alone


def test_unknown_attacker_and_bad_settings_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match=r"^unknown attacker 'x'; choose one of .*drift"):
        get_attacker("x")
    run = AttackRun(frames(2), torch.zeros(2, 9), np.repeat(np.eye(3)[None], 2, 0))
    defense = Defense(DefenseSettings(), MOTION, NOISE)
    for eps in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match=r"eps must be in \(0, 1\]"):
            DriftAttacker().attack(tiny_chain(), defense, run, eps)
    for bad in ({"direction": "up"}, {"gate_fraction": 0.0}, {"max_rate": -1.0}):
        with pytest.raises(ValueError, match="drift"):
            DriftSettings(**bad)
    with pytest.raises(ValueError, match="R_cam"):
        AttackRun(frames(2), torch.zeros(2, 9), np.eye(3)[None])

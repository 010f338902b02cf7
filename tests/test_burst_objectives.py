"""The burst attacker's objectives on what is judged (issue 39): the filter mirror's protection level is the
real filter's on the accepted path (first start with its trusted frames, and taken over mid-run), the
error / PL objective ascends it through the mirror, the hinge margin stops paying inside the threshold,
and the candidates are judged by the failing frames of their index (test_burst's tiny PoseNet, CPU)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_burst import MOTION, NOISE, N, scene  # noqa: F401  (its tiny PoseNet, LSTM and run)

from pipeline.attackers.base import margin_cost
from pipeline.attackers.burst import WIDE_LAMBDAS, BurstAttacker
from pipeline.attackers.filter_mirror import FilterMirror
from pipeline.defense.fusion import Defense
from pipeline.defense.kalman import MotionFilter
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.rotations import rotvec_to_matrix, sixd_to_matrix, sixd_to_matrix_t


@pytest.mark.parametrize("trusted_start,correlated", [(0, 0.0), (3, 0.0), (0, 0.5), (3, 0.5)])
def test_the_mirror_replays_the_protection_level(scene, trusted_start: int, correlated: float) -> None:
    model, _, run, _ = scene
    rng = np.random.default_rng(1)
    with torch.no_grad():
        pose = model(torch.clamp(run.images + 0.05 * torch.randn(run.images.shape), 0, 1)).double()
    pose[5, :3] += torch.tensor([0.4, -0.3, 1.5], dtype=torch.float64)  # a Huber-weighted frame
    R_cam = np.stack([rotvec_to_matrix(rng.normal(0, 0.3, 3)) for _ in range(N)])
    u = rng.normal(0, 0.05, (N, 3))
    motion = dataclasses.replace(MOTION, cusum_threshold=1e9, trusted_start=trusted_start, correlated_error=correlated)
    real = MotionFilter(motion, NOISE)
    mirror = FilterMirror(real, 2)
    assert torch.isinf(mirror.protection_level()).all()
    for k in range(N):
        t, R6 = pose[k, :3], pose[k, 3:]
        mirror.step(t.expand(2, 3), sixd_to_matrix_t(R6.expand(2, 6)), R_cam[k], u[k])
        if k == 0:
            real.start_from(t.numpy(), R_cam[k], sixd_to_matrix(R6.numpy()))
        else:
            real.check(t.numpy(), R_cam[k], u[k], sixd_to_matrix(R6.numpy()))
            real.test_sequence()
            real.accept()
        np.testing.assert_allclose(
            mirror.protection_level().numpy(), real.protection_level, rtol=1e-8
        )  # float64, summed in another order
        if k == 4:
            mirror = FilterMirror(real, 2)  # taken over from a started filter
    assert real.protection_level > 0


def test_the_hinge_stops_paying_inside_the_threshold() -> None:
    z = torch.tensor([-2.0, -0.6, -0.4, 0.5])
    np.testing.assert_allclose(margin_cost(z, 0.5).numpy(), [0.0, 0.0, 0.1, 1.0], atol=1e-7)
    assert (margin_cost(z, None) > 0).all()  # softplus pays everywhere


@pytest.mark.parametrize("objective", ["error_al", "error_pl"])
def test_index_objectives_run_nested_and_are_judged_by_their_failing_frames(scene, objective: str) -> None:
    _, chain, run, threshold = scene
    attacker = BurstAttacker(alert_limit=0.05, steps=2, restarts=2, lambdas=(0.0, 3.0), objective=objective, hinge=0.5)
    res = attacker.nested(chain, Defense(DefenseSettings(threshold=threshold), MOTION, NOISE), run, [0.02, 0.05])
    worst = [b[0] for b in res.bursts]
    assert [w.objective for w in worst] == [objective] * 2 and worst[0].mi is not None
    failing = worst[-1].mi if objective == "error_pl" else worst[-1].hmi
    assert worst[-1].key[0] == int(failing.sum())
    assert [w.key for w in worst] == sorted(w.key for w in worst)  # nested: never weaker
    assert worst[-1].score > 0


def test_bad_objectives_are_one_line(scene) -> None:
    _, chain, run, _ = scene
    with pytest.raises(ValueError, match="objective"):
        BurstAttacker(alert_limit=1.0, objective="fear")
    with pytest.raises(ValueError, match="hinge"):
        BurstAttacker(alert_limit=1.0, hinge=-1.0)
    with pytest.raises(ValueError, match="error_pl needs a defense"):
        BurstAttacker(alert_limit=1.0, steps=1, restarts=1, objective="error_pl").attack(chain, None, run, 0.02)
    assert WIDE_LAMBDAS[0] == 0.0 and max(WIDE_LAMBDAS) >= 100

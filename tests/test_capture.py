"""Attackers that go for the mission (issue 39) on a toy chain with the real filter, fusion and closed loop:
capture at acquisition and a drift from frame 0 make the defended chaser dock in the wrong place unflagged,
where a plain per-frame attack of the same budget is flagged and the chaser holds (a safe abort); on a
recorded trajectory the capture and the drift from acquisition stay unflagged and available, the capture
fails error / AL_p at the goal, and the drift inside the protection level's trusted window is misleading
where the same drift right after it is not. Toy chain: each channel's mean of a 4 x 4 image encodes one
camera-frame axis (75 m per unit), so an eps moves the estimate by at most 75 eps per axis (1.47 m at eps
0.02 as 8-bit levels); its per-frame attack is exact (`shift`), the capture's default PGD is checked apart."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.attackers.base import AttackRun
from pipeline.attackers.capture import CaptureAttacker, CaptureInLoop, CaptureSettings
from pipeline.attackers.drift import DriftAttacker, DriftSettings, start_frame
from pipeline.attackers.suite import get_attacker
from pipeline.defense.chain import ChainOutput, Defended
from pipeline.defense.fusion import Defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import AlertLimitSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.evaluation.integrity_runs import Track, fly, plan_attack
from pipeline.evaluation.measures import DOCKED, HELD, MISSED, TIMED_OUT, docking, trajectory_measures
from pipeline.geometry.camera import Intrinsics
from pipeline.guidance.law import AttackWindow, Estimate, GuidanceSettings, run_rendezvous
from pipeline.guidance.settings import ExecutionSettings

G, OFFSET = 75.0, np.array([37.5, 37.5, 0.0])  # metres per unit of channel mean; offset (m)
EPS = 0.02
WIDE = Intrinsics(160, 90, 20.0, 20.0, 79.5, 44.5)
NOISE = NoiseModel((0.12, 0.12, 0.12), (0.0, 0.0, 0.0), 1.0, 0.0)
MOTION = MotionSettings(trusted_start=20, position_noise=0.03)  # the closed loop: commands executed with error
EXACT = MotionSettings(trusted_start=20)  # recorded trajectories: commands executed exactly
IDENTITY6 = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]


class ToyPose(nn.Module):
    """images (B, 3, 4, 4) -> (pose (B, 9): t = G * channel means - OFFSET, a fixed attitude; logit (B,): -5)."""

    temporal = False

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        t = G * x.mean(dim=(2, 3)) - torch.as_tensor(OFFSET, dtype=x.dtype)
        return torch.cat([t, torch.tensor(IDENTITY6, dtype=x.dtype).expand(len(x), 6)], 1), -5.0 + 0.0 * x.sum(
            (1, 2, 3)
        )


class ToyOnboard:
    """The OnboardChain stand-in over ToyPose (what `fly` reads)."""

    def __init__(self, pose: ToyPose):
        self.pose = pose

    def __call__(self, x: torch.Tensor) -> ChainOutput:
        with torch.no_grad():
            p, logit = self.pose(x)
        prob = torch.sigmoid(logit)
        return ChainOutput(p, torch.zeros(len(x), 9, 1), prob, prob >= 0.5)


def encode(t: np.ndarray) -> np.ndarray:
    """uint8 (4, 4, 3) whose channel means read back as t (camera frame, m) to G / 255 / 16 m."""
    out = np.zeros((16, 3), np.uint8)
    for i in range(3):
        total = int(round((t[i] + OFFSET[i]) / G * 255 * 16))
        out[:, i] = total // 16 + (np.arange(16) < total % 16)
    return out.reshape(4, 4, 3)


def shift(
    chain: ToyPose,
    x: torch.Tensor,
    target: torch.Tensor,
    eps: float,
    logit_threshold,
    generator,
    start: torch.Tensor | None = None,
) -> torch.Tensor:
    """The toy's exact FrameAttack: each channel's mean moved toward the target's axis by whole 8-bit levels
    spread over its 16 pixels, at most floor(255 eps) levels per pixel (a start changes nothing: it is exact)."""
    levels = int(np.floor(eps * 255 + 1e-9))
    with torch.no_grad():
        t = chain(x)[0][:, :3]
    want = ((target[:, :3] - t) / G * 255 * 16).round().clamp(-16 * levels, 16 * levels).to(torch.int64)
    out = torch.round(x * 255).to(torch.int64)
    for b in range(len(x)):
        for i in range(3):
            k = int(want[b, i])
            per = torch.full((16,), abs(k) // 16, dtype=torch.int64) + (torch.arange(16) < abs(k) % 16)
            out[b, i] += (int(np.sign(k)) * per).view(4, 4)
    return out.clamp(0, 255).to(torch.uint8)


def plain(chain: ToyPose, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The plain per-frame attack: every axis pushed as far as eps allows away from the truth (the per-frame
    worst position error), stored as 8 bits."""
    t = chain(x)[0][:, :3].detach()
    return shift(chain, x, torch.cat([t + 1e3 * torch.sign(t - y[:, :3]), y[:, 3:]], 1), EPS, None, None)


class ToyCamera:
    """Renders the true camera-frame position (plus 0.1 m of seeded noise) into a toy image; attacked frames
    go through `attack(x, y)`; the estimate carries no attitude (no attitude check)."""

    def __init__(self, chain: ToyPose, seed: int) -> None:
        self.chain, self.rng, self.attack = chain, np.random.default_rng(seed), None

    def render(self, R: np.ndarray, t: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(encode(t + self.rng.normal(size=3) * 0.1)).permute(2, 0, 1)[None].float() / 255

    def estimate(self, x: torch.Tensor, attacked: bool, pose: tuple) -> Estimate:
        if attacked:
            x = self.attack(x, torch.as_tensor(np.r_[pose[1], IDENTITY6], dtype=torch.float32)[None])
        with torch.no_grad():
            p, logit = self.chain(x)
        return Estimate(p[0, :3].double().numpy(), float(torch.sigmoid(logit[0])), None)


def _fly_loop(attacker: str, seed: int, defended: bool = True):
    """One closed-loop approach (true_state with execution error, recover defense or undefended) attacked on
    every frame from acquisition by `attacker` -> (its Docking, flags (or None))."""
    chain = ToyPose()
    s = GuidanceSettings(
        variant="true_state",
        defense="recover" if defended else "undefended",
        max_steps=60,
        execution=ExecutionSettings(seed=seed),
    )
    cam, observe = ToyCamera(chain, seed), None
    if attacker == "plain":
        cam.attack = lambda x, y: plain(chain, x, y).float() / 255
    else:
        plan = (
            CaptureSettings("lateral", initial=1.5)
            if attacker == "capture"
            else CaptureSettings("lateral", initial=0.05, rate=0.1)
        )  # a drift from frame 0, grown under the checks
        loop = CaptureInLoop(chain, EPS, plan, frame_attack=shift, seed=seed)
        cam.attack, observe = loop, loop.observe
    d = Defense(DefenseSettings(), MOTION, NOISE) if defended else None
    r = run_rendezvous(cam.render, cam.estimate, WIDE, s, AttackWindow(60.0, 60), defense=d, observe=observe)
    return docking(r, s.goal, s.tolerance, 5.0), r.flags


@pytest.mark.parametrize("seed", [0, 1])
def test_capture_and_drift_beat_a_plain_per_frame_attack_in_the_closed_loop(seed: int) -> None:
    """Defended chain: the plain per-frame attack is flagged and the chaser holds (safe); the capture (a held
    1.5 m lateral bias) and the drift from frame 0 pass every check and dock it ~1.5 m off: mission failures.
    The undefended control fails under the plain attack too."""
    held, flags = _fly_loop("plain", seed)
    assert held.outcome == HELD and not held.failed and flags.mean() > 0.8
    for attacker in ("capture", "drift"):
        d, flags = _fly_loop(attacker, seed)
        assert d.outcome == MISSED and d.failed and not flags.any(), attacker
        assert 1.2 < d.lateral_miss < 1.7 and abs(d.range_miss) < 0.4
    assert _fly_loop("plain", seed, defended=False)[0].failed


@pytest.fixture(scope="module")
def recorded():
    """A 40-frame toy approach 60 m -> 10 m (camera = world axes), its Track and the AttackRun of it."""
    n = 40
    rel = np.column_stack([np.linspace(6.0, 0.0, n), np.linspace(-4.0, 0.0, n), np.linspace(60.0, 10.0, n)])
    images = np.stack([encode(t) for t in rel + np.random.default_rng(0).normal(size=(n, 3)) * 0.1])
    labels = np.column_stack([rel, np.tile(IDENTITY6, (n, 1))])
    track = Track("T", images, labels)
    run = AttackRun(track.frames(), torch.as_tensor(labels, dtype=torch.float32), track.R_cam, track.u)
    return track, run


def _measures(track: Track, stored: torch.Tensor | None):
    defended = Defended(DefenseSettings(), EXACT, NOISE)
    f = fly(
        ToyOnboard(ToyPose()),
        defended,
        track,
        AlertLimitSettings(kind="persistent"),
        8,
        None if stored is None else stored.permute(0, 2, 3, 1).numpy(),
    )
    return trajectory_measures(f.frames, f.trace.flag), f


def test_on_a_recorded_trajectory_capture_and_drift_stay_unflagged_where_the_plain_attack_is_held(recorded) -> None:
    track, run = recorded
    chain, defense = ToyPose(), Defense(DefenseSettings(), EXACT, NOISE)
    clean, _ = _measures(track, None)
    assert clean.flags == 0 and not clean.failed and clean.final_error < 0.3
    after = AttackRun(run.images, run.labels, run.R_cam, run.u, np.arange(len(run)) >= 1)  # acquisition left clean
    stored = run.stored().clone()
    stored[1:] = plain(chain, run.images[1:], run.labels[1:])
    p, _ = _measures(track, stored)
    assert p.flags > 0.75 * len(run) and p.availability < 0.3 and not p.failed  # flagged, held: the chain knows
    cap, _ = _measures(
        track,
        CaptureAttacker(CaptureSettings("lateral", initial=1.5), frame_attack=shift).attack(chain, defense, run, EPS),
    )
    # available on every frame but the start, which is on probation (held) until the next frame passes
    assert cap.flags == 0 and cap.availability == 1 - 1 / len(run) and cap.failed and cap.final_error > 1.3
    drifts = {}
    for start in ("acquisition", "after_trusted"):
        mask = np.arange(len(run)) >= start_frame(start, EXACT)
        drifted = DriftAttacker(DriftSettings("lateral"), frame_attack=shift).attack(
            chain, defense, AttackRun(run.images, run.labels, run.R_cam, run.u, mask), EPS
        )
        drifts[start] = _measures(track, drifted)
    early, late = (drifts[k][0] for k in ("acquisition", "after_trusted"))
    assert early.flags == late.flags == 0 and early.availability == late.availability == 1 - 1 / len(run)
    assert early.final_error > max(0.6, 3 * late.final_error, 2 * p.max_error_al)
    assert early.mi > 0.8 * len(run) and late.mi == 0  # inside the PL's trusted window the PL misleads
    assert after.mask[0] == 0 and start_frame("acquisition", EXACT) == 0 and start_frame("after_trusted", EXACT) == 21


def test_the_batched_runner_takes_capture_plans_and_the_undefended_control(recorded) -> None:
    """plan_attack runs CaptureSettings plans like drift ones, and the undefended control (no defense: the
    wanted bias delivered as is, no detector margin)."""
    track, _ = recorded
    chain = ToyPose()
    clean = [fly(ToyOnboard(chain), Defended(DefenseSettings(), EXACT, NOISE), track, AlertLimitSettings(), 8)]
    plans = [CaptureSettings("los", initial=1.0), DriftSettings("lateral", max_rate=0.05)]
    for defended in (Defended(DefenseSettings(), EXACT, NOISE), None):
        stored = plan_attack(chain, defended, [track], clean, [(plan, 0) for plan in plans], EPS, 0, frame_attack=shift)
        f = [fly(ToyOnboard(chain), defended, track, AlertLimitSettings(), 8, s[0]) for s in stored]
        los = np.einsum(
            "ij,ij->i",
            f[0].pose[:, :3] - clean[0].pose[:, :3],
            track.labels[:, :3] / np.linalg.norm(track.labels[:, :3], axis=1, keepdims=True),
        )
        assert np.median(los) > 0.8  # the capture's 1 m, outward
        grown = abs(f[1].pose[-1, 0] - clean[0].pose[-1, 0])  # the drift grew across the LOS:
        assert grown > (0.3 if defended else 1.0)  # under the checks, or freely
        assert defended is not None or not f[0].trace.flag.any()


def test_the_capture_default_pgd_stays_within_eps_and_moves_the_estimate_its_way(recorded) -> None:
    track, run = recorded
    chain = ToyPose()
    stored = get_attacker("capture", settings=CaptureSettings("lateral", initial=1.0)).attack(
        chain, Defense(DefenseSettings(), EXACT, NOISE), run, EPS
    )
    delta = (stored.float() - run.stored().float()).abs().max()
    assert delta <= np.ceil(EPS * 255) and delta > 0
    with torch.no_grad():
        moved = (chain(stored.float() / 255)[0] - chain(run.images)[0])[:, 0].numpy()
    assert np.median(moved) > 0.5


@pytest.mark.parametrize(
    "change, word",
    [
        ({"direction": "up"}, "direction"),
        ({"initial": 0.0}, "initial"),
        ({"rate": -1.0}, "rate"),
        ({"final": 0.5}, "final"),
        ({"gate_fraction": 1.5}, "gate_fraction"),
    ],
)
def test_bad_capture_settings_are_one_line(change: dict, word: str) -> None:
    with pytest.raises(ValueError, match=word):
        CaptureSettings(**change)
    with pytest.raises(ValueError, match="max_rate"):
        DriftAttacker(DriftSettings("los")).attack(
            ToyPose(), None, AttackRun(torch.zeros(1, 3, 4, 4), torch.zeros(1, 9), np.eye(3)[None]), EPS
        )
    with pytest.raises(ValueError, match="start"):
        start_frame("later", MOTION)


@pytest.mark.parametrize("steps, outcome", [(55, TIMED_OUT), (60, DOCKED)])
def test_detect_and_hold_that_spends_its_step_budget_on_holds_times_out(steps: int, outcome: str) -> None:
    """Detect-and-hold against 10 flagged frames at acquisition: it holds 10 steps, then flies on; with 55 steps the
    budget runs out about 5 m short, still approaching by its own estimate: timed out (an availability loss, not a
    failure); with 60 it docks."""
    chain = ToyPose()
    s = GuidanceSettings(variant="true_state", defense="hold", max_steps=steps, execution=ExecutionSettings(seed=0))
    cam = ToyCamera(chain, 0)
    cam.attack = lambda x, y: plain(chain, x, y).float() / 255
    r = run_rendezvous(
        cam.render, cam.estimate, WIDE, s, AttackWindow(60.0, 10), defense=Defense(DefenseSettings(), MOTION, NOISE)
    )
    d = docking(r, s.goal, s.tolerance, 5.0, s.max_step)
    assert d.outcome == outcome and not d.failed and d.hold_steps == 10
    assert d.arrived == (outcome == DOCKED)

"""The slow drift: false-data injection that walks a chi-square-gated Kalman filter away, frame by frame.

Mo and Sinopoli (2010): a filter that gates its innovations one frame at a time cannot tell a bias
that grows slowly enough from the motion it models. The attacker knows the defense and its state
(`pipeline.defense.fusion.Defense`: the motion filter of pipeline/defense/kalman.py, its noise
model, gate and sequential test) and simulates it step by step on a copy (`DriftPlanner`). Each
frame it offsets the pose estimate by a bias b (metres) along a unit direction d, the line of sight
("los": the target looks farther away) or across it ("lateral": the camera x axis made orthogonal
to the line of sight), both fixed in world axes when the drift starts, and takes the largest b (or,
with `max_rate`, the b nearest the last one plus the rate) whose innovation stays under
`gate_fraction` of the gate's NIS and keeps every CUSUM statistic of the sequential test under
`cusum_fraction` of its threshold (`stealthy_bias`, from the filter's own predicted covariance;
`cusum_fraction` None: an attacker that ignores the sequential test, as against a gate alone).
Every frame passes the checks, the filter updates on it and its state (the trusted estimate that
guidance flies on) moves with the bias. Against a gate alone the next frame's bias can grow again
by about the gate's width; the sequential test holds the persistent normalized innovation under its
reference value c, so the ramp the drift can keep up slows to what the filter's process noise
allows (pipeline/defense/protection.py: the error it causes is within the protection level's c
term). `max_rate` (m/frame) caps the growth of b per frame. At `gate_fraction` <= the soft gate
(MotionSettings.soft_gate, 0.5) no frame is even down-weighted.

At the pixel level (`DriftAttacker`) each attacked frame is a targeted L-inf PGD toward the estimate
the drift wants (the clean estimate + b d; attitude kept at the clean estimate's) with the
detector's margin in the objective (its logit above the threshold's, through a softplus, or a hinge
that stops paying once the logit is under the threshold's by a margin), stored as 8 bits
(`pipeline.attacks.gradient.quantize`); the simulated defense then steps on what the chain reads from
the stored image, so the plan follows what was actually delivered. The per-frame attack is a
`FrameAttack` (`TargetedPGD` by default): any attack of that signature drops in. `TargetedPGD(start="lift",
bpda=True)` is the one strong enough past the robust model's black-level clamp (0.07): it starts from the
background-lifting start (pipeline/attacks/starts.py) and differentiates through the clamp as the identity
(BPDA, pipeline/attacks/bpda.py); a frame attack may also be given a start (`start`: e.g. the previous frame's
perturbation on the next frame, a warm start: consecutive frames of an approach differ little).

Where the drift starts (`start_frame`): the filter starts on the first frame the detector lets through
and the protection level assumes the `trusted_start` frames after it fault-free (its assumption A,
pipeline/defense/protection.py). "acquisition" (frame 0) drifts from the filter's first update on,
inside that blind window; "after_trusted" starts on the first frame the PL accounts for. Against the
undefended chain (`defense` None) nothing checks the bias: it grows by `max_rate` every frame.
"""

from __future__ import annotations

import contextlib
import copy
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from pipeline.attackers.base import AttackRun, chain_outputs, margin_cost, pose_logit, probability_logit
from pipeline.attacks.adaptive import DifferentiableChain
from pipeline.attacks.bpda import black_level, bpda_forward
from pipeline.attacks.gradient import LossFn, check_eps, pgd, project, quantize
from pipeline.attacks.starts import STARTS as FRAME_STARTS
from pipeline.attacks.starts import get_start
from pipeline.defense.fusion import Decision, Defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.kalman import MotionFilter
from pipeline.geometry.rotations import sixd_to_matrix

DIRECTIONS = ("los", "lateral", "near", "vertical")
STARTS = ("acquisition", "after_trusted")


def start_frame(start: str | int, motion: MotionSettings) -> int:
    """The first attacked frame of a drift: "acquisition" 0 (the filter starts on frame 0 of a clean
    trajectory and the drift takes its first update), "after_trusted" 1 + motion.trusted_start (the first
    frame the protection level accounts for), or a frame number >= 0."""
    if isinstance(start, str):
        if start not in STARTS:
            raise ValueError(f"unknown drift start {start!r}; choose one of {', '.join(STARTS)} or a frame number")
        return 0 if start == "acquisition" else 1 + int(motion.trusted_start)
    if int(start) != start or start < 0:
        raise ValueError(f"drift start frame must be a whole number >= 0, got {start!r}")
    return int(start)


@dataclass(frozen=True)
class DriftSettings:
    """direction: "los" (along the line of sight, away from the chaser), "near" (toward it), "lateral" or
    "vertical" (the camera x or y axis across the line of sight);
    gate_fraction: every innovation's NIS stays under this fraction of the gate, in (0, 1];
    max_rate: cap on the growth of the bias per frame (m/frame), None for none; cusum_fraction:
    every CUSUM statistic of the sequential test stays under this fraction of its threshold, in (0,
    1] (None: the drift ignores the sequential test)."""

    direction: str = "los"
    gate_fraction: float = 0.5
    max_rate: float | None = None
    cusum_fraction: float | None = 0.5

    def __post_init__(self) -> None:
        if self.direction not in DIRECTIONS:
            raise ValueError(f"unknown drift direction {self.direction!r}; choose one of {', '.join(DIRECTIONS)}")
        if not 0 < float(self.gate_fraction) <= 1:
            raise ValueError(f"drift gate_fraction must be in (0, 1], got {self.gate_fraction}")
        if self.max_rate is not None and not (math.isfinite(self.max_rate) and self.max_rate > 0):
            raise ValueError(f"drift max_rate (m/frame) must be a finite number > 0 or None, got {self.max_rate}")
        if self.cusum_fraction is not None and not 0 < float(self.cusum_fraction) <= 1:
            raise ValueError(f"drift cusum_fraction must be in (0, 1] or None, got {self.cusum_fraction}")

    def planner(self, defense: Defense | None) -> "DriftPlanner":
        """This drift's planner against (a copy of) `defense` (None: the undefended chain)."""
        return DriftPlanner(defense, self)


def drift_direction(t: np.ndarray, direction: str) -> np.ndarray:
    """Unit vector (3,) of the camera frame along which the drift pushes an estimate at `t` (camera
    frame, m): the line of sight t / |t| ("los"), its opposite ("near"), or the camera x ("lateral") or y
    ("vertical") axis made orthogonal to it."""
    los = np.asarray(t, np.float64) / np.linalg.norm(t)
    if direction in ("los", "near"):
        return los if direction == "los" else -los
    if direction in ("lateral", "vertical"):
        side = np.eye(3)[0 if direction == "lateral" else 1] - los[0 if direction == "lateral" else 1] * los
        return side / np.linalg.norm(side)
    raise ValueError(f"unknown drift direction {direction!r}; choose one of {', '.join(DIRECTIONS)}")


def stealthy_bias(
    motion: MotionFilter,
    t_clean: np.ndarray,
    R_cam: np.ndarray,
    u: np.ndarray | None,
    direction: np.ndarray,
    limit: float,
    wanted: float = math.inf,
    cusum_limit: float | None = None,
) -> float:
    """The bias b (m) nearest `wanted` among those whose estimate t_clean + b * direction (camera
    frame, m) passes `motion`'s next check with a position NIS <= `limit` and, with `cusum_limit`,
    leaves every CUSUM statistic of its sequential test <= `cusum_limit` (the b of least NIS, or of
    the CUSUM interval's middle, when none does). `motion` is not changed.

    The NIS is that of `MotionFilter.check` after predicting with `u` (world, m): innovation
    y(b) = z(b) - prediction, S(b) = P + R(b) with z, R the filter's measurement and its covariance
    (noise model, camera attitude R_cam camera -> world). z is linear in b up to the range-dependent
    noise bias, so the quadratic y^T S^-1 y <= limit and the CUSUM's linear bounds on the innovation
    along each camera axis over its standard deviation are solved for their interval of b at the current b a few times, then checked
    exactly (bisection toward a point inside if the linearisation overshot).
    """
    f = copy.deepcopy(motion)
    f.check(t_clean, R_cam, u)
    p, P = f.position, f.pos.P
    t_clean, R_cam = np.asarray(t_clean, np.float64), np.asarray(R_cam, np.float64)
    c, high, low = f.cusum.reference, np.array(f.cusum.high), np.array(f.cusum.low)

    rng = f.predicted_range

    def terms(b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z, Rz = f.measurement(t_clean + b * direction, R_cam, rng)
        return z - p, P + Rz, np.linalg.inv(P + Rz)

    def ok(b: float) -> bool:
        y, S, S_inv = terms(b)
        r = (R_cam.T @ y) / np.sqrt(np.diag(R_cam.T @ S @ R_cam))
        within = cusum_limit is None or (max((high + r - c).max(), (low - r - c).max()) <= cusum_limit)
        return float(y @ S_inv @ y) <= limit and within

    b, lo, hi, g = 0.0, -math.inf, math.inf, R_cam @ direction
    for _ in range(3):
        y, S, S_inv = terms(b)
        y0 = y - g * b
        a, beta, gamma = g @ S_inv @ g, g @ S_inv @ y0, y0 @ S_inv @ y0
        half = math.sqrt(max(beta * beta - a * (gamma - limit), 0.0)) / a
        lo, hi = -beta / a - half, -beta / a + half
        if cusum_limit is not None:  # the test works along the camera axes (kalman._camera_normalized)
            lo, hi = _cusum_interval(
                R_cam.T @ y0, direction, np.sqrt(np.diag(R_cam.T @ S @ R_cam)), high, low, c, cusum_limit, lo, hi
            )
        b = float(min(max(wanted, lo), hi))
    inside = (lo + hi) / 2 if hi >= lo else lo
    if ok(b) or not ok(inside):
        return b if ok(b) else float(inside)
    for _ in range(30):  # inside passes, b does not: bisect on the segment
        mid = (inside + b) / 2
        inside, b = (mid, b) if ok(mid) else (inside, mid)
    return float(inside)


def _cusum_interval(
    y0: np.ndarray,
    g: np.ndarray,
    sigma: np.ndarray,
    high: np.ndarray,
    low: np.ndarray,
    c: float,
    limit: float,
    lo: float,
    hi: float,
) -> tuple[float, float]:
    """[lo, hi] narrowed to the b whose normalized innovations r = (y0 + g b) / sigma (3,) keep both
    CUSUM statistics of each axis (high + r - c, low - r - c) <= limit; an empty intersection comes
    back as the CUSUM interval's own ends (what the sequential test allows, the gate aside)."""
    r_hi, r_lo = limit + c - high, low - c - limit  # r must lie in [r_lo, r_hi] per axis
    c_lo, c_hi = -math.inf, math.inf
    for i in range(3):
        if abs(g[i]) < 1e-12:
            continue
        ends = sorted(((r_lo[i] * sigma[i] - y0[i]) / g[i], (r_hi[i] * sigma[i] - y0[i]) / g[i]))
        c_lo, c_hi = max(c_lo, ends[0]), min(c_hi, ends[1])
    both = max(lo, c_lo), min(hi, c_hi)
    return both if both[0] <= both[1] else (c_lo, c_hi)


class BiasPlanner:
    """What a planner-driven attacker (drift, capture) keeps: a copy of `defense` (the caller's left as it
    was; None: the undefended chain) that `deliver` steps on the estimate actually delivered, its
    `settings`, the last planned `bias` (m) and its `direction` (world axes, fixed once chosen: a bias that
    turned with the dragged state would turn across it). Subclasses give `target`."""

    def __init__(self, defense: Defense | None, settings: object):
        self.defense = copy.deepcopy(defense)
        self.settings = settings
        self.bias = 0.0
        self.direction: np.ndarray | None = None

    def target(self, t_clean: np.ndarray, R_cam: np.ndarray, u: np.ndarray | None) -> np.ndarray:
        """The camera-frame estimate (m) wanted for a frame whose clean estimate is t_clean (camera frame, m)."""
        raise NotImplementedError

    def deliver(
        self, t: np.ndarray, prob: float, R_cam: np.ndarray, u: np.ndarray | None, R_pred: np.ndarray | None = None
    ) -> Decision | None:
        """Step the simulated defense on the delivered estimate (`Defense.step`'s arguments; None undefended)."""
        return None if self.defense is None else self.defense.step(t, prob, R_cam, u, R_pred)


class DriftPlanner(BiasPlanner):
    """The drift against a copy of `defense` (None: the undefended chain, the bias then grows by
    `max_rate` every frame): `target` gives the estimate the drift wants for a frame. Before the filter
    starts (no trusted estimate yet) the bias is 0. `direction` is fixed when the drift starts, from the
    filter's state (its line of sight moved by the command; the clean estimate's without a defense), not
    from a noisy estimate."""

    def __init__(self, defense: Defense | None, settings: DriftSettings):
        if defense is None and settings.max_rate is None:
            raise ValueError("a drift against the undefended chain needs a max_rate (m/frame): nothing bounds it")
        super().__init__(defense, settings)

    def target(self, t_clean: np.ndarray, R_cam: np.ndarray, u: np.ndarray | None) -> np.ndarray:
        """The camera-frame estimate (m) the drift wants for a frame whose clean estimate is t_clean."""
        s, R_cam = self.settings, np.asarray(R_cam, np.float64)
        if self.defense is None:
            if self.direction is None:
                self.direction = R_cam @ drift_direction(t_clean, s.direction)
            self.bias += s.max_rate
            return np.asarray(t_clean, np.float64) + self.bias * (R_cam.T @ self.direction)
        motion = self.defense.filter
        if not motion.started:
            return np.asarray(t_clean, np.float64)
        if self.direction is None:  # world axes, from the state's line of sight when the drift starts
            ahead = motion.position + (0.0 if u is None else np.asarray(u, np.float64))
            self.direction = R_cam @ drift_direction(R_cam.T @ ahead, s.direction)
        d = R_cam.T @ self.direction
        wanted = math.inf if s.max_rate is None else self.bias + s.max_rate
        cusum = None if s.cusum_fraction is None else s.cusum_fraction * motion.cusum.threshold
        self.bias = stealthy_bias(motion, t_clean, R_cam, u, d, s.gate_fraction * motion.gate, wanted, cusum)
        return np.asarray(t_clean, np.float64) + self.bias * d


@dataclass(frozen=True)
class DriftTrace:
    """A drift planned on estimates: delivered (N, 3) camera-frame estimates (m), bias (N,) the
    planned bias (m; 0 on frames not attacked), flag (N,) and trusted (N, 3) (world, m) of the
    simulated defense."""

    delivered: np.ndarray
    bias: np.ndarray
    flag: np.ndarray
    trusted: np.ndarray


def drift_estimates(
    defense: Defense,
    settings: DriftSettings,
    t_clean: np.ndarray,
    prob: np.ndarray,
    R_cam: np.ndarray,
    u: np.ndarray | None = None,
    attacked: np.ndarray | None = None,
) -> DriftTrace:
    """The drift fed directly as the measurement error (no network): each attacked frame's estimate
    is its clean estimate t_clean (N, 3) (camera frame, m) + the planned bias; prob (N,) the
    detector's probabilities, R_cam (N, 3, 3), u (N, 3) or None, attacked (N,) bool or None (all)."""
    n = len(t_clean)
    attacked = np.ones(n, bool) if attacked is None else np.asarray(attacked, bool)
    planner = DriftPlanner(defense, settings)
    delivered, bias, flag, trusted = np.zeros((n, 3)), np.zeros(n), np.zeros(n, bool), np.zeros((n, 3))
    for k in range(n):
        uk = None if u is None else u[k]
        delivered[k] = planner.target(t_clean[k], R_cam[k], uk) if attacked[k] else t_clean[k]
        bias[k] = planner.bias if attacked[k] else 0.0
        decision = planner.deliver(delivered[k], float(prob[k]), R_cam[k], uk)
        flag[k], trusted[k] = decision.flag, decision.trusted
    return DriftTrace(delivered, bias, flag, trusted)


def targeted_objective(
    target: Tensor, logit_threshold: float, margin_weight: float, hinge: float | None = None
) -> LossFn:
    """What the targeted PGD ascends: -(|t - t*|^2 (m^2) + |r6 - r6*|^2) - margin_weight *
    softplus(logit - logit_threshold), with target (B, 9) = (t*, r6*) the wanted pose: the estimate
    pulled to the target while the detector's logit is kept below its threshold's. With `hinge` m the
    margin is max(0, logit - logit_threshold + m): nothing is paid once the logit is m below it. A chain
    without a detector (a bare pose model) pays no margin."""

    def objective(out: Tensor | tuple[Tensor, Tensor], _: Tensor) -> Tensor:
        pose, logit = pose_logit(out)
        miss = ((pose[:, :3] - target[:, :3]) ** 2).sum(1) + ((pose[:, 3:] - target[:, 3:]) ** 2).sum(1)
        if logit is None or margin_weight == 0:
            return -miss.mean()
        return -(miss + margin_weight * margin_cost(logit - logit_threshold, hinge)).mean()

    return objective


def targeted_pgd(
    chain: DifferentiableChain,
    x: Tensor,
    target: Tensor,
    eps: float,
    logit_threshold: float,
    *,
    margin_weight: float = 1.0,
    steps: int = 20,
    step_size: float | None = None,
    generator: torch.Generator | None = None,
    hinge: float | None = None,
) -> Tensor:
    """Frames x (B, 3, H, W) on the 8-bit grid pulled toward the pose `target` (B, 9) [m, 6-D] by
    L-inf PGD on `targeted_objective` through `chain` (detector margin against `logit_threshold`,
    the logit of its probability threshold; `hinge` its margin), stored as 8 bits: uint8 (B, 3, H, W)."""
    objective = targeted_objective(target, logit_threshold, margin_weight, hinge)
    x_adv = pgd(chain, x, target, eps, objective, steps=steps, step_size=step_size, generator=generator)
    return quantize(x_adv, x)


class FrameAttack(Protocol):
    """A per-frame targeted attack the chain-level attackers call (drift, capture): frames x (B, 3, H, W)
    on the 8-bit grid pulled toward the poses `target` (B, 9) [m, 6-D] within L-inf `eps`, with the
    detector's logit kept under `logit_threshold` (None: no detector to evade, the undefended chain),
    random draws from `generator`, from the images `start` (B, 3, H, W) when given (projected into the ball;
    None: the attack's own start) -> the stored frames, uint8 (B, 3, H, W)."""

    def __call__(
        self,
        chain: DifferentiableChain,
        x: Tensor,
        target: Tensor,
        eps: float,
        logit_threshold: float | None,
        generator: torch.Generator,
        start: Tensor | None = None,
    ) -> Tensor: ...


@dataclass(frozen=True)
class TargetedPGD:
    """The default `FrameAttack`: `targeted_pgd` with `steps` steps of `step_size` (default 2.5 eps /
    steps), `margin_weight` times the detector's margin (softplus, or a hinge of `hinge` logits), from
    `start` (pipeline.attacks.starts.STARTS: "random", or "lift" above a black-level clamp) or the caller's
    start images; `bpda`: the gradient through the pose network's black-level clamp as the identity (a chain
    whose pose network, `chain.model`, has one; no effect on a network without a clamp)."""

    steps: int = 20
    step_size: float | None = None
    margin_weight: float = 1.0
    hinge: float | None = None
    start: str = "random"
    bpda: bool = False

    def __post_init__(self) -> None:
        if int(self.steps) < 1:
            raise ValueError(f"targeted PGD steps (per frame) must be >= 1, got {self.steps}")
        if not (math.isfinite(self.margin_weight) and self.margin_weight >= 0):
            raise ValueError(f"targeted PGD margin_weight must be a finite number >= 0, got {self.margin_weight}")
        if self.hinge is not None and not (math.isfinite(self.hinge) and self.hinge >= 0):
            raise ValueError(f"targeted PGD hinge must be a finite number >= 0 or None, got {self.hinge}")
        if self.start not in FRAME_STARTS:
            raise ValueError(f"unknown targeted PGD start {self.start!r}; choose one of {', '.join(FRAME_STARTS)}")

    def __call__(
        self,
        chain: DifferentiableChain,
        x: Tensor,
        target: Tensor,
        eps: float,
        logit_threshold: float | None,
        generator: torch.Generator,
        start: Tensor | None = None,
    ) -> Tensor:
        weight = 0.0 if logit_threshold is None else self.margin_weight
        threshold = 0.0 if logit_threshold is None else logit_threshold
        if start is None and self.start == "random" and not self.bpda:  # plain PGD, as `targeted_pgd`
            return targeted_pgd(
                chain,
                x,
                target,
                eps,
                threshold,
                margin_weight=weight,
                steps=int(self.steps),
                step_size=self.step_size,
                generator=generator,
                hinge=self.hinge,
            )
        eps = check_eps(eps)
        objective = targeted_objective(target, threshold, weight, self.hinge)
        model = getattr(chain, "model", chain)  # the pose network (a PerFrameChain's), whose clamp BPDA passes
        alpha = 2.5 * eps / int(self.steps) if self.step_size is None else float(self.step_size)
        x = x.detach()
        x_adv = (
            get_start(self.start, x, eps, black_level(model), generator)
            if start is None
            else project(start.detach(), x, eps)
        )
        with bpda_forward(model, chain) if self.bpda else contextlib.nullcontext(chain) as forward:
            for _ in range(int(self.steps)):
                x_adv = x_adv.detach().requires_grad_(True)
                with torch.enable_grad():
                    (grad,) = torch.autograd.grad(objective(forward(x_adv), target), x_adv)
                x_adv = project(x_adv.detach() + alpha * grad.sign(), x, eps)
        return quantize(x_adv, x)


def planned_attack(
    chain: DifferentiableChain,
    run: AttackRun,
    eps: float,
    planner: BiasPlanner,
    frame_attack: FrameAttack,
    logit_threshold: float | None,
    generator: torch.Generator,
) -> Tensor:
    """The stored run (uint8 (N, 3, H, W)) of a planner-driven attacker (drift, capture): each attacked
    frame of `run`, in time order, goes through `frame_attack` toward the pose the `planner` wants (its
    clean attitude kept), and the planner then steps on what the chain reads from the stored frame."""
    stored, mask = run.stored().clone(), run.mask
    clean_pose, clean_prob = chain_outputs(chain, run.images)
    for k in range(len(run)):
        uk = None if run.u is None else run.u[k]
        pose, prob = clean_pose[k], clean_prob[k]
        if mask[k]:
            wanted = planner.target(pose[:3], run.R_cam[k], uk)
            target = torch.as_tensor(np.concatenate([wanted, pose[3:]]), dtype=run.images.dtype)[None]
            stored[k] = frame_attack(chain, run.images[k : k + 1], target, eps, logit_threshold, generator)[0]
            (pose,), (prob,) = chain_outputs(chain, stored[k : k + 1].float() / 255.0)
        planner.deliver(pose[:3], float(prob), run.R_cam[k], uk, sixd_to_matrix(pose[3:]))
    return stored


class DriftAttacker:
    """The drift at the pixel level (pipeline/attackers/base.py's interface): each attacked frame, in
    time order, is a `frame_attack` (default `TargetedPGD(steps, step_size, margin_weight)`: `steps`
    steps of `step_size`, default 2.5 eps / steps, one random start drawn from `seed`, `margin_weight`
    times the detector's margin against its threshold) toward the pose the `DriftPlanner` wants.
    `defense` None: the undefended chain (the drift then needs `settings.max_rate`)."""

    name = "drift"

    def __init__(
        self,
        settings: DriftSettings = DriftSettings(),
        *,
        steps: int = 20,
        step_size: float | None = None,
        margin_weight: float = 1.0,
        seed: int = 0,
        frame_attack: FrameAttack | None = None,
    ):
        if int(steps) < 1:
            raise ValueError(f"drift steps (PGD steps per frame) must be >= 1, got {steps}")
        if not (math.isfinite(margin_weight) and margin_weight >= 0):
            raise ValueError(f"drift margin_weight must be a finite number >= 0, got {margin_weight}")
        self.settings, self.seed = settings, int(seed)
        self.frame_attack = (
            TargetedPGD(int(steps), step_size, float(margin_weight)) if frame_attack is None else frame_attack
        )

    def attack(self, chain: DifferentiableChain, defense: Defense | None, run: AttackRun, eps: float) -> Tensor:
        """The stored images (uint8 (N, 3, H, W)) the drift delivers for `run` at L-inf budget eps."""
        eps = check_eps(eps)
        threshold = None if defense is None else probability_logit(defense.settings.threshold)
        return planned_attack(
            chain,
            run,
            eps,
            self.settings.planner(defense),
            self.frame_attack,
            threshold,
            torch.Generator().manual_seed(self.seed),
        )

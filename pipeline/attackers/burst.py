"""The burst attacker (issue 26): drive the estimate the defense flies on past the alert limit, unflagged.

A burst is a run of consecutive attacked frames (`AttackRun.mask`). The attacker knows the chain
(pose network and detector) and the defense with its state: before each burst it feeds its own
copy of the defense the frames before it, then crafts the burst's K frames jointly, ascending

    J = mean_k min(e_k, c AL_k) - lambda * mean_k (softplus(logit_k - logit(p*))
                                                  + softplus((NIS_pos_k - g) / g) + softplus((NIS_att_k - g) / g)
                                                  + softplus((G_k - h) / h))

where e_k is the error of the trusted estimate (the motion filter's state after frame k, advanced
through the burst as the defense would if it accepted the frames: `FilterMirror`) against the
true rel (world frame, m), AL_k the alert limit (m) at the frame's true range, c the cap (a bounded
objective: past c AL the budget goes to stealth), p* the probability at or above which the detector
stops the frame from updating the filter (the threshold, or `update_below`; the detector's term
is left out under fusion "motion"), g the gate's NIS bound, G_k the sequential test's largest CUSUM
statistic after frame k and h its threshold (pipeline/defense/sequential.py). Each margin is > 0
where that check stops the frame. L-inf PGD (signed steps of `step_size` eps / steps, `steps` of them) runs from
`restarts` starts (batched) for each lambda of the grid in turn (the lambda search); the best
iterate of each run (by J) and its last are stored as 8-bit (`quantize`) and put through the REAL
chain and defense: the burst keeps the candidate with the most hazardously misleading frames (HMI:
unflagged, tracking, PL <= AL (available), trusted error > AL), then the fewest flagged frames, then the largest mean
capped trusted error (`BurstOutcome.key`): the best successful-and-undetected result.

Objectives on what is judged (`BurstAttacker.objective`): "error" is the J above; "error_al" ascends
mean_k min(e_k / AL_k, c) (the safety index against the alert limit, e.g. the persistent-bias AL of
pipeline/defense/integrity.py) and "error_pl" mean_k min(e_k / PL_k, c) (against the protection
level, replayed differentiably by `FilterMirror.protection_level`; a defended chain only). Their
candidates are judged by (frames failing the index: HMI for "error_al", misleading (unflagged, tracking,
error > PL) for "error_pl"; - flagged frames; the largest index over the frames flown). Hinge
margins (`hinge` m): each margin term softplus(z) becomes max(0, z + m), so the attacker stops paying for
stealth once a check is under its threshold by m (in the units of z: the logit, or the fraction of the
gate / CUSUM threshold) instead of paying everywhere inside it. `WIDE_LAMBDAS` is a wider lambda search.

Nested in eps (`BurstAttacker.nested`): for increasing eps, restart 0 starts from the burst's
solution at the previous eps (projected into the new ball), and that stored solution is itself a
candidate, so a burst's worst case cannot drop as eps grows (exactly so for the first burst of a
run; a later burst meets the filter state the earlier bursts at this eps left, and its inherited
candidate is judged again in that state). Without a defense (`defense` None: the undefended chain
flies on the raw estimate, nothing flags) the trusted estimate is the raw one, and with lambda 0
and a cap the errors never reach, restart 0 of the run's first burst at the first eps is plain PGD
(`pipeline.attacks.gradient.pgd`, same seed) on the mean position error, step for step.

Cost: steps x restarts x K frame-gradients per lambda tried, per burst and eps (the chain's
forward and backward; the filter mirror and the real defense add little).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from pipeline.attackers.base import AttackRun, chain_outputs, margin_cost, pose_logit
from pipeline.attackers.filter_mirror import DTYPE, FilterMirror
from pipeline.attacks.adaptive import DifferentiableChain, check_lambdas
from pipeline.attacks.gradient import check_eps, project, quantize
from pipeline.defense.fusion import TRACK, Defense
from pipeline.geometry.rotations import sixd_to_matrix, sixd_to_matrix_t

AlertLimit = float | Callable[[np.ndarray], np.ndarray]
OBJECTIVES = ("error", "error_al", "error_pl")
WIDE_LAMBDAS = (0.0, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  # a wider lambda search than the default


@dataclass(frozen=True)
class BurstOutcome:
    """One burst's worst case at `eps`, as stored and as the real defense saw it.

    found_at: the eps it was crafted at (<= eps); lam, restart: the run that found it; images: (K,
    3, H, W) uint8; pose (K, 9) [m, 6-D] and prob (K,) of the chain on them; trusted_error,
    raw_error (K,) m; flag, hmi (K,) bool; mode (K,) str; score: mean capped trusted error (m) (objective
    "error"), else the largest error / AL or error / PL over the frames flown (unflagged, tracking); mi (K,) bool unflagged
    tracking frames with error > PL (None without a defense); objective: the one it was judged by.
    """

    eps: float
    found_at: float
    lam: float
    restart: int
    images: Tensor
    pose: np.ndarray
    prob: np.ndarray
    trusted_error: np.ndarray
    raw_error: np.ndarray
    flag: np.ndarray
    mode: np.ndarray
    hmi: np.ndarray
    score: float
    mi: np.ndarray | None = None
    objective: str = "error"

    @property
    def key(self) -> tuple[int, int, float]:
        """(HMI frames, or misleading frames under "error_pl"; - flagged frames; score): larger is worse
        for the defense."""
        failing = self.mi if self.objective == "error_pl" else self.hmi
        return int(failing.sum()), -int(self.flag.sum()), float(self.score)


@dataclass(frozen=True)
class NestedResult:
    """`BurstAttacker.nested` over a run: per eps (increasing), the stored run (N, 3, H, W) uint8
    and the worst case of each burst in time order."""

    eps: tuple[float, ...]
    images: list[Tensor]
    bursts: list[list[BurstOutcome]]


def bursts_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """The (start, stop) of each run of consecutive True frames in `mask` (N,)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


@dataclass
class _Burst:
    """One burst of K frames against the defense state `defense` (read only; None: undefended)."""

    chain: DifferentiableChain
    defense: Defense | None
    x: Tensor  # (K, 3, H, W) clean frames, 8-bit grid
    labels: Tensor  # (K, 9)
    R_cam: np.ndarray  # (K, 3, 3)
    u: np.ndarray | None  # (K, 3)
    alert_limit: np.ndarray  # (K,) m
    cap: float
    objective: str = "error"
    hinge: float | None = None
    truth: np.ndarray = field(init=False)  # (K, 3) true rel, world frame (m)
    logit_doubt: float | None = field(init=False)

    def __post_init__(self) -> None:
        self.truth = np.einsum("kij,kj->ki", self.R_cam, self.labels[:, :3].double().numpy())
        s = None if self.defense is None else self.defense.settings
        doubt = None
        if s is not None and s.fusion != "motion":
            doubt = s.threshold if s.update_below is None else s.update_below
        self.logit_doubt = None if doubt is None else float(np.log(doubt / (1 - doubt)))
        if self.objective == "error_pl" and self.defense is None:
            raise ValueError("burst objective error_pl needs a defense (the undefended chain has no protection level)")

    def objective_of(self, X: Tensor, lam: Tensor) -> Tensor:
        """J (R,) of R candidate bursts X (R, K, 3, H, W): the capped index of `objective` - lam * margins."""
        R, K = X.shape[:2]
        pose, logit = pose_logit(self.chain(X.flatten(0, 1)))
        pose = pose.to(DTYPE).view(R, K, 9)
        margin = torch.zeros(R, dtype=DTYPE)
        m = self.hinge
        if self.defense is None:
            trusted = torch.einsum("kij,rkj->rki", torch.as_tensor(self.R_cam), pose[..., :3])
        else:
            mirror, levels, pls = FilterMirror(self.defense.filter, R), [], []
            for k in range(K):
                level, nis_p, nis_a, cusum = mirror.step(
                    pose[:, k, :3],
                    sixd_to_matrix_t(pose[:, k, 3:]),
                    self.R_cam[k],
                    None if self.u is None else self.u[k],
                )
                levels.append(level)
                if self.objective == "error_pl":
                    pls.append(mirror.protection_level())
                g, h = mirror.gate, mirror.threshold
                margin = (
                    margin
                    + margin_cost((nis_p - g) / g, m)
                    + margin_cost((nis_a - g) / g, m)
                    + margin_cost((cusum - h) / h, m)
                )
            trusted = torch.stack(levels, 1)
            if self.logit_doubt is not None and logit is not None:
                margin = margin + margin_cost(logit.to(DTYPE).view(R, K) - self.logit_doubt, m).sum(1)
        err = (trusted - torch.as_tensor(self.truth)).norm(dim=2)
        if self.objective == "error":
            harm = torch.minimum(err, torch.as_tensor(self.cap * self.alert_limit)).mean(1)
        else:
            bound = torch.stack(pls, 1) if self.objective == "error_pl" else torch.as_tensor(self.alert_limit)
            harm = torch.clamp(err / bound, max=self.cap).mean(1)
        return harm - lam * margin / K

    def evaluate(self, stored: Tensor, eps: float, runs: list[tuple[float, int, float]]) -> list[BurstOutcome]:
        """The real chain and defense on C stored candidates (C, K, 3, H, W) uint8; `runs`: (lam,
        restart, found_at) of each."""
        C, K = stored.shape[:2]
        with torch.no_grad():
            pose, logit = pose_logit(self.chain(stored.flatten(0, 1).float() / 255.0))
        pose = pose.double().view(C, K, 9).numpy()
        prob = np.zeros((C, K)) if logit is None else torch.sigmoid(logit.double()).view(C, K).numpy()
        return [self._outcome(stored[c], pose[c], prob[c], eps, *runs[c]) for c in range(C)]

    def _outcome(
        self, images: Tensor, pose: np.ndarray, prob: np.ndarray, eps: float, lam: float, restart: int, found_at: float
    ) -> BurstOutcome:
        K = len(pose)
        pl = np.zeros(K)  # undefended: no protection level
        if self.defense is None:
            trusted, flag, mode = np.einsum("kij,kj->ki", self.R_cam, pose[:, :3]), np.zeros(K, bool), np.full(K, TRACK)
        else:
            d = copy.deepcopy(self.defense)
            out = [
                d.step(
                    pose[k, :3],
                    float(prob[k]),
                    self.R_cam[k],
                    None if self.u is None else self.u[k],
                    sixd_to_matrix(pose[k, 3:]),
                )
                for k in range(K)
            ]
            trusted = np.array([o.trusted for o in out])
            flag, mode, pl = (
                np.array([o.flag for o in out]),
                np.array([o.mode for o in out]),
                np.array([o.pl for o in out]),
            )
        err = np.linalg.norm(trusted - self.truth, axis=1)
        err = np.where(np.isfinite(err), err, 0.0)  # no estimate yet: nothing misleads
        flown = ~flag & (mode == TRACK)
        available = flown & (pl <= self.alert_limit)
        hmi = available & (err > self.alert_limit)
        mi = None if self.defense is None else flown & (err > pl)
        if self.objective == "error":
            score = float(np.minimum(err, self.cap * self.alert_limit).mean())
        else:
            ratio = err / (pl if self.objective == "error_pl" else self.alert_limit)
            score = float(np.max(ratio[flown], initial=0.0))
        return BurstOutcome(
            eps,
            found_at,
            lam,
            restart,
            images,
            pose,
            prob,
            err,
            np.linalg.norm(pose[:, :3] - self.labels[:, :3].double().numpy(), axis=1),
            flag,
            mode,
            hmi,
            score,
            mi,
            self.objective,
        )


@dataclass(frozen=True)
class BurstAttacker:
    """The burst attacker (`pipeline.attackers.base.SequenceAttacker`); see the module docstring.

    alert_limit: AL (m), a number or a function of the true range (m) per frame; cap: c, the
    objective's ceiling in units of AL; steps (>= 1) and restarts (>= 1) per lambda of `lambdas`
    (>= 0, searched in increasing order); step_size: signed-step length in units of eps / steps;
    seed: the random starts'; ladder: the eps (in (0, 1]) that `attack(..., eps)` climbs through
    below eps (the nesting); early_stop: skip the remaining lambdas of a burst (and a larger eps's
    search) once every frame of it is HMI: no candidate can count more HMI frames, though one might
    have a larger error (False: always search the whole grid); objective: one of OBJECTIVES (module
    docstring); hinge: the margins' hinge m (>= 0; None: softplus, as before).
    """

    alert_limit: AlertLimit
    cap: float = 2.0
    steps: int = 50
    restarts: int = 3
    lambdas: tuple[float, ...] = (0.0, 1.0, 10.0)
    step_size: float = 2.5
    seed: int = 0
    ladder: tuple[float, ...] = ()
    early_stop: bool = True
    objective: str = "error"
    hinge: float | None = None
    name: str = field(default="burst", init=False)

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"unknown burst objective {self.objective!r}; choose one of {', '.join(OBJECTIVES)}")
        if self.hinge is not None and not (np.isfinite(self.hinge) and self.hinge >= 0):
            raise ValueError(f"burst hinge must be a finite number >= 0 or None, got {self.hinge}")
        if not callable(self.alert_limit) and not float(self.alert_limit) > 0:
            raise ValueError(f"burst alert_limit (m) must be positive, got {self.alert_limit}")
        for key, value in (("cap", self.cap), ("step_size", self.step_size)):
            if not float(value) > 0:
                raise ValueError(f"burst {key} must be positive, got {value}")
        for key, value in (("steps", self.steps), ("restarts", self.restarts)):
            if int(value) < 1:
                raise ValueError(f"burst {key} must be >= 1, got {value}")
        check_lambdas(list(self.lambdas))
        for e in self.ladder:
            check_eps(e)

    def attack(self, chain: DifferentiableChain, defense: Defense | None, run: AttackRun, eps: float) -> Tensor:
        """The run as stored (N, 3, H, W) uint8, each burst at its worst case at `eps`, nested
        through the `ladder` eps below `eps`."""
        eps = check_eps(eps)
        return self.nested(chain, defense, run, [e for e in sorted(self.ladder) if e < eps] + [eps]).images[-1]

    def nested(
        self, chain: DifferentiableChain, defense: Defense | None, run: AttackRun, eps: list[float]
    ) -> NestedResult:
        """Every burst of `run` at each eps of the increasing list `eps`, the larger eps starting
        from the smaller one's solutions. `defense`: the defense in the state before the run (only
        copies are stepped); None: undefended."""
        eps = [check_eps(e) for e in eps]
        if not eps or any(b <= a for a, b in zip(eps, eps[1:])):
            raise ValueError(f"burst eps must be a non-empty increasing list, got {eps}")
        gen = torch.Generator().manual_seed(int(self.seed))
        was_training = chain.training
        chain.eval()
        try:
            pose, prob = chain_outputs(chain, run.images)
            images, bursts, previous = [], [], None
            for e in eps:
                stored, previous = self._pass(chain, defense, run, e, pose, prob, previous, gen)
                images.append(stored)
                bursts.append(previous)
        finally:
            chain.train(was_training)
        return NestedResult(tuple(eps), images, bursts)

    def _pass(
        self,
        chain: DifferentiableChain,
        defense: Defense | None,
        run: AttackRun,
        eps: float,
        pose: np.ndarray,
        prob: np.ndarray,
        previous: list[BurstOutcome] | None,
        gen: torch.Generator,
    ) -> tuple[Tensor, list[BurstOutcome]]:
        """One eps over the run: clean frames and crafted bursts fed in time order to a copy of the defense."""
        d, pose, prob = copy.deepcopy(defense), pose.copy(), prob.copy()
        stored, outcomes, done = run.stored(), [], 0

        def feed(stop: int) -> None:
            for k in range(done, stop) if d is not None else ():
                u = None if run.u is None else run.u[k]
                d.step(pose[k, :3], float(prob[k]), run.R_cam[k], u, sixd_to_matrix(pose[k, 3:]))

        for b, (lo, hi) in enumerate(bursts_of(run.mask)):
            feed(lo)
            done = lo
            y = run.labels[lo:hi]
            rng = np.linalg.norm(y[:, :3].double().numpy(), axis=1)
            al = self._alert_limit(rng)
            burst = _Burst(
                chain,
                d,
                run.images[lo:hi],
                y,
                np.asarray(run.R_cam[lo:hi], np.float64),
                None if run.u is None else np.asarray(run.u[lo:hi], np.float64),
                np.array(al, np.float64),
                float(self.cap),
                self.objective,
                self.hinge,
            )
            worst = self._burst(burst, eps, None if previous is None else previous[b], gen)
            stored[lo:hi], pose[lo:hi], prob[lo:hi] = worst.images, worst.pose, worst.prob
            outcomes.append(worst)
            feed(hi)
            done = hi
        return stored, outcomes

    def _alert_limit(self, rng: np.ndarray) -> np.ndarray:
        """AL (K,) m at the true ranges `rng` (K,) m; a limit that is not positive is one line."""
        al = self.alert_limit(rng) if callable(self.alert_limit) else float(self.alert_limit)
        al = np.broadcast_to(np.asarray(al, np.float64), rng.shape)
        if not (np.isfinite(al) & (al > 0)).all():
            raise ValueError(f"burst alert_limit (m) must be positive at every range, got {al.min()} at some frame")
        return al

    def _burst(self, burst: _Burst, eps: float, previous: BurstOutcome | None, gen: torch.Generator) -> BurstOutcome:
        """The burst's worst case at eps: the previous eps's solution, then for each lambda in
        increasing order the best and last iterates of its restarts (batched), judged on the stored
        images by the real defense; with `early_stop`, no further lambda once every frame is HMI."""
        x = burst.x
        starts = []
        for r in range(int(self.restarts)):
            if r == 0 and previous is not None:
                starts.append(project(previous.images.float() / 255.0, x, eps))
            else:
                noise = torch.rand(x.shape, generator=gen, dtype=x.dtype)
                starts.append(project(x + (2 * noise - 1) * eps, x, eps))
        found = (
            []
            if previous is None
            else burst.evaluate(previous.images[None], eps, [(previous.lam, previous.restart, previous.found_at)])
        )
        for lam in sorted(float(v) for v in self.lambdas):
            if self.early_stop and found and max(o.key for o in found)[0] == len(x):
                break
            best, last = self._ascend(burst, x, torch.stack(starts), torch.full((len(starts),), lam, dtype=DTYPE), eps)
            runs = [(lam, r, eps) for r in range(len(starts))]
            found += burst.evaluate(torch.stack([quantize(c, x) for c in torch.cat([best, last])]), eps, runs + runs)
        return max(found, key=lambda o: o.key)

    def _ascend(self, burst: _Burst, x: Tensor, X: Tensor, lam: Tensor, eps: float) -> tuple[Tensor, Tensor]:
        """Signed-gradient ascent of `burst.objective_of` from X (R, K, 3, H, W), projected into the
        eps ball and [0, 1]; returns (best iterate of each run by J, last iterate)."""
        alpha = float(self.step_size) * eps / int(self.steps)
        best, best_j = X.clone(), torch.full((len(X),), -torch.inf, dtype=DTYPE)
        for i in range(int(self.steps) + 1):
            X = X.detach().requires_grad_(i < int(self.steps))
            with torch.enable_grad() if X.requires_grad else torch.no_grad():
                J = burst.objective_of(X, lam)
                grad = torch.autograd.grad(J.sum(), X)[0] if X.requires_grad else None
            better = J.detach() > best_j
            best[better], best_j = X.detach()[better], torch.where(better, J.detach(), best_j)
            if grad is not None:
                X = project(X.detach() + alpha * grad.sign(), x, eps)
        return best, X.detach()

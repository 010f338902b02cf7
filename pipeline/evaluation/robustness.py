"""Robustness rows of the safety chain: detection rate, harmful-undetected rate, pose error.

For a set of attacked frames with their position errors (m) and the chain's flags:
- detection rate = flagged frames / attacked frames;
- harmful-undetected rate = frames whose position error exceeds the harm threshold `harm_m` (m)
  and that the chain did not flag / attacked frames: the safety number;
- position error = mean ||t_pred - t_gt|| (m, camera frame) over the attacked frames.
Every rate carries its 95% Wilson interval (`pipeline.stats`): the frames are distinct held-out
test frames, each attacked once, so they are independent trials of the attack.
For benign corruptions, the false-alarm rate = flagged frames / corrupted frames.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import torch

from pipeline.seeds import seed_for
from pipeline.stats import rate

Craft = Callable[[Any, Any], Any]  # (x (B, 3, H, W) in [0, 1], y (B, 9)) -> float adversarial images in [0, 1]


@dataclass(frozen=True)
class AttackSpec:
    """One attack row to run: its name, group (seen, transfer, adaptive, surrogate), eps, lambda
    (adaptive only), the attack and its cost in gradient evaluations per frame."""

    attack: str
    group: str
    eps: float
    lam: float | None
    craft: Craft
    cost: int


def _check(position_error: np.ndarray, flag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.asarray(position_error, dtype=np.float64).ravel()
    flag = np.asarray(flag, dtype=bool).ravel()
    if pos.shape != flag.shape or pos.size == 0:
        raise ValueError(f"position errors {pos.shape} and flags {flag.shape} must be equal, non-empty")
    if not np.isfinite(pos).all():
        raise ValueError(f"{int((~np.isfinite(pos)).sum())} position errors are NaN or infinite")
    return pos, flag


def harmful_undetected(position_error: np.ndarray, flag: np.ndarray, harm_m: float) -> np.ndarray:
    """(N,) bool: position error > harm_m (m) and not flagged."""
    pos, flag = _check(position_error, flag)
    return (pos > harm_m) & ~flag


def attack_row(
    attack: str,
    group: str,
    eps: float,
    position_error: np.ndarray,
    flag: np.ndarray,
    harm_m: float,
    lam: float | None = None,
) -> dict[str, Any]:
    """One attack's row: rates with Wilson 95% intervals and the mean position error (m).

    `group`: transfer, adaptive, surrogate or seen (the detector's own training attack);
    `lam` is the adaptive attack's lambda (None for the other groups). `harmful_rate` is the
    fraction of frames beyond `harm_m` whether flagged or not (what the attack achieves undefended).
    """
    pos, flag = _check(position_error, flag)
    det = rate(flag)
    hu = rate(harmful_undetected(pos, flag, harm_m))
    harmful = rate(pos > harm_m)
    return {
        "attack": attack,
        "group": group,
        "eps": float(eps),
        "adaptive": group == "adaptive",
        "lambda": None if lam is None else float(lam),
        "n": int(pos.size),
        "detection_rate": det.value,
        "harmful_undetected_rate": hu.value,
        "position_error_m": float(pos.mean()),
        "ci95_detection": det.ci(),
        "ci95_harmful_undetected": hu.ci(),
        "harmful_rate": harmful.value,
        "ci95_harmful": harmful.ci(),
    }


def corruption_row(
    corruption: str, strength: float, position_error: np.ndarray, flag: np.ndarray, shipped_flag: np.ndarray
) -> dict[str, Any]:
    """One benign corruption's row: the false-alarm rates of the detector at its own threshold (`flag`) and at
    the threshold the shipped chain flies with (`shipped_flag`), each with its Wilson 95% interval, and the
    mean position error (m)."""
    pos, flag = _check(position_error, flag)
    _, shipped_flag = _check(position_error, shipped_flag)
    fa, shipped = rate(flag), rate(shipped_flag)
    return {
        "corruption": corruption,
        "strength": float(strength),
        "n": int(pos.size),
        "false_alarm_rate": fa.value,
        "ci95_false_alarm": fa.ci(),
        "shipped_false_alarm_rate": shipped.value,
        "ci95_shipped_false_alarm": shipped.ci(),
        "position_error_m": float(pos.mean()),
    }


def worst_over_lambda(
    position_errors: Sequence[np.ndarray], flags: Sequence[np.ndarray], harm_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The attacker who tries every lambda and keeps, per frame, the best image for them.

    Inputs: one (N,) position-error and one (N,) flag array per lambda, same frames in the same
    order. Per frame the kept image is, in this order of preference: harmful and unflagged, then
    unflagged, then the largest position error. Returns (position error (N,), flag (N,), index of
    the kept lambda (N,)).
    """
    pos = np.stack([_check(p, f)[0] for p, f in zip(position_errors, flags)])
    flag = np.stack([np.asarray(f, dtype=bool).ravel() for f in flags])
    if pos.shape != flag.shape or pos.shape[0] == 0:
        raise ValueError("worst_over_lambda needs one position-error and one flag array per lambda")
    hu = (pos > harm_m) & ~flag
    # lexsort sorts by the last key first; take the largest (last) per frame
    order = np.lexsort((pos, ~flag, hu), axis=0)
    pick = order[-1]
    cols = np.arange(pos.shape[1])
    return pos[pick, cols], flag[pick, cols], pick


def worst_by_eps(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per eps (key "%g"): the attack row with the highest harmful-undetected rate, as
    {attack, group, lambda, n, harmful_undetected_rate, ci95_harmful_undetected}."""
    out: dict[str, dict[str, Any]] = {}
    for row in rows:
        key = f"{row['eps']:g}"
        if key not in out or row["harmful_undetected_rate"] > out[key]["harmful_undetected_rate"]:
            out[key] = {
                k: row[k]
                for k in ("attack", "group", "lambda", "n", "harmful_undetected_rate", "ci95_harmful_undetected")
            }
    return out


def _stored(craft: Craft) -> Craft:
    """`craft` whose images are stored as 8-bit and read back, as every attacked frame is."""
    from pipeline.attacks.gradient import quantize

    return lambda x, y: quantize(craft(x, y), x).float() / 255.0


def run_attack_rows(
    chain: Any,
    images: np.ndarray,
    targets: np.ndarray,
    specs: Sequence[AttackSpec],
    harm_m: float,
    batch_size: int,
    progress: Callable[[Iterable[int]], Iterable[int]] = iter,
    pgd_is_lambda0: bool = False,
) -> list[dict[str, Any]]:
    """Every spec's row on the frames (uint8 (N, H, W, 3), labels (N, 9) [m, 6-D]), each attacked
    image stored as 8-bit (`pipeline.attacks.gradient.quantize`) before `chain` (a OnboardChain) reads it;
    then per eps the adaptive attack's worst case over lambda. With `pgd_is_lambda0`, the adaptive
    run at lambda = 0 (plain PGD on the same seed) is also the `pgd` transfer row."""
    from pipeline.defense.chain import run_sequence
    from pipeline.pose.metrics import pose_errors

    attacked = np.ones(len(images), bool)
    rows: list[dict[str, Any]] = []
    per_lambda: dict[float, list[tuple[np.ndarray, np.ndarray]]] = {}
    for s in specs:
        res = run_sequence(chain, images, targets, attacked, _stored(s.craft), batch_size, progress)
        pos = pose_errors(res.pose, targets)[0]
        rows.append(attack_row(s.attack, s.group, s.eps, pos, res.flag, harm_m, s.lam))
        if s.group == "adaptive":
            per_lambda.setdefault(s.eps, []).append((pos, res.flag))
            if s.lam == 0.0 and pgd_is_lambda0:
                rows.append(attack_row("pgd", "transfer", s.eps, pos, res.flag, harm_m))
    for e, runs in per_lambda.items():
        pos, flag, _ = worst_over_lambda([v[0] for v in runs], [v[1] for v in runs], harm_m)
        rows.append(attack_row("adaptive pgd, worst over lambda", "adaptive", e, pos, flag, harm_m))
    order = {"seen": 0, "transfer": 1, "adaptive": 2, "surrogate": 3}
    return sorted(rows, key=lambda row: order.get(row["group"], len(order)))


def attack_specs(
    pose: Any,
    surrogate: Any,
    target: Any,
    *,
    eps: Sequence[float],
    unseen_eps: Sequence[float],
    transfer: Sequence[tuple[str, str, str | None]],
    lambdas: Sequence[float],
    surrogate_attacks: Sequence[tuple[str, str, str | None]],
    steps: int,
    mi_steps: int,
    momentum: float,
    loss: str,
    seed: int,
) -> list[AttackSpec]:
    """The attack rows to run, in report order, on `pose` (and `surrogate`: objects with `.model` and
    `.loss`, the learned training loss) and the adaptive `target` (pipeline.attacks.adaptive.PerFrameChain).
    `transfer`, `surrogate_attacks`: (name, method, loss or None = `loss`). PGD takes `steps`
    gradients, MI-FGSM `mi_steps` (attack.steps, as in the attack stage). PGD at eps index i uses the
    "robustness.pgd" stream (pipeline/seeds.py), so plain PGD and the adaptive attack at lambda = 0 are one run (the
    `pgd` row is then taken from it, pipeline.evaluation.robustness.run_attack_rows)."""
    from pipeline.attacks.gradient import attack_loss

    r = _AttackRows(steps, mi_steps, momentum, loss, seed)
    out = [r.spec("fgsm", "fgsm", None, "seen", e, r.gen("robustness.fgsm", 0), pose) for e in eps]
    out += [r.spec("fgsm", "fgsm", None, "transfer", e, r.gen("robustness.fgsm", 0), pose) for e in unseen_eps]
    pgd_is_lambda0 = "pgd" in [name for name, _, _ in transfer] and 0.0 in lambdas
    out += [
        r.spec(
            name,
            method,
            lname,
            "transfer",
            e,
            r.gen("robustness.pgd", i) if name == "pgd" else r.gen("robustness.transfer", 10 * j + i),
            pose,
        )
        for j, (name, method, lname) in enumerate(transfer)
        for i, e in enumerate(eps)
        if not (name == "pgd" and pgd_is_lambda0)
    ]
    out += r.adaptive(target, attack_loss(loss, pose.loss), eps, lambdas)
    out += [
        replace(
            r.spec(name, method, lname, "surrogate", e, r.gen("robustness.surrogate", 10 * j + i), surrogate),
            attack=f"surrogate {name}",
        )
        for j, (name, method, lname) in enumerate(surrogate_attacks)
        for i, e in enumerate(eps)
    ]
    return out


@dataclass(frozen=True)
class _AttackRows:
    """The settings every row of `attack_specs` shares: PGD's `steps`, MI-FGSM's `mi_steps` and `momentum`, the
    attack `loss` of rows that name none, and the `seed` of the attacks' generator streams (pipeline/seeds.py)."""

    steps: int
    mi_steps: int
    momentum: float
    loss: str
    seed: int

    def gen(self, stream: str, k: int) -> torch.Generator:
        """A CPU generator seeded with the stream's k-th seed."""
        return torch.Generator().manual_seed(seed_for(self.seed, stream, k))

    def cost(self, method: str) -> int:
        """Gradient evaluations per frame of an attack method."""
        return {"fgsm": 1, "pgd": self.steps}.get(method, self.mi_steps)

    def spec(
        self, name: str, method: str, lname: str | None, group: str, e: float, g: torch.Generator, model: Any
    ) -> AttackSpec:
        """The row of attack `method` with loss `lname` (None: the default) at eps `e` on `model` (`.model`,
        `.loss`), its randomness drawn from `g`."""
        from pipeline.attacks.gradient import attack_loss, get_attack

        fn = get_attack(
            method, steps=self.cost(method), step_size=None, random_start=True, momentum=self.momentum, generator=g
        )
        lf = attack_loss(lname or self.loss, model.loss)
        return AttackSpec(name, group, e, None, lambda x, y: fn(model.model, x, y, e, lf), self.cost(method))

    def adaptive(self, target: Any, full: Any, eps: Sequence[float], lambdas: Sequence[float]) -> list[AttackSpec]:
        """The adaptive PGD rows on the chain `target` with the loss `full`, per eps and lambda; eps index i
        draws from the "robustness.pgd" stream's i-th generator, as plain PGD does."""
        from pipeline.attacks.adaptive import adaptive_pgd

        steps = self.steps
        return [
            AttackSpec(
                "adaptive pgd",
                "adaptive",
                e,
                lam,
                lambda x, y, e=e, lam=lam, g=self.gen("robustness.pgd", i): adaptive_pgd(
                    target, x, y, e, full, lam, steps=steps, generator=g
                ),
                steps,
            )
            for i, e in enumerate(eps)
            for lam in lambdas
        ]


# ----------------------------------------------------------------------------- the fused chain on trajectories
def world_motion(targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam (N, 3, 3) camera -> world, u (N, 3) commanded displacement of rel per frame, world, m;
    row 0 zero) of one trajectory from its labels (N, 9) [t camera frame m, 6-D target -> camera],
    for a target that does not rotate in the world frame (R_target = I, as the eval_render
    trajectories are rendered): R = R_cam^T, rel = R_cam t (pipeline/geometry/trajectories.py)."""
    from pipeline.geometry.rotations import sixd_to_matrix

    R_cam = np.swapaxes(sixd_to_matrix(targets[:, 3:]), 1, 2)
    rel = np.einsum("nij,nj->ni", R_cam, np.asarray(targets[:, :3], np.float64))
    return R_cam, np.vstack([np.zeros(3), np.diff(rel, axis=0)])


def burst_schedule(n_frames: int, length: int, every: int) -> list[tuple[int, int]]:
    """Bursts (start, stop) of `length` frames starting every `every` frames, the first after `every`
    clean frames (the motion filter starts on them), all inside the trajectory."""
    if length < 1 or every <= length:
        raise ValueError(f"bursts need length >= 1 and a spacing longer than a burst, got {length} and {every}")
    return [(s, s + length) for s in range(every, n_frames - length + 1, every)]


def pose_estimates(chain: Any, images: np.ndarray, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The chain on clean uint8 frames (N, H, W, 3): (pose (N, 9) [m, 6-D], detector probability (N,))."""
    from pipeline.defense.chain import run_sequence

    res = run_sequence(
        chain, images, np.zeros((len(images), 9), np.float32), np.zeros(len(images), bool), None, batch_size
    )
    return res.pose.astype(np.float64), res.prob


def fused_row(
    attack: str,
    eps: float,
    lam: float | None,
    position_error: np.ndarray,
    flag: np.ndarray,
    groups: np.ndarray,
    harm_m: float,
) -> dict[str, Any]:
    """A row against the fused chain: the attacked frames of whole trajectories, rates with a
    percentile bootstrap over trajectories (`groups`: trajectory id per frame; frames of a burst,
    and bursts of one filter run, are not independent)."""
    from pipeline.stats import bootstrap_rate

    pos, flag = _check(position_error, flag)
    det = bootstrap_rate(flag, groups)
    hu = bootstrap_rate(harmful_undetected(pos, flag, harm_m), groups)
    harmful = bootstrap_rate(pos > harm_m, groups)
    return {
        "attack": attack,
        "group": "fused",
        "chain": "fused",
        "eps": float(eps),
        "adaptive": True,
        "lambda": None if lam is None else float(lam),
        "n": int(pos.size),
        "trajectories": int(len(np.unique(groups))),
        "ci_method": "bootstrap over trajectories",
        "detection_rate": det.value,
        "harmful_undetected_rate": hu.value,
        "position_error_m": float(pos.mean()),
        "ci95_detection": det.ci(),
        "ci95_harmful_undetected": hu.ci(),
        "harmful_rate": harmful.value,
        "ci95_harmful": harmful.ci(),
    }

"""Robustness rows of the safety chain (SPEC 11): detection rate, harmful-undetected rate, pose error.

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

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from pipeline.stats import rate

Craft = Callable[[Any, Any], Any]   # (x (B, 3, H, W) in [0, 1], y (B, 9)) -> float adversarial images in [0, 1]


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


def attack_row(attack: str, group: str, eps: float, position_error: np.ndarray, flag: np.ndarray, harm_m: float,
               lam: float | None = None) -> dict[str, Any]:
    """One attack's row: rates with Wilson 95% intervals and the mean position error (m).

    `group`: transfer, adaptive, surrogate or seen (the detector's own training attack);
    `lam` is the adaptive attack's lambda (None for the other groups). `harmful_rate` is the
    fraction of frames beyond `harm_m` whether flagged or not (what the attack achieves undefended).
    """
    pos, flag = _check(position_error, flag)
    det = rate(flag)
    hu = rate(harmful_undetected(pos, flag, harm_m))
    harmful = rate(pos > harm_m)
    return {"attack": attack, "group": group, "eps": float(eps), "adaptive": group == "adaptive",
            "lambda": None if lam is None else float(lam), "n": int(pos.size),
            "detection_rate": det.value, "harmful_undetected_rate": hu.value, "position_error_m": float(pos.mean()),
            "ci95_detection": det.ci(), "ci95_harmful_undetected": hu.ci(),
            "harmful_rate": harmful.value, "ci95_harmful": harmful.ci()}


def corruption_row(corruption: str, strength: float, position_error: np.ndarray, flag: np.ndarray) -> dict[str, Any]:
    """One benign corruption's row: false-alarm rate with its Wilson 95% interval, mean position error (m)."""
    pos, flag = _check(position_error, flag)
    fa = rate(flag)
    return {"corruption": corruption, "strength": float(strength), "n": int(pos.size), "false_alarm_rate": fa.value,
            "ci95_false_alarm": fa.ci(), "position_error_m": float(pos.mean())}


def worst_over_lambda(position_errors: Sequence[np.ndarray], flags: Sequence[np.ndarray],
                      harm_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
            out[key] = {k: row[k] for k in ("attack", "group", "lambda", "n", "harmful_undetected_rate",
                                             "ci95_harmful_undetected")}
    return out


def _stored(craft: Craft) -> Craft:
    """`craft` whose images are stored as 8-bit and read back, as every attacked frame is."""
    from pipeline.attacks import quantize

    return lambda x, y: quantize(craft(x, y), x).float() / 255.0


def run_attack_rows(chain: Any, images: np.ndarray, targets: np.ndarray, specs: Sequence[AttackSpec], harm_m: float,
                    batch_size: int, progress: Callable[[Iterable[int]], Iterable[int]] = iter,
                    pgd_is_lambda0: bool = False) -> list[dict[str, Any]]:
    """Every spec's row on the frames (uint8 (N, H, W, 3), labels (N, 9) [m, 6-D]), each attacked
    image stored as 8-bit (`pipeline.attacks.quantize`) before `chain` (a SafetyChain) reads it;
    then per eps the adaptive attack's worst case over lambda. With `pgd_is_lambda0`, the adaptive
    run at lambda = 0 (plain PGD on the same seed) is also the `pgd` transfer row."""
    from pipeline.chain import run_sequence
    from pipeline.training import pose_errors

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

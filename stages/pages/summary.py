"""reports/metrics/summary.json, what `dvc metrics show` and `dvc exp show` print: the run's headline
numbers, flat, with short keys (`dvc metrics show` fits in 120 columns), no times. Errors in their
units (m, deg), every rate in percent; a number whose stage did not produce it is left out.

The per-stage metrics JSONs (reports/metrics/<stage>.json) keep every detail; this file only picks from them.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

Metrics = dict[str, dict[str, Any]]


class Headline(NamedTuple):
    key: str                                  # summary.json key (at most 8 characters)
    what: str                                 # what the number is, with its unit
    get: Callable[[Metrics], float]           # from the stage metrics (keyed by metrics file stem)
    decimals: int = 2                         # rounding in summary.json


def _smallest_eps(per_eps: dict[str, Any]) -> str:
    return min(per_eps, key=float)


def _defended(m: Metrics, rate: str) -> float:
    """A rate of the defended (fused) chain at the smallest evaluated eps, in percent."""
    per_eps = m["evaluate"]["fused"]["per_eps"]
    return 100 * per_eps[_smallest_eps(per_eps)][rate]["value"]


def _held(m: Metrics) -> float:
    """Closed-loop attacked runs (that met the attack) whose rendezvous held with detect-and-recover, all dynamics (%)."""
    held = [v for d in m["guidance"]["defended"]["dynamics"].values() for v in d["recover"]["held"].values()]
    return 100 * sum(k for k, _ in held) / sum(n for _, n in held)


def worst_hmi(m: Metrics, eps: str) -> float:
    """The HMI the worst chain-level attacker caused on the shipped chain at `eps` (%; integrity rows)."""
    return 100 * m["robustness"]["integrity"]["worst_hmi"][eps]["hmi"]["value"]


def in_loop_collisions(m: Metrics, defense: str = "recover") -> float:
    """In-loop attacked runs (that met the attack) that collided, `defense` variant, all dynamics and eps (%)."""
    counts = [c for d in m["guidance"]["in_loop"]["counts"].values() for c in d[defense].values()]
    return 100 * sum(c[0] for c in counts) / sum(c[3] for c in counts)


HEADLINES: list[Headline] = [
    Headline("pos_m", "pose, test mean position error (m)", lambda m: m["train"]["test"]["pos_mean_m"], 3),
    Headline("att_deg", "pose, test mean attitude error (deg)", lambda m: m["train"]["test"]["att_mean_deg"]),
    Headline("lstm", "LSTM detector accuracy on the SHAP test split (%)",
             lambda m: 100 * m["detect"]["detectors"]["lstm"]["all"]["accuracy"]),
    Headline("chain", "integrated detection accuracy, mean over eps (%)", lambda m: 100 * m["evaluate"]["accuracy_mean"]),
    Headline("held", "closed loop, attacked runs held with detect-and-recover (%)", _held),
    Headline("hmi01", "integrity: worst HMI caused by a chain-level attack at eps 0.01 (%)", lambda m: worst_hmi(m, "0.01")),
    Headline("hmi05", "integrity: worst HMI caused by a chain-level attack at eps 0.05 (%)", lambda m: worst_hmi(m, "0.05")),
    Headline("avail", "integrity: availability of the trusted estimate without attack (%)",
             lambda m: 100 * m["robustness"]["integrity"]["clean"]["availability"]["value"]),
    Headline("collide", "closed loop, in-loop attacker: collisions with detect-and-recover (%)", in_loop_collisions),
]

# headline numbers of the paper's per-frame view and the lab that the seed spread (scripts/variance.py) and the
# README's "sd over seeds" read, left out of summary.json so that `dvc metrics show` fits in 120 columns
SEED_ONLY: list[Headline] = [
    Headline("defended", "defended chain accuracy at the smallest eps (%)", lambda m: _defended(m, "accuracy")),
    Headline("clean_fa", "defended chain false alarms on attack-free runs (%)", lambda m: _defended(m, "fpr_clean")),
    Headline("harm_und", "worst harmful-undetected rate of the burst attack on the defended chain, any eps (%)",
             lambda m: 100 * max(w["harmful_undetected_rate"]
                                 for w in m["robustness"]["worst_harmful_undetected_fused"].values())),
    Headline("lab", "lab detection accuracy, mean over eps (%)", lambda m: 100 * m["lab"]["accuracy_mean"]),
]


def summary(metrics: Metrics) -> dict[str, float]:
    """The headline numbers of the stage metrics, rounded; those a stage did not produce are left out."""
    out = {}
    for h in HEADLINES:
        try:
            out[h.key] = round(float(h.get(metrics)), h.decimals)
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            continue
    return out

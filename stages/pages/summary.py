"""reports/metrics/summary.json, what `dvc metrics show` and `dvc exp show` print: the run's headline
numbers, no times, grouped by what they measure ({"pose": {"standard_position_m": ...}, ...}), so DVC's columns
read `pose.standard_position_m`. Each name is `<chain>_<what>[_eps_<eps>]_<unit>`: the chain (`standard`, the
paper's reproduction, or `shipped`, the robust model's defended chain), the attack budget where the number is at one
(`_eps_0_01`; `min_eps` at the smallest evaluated), and the unit: `_m`, `_deg`, or `_pct` (every rate in percent);
a number whose stage did not produce it is left out.

The per-stage metrics JSONs (reports/metrics/<stage>.json) keep every detail; this file only picks from them.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

Metrics = dict[str, dict[str, Any]]


class Headline(NamedTuple):
    key: str                                  # dotted summary.json key, <group>.<what>_<unit> (DVC's column)
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
    """Closed-loop attacked runs (that met the attack) whose rendezvous held with detect-and-recover, all
    dynamics (%)."""
    held = [v for d in m["guidance"]["defended"]["dynamics"].values() for v in d["recover"]["held"].values()]
    return 100 * sum(k for k, _ in held) / sum(n for _, n in held)


def worst_hmi(m: Metrics, eps: str, chain: str = "integrity") -> float:
    """The HMI the worst chain-level attacker caused at `eps` (%; integrity rows) on the shipped chain (`chain` =
    "integrity") or the standard model's ("integrity_standard")."""
    return 100 * m["robustness"][chain]["worst_hmi"][eps]["hmi"]["value"]


def in_loop_collisions(m: Metrics, defense: str = "recover") -> float:
    """In-loop attacked runs (that met the attack) that collided, `defense` variant, all dynamics and eps (%)."""
    counts = [c for d in m["guidance"]["in_loop"]["counts"].values() for c in d[defense].values()]
    return 100 * sum(c[0] for c in counts) / sum(c[3] for c in counts)


# Which model: the paper's reproduction rows run on the standard model (`standard_*`); everything else on the chain
# that ships (`shipped_*`: the robust model, its detector and defense).
HEADLINES: list[Headline] = [
    Headline("pose.standard_position_m", "pose, standard model: test mean position error (m)",
             lambda m: m["train"]["test"]["pos_mean_m"], 3),
    Headline("pose.standard_attitude_deg", "pose, standard model: test mean attitude error (deg)",
             lambda m: m["train"]["test"]["att_mean_deg"]),
    Headline("pose.shipped_position_m", "pose, robust model (ships): test mean position error (m)",
             lambda m: m["robust"]["robust"]["test"]["pos_mean_m"], 3),
    Headline("pose.shipped_attitude_deg", "pose, robust model (ships): test mean attitude error (deg)",
             lambda m: m["robust"]["robust"]["test"]["att_mean_deg"]),
    Headline("detector.standard_accuracy_pct", "LSTM detector accuracy on the SHAP test split, standard model (%)",
             lambda m: 100 * m["detect"]["detectors"]["lstm"]["all"]["accuracy"]),
    Headline("detector.shipped_accuracy_pct", "the shipped detector's accuracy on its SHAP test split, robust "
             "model (%)", lambda m: 100 * m["detect_robust"]["detectors"]["lstm"]["all"]["accuracy"]),
    Headline("integrated.standard_accuracy_pct", "integrated detection accuracy, mean over eps, standard model (%)",
             lambda m: 100 * m["evaluate"]["accuracy_mean"]),
    Headline("defended.shipped_accuracy_min_eps_pct", "defended chain (ships) accuracy at the smallest eps (%)",
             lambda m: _defended(m, "accuracy")),
    Headline("defended.shipped_clean_false_alarm_pct", "defended chain (ships) false alarms on attack-free runs (%)",
             lambda m: _defended(m, "fpr_clean")),
    Headline("robustness.shipped_harmful_missed_pct",
             "worst harmful-undetected rate of the burst attack on the defended chain (ships), any eps (%; paper's view)",
             lambda m: 100 * max(w["harmful_undetected_rate"]
                                 for w in m["robustness"]["worst_harmful_undetected_fused"].values())),
    Headline("lab.standard_accuracy_pct", "lab detection accuracy, mean over eps, standard model (%)",
             lambda m: 100 * m["lab"]["accuracy_mean"]),
    Headline("lab.shipped_clean_false_alarm_pct", "lab: the shipped chain's detector false alarms on clean frames (%)",
             lambda m: 100 * m["lab"]["shipped"]["rate"]),
    Headline("guidance.shipped_held_pct", "closed loop (ships): attacked runs held with detect-and-recover (%)", _held),
    Headline("integrity.shipped_hmi_eps_0_01_pct", "integrity (ships): worst HMI caused by a chain-level attack at eps "
             "0.01 (%)", lambda m: worst_hmi(m, "0.01")),
    Headline("integrity.shipped_hmi_eps_0_05_pct", "integrity (ships): worst HMI caused by a chain-level attack at eps "
             "0.05 (%)", lambda m: worst_hmi(m, "0.05")),
    Headline("integrity.standard_hmi_eps_0_01_pct", "integrity, standard model's chain: worst HMI at eps 0.01 (%)",
             lambda m: worst_hmi(m, "0.01", "integrity_standard")),
    Headline("integrity.standard_hmi_eps_0_05_pct", "integrity, standard model's chain: worst HMI at eps 0.05 (%)",
             lambda m: worst_hmi(m, "0.05", "integrity_standard")),
    Headline("integrity.shipped_clean_availability_pct", "integrity (ships): availability of the trusted estimate "
             "without attack (%)", lambda m: 100 * m["robustness"]["integrity"]["clean"]["availability"]["value"]),
    Headline("in_loop.shipped_recover_collisions_pct", "closed loop (ships), in-loop attacker: collisions with "
             "detect-and-recover (%)", in_loop_collisions),
]


# The keys before issue 41 named their chain and eps consistently (new key -> former key): reports/variance.json,
# written from seed runs made before the renames, still names the former ones (stages/pages/readme.py reads both).
FORMER_KEYS = {
    "pose.standard_position_m": "pose.test_position_m",
    "pose.standard_attitude_deg": "pose.test_attitude_deg",
    "pose.shipped_position_m": "pose.robust_test_position_m",
    "pose.shipped_attitude_deg": "pose.robust_test_attitude_deg",
    "detector.standard_accuracy_pct": "detector.lstm_accuracy_pct",
    "detector.shipped_accuracy_pct": "detector.robust_lstm_accuracy_pct",
    "integrated.standard_accuracy_pct": "integrated.accuracy_pct",
    "defended.shipped_accuracy_min_eps_pct": "defended.accuracy_pct",
    "defended.shipped_clean_false_alarm_pct": "defended.clean_false_alarm_pct",
    "robustness.shipped_harmful_missed_pct": "robustness.harmful_undetected_pct",
    "lab.standard_accuracy_pct": "lab.accuracy_pct",
    "guidance.shipped_held_pct": "guidance.defended_held_pct",
    "integrity.shipped_hmi_eps_0_01_pct": "integrity.worst_hmi_eps_0_01_pct",
    "integrity.shipped_hmi_eps_0_05_pct": "integrity.worst_hmi_eps_0_05_pct",
    "integrity.standard_hmi_eps_0_01_pct": "integrity.standard_worst_hmi_0_01_pct",
    "integrity.standard_hmi_eps_0_05_pct": "integrity.standard_worst_hmi_0_05_pct",
    "integrity.shipped_clean_availability_pct": "integrity.clean_availability_pct",
    "in_loop.shipped_recover_collisions_pct": "in_loop.recover_collisions_pct",
}


def headline_values(metrics: Metrics) -> dict[str, float]:
    """The headline numbers of the stage metrics by dotted key, rounded; those a stage did not produce are
    left out."""
    out = {}
    for h in HEADLINES:
        try:
            out[h.key] = round(float(h.get(metrics)), h.decimals)
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            continue
    return out


def summary(metrics: Metrics) -> dict[str, dict[str, float]]:
    """summary.json: `headline_values` nested by the group before each key's dot."""
    out: dict[str, dict[str, float]] = {}
    for key, value in headline_values(metrics).items():
        group, name = key.split(".", 1)
        out.setdefault(group, {})[name] = value
    return out

"""The run's headline numbers (the README's results table, the seed spread) and reports/metrics/summary.json, what
`dvc metrics show` and `dvc exp show` print: the dozen of them in `DVC_METRICS`, no times, grouped by what they measure ({"pose": {"standard_position_m": ...}, ...}), so DVC's columns
read `pose.standard_position_m`. Each name is `<chain>_<what>[_eps_<eps>]_<unit>`: the chain (`standard`, the
paper's reproduction, `shipped`, the robust model's defended chain, or `control`, the undefended robust model), the
attack budget where the number is at one (`_eps_0_01`; `min_eps` at the smallest evaluated), and the unit: `_m`,
`_deg`, `_pct` (every rate in percent), `_eps` (an L-inf budget, pixels in [0, 1]) or `_ratio` (dimensionless); a
number whose stage did not produce it is left out, and an `optional` one may be absent from a complete run (a chain
that held over the whole eps grid has no breaking point; one that broke below eps 0.05 has no rows there,
integrity.stop_at_break; the burst flies only where integrity.attackers has it).

The per-stage metrics JSONs (reports/metrics/<stage>.json) keep every detail; this file only picks from them.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

Metrics = dict[str, dict[str, Any]]


class Headline(NamedTuple):
    key: str  # dotted summary.json key, <group>.<what>_<unit> (DVC's column)
    what: str  # what the number is, with its unit
    get: Callable[[Metrics], float]  # from the stage metrics (keyed by metrics file stem)
    decimals: int = 2  # rounding in summary.json
    optional: bool = False  # may be absent from a complete run (module docstring)


def _smallest_eps(per_eps: dict[str, Any]) -> str:
    return min(per_eps, key=float)


def _defended(m: Metrics, rate: str) -> float:
    """A rate of the defended (fused) chain at the smallest evaluated eps, in percent."""
    per_eps = m["evaluate"]["fused"]["per_eps"]
    return 100 * per_eps[_smallest_eps(per_eps)][rate]["value"]


def _docked(m: Metrics) -> float:
    """Closed-loop attacked runs (that met the attack) that docked with detect-and-recover, true-state
    dynamics (the paper dynamics, prediction = truth by construction, leave the headline) (%)."""
    docked = list(m["guidance"]["defended"]["dynamics"]["true_state"]["recover"]["docked"].values())
    return 100 * sum(k for k, _ in docked) / sum(n for _, n in docked)


def worst_hmi(m: Metrics, eps: str, chain: str = "robust") -> float:
    """The HMI the worst chain-level attacker caused at `eps` (%; integrity rows) on the shipped chain (`chain` =
    "robust") or the standard model's ("standard")."""
    return 100 * m["robustness"]["integrity"]["chains"][chain]["worst_hmi"][eps]["hmi"]["value"]


def breaking_eps(m: Metrics, chain: str) -> float:
    """The chain's breaking point (the smallest eps at which an attacker fails a trajectory; integrity.chains);
    a chain that held over the grid has none (left out)."""
    value = m["robustness"]["integrity"]["breaking_eps"][chain]
    if value is None:
        raise KeyError(chain)
    return value


def docking_miss(m: Metrics, eps: str | None = None) -> float:
    """Detect-and-recover under true-state dynamics (closed loop): the no-attack run's docking miss (m), or with
    `eps` the largest miss of the attacked runs at it."""
    v = m["guidance"]["closed_loop"]["variants"]["true_state"]["recover"]
    return v["clean"]["miss"] if eps is None else v["per_eps"][eps]["largest_miss_m"]


def in_loop_collisions(m: Metrics, defense: str = "recover") -> float:
    """In-loop attacked runs (that met the attack) that collided, `defense` variant, all dynamics and eps (%)."""
    counts = [c for d in m["guidance"]["in_loop"]["counts"].values() for c in d[defense].values()]
    return 100 * sum(c[0] for c in counts) / sum(c[3] for c in counts)


# Which model: the paper's reproduction rows run on the standard model (`standard_*`); everything else on the chain
# that ships (`shipped_*`: the robust model, its detector and defense).
HEADLINES: list[Headline] = [
    Headline(
        "pose.standard_position_m",
        "pose, standard model: test mean position error (m)",
        lambda m: m["train"]["test"]["pos_mean_m"],
        3,
    ),
    Headline(
        "pose.standard_attitude_deg",
        "pose, standard model: test mean attitude error (deg)",
        lambda m: m["train"]["test"]["att_mean_deg"],
    ),
    Headline(
        "pose.shipped_position_m",
        "pose, robust model (ships): test mean position error (m)",
        lambda m: m["robust"]["robust"]["test"]["pos_mean_m"],
        3,
    ),
    Headline(
        "pose.shipped_attitude_deg",
        "pose, robust model (ships): test mean attitude error (deg)",
        lambda m: m["robust"]["robust"]["test"]["att_mean_deg"],
    ),
    Headline(
        "detector.standard_accuracy_pct",
        "LSTM detector accuracy on the SHAP test split, standard model (%)",
        lambda m: 100 * m["detect"]["detectors"]["lstm"]["all"]["accuracy"],
    ),
    Headline(
        "detector.shipped_accuracy_pct",
        "the shipped detector's accuracy on its SHAP test split, robust model (%)",
        lambda m: 100 * m["detect_robust"]["detectors"]["lstm"]["all"]["accuracy"],
    ),
    Headline(
        "integrated.standard_accuracy_pct",
        "integrated detection accuracy, mean over eps, standard model (%)",
        lambda m: 100 * m["evaluate"]["accuracy_mean"],
    ),
    Headline(
        "defended.shipped_accuracy_min_eps_pct",
        "defended chain (ships) accuracy at the smallest eps (%)",
        lambda m: _defended(m, "accuracy"),
    ),
    Headline(
        "defended.shipped_clean_false_alarm_pct",
        "defended chain (ships) false alarms on attack-free runs (%)",
        lambda m: _defended(m, "fpr_clean"),
    ),
    Headline(
        "robustness.shipped_harmful_missed_pct",
        "worst harmful-undetected rate of the burst attack on the defended chain (ships), any eps (%; paper's view)",
        lambda m: (
            100 * max(w["harmful_undetected_rate"] for w in m["robustness"]["worst_harmful_undetected_fused"].values())
        ),
        2,
        True,
    ),  # the burst flies where integrity.attackers has it (the paper profile, rpod integrity)
    Headline(
        "lab.standard_accuracy_pct",
        "lab detection accuracy, mean over eps, standard model (%)",
        lambda m: 100 * m["lab"]["accuracy_mean"],
    ),
    Headline(
        "lab.shipped_clean_false_alarm_pct",
        "lab: the shipped chain's detector false alarms on clean frames (%)",
        lambda m: 100 * m["lab"]["shipped"]["rate"],
    ),
    Headline(
        "guidance.shipped_docked_pct", "closed loop (ships): attacked runs docked with detect-and-recover (%)", _docked
    ),
    Headline(
        "integrity.shipped_hmi_eps_0_01_pct",
        "integrity (ships): worst HMI caused by a chain-level attack at eps 0.01 (%)",
        lambda m: worst_hmi(m, "0.01"),
    ),
    Headline(
        "integrity.shipped_hmi_eps_0_05_pct",
        "integrity (ships): worst HMI caused by a chain-level attack at eps 0.05 (%)",
        lambda m: worst_hmi(m, "0.05"),
        2,
        True,
    ),
    Headline(
        "integrity.standard_hmi_eps_0_01_pct",
        "integrity, standard model's chain: worst HMI at eps 0.01 (%)",
        lambda m: worst_hmi(m, "0.01", "standard"),
    ),
    Headline(
        "integrity.standard_hmi_eps_0_05_pct",
        "integrity, standard model's chain: worst HMI at eps 0.05 (%)",
        lambda m: worst_hmi(m, "0.05", "standard"),
        2,
        True,
    ),
    Headline(
        "integrity.shipped_clean_availability_pct",
        "integrity (ships): availability of the trusted estimate without attack (%)",
        lambda m: 100 * m["robustness"]["integrity"]["clean"]["availability"]["value"],
    ),
    Headline(
        "in_loop.shipped_recover_collisions_pct",
        "closed loop (ships), in-loop attacker: collisions with detect-and-recover (%)",
        in_loop_collisions,
    ),
    # issue 39: the evidence that can fail (eps is the breaking point's unit: an L-inf budget, pixels in [0, 1])
    Headline(
        "integrity.shipped_breaking_eps",
        "breaking point of the shipped chain: smallest eps at which an attacker "
        "fails a trajectory (error / AL > 1 on an available frame)",
        lambda m: breaking_eps(m, "robust"),
        3,
        True,
    ),
    Headline(
        "integrity.standard_breaking_eps",
        "breaking point of the standard model's chain",
        lambda m: breaking_eps(m, "standard"),
        3,
        True,
    ),
    Headline(
        "integrity.control_breaking_eps",
        "breaking point of the undefended robust control",
        lambda m: breaking_eps(m, "control"),
        3,
        True,
    ),
    Headline(
        "integrity.shipped_error_al_0_05_ratio",
        "shipped chain: largest trusted error / AL (persistent "
        "AL, available frames) at eps 0.05, worst over attackers and trajectories",
        lambda m: m["robustness"]["integrity"]["chains"]["robust"]["summary"]["per_eps"]["0.05"]["max_error_al"],
        2,
        True,
    ),
    Headline(
        "closed_loop.recover_docking_miss_m",
        "closed loop (ships, detect-and-recover, true-state dynamics): docking miss without attack (m)",
        docking_miss,
    ),
    Headline(
        "closed_loop.recover_miss_0_05_m",
        "closed loop (ships, detect-and-recover, true-state "
        "dynamics): largest docking miss of the attacked runs at eps 0.05 (m)",
        lambda m: docking_miss(m, "0.05"),
    ),
]


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


# The dozen or so numbers `dvc metrics show` prints (summary.json), so that its row reads in a terminal: what each
# chain's pose costs, whether the shipped detector and defense catch attacks without false alarms, and the evidence
# that can fail (the breaking point of each chain, the control's included, and the worst HMI at eps 0.05). Every
# other headline stays in the README's results table and the seed spread (reports/variance.md).
DVC_METRICS = (
    "pose.standard_position_m",
    "pose.shipped_position_m",
    "pose.shipped_attitude_deg",
    "detector.shipped_accuracy_pct",
    "defended.shipped_accuracy_min_eps_pct",
    "defended.shipped_clean_false_alarm_pct",
    "integrity.shipped_clean_availability_pct",
    "integrity.shipped_hmi_eps_0_05_pct",
    "integrity.standard_hmi_eps_0_05_pct",
    "integrity.shipped_breaking_eps",
    "integrity.standard_breaking_eps",
    "integrity.control_breaking_eps",
    "closed_loop.recover_docking_miss_m",
)


def summary(metrics: Metrics) -> dict[str, dict[str, float]]:
    """summary.json: the `DVC_METRICS` among `headline_values`, nested by the group before each key's dot."""
    out: dict[str, dict[str, float]] = {}
    for key, value in headline_values(metrics).items():
        if key not in DVC_METRICS:
            continue
        group, name = key.split(".", 1)
        out.setdefault(group, {})[name] = value
    return out

"""The paper's numbers, each once and as printed there; every page, stage and script that quotes
one imports it from here (so a correction is one edit)."""
from __future__ import annotations

POSITION_M = 0.49              # pose network, test mean position error (m)
ATTITUDE_DEG = 0.68            # pose network, test mean attitude error (deg)
DETECTOR_ACCURACY = 0.9990     # LSTM-on-SHAP detector, test accuracy (fraction)
INTEGRATED = 99.21             # integrated evaluation, accuracy over the 2,500-frame trajectories (%)
INTEGRATED_EPS = {"0.5": 100.0, "0.3": 99.99, "0.1": 99.97, "0.05": 99.99, "0.01": 97.67}   # per eps (%)
LAB = 96.29                    # lab (mock-up) evaluation, average accuracy (%)
LAB_EPS = {"0.5": 100.0, "0.3": 100.0, "0.1": 100.0, "0.05": 98.44, "0.01": 90.44}         # per eps (%)
LAB_RANGES = {3.122: 51.18}    # representative-range table: lab z (m) -> synthetic z (m), as printed
P_START = 0.2                  # integrated and lab evaluation: a frame outside an attack starts one with this probability
ATTACK_LENGTH = 5              # integrated evaluation: frames per attack
LAB_ATTACK_LENGTH = 10         # lab evaluation: frames per attack


def by_eps(per_eps: dict[str, float]) -> dict[float, float]:
    """A per-eps table keyed by the eps value (float) instead of its printed string."""
    return {float(e): v for e, v in per_eps.items()}

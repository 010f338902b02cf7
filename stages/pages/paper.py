"""The paper's numbers, each once and as printed there; every page, stage and script that quotes
one imports it from here (so a correction is one edit)."""

from __future__ import annotations

POSITION_M = 0.49  # pose network, test mean position error (m)
ATTITUDE_DEG = 0.68  # pose network, test mean attitude error (deg)
DETECTOR_ACCURACY = 0.9990  # LSTM-on-SHAP detector, test accuracy (fraction)
INTEGRATED = 99.21  # integrated evaluation, accuracy over the 2,500-frame trajectories (%)
INTEGRATED_EPS = {"0.5": 100.0, "0.3": 99.99, "0.1": 99.97, "0.05": 99.99, "0.01": 97.67}  # per eps (%)
LAB = 96.29  # lab (mock-up) evaluation, average accuracy (%)
LAB_EPS = {"0.5": 100.0, "0.3": 100.0, "0.1": 100.0, "0.05": 98.44, "0.01": 90.44}  # per eps (%)
LAB_RANGES = {3.122: 51.18}  # representative-range table: lab z (m) -> synthetic z (m), as printed
EVAL_TRAJECTORIES = 3  # integrated evaluation: fresh test trajectories, as printed
EVAL_FRAMES = 2500  # ... frames each, as printed
EVAL_STEP_M = 0.25  # ... metres of range per frame, as printed (60 -> 10 m)
P_START = 0.2  # integrated and lab evaluation: a frame outside an attack starts one with this probability
ATTACK_LENGTH = 5  # integrated evaluation: frames per attack
LAB_ATTACK_LENGTH = 10  # lab evaluation: frames per attack


def by_eps(per_eps: dict[str, float]) -> dict[float, float]:
    """A per-eps table keyed by the eps value (float) instead of its printed string."""
    return {float(e): v for e, v in per_eps.items()}


def frames_note() -> str:
    """One sentence: the paper's evaluation trajectories as printed cannot all hold (frames x step != 50 m)."""
    span = EVAL_FRAMES * EVAL_STEP_M
    return (
        f"The paper's evaluation is printed inconsistently: {EVAL_TRAJECTORIES} trajectories of {EVAL_FRAMES:,} "
        f"frames at {EVAL_STEP_M:g} m per frame would each span {span:g} m of range, not the 50 m from 60 to 10 m "
        f"(that is {50 / EVAL_STEP_M:.0f} frames at {EVAL_STEP_M:g} m, or {100 * 50 / EVAL_FRAMES:g} cm per frame at "
        f"{EVAL_FRAMES:,} frames); its accuracies are quoted as printed."
    )

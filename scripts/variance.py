"""Write reports/variance.md: the spread of the headline numbers over runs that differ only in `seed`.

Each RUN is a checkout (or copy) that ran `dvc repro` (or part of it) on the same profile with its own
seed; the numbers are read from RUN/reports/metrics/*.json, so a run that stopped after `train` adds
its pose numbers only (each row says how many runs it has).

    for s in 1 2; do   # in copies of the repository (git ls-files + .dvc/), one per seed
      rpod params default -S seed=$s && dvc repro
    done
    python scripts/variance.py . /path/to/seed1 /path/to/seed2

Results only (no times), so `git diff reports/` shows what changed.
"""
from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.report import markdown_table  # noqa: E402
from stages.io import atomic_write_text  # noqa: E402

# (key, headline number, metrics file, getter): percentages as percent, errors in their units. The key
# names the number in reports/variance.json, which `rpod report` reads to show the spread in README.md.
HEADLINES: list[tuple[str, str, str, Callable[[dict[str, Any]], float]]] = [
    ("pose_position_m", "pose, test position error (m)", "train", lambda m: m["test"]["pos_mean_m"]),
    ("pose_attitude_deg", "pose, test attitude error (deg)", "train", lambda m: m["test"]["att_mean_deg"]),
    ("pose_tz_pct", "pose, tz error at 10-30 m (% of range)", "train", lambda m: m["test"]["tz_pct_10_30"]),
    ("fgsm_position_m_0.05", "FGSM position error at eps 0.05 (m)", "attack",
     lambda m: m["eps"]["0.05"]["position_mean_m"]),
    ("undefended_lost_pct", "closed loop, attacked runs that lost the rendezvous, undefended (%)", "guidance",
     lambda m: 100 * _lost(m)),
    ("recover_held_pct", "closed loop, attacked runs held, detect-and-recover, paper dynamics (%)", "guidance",
     lambda m: 100 * _held(m["defended"]["dynamics"]["paper"]["recover"])),
    ("lstm_accuracy_pct", "LSTM detector accuracy, SHAP test split (%)", "detect",
     lambda m: 100 * m["detectors"]["lstm"]["all"]["accuracy"]),
    ("lstm_recall_0.01_pct", "LSTM detection rate at eps 0.01 (%)", "detect",
     lambda m: 100 * m["detectors"]["lstm"]["0.01"]["recall"]),
    ("integrated_pct", "integrated accuracy, mean over eps (%)", "evaluate", lambda m: 100 * m["accuracy_mean"]),
    ("integrated_0.01_pct", "integrated accuracy at eps 0.01 (%)", "evaluate",
     lambda m: 100 * m["per_eps"]["0.01"]["accuracy"]),
    ("defended_0.01_pct", "defended chain accuracy at eps 0.01 (%)", "evaluate",
     lambda m: 100 * m["fused"]["per_eps"]["0.01"]["accuracy"]["value"]),
    ("defended_fpr_clean_pct", "defended chain false alarms on attack-free runs (%)", "evaluate",
     lambda m: 100 * m["fused"]["per_eps"]["0.01"]["fpr_clean"]["value"]),
    ("lab_pct", "lab detection accuracy (%)", "lab", lambda m: 100 * m["accuracy_mean"]),
    ("fused_hu_0.05_pct", "worst harmful-undetected at eps 0.05, fused chain (%)", "robustness",
     lambda m: 100 * m["worst_harmful_undetected_fused"]["0.05"]["harmful_undetected_rate"]),
    ("fused_hu_0.01_pct", "worst harmful-undetected at eps 0.01, fused chain (%)", "robustness",
     lambda m: 100 * m["worst_harmful_undetected_fused"]["0.01"]["harmful_undetected_rate"]),
    ("lstm_hu_0.05_pct", "worst harmful-undetected at eps 0.05, LSTM alone (%)", "robustness",
     lambda m: 100 * m["worst_harmful_undetected"]["0.05"]["harmful_undetected_rate"]),
    ("lstm_hu_0.01_pct", "worst harmful-undetected at eps 0.01, LSTM alone (%)", "robustness",
     lambda m: 100 * m["worst_harmful_undetected"]["0.01"]["harmful_undetected_rate"]),
]


def _lost(m: dict[str, Any]) -> float:
    """Fraction of the attacked closed-loop runs (undefended) that lost the rendezvous."""
    runs = [r for r in m["runs"] if r.get("attacked_frames", 1) > 0]
    return sum(r["outcome"] != "rendezvous held" for r in runs) / len(runs)


def _held(variant: dict[str, Any]) -> float:
    """Fraction of attacked runs held over every start of one defended variant ({start: [held, runs]})."""
    return sum(v[0] for v in variant["held"].values()) / sum(v[1] for v in variant["held"].values())



def _value(run: Path, stage: str, get: Callable[[dict[str, Any]], float]) -> float | None:
    """The number from RUN's metrics of `stage`, or None when the stage did not run there: metrics that
    name a pose model (`model_hash`) count only when it is RUN's own models/pose.pt (a copy of the
    repository carries the committed metrics of stages it never ran)."""
    from stages.io import file_hash

    path = run / "reports" / "metrics" / f"{stage}.json"
    if not path.exists():
        return None
    metrics = json.loads(path.read_text())
    pose = run / "models" / "pose.pt"
    if "model_hash" in metrics and (not pose.exists() or metrics["model_hash"] != file_hash(pose)):
        return None
    try:
        return float(get(metrics))
    except (KeyError, TypeError):
        return None


def _seed(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("seed", "?"))


def variance_rows(runs: list[Path]) -> list[dict[str, Any]]:
    """One row per headline number: runs that have it, mean, standard deviation (n - 1), min, max."""
    rows = []
    for key, name, stage, get in HEADLINES:
        values = [v for v in (_value(r, stage, get) for r in runs) if v is not None]
        if not values:
            continue
        sd: float | str = statistics.stdev(values) if len(values) > 1 else "-"  # no spread from one run
        rows.append({"key": key, "headline number": name, "runs": len(values), "mean": statistics.mean(values),
                     "sd": sd, "min": min(values), "max": max(values)})
    return rows


def main(paths: list[str]) -> None:
    runs = [Path(p).resolve() for p in paths]
    missing = [str(r / "params.yaml") for r in runs if not (r / "params.yaml").exists()]
    if missing:
        raise SystemExit(f"not a run of this repository (no params.yaml): {', '.join(missing)}")
    profiles = {yaml_profile(r) for r in runs}
    if len(profiles) != 1:
        raise SystemExit(f"runs of different profiles: {sorted(profiles)}")
    rows = variance_rows(runs)
    profile = profiles.pop()
    seeds = [_seed(r) for r in runs]
    text = f"""# Seed variance

The headline numbers over runs of the `{profile}` profile that differ only in `seed`
({', '.join(seeds)}): a change smaller than about two standard deviations here is
not a result. "runs" counts the runs that produced the number (a run may stop after `train`).
Written by `scripts/variance.py`, with reports/variance.json (read by `rpod report` to show the spread
beside the headline numbers in README.md).

{markdown_table([{k: v for k, v in r.items() if k != "key"} for r in rows], decimals=3)}"""
    spread = {"profile": profile, "seeds": seeds,
              "numbers": {r["key"]: {k: r[k] for k in ("runs", "mean", "sd", "min", "max")} for r in rows}}
    atomic_write_text(ROOT / "reports" / "variance.json", json.dumps(spread, indent=1) + "\n")
    atomic_write_text(ROOT / "reports" / "variance.md", text)
    print(text)


def yaml_profile(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("profile_name", "?"))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(sys.argv[1:])

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

# (headline number, metrics file, getter): percentages as percent, errors in their units
HEADLINES: list[tuple[str, str, Callable[[dict[str, Any]], float]]] = [
    ("pose, test position error (m)", "train", lambda m: m["test"]["pos_mean_m"]),
    ("pose, test attitude error (deg)", "train", lambda m: m["test"]["att_mean_deg"]),
    ("pose, tz error at 10-30 m (% of range)", "train", lambda m: m["test"]["tz_pct_10_30"]),
    ("FGSM position error at eps 0.05 (m)", "attack", lambda m: m["eps"]["0.05"]["position_mean_m"]),
    ("LSTM detector accuracy, SHAP test split (%)", "detect", lambda m: 100 * m["detectors"]["lstm"]["all"]["accuracy"]),
    ("LSTM detection rate at eps 0.01 (%)", "detect", lambda m: 100 * m["detectors"]["lstm"]["0.01"]["recall"]),
    ("integrated accuracy, mean over eps (%)", "evaluate", lambda m: 100 * m["accuracy_mean"]),
    ("integrated accuracy at eps 0.01 (%)", "evaluate", lambda m: 100 * m["per_eps"]["0.01"]["accuracy"]),
    ("defended chain accuracy at eps 0.01 (%)", "evaluate",
     lambda m: 100 * m["fused"]["per_eps"]["0.01"]["accuracy"]["value"]),
    ("lab detection accuracy (%)", "lab", lambda m: 100 * m["accuracy_mean"]),
    ("worst harmful-undetected at eps 0.01, fused chain (%)", "robustness",
     lambda m: 100 * m["worst_harmful_undetected_fused"]["0.01"]["harmful_undetected_rate"]),
]


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
    for name, stage, get in HEADLINES:
        values = [v for v in (_value(r, stage, get) for r in runs) if v is not None]
        if not values:
            continue
        sd: float | str = statistics.stdev(values) if len(values) > 1 else "-"  # no spread from one run
        rows.append({"headline number": name, "runs": len(values), "mean": statistics.mean(values), "sd": sd,
                     "min": min(values), "max": max(values)})
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
    text = f"""# Seed variance

The headline numbers over runs of the `{profiles.pop()}` profile that differ only in `seed`
({', '.join(_seed(r) for r in runs)}): a change smaller than about two standard deviations here is
not a result. "runs" counts the runs that produced the number (a run may stop after `train`).
Written by `scripts/variance.py`.

{markdown_table(rows, decimals=3)}"""
    atomic_write_text(ROOT / "reports" / "variance.md", text)
    print(text)


def yaml_profile(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("profile_name", "?"))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(sys.argv[1:])

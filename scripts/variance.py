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

from pipeline.report.markdown import markdown_table  # noqa: E402
from pipeline.io.atomic import atomic_write_text  # noqa: E402
from stages.pages.summary import HEADLINES as SUMMARY_HEADLINES, SEED_ONLY, Headline, Metrics  # noqa: E402

# The headline numbers: summary.json's (stages/pages/summary.py: `dvc metrics show`: the integrity rows among
# them), its SEED_ONLY ones and a few more that only the seed spread needs. Keys name them in reports/variance.json, which `rpod report` reads to
# show the spread beside the README's headline numbers.
def _lost(m: Metrics) -> float:
    """Percent of the attacked closed-loop runs (undefended) that lost the rendezvous."""
    runs = [r for r in m["guidance"]["runs"] if r.get("attacked_frames", 1) > 0]
    return 100 * sum(r["outcome"] != "rendezvous held" for r in runs) / len(runs)


def _paper_held(m: Metrics) -> float:
    """Percent of attacked runs held with detect-and-recover under the paper's dynamics."""
    held = m["guidance"]["defended"]["dynamics"]["paper"]["recover"]["held"].values()
    return 100 * sum(k for k, _ in held) / sum(n for _, n in held)


def _worst(m: Metrics, key: str, eps: str) -> float:
    return 100 * m["robustness"][key][eps]["harmful_undetected_rate"]


HEADLINES: list[Headline] = [
    *SUMMARY_HEADLINES,
    *SEED_ONLY,
    Headline("pose_tz_pct", "pose, tz error at 10-30 m (% of range)", lambda m: m["train"]["test"]["tz_pct_10_30"]),
    Headline("fgsm_position_m_0.05", "FGSM position error at eps 0.05 (m)",
             lambda m: m["attack"]["eps"]["0.05"]["position_mean_m"]),
    Headline("undefended_lost_pct", "closed loop, attacked runs that lost the rendezvous, undefended (%)", _lost),
    Headline("recover_held_pct", "closed loop, attacked runs held, detect-and-recover, paper dynamics (%)",
             _paper_held),
    Headline("lstm_recall_0.01_pct", "LSTM detection rate at eps 0.01 (%)",
             lambda m: 100 * m["detect"]["detectors"]["lstm"]["0.01"]["recall"]),
    Headline("integrated_0.01_pct", "integrated accuracy at eps 0.01 (%)",
             lambda m: 100 * m["evaluate"]["per_eps"]["0.01"]["accuracy"]),
    Headline("fused_hu_0.05_pct", "worst harmful-undetected at eps 0.05, fused chain (%)",
             lambda m: _worst(m, "worst_harmful_undetected_fused", "0.05")),
    Headline("fused_hu_0.01_pct", "worst harmful-undetected at eps 0.01, fused chain (%)",
             lambda m: _worst(m, "worst_harmful_undetected_fused", "0.01")),
    Headline("lstm_hu_0.05_pct", "worst harmful-undetected at eps 0.05, LSTM alone (%)",
             lambda m: _worst(m, "worst_harmful_undetected", "0.05")),
    Headline("lstm_hu_0.01_pct", "worst harmful-undetected at eps 0.01, LSTM alone (%)",
             lambda m: _worst(m, "worst_harmful_undetected", "0.01")),
]


def run_metrics(run: Path) -> Metrics:
    """RUN's stage metrics by file stem, without those of stages that did not run there: metrics that
    name a pose model (`model_hash`) count only when it is RUN's own models/pose.pt (a copy of the
    repository carries the committed metrics of stages it never ran)."""
    from pipeline.io.atomic import file_hash

    pose = run / "models" / "pose.pt"
    own = file_hash(pose) if pose.exists() else None
    out = {}
    for path in sorted((run / "reports" / "metrics").glob("*.json")):
        metrics = json.loads(path.read_text())
        if "model_hash" not in metrics or metrics["model_hash"] == own:
            out[path.stem] = metrics
    return out


def _value(metrics: Metrics, get: Callable[[Metrics], float]) -> float | None:
    try:
        return float(get(metrics))
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return None


def _seed(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("seed", "?"))


def variance_rows(runs: list[Path]) -> list[dict[str, Any]]:
    """One row per headline number: runs that have it, mean, standard deviation (n - 1), min, max."""
    rows = []
    metrics = [run_metrics(r) for r in runs]
    for key, name, get, _ in HEADLINES:
        values = [v for v in (_value(m, get) for m in metrics) if v is not None]
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

"""Write reports/variance.md: the spread of the headline numbers over runs that differ only in `seed`, and in
the CPU instruction set torch's kernels used (issue 27: AVX2 vs the machine's best, AVX-512 here).

Each RUN is a checkout (or copy) that ran `dvc repro` (or part of it) on the same profile with its own
seed (and instruction-set cap, `RPOD_CPU_ISA`: stages/config/cpu.py); the numbers are read from
RUN/reports/metrics/*.json, so a run that stopped after `train` adds its pose numbers only (each row
says how many runs it has). A run is named by its seed (params.yaml) and the kernels its torch stages
ran (the `cpu_isa` stamp of its metrics); `ISA=RUN` names the instruction set by hand (a run made
before the stamp, or on another machine).

    for s in 1 2; do   # in copies of the repository (git ls-files + .dvc/), one per seed and cap
      rpod params default -S seed=$s && dvc repro                        # AVX2 (the default cap)
    done
    RPOD_CPU_ISA=native dvc repro                                        # the machine's best, in another copy
    python scripts/variance.py . /path/to/seed1 /path/to/seed2 /path/to/seed0-native

With runs of more than one instruction set, reports/variance.md also carries the seed x ISA table:
every run's value and the largest difference between instruction sets at one seed, beside the
spread over seeds at one instruction set. Results only (no times), so `git diff reports/` shows what changed.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.io.atomic import atomic_write_text  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from stages.pages.summary import HEADLINES as SUMMARY_HEADLINES  # noqa: E402
from stages.pages.summary import Headline, Metrics  # noqa: E402


# The headline numbers: summary.json's (stages/pages/summary.py: `dvc metrics show`: the integrity rows among
# them) and a few more that only the seed spread needs. Keys name them in reports/variance.json, which
# `rpod report` reads to show the spread beside the README's headline numbers.
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
    Headline("pose_tz_pct", "pose, tz error at 10-30 m (% of range)", lambda m: m["train"]["test"]["tz_pct_10_30"]),
    Headline(
        "fgsm_position_m_0.05",
        "FGSM position error at eps 0.05 (m)",
        lambda m: m["attack"]["eps"]["0.05"]["position_mean_m"],
    ),
    Headline("undefended_lost_pct", "closed loop, attacked runs that lost the rendezvous, undefended (%)", _lost),
    Headline(
        "recover_held_pct", "closed loop, attacked runs held, detect-and-recover, paper dynamics (%)", _paper_held
    ),
    Headline(
        "lstm_recall_0.01_pct",
        "LSTM detection rate at eps 0.01 (%)",
        lambda m: 100 * m["detect"]["detectors"]["lstm"]["0.01"]["recall"],
    ),
    Headline(
        "lstm_eval_fa_pct",
        "LSTM alone at its own threshold, false alarms on clean evaluation frames (%)",
        lambda m: 100 * m["detect"]["eval_alarms"]["rate"],
    ),
    Headline(
        "shipped_test_fa_pct",
        "shipped detector at its calibrated threshold, clean pose-test frames flagged (%)",
        lambda m: 100 * m["robustness"]["corruptions"][0]["shipped_false_alarm_rate"],
    ),
    Headline(
        "shipped_lab_max_prob",
        "shipped detector, largest probability on clean lab frames (threshold ~0.99-1)",
        lambda m: m["lab"]["shipped"]["probability_max"],
    ),
    Headline(
        "integrated_0.01_pct",
        "integrated accuracy at eps 0.01 (%)",
        lambda m: 100 * m["evaluate"]["per_eps"]["0.01"]["accuracy"],
    ),
    Headline(
        "fused_hu_0.05_pct",
        "worst harmful-undetected at eps 0.05, fused chain (%)",
        lambda m: _worst(m, "worst_harmful_undetected_fused", "0.05"),
    ),
    Headline(
        "fused_hu_0.01_pct",
        "worst harmful-undetected at eps 0.01, fused chain (%)",
        lambda m: _worst(m, "worst_harmful_undetected_fused", "0.01"),
    ),
    Headline(
        "lstm_hu_0.05_pct",
        "worst harmful-undetected at eps 0.05, LSTM alone (%)",
        lambda m: _worst(m, "worst_harmful_undetected", "0.05"),
    ),
    Headline(
        "lstm_hu_0.01_pct",
        "worst harmful-undetected at eps 0.01, LSTM alone (%)",
        lambda m: _worst(m, "worst_harmful_undetected", "0.01"),
    ),
]


def run_metrics(run: Path) -> Metrics:
    """RUN's stage metrics by file stem, without those of stages that did not run there: metrics that
    name a pose model (`model_hash`) count only when it is RUN's own checkpoint of that model (`model`: standard,
    models/pose.pt, when not named; robust, models/pose_robust.pt), as a copy of the repository carries the
    committed metrics of stages it never ran."""
    from pipeline.io.atomic import file_hash
    from stages.artifacts.paths import CHAINS

    own = {m.value: file_hash(run / f.pose) if (run / f.pose).exists() else None for m, f in CHAINS.items()}
    out = {}
    for path in sorted((run / "reports" / "metrics").glob("*.json")):
        metrics = json.loads(path.read_text())
        if "model_hash" not in metrics or metrics["model_hash"] == own.get(metrics.get("model", "standard")):
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


def run_isa(metrics: Metrics) -> str:
    """The instruction set RUN's torch kernels used, from the `cpu_isa` stamp of its metrics (train's first):
    the kernels torch reported ("AVX2", "AVX512"), else the cap; "?" for a run from before the stamp."""
    for name in sorted(metrics, key=lambda n: n != "train"):
        stamp = metrics[name].get("cpu_isa")
        if isinstance(stamp, dict) and (stamp.get("kernels") or stamp.get("cap")):
            return str(stamp.get("kernels") or stamp.get("cap"))
    return "?"


def parse_runs(args: list[str]) -> list[tuple[Path, str | None]]:
    """Command-line runs: PATH, or ISA=PATH to name the instruction set by hand."""
    out = []
    for arg in args:
        isa, sep, path = arg.partition("=")
        out.append((Path(path).resolve(), isa) if sep and "/" not in isa else (Path(arg).resolve(), None))
    return out


def variance_rows(runs: list[Path]) -> list[dict[str, Any]]:
    """One row per headline number: runs that have it, mean, standard deviation (n - 1), min, max."""
    rows = []
    metrics = [run_metrics(r) for r in runs]
    for key, name, get, *_ in HEADLINES:
        values = [v for v in (_value(m, get) for m in metrics) if v is not None]
        if not values:
            continue
        sd: float | str = statistics.stdev(values) if len(values) > 1 else "-"  # no spread from one run
        rows.append(
            {
                "key": key,
                "headline number": name,
                "runs": len(values),
                "mean": statistics.mean(values),
                "sd": sd,
                "min": min(values),
                "max": max(values),
            }
        )
    return rows


def isa_rows(runs: list[Path], seeds: list[str], isas: list[str]) -> list[dict[str, Any]]:
    """The seed x ISA table: per headline number every run's value (column "seed S, ISA"), the largest
    difference between instruction sets at one seed, and the spread over seeds at one instruction set
    (the pooled standard deviation of the instruction sets with two seeds or more)."""
    metrics = [run_metrics(r) for r in runs]
    names = [f"seed {s}, {i}" for s, i in zip(seeds, isas)]
    rows = []
    for key, name, get, *_ in HEADLINES:
        values = [_value(m, get) for m in metrics]
        if all(v is None for v in values):
            continue
        row: dict[str, Any] = {"key": key, "headline number": name}
        row.update({n: "-" if v is None else v for n, v in zip(names, values)})
        by_seed: dict[str, list[float]] = {}
        by_isa: dict[str, list[float]] = {}
        for s, i, v in zip(seeds, isas, values):
            if v is not None:
                by_seed.setdefault(s, []).append(v)
                by_isa.setdefault(i, []).append(v)
        gaps = [max(v) - min(v) for v in by_seed.values() if len(v) > 1]
        spread = [statistics.variance(v) for v in by_isa.values() if len(v) > 1]
        row["largest ISA difference at one seed"] = max(gaps) if gaps else "-"
        row["sd over seeds, one ISA"] = statistics.mean(spread) ** 0.5 if spread else "-"
        rows.append(row)
    return rows


def main(args: list[str]) -> None:
    given = parse_runs(args)
    runs = [r for r, _ in given]
    missing = [str(r / "params.yaml") for r in runs if not (r / "params.yaml").exists()]
    if missing:
        raise SystemExit(f"not a run of this repository (no params.yaml): {', '.join(missing)}")
    profiles = {yaml_profile(r) for r in runs}
    if len(profiles) != 1:
        raise SystemExit(f"runs of different profiles: {sorted(profiles)}")
    rows = variance_rows(runs)
    profile = profiles.pop()
    seeds = [_seed(r) for r in runs]
    isas = [isa or run_isa(run_metrics(r)) for r, isa in given]
    table = markdown_table([{k: v for k, v in r.items() if k != "key"} for r in rows], decimals=3)
    text = f"""# Seed variance

The headline numbers over runs of the `{profile}` profile that differ only in `seed`
({", ".join(seeds)}){_isa_note(isas)}: a change smaller than about two standard deviations here is
not a result. "runs" counts the runs that produced the number (a run may stop after `train`).
Written by `scripts/variance.py`, with reports/variance.json (read by `rpod report` to show the spread
beside the headline numbers in README.md).

{_unmet_note(runs, seeds, isas)}{table}{_isa_section(runs, seeds, isas)}"""
    spread = {
        "profile": profile,
        "seeds": seeds,
        "isas": isas,
        "numbers": {r["key"]: {k: r[k] for k in ("runs", "mean", "sd", "min", "max")} for r in rows},
    }
    atomic_write_text(ROOT / "reports" / "variance.json", json.dumps(spread, indent=1) + "\n")
    atomic_write_text(ROOT / "reports" / "variance.md", text)
    print(text)


def _unmet_note(runs: list[Path], seeds: list[str], isas: list[str]) -> str:
    """One line per run whose calibration missed its target and carried on (`defense.allow_unmet`), from the
    `unmet` list `rpod calibrate` records in each defense file (models/defense*.json); "" when none did."""
    lines = []
    for run, seed, isa in zip(runs, seeds, isas):
        for path in sorted((run / "models").glob("defense*.json")):
            for line in json.loads(path.read_text()).get("unmet") or []:
                lines.append(
                    f"- seed {seed}, {isa}: {path.name}: {line.split('; set defense.allow_unmet')[0]} "
                    "(the run went on with `defense.allow_unmet: true`)"
                )
    return "Calibrations that missed their target:\n\n" + "\n".join(lines) + "\n\n" if lines else ""


def _isa_note(isas: list[str]) -> str:
    """How the runs' instruction sets enter the first table."""
    if len(set(isas)) < 2:
        return f", all with torch's {isas[0]} kernels" if isas and isas[0] != "?" else ""
    return f" and in the instruction set of torch's CPU kernels ({', '.join(sorted(set(isas)))})"


def _isa_section(runs: list[Path], seeds: list[str], isas: list[str]) -> str:
    """The seed x ISA table, when the runs used more than one instruction set."""
    if len(set(isas)) < 2:
        return ""
    rows = isa_rows(runs, seeds, isas)
    return f"""
## Seed x instruction set

Each run's value: the same seed with another instruction set (torch's AVX2 kernels, `rpod`'s default
cap, or the machine's best: `RPOD_CPU_ISA=native`, stages/config/cpu.py) trains another pose model,
and everything after it differs. "largest ISA difference at one seed" beside "sd over seeds, one ISA"
(the pooled spread over seeds): a difference well inside about two standard deviations is a draw like
another seed; a larger one is a dependence on the machine.

{markdown_table([{k: v for k, v in r.items() if k != "key"} for r in rows], decimals=3)}"""


def yaml_profile(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("profile_name", "?"))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(sys.argv[1:])

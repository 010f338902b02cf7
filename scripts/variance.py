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

import hashlib
import json
import statistics
import sys
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.guidance.law import DOCKED  # noqa: E402
from pipeline.io.atomic import atomic_write_text  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from stages.pages.summary import HEADLINES as SUMMARY_HEADLINES  # noqa: E402
from stages.pages.summary import Headline, Metrics  # noqa: E402


# The headline numbers: summary.json's (stages/pages/summary.py: `dvc metrics show`: the integrity rows among
# them) and a few more that only the seed spread needs. Keys name them in reports/variance.json, which
# `rpod report` reads to show the spread beside the README's headline numbers.
def _not_docked(m: Metrics) -> float:
    """Percent of the attacked closed-loop runs (undefended) that did not dock."""
    runs = [r for r in m["guidance"]["runs"] if r.get("attacked_frames", 1) > 0]
    return 100 * sum(r["outcome"] != DOCKED for r in runs) / len(runs)


def _paper_docked(m: Metrics) -> float:
    """Percent of attacked runs docked with detect-and-recover under the paper's dynamics."""
    docked = m["guidance"]["defended"]["dynamics"]["paper"]["recover"]["docked"].values()
    return 100 * sum(k for k, _ in docked) / sum(n for _, n in docked)


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
    Headline("undefended_not_docked_pct", "closed loop, attacked runs that did not dock, undefended (%)", _not_docked),
    Headline(
        "recover_docked_pct", "closed loop, attacked runs docked, detect-and-recover, paper dynamics (%)", _paper_docked
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
    """RUN's stage metrics by file stem, without those of stages that did not run there, as a copy of the
    repository carries the committed metrics of stages it never ran: a metrics file that RUN's dvc.lock (or
    optional/dvc.lock) records counts only when the recorded stage ran with RUN's seed and wrote this very file
    (its md5; a stage without a `seed` param is judged by the md5 only); metrics that name a pose model
    (`model_hash`) count only when it is RUN's own checkpoint of that model (`model`: standard, models/pose.pt,
    when not named; robust, models/pose_robust.pt)."""
    from pipeline.io.atomic import file_hash
    from stages.artifacts.paths import CHAINS

    own = {m.value: file_hash(run / f.pose) if (run / f.pose).exists() else None for m, f in CHAINS.items()}
    locked, seed = lock_records(run), _seed(run)
    out = {}
    for path in sorted((run / "reports" / "metrics").glob("*.json")):
        record = locked.get(path.relative_to(run).as_posix())
        data = path.read_bytes()
        if record is not None and (record[0] != hashlib.md5(data).hexdigest() or record[1] not in (seed, None)):
            continue
        metrics = json.loads(data)
        if "model_hash" not in metrics or metrics["model_hash"] == own.get(metrics.get("model", "standard")):
            out[path.stem] = metrics
    return out


def lock_records(run: Path) -> dict[str, tuple[str, str | None]]:
    """Per output path that RUN's dvc.lock and optional/dvc.lock record: (its md5, the stage's `seed` param; None
    for a stage without one)."""
    import yaml

    out = {}
    for lock in (run / "dvc.lock", run / "optional" / "dvc.lock"):
        if not lock.exists():
            continue
        try:
            for stage in (yaml.safe_load(lock.read_text()) or {}).get("stages", {}).values():
                seed = (stage.get("params") or {}).get("params.yaml", {}).get("seed")
                seed = None if seed is None else str(seed)
                for o in stage.get("outs", []):
                    out[o["path"]] = (str(o.get("md5")), seed)
        except (yaml.YAMLError, AttributeError, KeyError, TypeError) as e:
            raise SystemExit(f"variance: {lock}: not a readable dvc.lock ({type(e).__name__}: {e})") from None
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

{_one_run_note(runs)}{_unmet_note(runs, seeds, isas)}{table}{_isa_section(runs, seeds, isas)}{pooled_section(runs, seeds)}"""
    spread = {
        "profile": profile,
        "seeds": seeds,
        "isas": isas,
        "numbers": {r["key"]: {k: r[k] for k in ("runs", "mean", "sd", "min", "max")} for r in rows},
    }
    atomic_write_text(ROOT / "reports" / "variance.json", json.dumps(spread, indent=1) + "\n")
    atomic_write_text(ROOT / "reports" / "variance.md", text)
    print(text)


def _one_run_note(runs: list[Path]) -> str:
    """A page of one run says it has no spread (the seed runs are still to be added)."""
    return (
        '**One run: no spread yet** (sd "-"); add the seed runs (above) before judging a change.\n\n'
        if len(runs) == 1
        else ""
    )


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


# Issue 39: each seed run flies its own trajectories (pipeline/seeds.py run_base), so the integrity campaign's
# trajectories of N runs are N times as many independent ones; chains as `rpod robustness` names them.
POOLED_CHAINS = {
    "robust": "shipped (robust model, its detector and defense)",
    "standard": "standard (the paper's reproduction, its detector and defense)",
    "control": "undefended robust control",
}


def _integrity_chains(m: Metrics) -> dict[str, Any]:
    """The run's integrity chains that carry the safety summary (issue 39's measures): a run made before them
    (no `summary`) has nothing to pool and is left out, not an error."""
    try:
        chains = m["robustness"]["integrity"]["chains"]
    except (KeyError, TypeError):
        return {}
    return {name: c for name, c in chains.items() if isinstance(c, dict) and "summary" in c}


def ratio_rows(metrics: list[Metrics], seeds: list[str]) -> list[dict[str, Any]]:
    """Per run with both chains: the shipped chain's and the control's breaking brackets, where their ratio lies
    and whether it is at least TARGET_RATIO (stages.pages.integrity.ratio_verdict)."""
    from stages.pages.integrity import TARGET_RATIO, bracket_text, breaking_bracket, ratio_verdict

    rows = []
    for s, m in zip(seeds, metrics):
        chains = _integrity_chains(m)
        if "robust" in chains and "control" in chains:
            b = {k: breaking_bracket(c["summary"]["per_eps"], c["summary"]["breaking_eps"]) for k, c in chains.items()}
            verdict, ratio = ratio_verdict(b["robust"], b["control"], TARGET_RATIO)
            rows.append(
                {
                    "run": f"seed {s}",
                    "shipped breaks in": bracket_text(b["robust"]),
                    "control breaks in": bracket_text(b["control"]),
                    "shipped / control": ratio,
                    f">= {TARGET_RATIO:g}x": verdict,
                }
            )
    return rows


def _largest_or_dash(values: list[Any]) -> Any:
    """The largest of `values` (None: a chain without a protection level), "-" when there is none."""
    present = [v for v in values if v is not None]
    return max(present) if present else "-"


def pooled_chain_rows(metrics: list[Metrics], seeds: list[str]) -> list[dict[str, Any]]:
    """Per chain: trajectories pooled over the runs, each run's breaking eps, the clean availability and false alarms
    (flagged clean frames; "-" where a run's trajectories lack the count) with a bootstrap over the pooled
    trajectories (pipeline/stats.py), the largest clean error / AL and error / PL (the PL bounds the clean error
    where this is at most 1)."""
    import numpy as np

    from pipeline.stats import bootstrap_rate
    from stages.pages.integrity import bracket_text, breaking_bracket

    rows = []
    for chain, name in POOLED_CHAINS.items():
        runs = [
            (s, _integrity_chains(m)[chain]["summary"]) for s, m in zip(seeds, metrics) if chain in _integrity_chains(m)
        ]
        if not runs:
            continue
        clean = [t for _, s in runs for t in s["clean"]["trajectories"]]
        hits = np.concatenate([np.arange(t["frames"]) < round(t["availability"] * t["frames"]) for t in clean])
        groups = np.repeat(np.arange(len(clean)), [t["frames"] for t in clean])
        avail = bootstrap_rate(hits, groups)
        flagged = [t.get("flags") for t in clean]
        alarms = (
            bootstrap_rate(np.concatenate([np.arange(t["frames"]) < t["flags"] for t in clean]), groups).pct()
            if None not in flagged
            else "-"
        )
        rows.append(
            {
                "chain": name,
                "runs": len(runs),
                "trajectories": len(clean),
                "breaking point per run (survived, broke]": ", ".join(
                    f"seed {s}: {bracket_text(breaking_bracket(b['per_eps'], b['breaking_eps']))}" for s, b in runs
                ),
                "clean availability (%)": avail.pct(),
                "clean false alarms (%)": alarms,
                "clean max error / AL": max(t["max_error_al"] for t in clean),
                "clean max error / PL": _largest_or_dash([t.get("max_error_pl") for t in clean]),
            }
        )
    return rows


def pooled_eps_rows(metrics: list[Metrics], seeds: list[str]) -> list[dict[str, Any]]:
    """Per chain and eps: the trajectories failed (error / AL > 1 on an available frame, worst over the
    attackers) of those flown, pooled over the runs that flew that eps (a chain stops after the eps it
    breaks at), with a Clopper-Pearson interval over the pooled trajectories, and the largest error / AL."""
    from pipeline.stats import clopper_pearson

    rows = []
    for chain in POOLED_CHAINS:
        per_run = [
            (s, _integrity_chains(m)[chain]["summary"]) for s, m in zip(seeds, metrics) if chain in _integrity_chains(m)
        ]
        for eps in sorted({e for _, r in per_run for e in r["per_eps"]}, key=float):
            flown = [(s, r["per_eps"][eps]) for s, r in per_run if eps in r["per_eps"]]
            failed = sum(p["failed"] for _, p in flown)
            trajectories = sum(p["trajectories"] for _, p in flown)
            stopped = [s for s, r in per_run if eps not in r["per_eps"]]
            rows.append(
                {
                    "chain": chain,
                    "eps": eps,
                    "runs flown": len(flown)
                    if not stopped
                    else f"{len(flown)} (seed {', '.join(stopped)} broke before)",
                    "trajectories failed / flown": f"{failed}/{trajectories}",
                    "failed (%)": clopper_pearson(failed, trajectories).pct(),
                    "largest error / AL": max(p["max_error_al"] for _, p in flown),
                    "largest final error (m)": max(p["final_error_max_m"] for _, p in flown),
                }
            )
    return rows


def closed_loop_rows(metrics: list[Metrics], seeds: list[str]) -> list[dict[str, Any]]:
    """Per closed-loop variant (true-state dynamics, reports/guidance.md): each run's breaking eps, and the
    attacked runs that failed their mission of those that met their attack, pooled per eps over the runs, with the
    largest error / AL of what the guidance flew on (the closed loop's safety index; "-" where no run recorded it),
    and the attacked runs that did not dock but did not fail (held, timed out: pipeline/evaluation/measures.py)."""
    from pipeline.evaluation.measures import HELD, TIMED_OUT

    have = [
        (s, m["guidance"]["closed_loop"]["variants"]["true_state"]) for s, m in zip(seeds, metrics) if "guidance" in m
    ]
    rows = []
    for variant in [k for k in have[0][1] if all(k in v for _, v in have)] if have else []:  # flown in every run
        row: dict[str, Any] = {
            "variant": variant,
            "breaking eps per run": ", ".join(f"seed {s}: {v[variant]['breaking_eps'] or 'none'}" for s, v in have),
            "no attack: largest miss (m)": max(v[variant]["clean"]["miss"] for _, v in have),
        }
        for eps in sorted({e for _, v in have for e in v[variant]["per_eps"]}, key=float):
            cells = [v[variant]["per_eps"][eps] for _, v in have if eps in v[variant]["per_eps"]]
            ratios = [c["largest_error_al"] for c in cells if c.get("largest_error_al") is not None]
            row[f"eps {eps}: failed / met, largest error / AL"] = (
                f"{sum(c['failed'] for c in cells)}/{sum(c['met'] for c in cells)}, "
                + (f"{max(ratios):.2f}" if ratios else "-")
            )
        cells = [c for _, v in have for c in v[variant]["per_eps"].values()]
        row["held / timed out"] = "/".join(
            str(sum(c.get("outcomes", {}).get(o, 0) for c in cells)) for o in (HELD, TIMED_OUT)
        )
        rows.append(row)
    columns = list(dict.fromkeys(k for row in rows for k in row))  # "-" where a variant flew no run at an eps
    return [{k: row.get(k, "-") for k in columns} for row in rows]


def pooled_section(runs: list[Path], seeds: list[str]) -> str:
    """The integrity campaign's trajectories pooled over the runs (issue 39): "" when no run has the campaign."""
    metrics = [run_metrics(r) for r in runs]
    chains = pooled_chain_rows(metrics, seeds)
    if not chains:
        return ""
    have = [s for s, m in zip(seeds, metrics) if "evaluate" in m]
    evaluation = sum(int(m["evaluate"]["trajectories"]) for m in metrics if "evaluate" in m)
    return f"""
## Independent trajectories pooled over the seed runs

Each seed run draws its own evaluation, validation and campaign trajectories (pipeline/seeds.py `run_base`),
so the runs' trajectories pool: {evaluation} evaluation trajectories of `rpod evaluate` over {len(have)} runs,
and per chain of the integrity campaign (`rpod robustness`, reports/robustness.md) the count below. Failure:
error / AL > 1 on an available frame, worst over the attackers flown (each nested in eps); the clean
availability's and false alarms' intervals are a bootstrap over the pooled trajectories (issue 39's targets: >= 99%
and <= 0.5%); clean max error / PL above 1 would be a clean frame whose error the protection level did not bound.

{markdown_table(chains, decimals=2)}
{markdown_table(pooled_eps_rows(metrics, seeds), decimals=2)}
A chain's breaking point lies between the largest eps it survived and the eps it broke at; issue 39's target asks the
shipped chain's to be at least twice the control's. What the two brackets allow, per run:

{markdown_table(ratio_rows(metrics, seeds))}
The closed loop (true-state dynamics, reports/guidance.md): mission failure = collision, lost target or a docking
miss beyond the tolerance; attacked runs that met their attack, pooled over the runs, with the largest error / AL of
what the guidance flew on (the estimate each command was computed from, against the persistent AL at the true range:
above 1 is the closed loop's HMI); "held / timed out" counts the
attacked runs that did not dock and did not fail (a hold at the end, or holds that spent the step budget on the way:
availability losses, which a denial of service would show as).

{markdown_table(closed_loop_rows(metrics, seeds), decimals=2)}"""


def yaml_profile(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text()).get("profile_name", "?"))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    main(sys.argv[1:])

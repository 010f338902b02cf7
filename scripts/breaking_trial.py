"""Issue 39: where each chain breaks, on a finer eps grid than the default campaign's.

The default campaign (`rpod robustness`) flies integrity.eps = 0.01, 0.05, 0.2: a chain's breaking eps b says it
held at every eps flown before b and failed a trajectory at b, so its breaking point lies in (the eps before b, b].
With the shipped chain and the undefended robust control both breaking at 0.2 there, whether the shipped one holds
twice the control's eps cannot be read off. This trial flies the same campaign (the run's models, trajectories,
attackers and measures; only the eps ladder differs: 0.01, 0.05, 0.07, 0.1, 0.14, 0.2, steps of about sqrt 2) in a
checkout of each seed run, and tabulates per run and chain the bracket (held at, broke at], and the range the ratio
shipped / control of the breaking points can take. The attackers are nested in eps (each eps starts from the
previous one's solution), so a finer ladder is a stronger attacker: it can break a chain at an eps where the coarse
ladder did not. Writes the section "Breaking eps on a finer grid" of reports/trials.md (results only).

Usage, per seed run S (a checkout at the run's dvc.lock, its outputs checked out: `dvc checkout`):
    rpod params default -S seed=S -S 'integrity.eps=[0.01,0.05,0.07,0.1,0.14,0.2]' && rpod robustness
then, with each run's params.yaml and reports/metrics/robustness.json copied into a folder RUN (same layout):
    python scripts/breaking_trial.py RUN [RUN ...]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.io.atomic import atomic_write_text, read_json  # noqa: E402
from pipeline.report.markdown import markdown_table, replace_section  # noqa: E402

SECTION = "Breaking eps on a finer grid"
CHAINS = {"robust": "shipped (robust model)", "control": "undefended robust control", "standard": "standard model"}


def bracket(per_eps: dict[str, Any], breaking: float | None) -> tuple[float | None, float | None]:
    """(the largest eps flown below the breaking eps, at which no trajectory failed; the breaking eps): the breaking
    point lies in (held, broke]; (largest eps flown, None) when the chain never broke."""
    flown = sorted(float(e) for e in per_eps)
    held = [e for e in flown if breaking is None or e < breaking]
    return (held[-1] if held else None), breaking


def ratio_range(shipped: tuple[float | None, float | None], control: tuple[float | None, float | None]) -> str:
    """Where shipped / control of the breaking points can lie, from their brackets (held, broke]: above held_s /
    broke_c and at most broke_s / held_c (no upper bound when the shipped chain never broke or the control broke at the
    first eps)."""
    (hs, bs), (hc, bc) = shipped, control
    if bc is None:
        return "- (the control did not break)"
    low = hs / bc if hs else 0.0
    high = f"at most {bs / hc:.2f}" if bs is not None and hc else "no upper bound"
    return f"above {low:.2f}, {high}"


def chain_rows(run: str, chains: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for key, name in CHAINS.items():
        if key not in chains:
            continue
        s = chains[key]["summary"]
        held, broke = bracket(s["per_eps"], s["breaking_eps"])
        per = sorted(s["per_eps"].items(), key=lambda kv: float(kv[0]))
        rows.append(
            {
                "run": run,
                "chain": name,
                "failed / flown per eps": ", ".join(f"{e}: {p['failed']}/{p['trajectories']}" for e, p in per),
                "held at": "-" if held is None else f"{held:g}",
                "broke at": "none in the grid" if broke is None else f"{broke:g}",
                "largest error / AL where it held": "-"
                if held is None
                else f"{s['per_eps'][_key(s['per_eps'], held)]['max_error_al']:.2f}",
            }
        )
    return rows


def _key(per_eps: dict[str, Any], eps: float) -> str:
    return next(e for e in per_eps if float(e) == eps)


def main(runs: list[str]) -> None:
    if not runs:
        raise SystemExit("usage: python scripts/breaking_trial.py RUN [RUN ...] (see the module docstring)")
    rows, ratios, ladders = [], [], set()
    for folder in runs:
        path = Path(folder) / "reports" / "metrics" / "robustness.json"
        if not path.exists():
            raise SystemExit(f"{path} not found: run `rpod robustness` there first (see the module docstring)")
        params = read_json(path)
        chains = params["integrity"]["chains"]
        run = f"seed {_seed(Path(folder))}"
        ladders.add(tuple(sorted({e for c in chains.values() for e in c["summary"]["eps_flown"]}, key=float)))
        rows += chain_rows(run, chains)
        if "robust" in chains and "control" in chains:
            b = {k: bracket(chains[k]["summary"]["per_eps"], chains[k]["summary"]["breaking_eps"]) for k in chains}
            ratios.append({"run": run, "shipped / control breaking point": ratio_range(b["robust"], b["control"])})
    body = _section(rows, ratios, sorted(ladders))
    page = ROOT / "reports" / "trials.md"
    old = page.read_text() if page.exists() else "# Trials\n"
    atomic_write_text(page, replace_section(old, SECTION, body))
    print(body)


def _seed(run: Path) -> str:
    import yaml

    return str(yaml.safe_load((run / "params.yaml").read_text())["seed"])


def _section(rows: list[dict[str, Any]], ratios: list[dict[str, Any]], ladders: list[tuple[str, ...]]) -> str:
    eps = "; ".join(", ".join(ladder) for ladder in ladders)
    return f"""`scripts/breaking_trial.py`: the default campaign of `rpod robustness` flown again on each seed run with a
finer eps ladder (eps flown: {eps}; a chain stops after the eps it breaks at), everything else as committed. A
chain breaks at the smallest eps at which an attacker fails a trajectory (error / AL > 1 on an available frame or a
docking miss); it held at the eps before, so its breaking point lies in (held at, broke at]. The attackers are nested
in eps, so this ladder is a stronger attacker than the default one.

{markdown_table(rows)}
The ratio of the shipped chain's breaking point to the control's, from the two brackets (issue 39's target: at least
2):

{markdown_table(ratios)}"""


if __name__ == "__main__":
    main(sys.argv[1:])

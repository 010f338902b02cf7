"""The defended section of reports/guidance.md (`rpod guidance`, SPEC 11): closed-loop rendezvous
success per variant (undefended, detect-and-hold, detect-and-recover) and dynamics."""
from __future__ import annotations

from typing import Any

DYNAMICS = {"paper": "paper (the chaser is placed at its estimate minus the command)",
            "true_state": "true state (the chaser moves by the command it sent)"}
VARIANTS = {"undefended": "undefended (paper)", "hold": "detect-and-hold", "recover": "detect-and-recover"}


def defended_section(d: dict[str, Any], g: dict[str, Any]) -> str:
    """Markdown: success rates with Wilson intervals per (dynamics, variant) and eps, and per S x K cell."""
    from pipeline.report import markdown_table
    from pipeline.stats import wilson

    summary, cells = [], []
    for dyn, variants in d["dynamics"].items():
        for variant, v in variants.items():
            row = {"dynamics": dyn, "variant": VARIANTS[variant],
                   "no-attack run": f"{v['baseline']['outcome']}, {v['baseline']['miss_m']:.2f} m"
                   + ("" if v["baseline"]["flags"] is None else f", {v['baseline']['flags']} flags")}
            for eps, (k, n) in v["held"].items():
                row[f"held % at eps {eps}"] = f"{wilson(k, n).pct()} ({k}/{n})"
            summary.append(row)
            for r in v["runs"]:
                cells.append({"dynamics": dyn, "variant": VARIANTS[variant], "eps": f"{r['eps']:g}",
                              "S (m)": f"{r['start_range']:g}", "K": r["length"],
                              "outcome": r["outcome"], "miss (m)": r["miss_m"], "steps": r["steps"],
                              "flags": "-" if r["flags"] is None else r["flags"],
                              "hold steps": "-" if r["hold_steps"] is None else r["hold_steps"]})
    return f"""
## The chain inside the loop: undefended, detect-and-hold, detect-and-recover

Every cell of the grid above flown again with the whole safety chain (pose, SHAP, detector) and the
calibrated defense of pipeline/defense.py inside the loop, one fresh defense per run, for each
dynamics: {'; '.join(DYNAMICS[k] for k in d['dynamics'])}. Undefended: guidance acts on every
estimate (the paper; under the table's dynamics these are the runs above). Detect-and-hold: a
flagged frame's estimate is not used and the chaser sends no command for that step.
Detect-and-recover: guidance acts on the defense's trusted estimate (the motion filter's state, its
prediction on flagged frames) and holds position after `defense.hold_after` consecutive flags until
clean frames return. Horizon: undefended runs last the no-attack arrival + {g['slack_steps']} steps
as above; a defended run lasts its own no-attack run's arrival + {g['slack_steps']} + K steps, since
holding on a flag costs a step per flagged frame: a defended chaser that arrives late by at most the
attack's length counts as held, one diverted or still short after that counts as lost. Success
rates carry 95% Wilson intervals over the runs of the grid (few runs: wide intervals).

{markdown_table(summary)}
![one run per variant](figures/guidance_defended.png)

Every run:

{markdown_table(cells, decimals=2)}"""

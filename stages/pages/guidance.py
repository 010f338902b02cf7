"""reports/guidance.md, the page of `rpod guidance`: first where the shipped chain's runs dock (the breaking point
per dynamics and variant, the docking-miss table, the docking targets, the assumptions); then one S x K table
per eps (the paper's grid, on the standard model); its defended section (the chain that ships, on the robust
model): closed-loop rendezvous success per variant (undefended, detect-and-hold, detect-and-recover) and dynamics;
the in-loop attacker."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from pipeline.guidance.law import DOCKED, LOST, MISSED, SUCCEEDED
from stages.config.evaluation import Integrity
from stages.config.schema import Params
from stages.config.sections import Guidance, Render

DYNAMICS = {
    "paper": "paper (the chaser is placed at its estimate minus the command: prediction = truth by "
    "construction, the paper's reproduction, no integrity evidence)",
    "true_state": "true state (the chaser moves by the command it sent, executed with the thrusters' error "
    "and Clohessy-Wiltshire motion)",
}
TARGET_EPS = 0.05  # issue 39: the shipped chain docks within the tolerance under every attack up to this eps
VARIANTS = {  # pipeline.guidance.grid.variant_key -> words: the shipped chain's variants, then the standard chain's
    "undefended": "undefended",
    "hold": "detect-and-hold",
    "recover": "detect-and-recover",
    "standard hold": "standard chain, detect-and-hold",
    "standard recover": "standard chain, detect-and-recover",
}


def defended_section(d: dict[str, Any], g: Guidance) -> str:
    """Markdown: success rates with Wilson intervals per (dynamics, variant) and eps, and per S x K cell."""
    from pipeline.report.markdown import markdown_table

    summary, cells = [], []
    for dyn, variants in d["dynamics"].items():
        for variant, v in variants.items():
            summary.append(_defended_row(dyn, variant, v))
            for r in v["runs"]:
                cells.append(_defended_run(dyn, variant, r))
    return f"""
## The chain inside the loop: undefended, detect-and-hold, detect-and-recover

Every cell of the grid above flown again with the chain that ships: the **robust model**
(models/pose_robust.pt; FGSM now crafted on it), its own detector (models/detector_robust.pt) and the
defense calibrated for it (models/defense.json, pipeline/defense/fusion.py) inside the loop, one fresh
defense per run, for each dynamics: {"; ".join(DYNAMICS[k] for k in d["dynamics"])}. Undefended: guidance
acts on every estimate of the robust model (as the paper's grid above does on the standard model's).
Detect-and-hold: a
flagged frame's estimate is not used and the chaser sends no command for that step.
Detect-and-recover: guidance acts on the defense's trusted estimate (the motion filter's state, its
prediction on flagged frames) and holds position after `defense.hold_after` consecutive flags until
clean frames return. Horizon: undefended runs last the no-attack arrival + {g.slack_steps} steps
as above; a defended run lasts its own no-attack run's arrival + {g.slack_steps} + K steps, since
holding on a flag costs a step per flagged frame: a defended chaser that arrives late by at most the
attack's length counts as docked, one diverted or still short after that does not. "Docked" is the paper's
success (within the docking tolerance when the run ends; "rendezvous held" in our earlier reports), not the defense's
hold: a run that holds far from the goal (a safe abort) is not docked. Rates count only the runs that met the
attack (a run that never reached S was not attacked: "not met") and carry 95% Wilson intervals over them (few
runs: wide intervals). Only what the attack caused counts against a chain: the attack kept a run from docking
when its own no-attack run docked, or when it ended more than the docking tolerance further from the target point
than that run; otherwise it reads "missed, as without attack". This is availability under attack (a safe abort
counts as much as a collision); whether a run failed its mission (unsafe) is the docking table's outcome at the
top of this page.

{markdown_table(summary)}{_clean_flags_text(d, g)}
![one attacked cell per variant: distance from the approach axis and to the target point](figures/guidance_defended.png)

Every run:

{markdown_table(cells, decimals=2)}"""


def _defended_row(dyn: str, variant: str, v: dict[str, Any]) -> dict[str, Any]:
    """A row of the defended summary: the no-attack run (miss in m) and per eps the runs docked (%, Wilson) and
    those the attack kept from docking."""
    from pipeline.stats import wilson

    row = {
        "dynamics": dyn,
        "variant": VARIANTS[variant],
        "no-attack run": f"{v['baseline']['outcome']}, {v['baseline']['miss_m']:.2f} m"
        + ("" if v["baseline"]["flags"] is None else f", {v['baseline']['flags']} flags"),
    }
    for eps, (k, n) in v["docked"].items():
        unmet = v.get("not_met", {}).get(eps, 0)
        denied = v.get("denied", {}).get(eps)
        row[f"docked % at eps {eps}"] = (
            f"{wilson(k, n).pct()} ({k}/{n})"
            + (
                ""
                if denied is None
                else f", kept from docking by the attack {wilson(*denied).pct()} ({denied[0]}/{denied[1]})"
            )
            + (f", {unmet} not met" if unmet else "")
        )
    return row


def _defended_run(dyn: str, variant: str, r: dict[str, Any]) -> dict[str, Any]:
    """A row of the defended runs' table: the cell (S in m, K), its outcome, miss (m), steps, flags and holds."""
    return {
        "dynamics": dyn,
        "variant": VARIANTS[variant],
        "eps": f"{r['eps']:g}",
        "S (m)": f"{r['start_range']:g}",
        "K": r["length"],
        "outcome": (
            "missed, as without attack"
            if r["outcome"] == SUCCEEDED and not r.get("attack_denied", True)
            else r["outcome"]
        ),
        "miss (m)": r["miss_m"],
        "steps": r["steps"],
        "flags": "-" if r["flags"] is None else r["flags"],
        "hold steps": "-" if r["hold_steps"] is None else r["hold_steps"],
    }


def _clean_flags_text(d: dict[str, Any], g: Guidance) -> str:
    """Why the defended no-attack runs of the paper dynamics raise flags (empty when they raise none)."""
    paper, other = d["dynamics"].get("paper"), d["dynamics"].get("true_state")
    flags = {k: v["baseline"]["flags"] for k, v in (paper or {}).items() if v["baseline"]["flags"]}
    if not flags:
        return ""
    arrival = paper.get("undefended", {}).get("baseline", {}).get("arrival_step")
    distance = float(np.linalg.norm(np.subtract(g.start, g.target)))
    pace = (
        ""
        if not arrival
        else f" (the undefended run arrives after {arrival} steps, not "
        f"{distance / g.max_step:.0f}: about {distance / arrival - g.max_step:.2f} m of range more per step than commanded)"
    )
    beside = (
        ""
        if other is None
        else " (true_state: "
        + ", ".join(
            f"{v['baseline']['flags']} with {VARIANTS[k]}"
            for k, v in other.items()
            if v["baseline"]["flags"] is not None
        )
        + ")"
    )
    return (
        f"\nFlags without an attack: in the paper dynamics the chaser lands where it believes it goes, so the "
        f"motion filter's prediction is the true state whatever its estimate was. A steady error of the pose model "
        f"on these views{pace}, which under true-state dynamics the filter carries in its state, here reaches the "
        f"innovations whole, and the sequential test flags it: "
        + ", ".join(f"{n} flags with {VARIANTS[k]}" for k, n in flags.items())
        + f" in the no-attack runs{beside}. "
        f"A flag there costs the frame's update (detect-and-recover flies on the prediction, which is exact) or a "
        f"step (detect-and-hold waits), not the approach.\n"
    )


def _horizon_text(m: dict[str, Any]) -> str:
    arrival = m["baseline"]["arrival_step"]
    if arrival is None:
        return f"Every run lasts {m['horizon']} steps (guidance.max_steps; the no-attack baseline did not arrive)."
    return (
        f"The no-attack baseline arrived after {arrival} steps (the nominal approach takes 50; in the paper "
        f"variant a bias of the estimate along the range changes how far the chaser moves per step), so every attacked run lasts {m['horizon']} steps: "
        f"that arrival plus guidance.slack_steps = {m['slack_steps']}, at most guidance.max_steps = {m['max_steps']}. "
        "An attack succeeds when the chaser is not at the target point by then."
    )


def _cell(r: dict[str, Any]) -> str:
    text = {
        DOCKED: DOCKED,
        SUCCEEDED: f"**{SUCCEEDED}**",
        LOST: f"**{LOST}** (step {r['steps']})",
        MISSED: "missed",
    }[r["outcome"]]
    frames = "" if r["attacked_frames"] == r["length"] else f", {r['attacked_frames']} attacked frames"
    return f"{text}, {r['miss_m']:.2f} m{frames}"


def guidance_page(m: dict[str, Any], g: Guidance, render: Render) -> str:
    """reports/guidance.md without the defended section: one S x K table per eps, from the metrics."""
    tables = _grid_tables(m, g)
    law = (
        "the next true position is computed from the estimate, `p_new = p_est - clip(p_est - p_tar, -1, 1)` "
        "(the paper's variant: the chaser ends up where it believes it goes, so one wrong estimate moves the true "
        "chaser by as much as the estimate is wrong, and any estimate within 1 m per axis of the target point puts "
        "it exactly there; `guidance.variant: true_state` applies the command to the true state instead)"
        if m["variant"] == "paper"
        else "the command `clip(p_est - p_tar, -1, 1)` is computed from the estimate and applied to the true state"
    )
    start, goal = (", ".join(f"{float(v):g}" for v in vs) for vs in (g.start, g.target))
    baseline = f"**No-attack baseline: {m['baseline']['outcome']}, final miss {m['baseline']['miss_m']:.2f} m.**"
    if m["baseline"]["outcome"] != DOCKED:
        baseline += (
            " The pose model cannot guide the chaser even without an attack, so a miss in the tables "
            "below cannot be blamed on the attack."
        )
    return f"""## The paper's grid: closed-loop rendezvous under attack

The paper's grid (the tables below) flies the **standard model** (models/pose.pt, the paper's reproduction)
undefended; the sections "The chain inside the loop" and "The in-loop attacker" fly the chain that ships,
the **robust model** with its own detector and defense.

The chaser starts at ({start}) m (the target's position relative to the chaser, target-centred frame,
approach along +z) and steers to ({goal}) m with at most {g.max_step:g} m per axis per step: {law}.
Every step renders a new {render.width}x{render.height} Blender image (the pose model's input size)
at the true pose, the pose CNN estimates the target position, and the chaser re-points its camera
at where it believes the target is. {_horizon_text(m)} A run succeeds for
the chaser when it ends within {m["tolerance"]:g} m of the target point; "target lost" means the
target's centre left the image, which ends the run. The attack ({m["method"]} on the {m["loss"]}
loss, images quantised to 8 bits as in `rpod attack`) starts at the first step at range <= S and
lasts K frames (fewer when the run ends first; the cell then says how many).

{baseline}

Cells: outcome, final distance to the target point.

{chr(10).join(tables)}
{m["renders"]} rendered frames for {m["steps"]} guidance steps (runs share the baseline's frames until
their attack starts), {m["attacked"]} attacked frames (time: reports/metrics/guidance.json).

![true range and estimate error per step, no attack and each (S, K)](figures/guidance_trajectories.png)

The full paper grid (eps 0.5, 0.3, 0.1, 0.05, 0.01; S = 60..10 m; K = 5..20) runs with
`dvc exp run -S profile=paper` (everything at paper scale) or, on the current model,
`dvc exp run -S 'guidance.eps=[0.5,0.3,0.1,0.05,0.01]' -S 'guidance.start_ranges=[60,50,40,30,20,10]' -S 'guidance.lengths=[5,10,15,20]'`.
"""


def _grid_tables(m: dict[str, Any], g: Guidance) -> list[str]:
    """Per eps of the paper's grid: a heading with the share of runs the attack made miss, and its S x K table
    (S in m)."""
    from pipeline.report.markdown import markdown_table

    tables = []
    for eps in dict.fromkeys(r["eps"] for r in m["runs"]):
        rows = []
        for s in g.start_ranges:
            row = {"S (m)": f"{float(s):g}"}
            for r in m["runs"]:
                if r["eps"] == eps and r["start_range"] == float(s):
                    row[f"K = {r['length']}"] = _cell(r)
            rows.append(row)
        rate = m["attack_success_rate"][f"{eps:g}"]
        share = (
            "no run met the attack"
            if rate is None or rate != rate
            else f"the chaser missed or lost the target in {rate:.0%} of the runs that met the attack"
        )
        tables.append(f"### eps = {eps:g}: {share}\n\n{markdown_table(rows)}")
    return tables


def in_loop_section(d: dict[str, Any], i: Integrity) -> str:
    """Markdown: the in-loop attacker's collisions, runs not docked and docked per (dynamics, variant, eps), and every run."""
    from pipeline.report.markdown import markdown_table

    summary = _in_loop_summary(d)
    runs = [
        {
            "dynamics": r["dynamics"],
            "variant": VARIANTS[r["defense"]],
            "eps": f"{r['eps']:g}",
            "goal": r["goal"],
            "S (m)": f"{r['start_range']:g}",
            "outcome": ("**collision**, " if r["collided"] else "") + r["outcome"],
            "closest range (m)": r["closest_range_m"],
            "miss (m)": r["miss_m"],
            "steps": r["steps"],
            "attacked": r["attacked_frames"],
            "flags": "-" if r["flags"] is None else r["flags"],
            "hold steps": "-" if r["hold_steps"] is None else r["hold_steps"],
        }
        for r in d["runs"]
    ]
    return f"""

## The in-loop attacker: collision course, miss and capture

On the chain that ships (robust model, its detector and defense) and, as the comparison, on the standard chain (the
paper's model with its own detector and calibrated defense, models/defense_standard.json: "standard chain" rows).
Goals "collide" and "miss": every frame from the
first step at range <= S (S in {", ".join(f"{s:g}" for s in i.in_loop_start_ranges)} m) to the end of the run is
crafted by an attacker who knows the chain (pose network and detector), the defense with its state, the guidance law
and where the chaser truly is (pipeline/attackers/in_loop.py): it looks one step ahead over estimates pushed along
and across the line of sight (as far as keeps the innovation under {i.drift_gate_fraction:g} of the motion gate once
the filter runs), keeps the one whose step brings the chaser nearest the target ("collide") or farthest from the
docking point ("miss"). Goal "capture" (pipeline/attackers/capture.py): a bias of
{i.capture_initial[0]:g} m across the line of sight from the first frame (acquisition, S = the start range), held
to the end under the same stealth bound. Each frame by targeted L-inf PGD ({i.in_loop_steps} steps, the detector's
margin in the objective) at eps {", ".join(f"{e:g}" for e in sorted(i.in_loop_eps))}, stored as 8 bits. Greedy: a
course that needs a detour is not found. A **collision** is a true range below `integrity.collision_range_m` = {d["collision_range_m"]:g} m anywhere on the path; **not
docked** a run that ends outside the tolerance (a safe abort included) or loses the target without a collision;
**docked** a run that ends within it. Horizon: the variant's no-attack arrival + `guidance.slack_steps`, plus as
many again for the defended variants (a chaser that holds on flags arrives late). Only the runs that
met the attack count; rates over goals and start ranges with 95% Wilson intervals (few runs: wide).

{markdown_table(summary)}
Every in-loop run:

{markdown_table(runs, decimals=2)}"""


def _in_loop_summary(d: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows per (dynamics, variant, eps) of the in-loop runs: collisions, runs not docked and docked (%, Wilson)."""
    from pipeline.stats import wilson

    summary = []
    for dyn, variants in d["counts"].items():
        for variant in [v for v in VARIANTS if v in variants]:
            for eps, (col, lost, docked, met, unmet) in sorted(variants[variant].items(), key=lambda kv: float(kv[0])):
                summary.append(
                    {
                        "dynamics": dyn,
                        "variant": VARIANTS[variant],
                        "eps": eps,
                        "runs met": met,
                        "collisions (%)": f"{wilson(col, met).pct()} ({col}/{met})",
                        "not docked, no collision (%)": f"{wilson(lost, met).pct()} ({lost}/{met})",
                        "docked (%)": f"{wilson(docked, met).pct()} ({docked}/{met})",
                        "not met": unmet,
                    }
                )
    return summary


def _break(x: float | None) -> str:
    return "none in the grid" if x is None else ("fails without attack" if x == 0 else f"{x:g}")


def docking_targets(d: dict[str, Any]) -> list[tuple[str, str, str]]:
    """The docking targets on the closed loop's true-state runs (`d`: guidance.json's closed_loop): (target,
    "met" / "**missed**" / "not shown", evidence); none without true-state runs."""
    ts = d["variants"].get("true_state", {})
    if not ts:
        return []
    und = ts.get("undefended", {}).get("breaking_eps")
    falsifiable = und is not None and und > 0  # failing without attack shows nothing about the attacks
    small = [x for k, x in ts.get("recover", {}).get("per_eps", {}).items() if float(k) <= TARGET_EPS]
    failed = sum(x["failed"] for x in small)
    clean_ok = ts.get("recover", {}).get("clean", {}) or {}
    return [
        (
            "falsifiable: the undefended chain fails its mission at some eps",
            "met" if falsifiable else "not shown" if und == 0 else "**missed**",
            f"undefended breaking eps {_break(und)}",
        ),
        (
            f"detect-and-recover, every attack up to eps {TARGET_EPS:g}: docking miss <= tolerance",
            "met" if small and not failed and clean_ok.get("outcome") == DOCKED else "**missed**",
            f"no-attack run {clean_ok.get('outcome', '-')} ({clean_ok.get('miss', float('nan')):.2f} m"
            f"{hold_why(clean_ok.get('final_hold'))}); {failed} failed of {sum(x['met'] for x in small)} attacked runs up to eps {TARGET_EPS:g}",
        ),
        _ratio_target(ts),
        *_index_targets(ts.get("recover", {}), small),
    ]


def _index_targets(rec: dict[str, Any], small: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """The safety index's targets on detect-and-recover (its record `rec`, its attacked cells `small` up to
    TARGET_EPS): no attacked run's flown estimate above AL, and the no-attack run's flown estimate within its PL (the
    closed-loop analogue of reports/robustness.md's clean row); none where the runs did not record the index."""
    clean = rec.get("clean") or {}
    ratios = [x["largest_error_al"] for x in small if x.get("largest_error_al") is not None]
    out = []
    if ratios:
        out.append(
            (
                f"detect-and-recover, every attack up to eps {TARGET_EPS:g}: max error / AL < 1 on what the guidance "
                "flew on",
                "met" if max(ratios) < 1 else "**missed**",
                f"largest error / AL {max(ratios):.2f}",
            )
        )
    if clean.get("max_error_pl") is not None:
        out.append(
            (
                "detect-and-recover without attack: the PL bounds what the guidance flew on (max error / PL <= 1)",
                "met" if clean["max_error_pl"] <= 1 else "**missed**",
                f"largest error / PL {clean['max_error_pl']:.2f}",
            )
        )
    return out


def hold_why(hold: dict[str, Any] | None) -> str:
    """Why a run's last hold began, from its `final_hold` record (pipeline/evaluation/closed_loop.py): "; held from
    frame N, R m out: PL > AL (parts), PL at the end", or "" where there is no record or no PL (a hold on a flag)."""
    if not hold or hold.get("pl_m") is None or hold.get("al_m") is None:
        return ""
    return (
        f"; held from frame {hold['frame']}, {hold['true_range_m']:.2f} m out: PL {hold['pl_m']:.2f} m (noise "
        f"{hold['noise_m']:.2f}, slow ramp {hold['ramp_m']:.2f}, transients {hold['transients_m']:.2f}"
        + (f", offset {hold['offset_m']:.2f}" if hold.get("offset_m") else "")
        + f") > AL "
        f"{hold['al_m']:.2f} m; {hold['frames_held']} frames later, at the end, PL {hold['pl_end_m']:.2f} m"
    )


def _ratio_target(ts: dict[str, Any]) -> tuple[str, str, str]:
    """Detect-and-recover's breaking point against twice the undefended chain's, from their brackets (survived, broke]
    (stages.pages.integrity.ratio_verdict); not shown when the undefended chain never broke or fails unattacked."""
    from stages.pages.integrity import bracket_text, breaking_bracket, ratio_verdict

    rec, und = (
        breaking_bracket(ts.get(k, {}).get("per_eps", {}), ts.get(k, {}).get("breaking_eps"))
        for k in ("recover", "undefended")
    )
    verdict, ratio = ratio_verdict(rec, und, 2.0)
    if und[1] == 0:
        verdict, ratio = "not shown", "the undefended chain fails without attack"
    return (
        "detect-and-recover breaking eps >= 2 x the undefended chain's",
        verdict,
        f"recover {bracket_text(rec)}, undefended {bracket_text(und)}: {ratio}",
    )


def closed_loop_section(d: dict[str, Any], p: Params) -> str:
    """Markdown the page leads with: the breaking point per dynamics and variant, the docking targets, the
    docking-miss table (true-state dynamics first), and what the runs assume."""
    v = d["variants"]
    order = [k for k in ("true_state", "paper") if k in v]
    breaks = "; ".join(f"{VARIANTS[k]} {_break(x['breaking_eps'])}" for k, x in v.get("true_state", {}).items())
    lines = docking_targets(d)
    missed = [t for t in lines if t[1] != "met"]
    head = (
        f"**Breaking point in the closed loop (true-state dynamics; smallest eps at which an attacked run failed "
        f"its mission): {breaks or 'no true-state runs'}.** "
        + (
            f"Targets not met: {'; '.join(f'{t} ({w}: {e})' for t, w, e in missed)}."
            if missed
            else "Every docking target is met in this grid."
        )
    )
    rows = _per_variant(v, order, _docking_cells)
    index = _per_variant(v, order, _safety_cells)
    runs = [
        {
            "dynamics": r["dynamics"],
            "variant": VARIANTS[r["defense"]],
            "attack": r["attack"],
            "eps": "-" if r["eps"] is None else f"{r['eps']:g}",
            "outcome": ("**" + r["outcome"] + "**") if r["failed"] else r["outcome"],
            "range miss (m)": r["range_miss"],
            "lateral miss (m)": r["lateral_miss"],
            "closest range (m)": r["closest_range"],
            "hold steps": r["hold_steps"],
        }
        for r in d["runs"]
        if r["dynamics"] == "true_state" and r["met"]
    ]
    return _closed_loop_text(d, p, head, lines, rows, runs, index)


def _per_variant(v: dict[str, Any], order: list[str], cells: Callable[[dict[str, Any]], dict[str, Any]]) -> list[Any]:
    """One row per dynamics (in `order`) and variant of the closed loop's `v`: its names, then `cells` of its record;
    every row with every column, "-" where a variant has none (no attacked run at that eps)."""
    rows = [
        {"dynamics": dyn, "variant": VARIANTS[variant], **cells(x)} for dyn in order for variant, x in v[dyn].items()
    ]
    columns = list(dict.fromkeys(k for row in rows for k in row))
    return [{k: row.get(k, "-") for k in columns} for row in rows]


def _docking_cells(x: dict[str, Any]) -> dict[str, Any]:
    """A variant's docking row: breaking eps, the no-attack outcome and miss (m), and per eps the failed and met runs
    and the largest miss (m); the attacked runs that did not dock but did not fail (held, timed out)."""
    from pipeline.evaluation.measures import HELD, TIMED_OUT

    c = x["clean"] or {}
    row = {
        "breaking eps": _break(x["breaking_eps"]),
        "no attack: outcome, miss (m)": f"{c.get('outcome', '-')}, {c.get('miss', float('nan')):.2f}",
    }
    for eps, k in x["per_eps"].items():
        row[f"eps {eps}: failed / met, largest miss (m)"] = f"{k['failed']}/{k['met']}, {k['largest_miss_m']:.2f}"
    row["held / timed out"] = "/".join(
        str(sum(k["outcomes"].get(o, 0) for k in x["per_eps"].values())) for o in (HELD, TIMED_OUT)
    )
    return row


def _safety_cells(x: dict[str, Any]) -> dict[str, Any]:
    """A variant's safety index row: what the guidance flew on, largest error / AL / largest error / PL, without
    attack and per eps over the attacked runs that met the attack ("-" where none counts)."""

    def pair(al: float | None, pl: float | None) -> str:
        return " / ".join("-" if y is None else f"{y:.2f}" for y in (al, pl))

    c = x["clean"] or {}
    row = {"no attack": pair(c.get("max_error_al"), c.get("max_error_pl"))}
    for eps, k in x["per_eps"].items():
        row[f"eps {eps}"] = pair(k.get("largest_error_al"), k.get("largest_error_pl"))
    return row


def _standard_text(d: dict[str, Any]) -> str:
    """The clause on the standard chain's runs, where the closed loop flew any ("" otherwise)."""
    flown = sorted({r["defense"] for r in d["runs"] if r.get("chain") == "standard"})
    return (
        ""
        if not flown
        else " but those of the standard chain (the standard model, its detector and its defense,\n"
        "models/defense_standard.json), which flies its no-attack run and the in-loop attackers as the comparison ("
        + ", ".join(VARIANTS[k] for k in flown)
        + ")"
    )


def _closed_loop_text(
    d: dict[str, Any],
    p: Params,
    head: str,
    lines: list[tuple[str, str, str]],
    rows: list[dict[str, Any]],
    runs: list[dict[str, Any]],
    index: list[dict[str, Any]],
) -> str:
    """The closed-loop section's text around its lead `head`: the docking targets `lines`, the assumptions, the
    docking table `rows`, the safety index table `index` and the attacked true-state `runs` (misses in m)."""
    from pipeline.report.markdown import markdown_table
    from stages.pages.integrity import attacker_names, process_noise

    x, standard = p.guidance.execution, _standard_text(d)
    return f"""# Closed-loop rendezvous: where the shipped chain docks

{head}

{markdown_table([{"target": t, "verdict": w, "evidence": e} for t, w, e in lines]) if lines else ""}
Assumptions: the shipped chain (robust model, its detector and its defense, models/defense.json) flies every run{
        standard
    }.
True-state dynamics: the chaser moves by the command it sent, executed with the thrusters' error
({100 * x.scale_std:g}% of the step and {100 * x.noise_std:g} cm per axis, 1-sigma per step; seeded, the same draws
in every run) and Clohessy-Wiltshire motion over {x.frame_interval:g} s per step (mean motion {x.mean_motion:g} rad/s,
{x.approach}); the defense is told the commands only (process noise per step, std per axis,
{process_noise(p.defense.position_noise, p.defense.position_noise_scale)}).
Detect-and-recover flies on the trusted estimate where it is available (PL <= AL, the
{p.integrity.alert_limit_kind.replace("_", "-")} AL at the trusted estimate's range) and holds elsewhere; the protection
level assumes no fault on the {p.defense.trusted_start} frames after the filter's first start and claims none on
them once the detector has flagged a frame of the run (the chaser holds until they are past). Mission failure: a
collision (true range below {d["collision_range_m"]:g} m), a lost target, or a miss beyond {d["tolerance_m"]:g} m
(docked in the wrong place); a run that ends held far from the goal is a safe abort, and one that timed out did not
dock either (its steps ran out with the chaser short of the goal on its line of sight, not arrived by its own
estimate, and its holds at least the rest of the approach at {p.guidance.max_step:g} m per step: the defense's holds
spent the step budget; the undefended chain never holds, so it cannot time out): both are availability losses,
not failures, counted in the column "held / timed out". The paper dynamics rows are the paper's reproduction (prediction = truth by construction) and no part of
the breaking point's headline. The in-loop attackers: {", ".join(attacker_names(g) for g in p.integrity.in_loop_goals)}
at eps {", ".join(f"{e:g}" for e in p.integrity.in_loop_eps)}; the grid's FGSM at eps {
        ", ".join(f"{e:g}" for e in p.guidance.eps)
    }.

Docking per dynamics and variant (only the attacked runs that met the attack count):

{markdown_table(rows)}
Safety index per dynamics and variant: what the guidance flew on (the estimate each command was computed from; a
held frame flies on nothing) judged as reports/robustness.md judges a trajectory, the largest error / AL (AL: the
{p.integrity.alert_limit_kind.replace("_", "-")} AL at the frame's true range; above 1 is the closed loop's HMI)
/ the largest error / PL (detect-and-recover only, which flies on the trusted estimate the PL bounds; detect-and-hold
flies on the raw estimate), without attack and over the attacked runs that met the attack at each eps:

{markdown_table(index)}
Every attacked true-state run that met its attack, where it ended (range miss: along the goal's line of sight,
positive short of the goal):

{markdown_table(runs, decimals=2)}
"""

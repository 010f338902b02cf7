"""The Integrity section of reports/robustness.md (`rpod robustness`): the trusted estimate the guidance flies
on, against the chain-level attackers, beside the same frames without the attack; and the words for
the in-loop attacker's table of reports/guidance.md."""
from __future__ import annotations

from typing import Any

from stages.config.schema import Params

TARGET_HMI = 0.01   # issue 27's target: the upper 95% bound of the attack's HMI at most 1%
NAMES = {"burst": "burst (nested)", "drift/los": "drift along the line of sight", "drift/lateral": "drift across it"}


def _pct(r: dict[str, Any] | None) -> str:
    """A rate of the metrics JSON ({"value", "ci", "n"}) in percent with its interval, or "-"."""
    from pipeline.stats import percent_ci

    return "-" if not r or not r.get("n") else percent_ci(r["value"], r["ci"], 1)


def _m(x: float) -> str:
    return "-" if x != x else f"{x:.2f}"


def integrity_table(rows: list[dict[str, Any]], with_mi: bool) -> str:
    """Per attacker and eps: what the attack caused beside the same frames unattacked."""
    from pipeline.report.markdown import markdown_table

    out = []
    for r in rows:
        cells = {"attacker": NAMES.get(r["attacker"], r["attacker"]), "eps": f"{r['eps']:g}", "frames": r["frames"],
                 "HMI caused (%)": _pct(r["hmi"]), "HMI without attack (%)": _pct(r["hmi_clean"])}
        if with_mi:
            cells["MI caused (%)"] = _pct(r["mi"])
        cells |= {"attacked frames flagged (%)": _pct(r["detected"]),
                  "same frames flagged without attack (%)": _pct(r["detected_clean"]),
                  "availability (%)": _pct(r["availability"]), "availability without attack (%)": _pct(r["availability_clean"]),
                  "trusted error mean / max (m)": f"{_m(r['trusted_error_mean_m'])} / {_m(r['trusted_error_max_m'])}",
                  "without attack (m)": f"{_m(r['clean_error_mean_m'])} / {_m(r['clean_error_max_m'])}"}
        out.append(cells)
    return markdown_table(out)


def worst_hmi(integrity: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per eps ("%g"): the attacker whose caused HMI is highest, with its rate ({"value", "ci", "n"}); attackers
    that tie are named together ("burst = drift/los"), the widest interval kept."""
    out: dict[str, dict[str, Any]] = {}
    for r in integrity["rows"]:
        key, value = f"{r['eps']:g}", r["hmi"]["value"]
        if value is None:
            continue
        w = out.get(key)
        if w is None or value > w["hmi"]["value"]:
            out[key] = {"attacker": r["attacker"], "hmi": r["hmi"]}
        elif value == w["hmi"]["value"]:
            wider = r["hmi"]["ci"][1] - r["hmi"]["ci"][0] > w["hmi"]["ci"][1] - w["hmi"]["ci"][0]
            out[key] = {"attacker": f"{w['attacker']} = {r['attacker']}", "hmi": r["hmi"] if wider else w["hmi"]}
    return out


def attacker_names(attacker: str) -> str:
    """`worst_hmi`'s attacker (names joined by " = ") in words."""
    return " = ".join(NAMES.get(a, a) for a in attacker.split(" = "))


def _al_text(integrity: dict[str, Any], p: Params) -> str:
    from pipeline.defense.integrity import AlertLimitSettings, alert_limit

    if integrity.get("alert_limit_m") is not None:
        return f"a fixed alert limit AL = {integrity['alert_limit_m']:g} m (`integrity.alert_limit_m`)"
    g = p.guidance
    s = AlertLimitSettings(float(g.tolerance), float(g.max_step), g.slack_steps, float(integrity["collision_range_m"]))
    at = ", ".join(f"{alert_limit(r, s):g} m at {r:g} m" for r in (60.0, 15.0, 10.0))
    return (f"the alert limit AL(range) = max(tol, min(tol + slack x step, range + step - collision range)), the largest "
            f"single-frame error the guidance law and the docking tolerance absorb (derived in "
            f"`pipeline/evaluation/integrity.py` from `guidance.tolerance`, `max_step`, `slack_steps` and "
            f"`integrity.collision_range_m` = {integrity['collision_range_m']:g} m): {at}")


def _verdict(worst: dict[str, dict[str, Any]]) -> str:
    lines = []
    for e, w in sorted(worst.items(), key=lambda kv: float(kv[0])):
        value, hi = w["hmi"]["value"], w["hmi"]["ci"][1]
        verdict = ("met" if hi is not None and hi <= TARGET_HMI else "**not met**" if value > TARGET_HMI else
                   "**not shown** (the interval reaches above it at this sample size)")
        lines.append(f"- eps {e}: {_pct(w['hmi'])}% ({attacker_names(w['attacker'])}); the target (upper "
                     f"bound <= {100 * TARGET_HMI:g}%) is {verdict}")
    return "\n".join(lines)


def _bursts(integrity: dict[str, Any]) -> str:
    """A line: bursts whose worst case has an HMI frame, per eps (the nested attacker's own count)."""
    from pipeline.stats import wilson

    counts = [(r["eps"], r["bursts_with_hmi"]) for r in integrity["rows"] if "bursts_with_hmi" in r]
    if not counts:
        return ""
    return ("\nBursts whose worst case holds at least one HMI frame (the burst attacker's own count, on the real "
            "chain and defense): " + "; ".join(f"eps {e:g}: {wilson(k, n).pct()}% ({k}/{n})" for e, (k, n) in counts)
            + ".\n")


def integrity_section(integrity: dict[str, Any], fused: dict[str, Any], p: Params) -> str:
    """Markdown: the Integrity section (definitions, attackers, clean line, table, worst case, figure)."""
    c, b, d = integrity["clean"], integrity["burst"], integrity["drift"]
    with_mi = bool(c.get("has_pl"))
    bound = "PL" if with_mi else "AL"
    return f"""## Integrity of the shipped chain (robust model): is the trusted estimate safe to fly on?

Guidance flies on the defense's **trusted estimate** (the motion filter's state; its prediction on
flagged frames), not on the raw CNN estimate, so this section judges that estimate, with the
vocabulary of satellite-navigation integrity monitoring. Per frame: the trusted estimate's error
against the truth (m) and {_al_text(integrity, p)}. A frame is **available** when the guidance flies on
it (defense mode track or coast{', and PL <= AL' if with_mi else ''}); **HMI** (hazardously misleading
information) = available and error > AL{'; **MI** = error > PL' if with_mi else ''}. Each attacked trajectory is
compared frame by frame with the same trajectory unattacked: "HMI caused" counts only the frames
that are HMI with the attack and not without it. Counted frames: from a trajectory's first attacked
frame to its end (every frame the attack can reach); flagged: over the attacked frames. Rates are
percent with 95% percentile-bootstrap intervals over the {c['trajectories']} eval_render trajectories; where the
bootstrap has no spread (no hit on any trajectory, or hits on every frame), the Wilson interval of the
{c['trajectories']} trajectories as trials instead: all that {c['trajectories']} trajectories without a hit can bound.

The attackers know the whole chain: the pose network, the detector (threshold and
its doubt level, calibrated from `defense.doubt_share`) and the calibrated defense with its state (pipeline/attacks/):
- **burst**: bursts of {b['burst_length']} frames every {fused['burst_every']} frames ({b['bursts']} bursts per eps), each crafted
  jointly by L-inf PGD on min(trusted error, {b['cap']:g} AL) minus lambda times the margins of every check (the
  detector's logit, both gates' NIS through a differentiable copy of the filter), {b['steps']} steps from
  {b['restarts']} starts per lambda, lambda searched over {', '.join(f'{v:g}' for v in b['lambdas'])}, the best candidate chosen on
  the real chain and defense (most HMI frames, then fewest flags, then largest error); nested in eps
  (the larger eps starts from the smaller one's solution), so its worst case cannot drop as eps grows;
- **drift**: from frame {d['start']} for {d['frames']} frames, a bias along the line of sight (the target looks
  farther away) or across it, growing each frame as far as keeps every innovation under
  {d['gate_fraction']:g} of the gate (Mo and Sinopoli 2010), each frame a targeted PGD ({d['steps']} steps) toward
  that estimate with the detector's margin in the objective.

Without any attack, on all {c['frames']} frames: availability {_pct(c['availability'])}%, HMI {_pct(c['hmi'])}%,
trusted error mean {_m(c['trusted_error_mean_m'])} m, max {_m(c['trusted_error_max_m'])} m.

{integrity_table(integrity['rows'], with_mi)}
Worst HMI the attack caused, any attacker (the integrity headline; issue 27's target is an upper
bound of at most {100 * TARGET_HMI:g}%):

{_verdict(integrity.get("worst_hmi") or worst_hmi(integrity))}
{_bursts(integrity)}
The sanity checks of the burst attacker (with every check removed it reaches at least plain PGD's raw
error; doubling its steps and restarts) are in reports/benchmarks.md, "Chain-level attacks".

![trusted error against {bound} (Stanford diagram) at the largest eps, and one trajectory over frames](figures/integrity.png)

"""


def standard_integrity_section(standard: dict[str, Any], shipped: dict[str, Any], p: Params) -> str:
    """Markdown: the integrity rows of the standard model's chain (the paper's reproduction) beside the shipped
    chain's worst case (`standard`: metrics `integrity_standard`; `shipped`: metrics `integrity`)."""
    from pipeline.report.markdown import markdown_table

    head = "## Integrity of the standard model's chain (the paper's reproduction)\n\n"
    if not standard.get("attackers"):
        return head + "Not run (`integrity.standard_attackers` is empty).\n\n"
    c = standard["clean"]
    with_mi = bool(c.get("has_pl"))
    names = ", ".join(NAMES.get(a, a) for a in standard["attackers"])
    both = [{"eps": e, "shipped chain (robust model), any attacker (%)": _pct(w["hmi"]) + f" ({attacker_names(w['attacker'])})",
             f"standard model's chain, {names} (%)": _pct(standard["worst_hmi"][e]["hmi"]) if e in standard["worst_hmi"]
             else "-"} for e, w in sorted(shipped.get("worst_hmi", {}).items(), key=lambda kv: float(kv[0]))]
    n, total = standard["trajectories"], shipped["clean"]["trajectories"]
    scope = (f"on all {n} eval_render trajectories" if n == total else
             f"on the first **{n} of the {total}** eval_render trajectories, so its intervals are wider than the shipped "
             f"chain's")
    return head + f"""The definitions and attackers of the section above, on the standard model (models/pose.pt) with its
own detector (models/detector.pt) and the defense calibrated for it (models/defense_standard.json, `rpod
calibrate --model standard`): **{names}** {scope} (`integrity.standard_attackers`,
`integrity.standard_trajectories`: the whole suite on both chains does not fit the default budget). Without any
attack, on all {c['frames']} frames of these trajectories: availability {_pct(c['availability'])}%, HMI
{_pct(c['hmi'])}%, trusted error mean {_m(c['trusted_error_mean_m'])} m, max {_m(c['trusted_error_max_m'])} m.

{integrity_table(standard['rows'], with_mi)}
Worst HMI caused per eps, both chains (the shipped chain over every attacker and trajectory above; the standard
one over the attackers and trajectories named here):

{markdown_table(both)}
{_bursts(standard)}
"""

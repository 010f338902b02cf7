"""The integrity sections of reports/robustness.md (`rpod robustness`): the safety evidence that can fail (the
breaking point per chain, the safety-index table, the Stanford counts, the issue's targets met or missed, the
assumptions every row rests on) and the descriptive rows of the shipped chain (what each attack caused beside the
same frames unattacked); the attackers' names in words for the other pages."""

from __future__ import annotations

from typing import Any, Optional

from pipeline.stats import percent_of
from stages.config.schema import Params

CHAINS = {
    "robust": "shipped (robust model, its detector and defense)",
    "standard": "standard (the paper's reproduction, its detector and defense)",
    "control": "undefended robust control (the shipped pose network alone)",
}
KINDS = {"capture": "capture", "drift": "drift", "burst": "burst (nested)"}
DIRECTIONS = {"los": "along the line of sight", "lateral": "across it"}
STARTS = {"acquisition": "acquisition", "after_trusted": "the end of the trusted start"}  # where a drift begins
TARGET_SHIPPED_EPS = 0.05  # issue 39: the shipped chain holds at every eps up to this
TARGET_RATIO = 2.0  # ... and breaks at least this many times the control's eps
TARGET_AVAILABILITY = 0.99  # clean availability at least this
TARGET_FALSE_ALARMS = 0.005  # clean false alarms at most this


def attacker_names(name: str) -> str:
    """An attacker's name in words: "capture/lateral 2 m" -> "capture across it, 2 m bias kept", "drift/los
    after_trusted" -> "drift along the line of sight, from the end of the trusted start"; names joined by " = " (a tie)
    each in words."""
    out = []
    for one in name.split(" = "):
        kind, _, rest = one.partition("/")
        direction, _, size = rest.partition(" ")
        words = KINDS.get(kind, kind) + (f" {DIRECTIONS.get(direction, direction)}" if direction else "")
        if kind == "drift" and size:
            out.append(f"{words}, from {STARTS.get(size, size)}")
        else:
            out.append(words + (f", {size} bias kept" if size else ""))
    return " = ".join(out)


def _starts(start: str) -> str:
    """Where the drifts begin, in words (integrity.drift_start; both: one drift from each start)."""
    return " and from ".join(STARTS.values()) if start == "both" else STARTS.get(start, start)


def _m(x: float | None) -> str:
    return "-" if x is None or x != x else f"{x:.2f}"


def _eps(x: float | None) -> str:
    return "none in the grid" if x is None else f"{x:g}"


Bracket = tuple[Optional[float], Optional[float]]  # (survived, broke at): a breaking point lies in (survived, broke]


def process_noise(sigma: float, scale: float) -> str:
    """The filter's process noise per frame as the reports say it: `sigma` m per axis, plus `scale` of the step."""
    return f"{sigma:g} m" if not scale else f"hypot({sigma:g} m, {100 * scale:g}% of the commanded step)"


def breaking_bracket(per_eps: dict[str, Any], breaking: float | None) -> Bracket:
    """(survived, broke): the largest eps flown below the breaking eps (no run failed there) and the breaking eps, so
    the breaking point lies in (survived, broke]; (the largest eps flown, None) when the chain never broke, survived
    None when it broke at the first eps. `per_eps`: keyed by the eps flown ("%g")."""
    flown = sorted(float(e) for e in per_eps)
    survived = [e for e in flown if breaking is None or e < breaking]
    return (survived[-1] if survived else None), breaking


def bracket_text(b: Bracket) -> str:
    survived, broke = b
    if broke is None:
        return "none in the grid" if survived is None else f"none (survived {survived:g})"
    return f"({survived:g}, {broke:g}]" if survived is not None else f"<= {broke:g}"


def ratio_verdict(a: Bracket, b: Bracket, target: float) -> tuple[str, str]:
    """Whether a chain's breaking point is at least `target` times another's, from their brackets (a breaking point
    in (survived, broke] lies above its survived eps and at most at its broke eps, so the ratio lies strictly between
    survived_a / broke_b and broke_a / survived_b): "met" when `a` survived `target` x the eps where `b` broke,
    "**missed**" when `a` broke at or below `target` x the eps where `b` survived, "not shown" when the brackets allow both (or `b`
    never broke); and where the ratio lies, in words."""
    (ha, ba), (hb, bb) = a, b
    if not bb:
        return "not shown", "the other did not break in the grid"
    low = ha / bb if ha else 0.0
    high = ba / hb if ba is not None and hb else None
    text = f"ratio above {low:.2f}" + ("" if high is None else f", below {high:.2f}")
    if low >= target * (1 - 1e-12):
        return "met", text
    if high is not None and high <= target * (1 + 1e-12):
        return "**missed**", text
    return "not shown", f"{text} (the grid cannot tell)"


def targets(integrity: dict[str, Any]) -> list[tuple[str, str, str]]:
    """Issue 39's targets on the open-loop evidence, and the protection level's own claim on the clean flights:
    (target, "met" / "**missed**" / "not shown", evidence)."""
    chains = integrity["chains"]
    shipped, control = chains["robust"]["summary"], chains["control"]["summary"]
    out = []
    c = control["breaking_eps"]
    out.append(
        (
            "falsifiable: the undefended control fails at some eps of the grid",
            "met" if c is not None else "**missed**",
            f"control breaking eps {_eps(c)} ({chains['control']['trajectories']} trajectories)",
        )
    )
    small = [e for e in integrity["eps"] if e <= TARGET_SHIPPED_EPS]
    flown = {float(e): shipped["per_eps"][f"{e:g}"] for e in shipped["eps_flown"]}
    failed = [e for e in small if e in flown and flown[e]["failed"]]
    unflown = [e for e in small if e not in flown]
    worst = max((flown[e]["max_error_al"] or 0.0 for e in small if e in flown), default=None)
    verdict = "**missed**" if failed or unflown else "met"
    out.append(
        (
            f"shipped chain, every attacker flown, eps <= {TARGET_SHIPPED_EPS:g}: max error / AL < 1 on every "
            "trajectory",
            verdict,
            f"largest error / AL {_m(worst)}"
            + (f"; failed at eps {', '.join(f'{e:g}' for e in failed)}" if failed else ""),
        )
    )
    bs, bc = (breaking_bracket(x["per_eps"], x["breaking_eps"]) for x in (shipped, control))
    verdict, ratio = ratio_verdict(bs, bc, TARGET_RATIO)
    out.append(
        (
            f"shipped breaking eps >= {TARGET_RATIO:g} x the control's",
            verdict,
            f"shipped {bracket_text(bs)}, control {bracket_text(bc)}: {ratio}",
        )
    )
    avail = shipped["clean"]["availability"]
    alarms = shipped["clean"]["false_alarms"]
    out.append(
        (
            f"clean availability >= {100 * TARGET_AVAILABILITY:g}% (execution error on)",
            "met" if avail["value"] is not None and avail["value"] >= TARGET_AVAILABILITY else "**missed**",
            f"{percent_of(avail)}%",
        )
    )
    out.append(
        (
            f"clean false alarms <= {100 * TARGET_FALSE_ALARMS:g}% (execution error on)",
            "met" if alarms["value"] is not None and alarms["value"] <= TARGET_FALSE_ALARMS else "**missed**",
            f"{percent_of(alarms)}%",
        )
    )
    return out + [_clean_protection(chains)]


def _clean_protection(chains: dict[str, Any]) -> tuple[str, str, str]:
    """The protection level's own claim on the clean flights: no frame's trusted error above its PL, on the chains
    that have one (shipped and standard)."""
    pl = {k: chains[k]["summary"]["clean"].get("max_error_pl") for k in ("robust", "standard") if k in chains}
    known = [v for v in pl.values() if v is not None]
    return (
        "clean: the PL bounds the trusted error on every frame (max error / PL <= 1, shipped and standard chains)",
        "met" if known and max(known) <= 1.0 else "**missed**",
        "largest clean error / PL: " + ", ".join(f"{'shipped' if k == 'robust' else k} {_m(v)}" for k, v in pl.items()),
    )


def lead(integrity: dict[str, Any], p: Params) -> str:
    """The section reports/robustness.md leads with: targets missed first, the breaking point per chain, the
    safety-index table, Stanford counts, each chain per trajectory, and the assumptions."""
    from pipeline.report.markdown import markdown_table

    integrity = in_order(integrity)
    chains = integrity["chains"]
    verdicts = targets(integrity)
    head = _head(integrity, verdicts)
    points = _points(chains)
    index, regions = _safety_index(integrity, chains)
    per_trajectory = _per_trajectory(chains)
    return f"""## Safety evidence that can fail

{head}

Which safety targets this page's evidence meets (the docking-miss targets of the closed loop are in
reports/guidance.md):

{markdown_table([{"target": t, "verdict": v, "evidence": e} for t, v, e in verdicts])}
{assumptions(integrity, p)}

### Breaking point per chain

{markdown_table(points)}{_how_it_broke(chains)}
### Safety index per chain and eps (worst over attackers, per trajectory; the largest over trajectories)

error / AL over the available frames (AL: {_kind(integrity, p)}); "single-frame": the same errors against the
single-frame AL; error / PL over the frames with a protection level (none on the undefended control); final error:
the trusted error on the last frame, the bias the chaser would dock with (a final error above the docking tolerance
fails a trajectory only where that frame is available: at the goal AL is the tolerance, so it is then an error / AL
above 1; on an unavailable last frame the chain has declared it cannot be trusted, and the closed loop holds, a
safe abort, reports/guidance.md); "trajectories with HMI": a descriptive
count over independent trajectories (Clopper-Pearson 95%), of the attacks tried only; "available frames": of the
frames under every attacker at that eps itself (summed, from each attack's first frame; not nested in eps), those
the chain would fly on, where the error / AL columns cannot see an attack that makes the chain declare itself
unavailable (the guidance holds: safe, but no docking); a count, like the Stanford-ESA table's (the frames of a
trajectory are not independent, so no interval is drawn from them).

{markdown_table(index)}{_lowest(chains, integrity["eps"])}{per_trajectory}
### Stanford-ESA regions (frames counted from each attack's first frame, every attacker summed)

{markdown_table(regions)}
"""


def _head(integrity: dict[str, Any], verdicts: list[tuple[str, str, str]]) -> str:
    """The lead's first paragraph: the breaking eps per chain, then the targets not met (or that all are)."""
    missed = [t for t in verdicts if t[1] != "met"]
    breaks = ", ".join(f"{CHAINS[k].split(' (')[0]} {_eps(v)}" for k, v in integrity["breaking_eps"].items())
    return f"**Breaking point (smallest eps at which an attacker fails a trajectory): {breaks}.** " + (
        f"Targets not met: {'; '.join(f'{t} ({v}: {e})' for t, v, e in missed)}."
        if missed
        else "Every target is met on this evidence."
    )


def _how_it_broke(chains: dict[str, Any]) -> str:
    """Where each defended chain's failures at its breaking eps fell (pipeline.evaluation.campaign.how_it_broke):
    inside the trusted-start frames after the filter's first start (assumption A) or later; "" without any."""
    lines = []
    for key in ("robust", "standard"):
        rows = chains.get(key, {}).get("summary", {}).get("how_it_broke") or []
        if not rows:
            continue
        inside = sum(r["inside_trusted_start"] for r in rows)
        each = "; ".join(
            f"{r['trajectory']} ({attacker_names(r['attacker'])}): started at frame {r['start_frame']}, failed at "
            f"{r['first_failure_frame']}"
            for r in rows
        )
        lines.append(
            f"- {CHAINS[key].split(' (')[0]} at eps {_eps(chains[key]['summary']['breaking_eps'])}: {inside} of "
            f"{len(rows)} failed flights first fail inside the trusted-start frames after the filter's first start "
            f"(assumption A: the PL assumes them fault-free, the detector alone guards them); {each}."
        )
    if not lines:
        return ""
    return (
        "\nWhere the defended chains' failures at their breaking eps fall (first failing frame of each failed flight):\n\n"
        + "\n".join(lines)
        + "\n"
    )


def _points(chains: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows of the breaking-point table: per chain its breaking eps, the eps flown and its clean rates (%) and
    errors (error / AL, error / PL)."""
    return [
        {
            "chain": CHAINS[k],
            "trajectories": v["trajectories"],
            "breaking eps": _eps(v["summary"]["breaking_eps"]),
            "eps flown": ", ".join(f"{e:g}" for e in v["summary"]["eps_flown"]),
            "clean availability (%)": percent_of(v["summary"]["clean"]["availability"]),
            "clean false alarms (%)": percent_of(v["summary"]["clean"]["false_alarms"]),
            "clean max error / AL": _m(v["summary"]["clean"]["max_error_al"]),
            "clean max error / PL": _m(v["summary"]["clean"]["max_error_pl"]),
        }
        for k, v in chains.items()
    ]


INDEX_COLUMNS = (  # the safety-index table's columns
    "chain",
    "eps",
    "max error / AL",
    "max error / AL single-frame",
    "max error / PL",
    "largest final error (m)",
    "trajectories failed",
    "worst attacker",
    "trajectories with HMI (%)",
    "available frames",
)


def _safety_index(
    integrity: dict[str, Any], chains: dict[str, Any]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Rows of the safety-index table (per chain and eps; errors in m or over AL / PL) and of the Stanford-ESA
    regions table (per chain and eps, then without attack)."""
    index, regions = [], []
    for k, v in chains.items():
        s = v["summary"]
        for e in integrity["eps"]:
            row = s["per_eps"].get(f"{e:g}")
            if row is None:  # the other columns "-" (not NaN)
                index.append(
                    dict.fromkeys(INDEX_COLUMNS, "-")
                    | {
                        "chain": k,
                        "eps": f"{e:g}",
                        "max error / AL": f"not flown (broken at {_eps(s['breaking_eps'])})",
                    }
                )
                continue
            index.append(
                {
                    "chain": k,
                    "eps": f"{e:g}",
                    "max error / AL": _m(row["max_error_al"]),
                    "max error / AL single-frame": _m(row["max_error_al_single"]),
                    "max error / PL": _m(row["max_error_pl"]),
                    "largest final error (m)": _m(row["final_error_max_m"]),
                    "trajectories failed": f"{row['failed']}/{row['trajectories']}",
                    "worst attacker": attacker_names(row["worst_attacker"] or "-"),
                    "trajectories with HMI (%)": percent_of(row["hmi_trajectories"]),
                    "available frames": _available(row["stanford"]),
                }
            )
            regions.append({"chain": k, "eps": f"{e:g}", **_regions(row["stanford"])})
        regions.append({"chain": k, "eps": "no attack", **_regions(s["clean"]["stanford"])})
    return index, regions


def _lowest(chains: dict[str, Any], eps: list[float]) -> str:
    """One line: per chain the eps it flew with the lowest share of available frames under attack (the first such
    eps), and that count."""
    parts = []
    for k, v in chains.items():
        rows = [(v["summary"]["per_eps"].get(f"{e:g}"), e) for e in eps]
        shares = [(a, e, r["stanford"]) for r, e in rows if r and (a := _available_share(r["stanford"])) is not None]
        if shares:
            _, at, stanford = min(shares, key=lambda x: (x[0], x[1]))
            parts.append(f"{CHAINS[k].split(' (')[0]} {_available(stanford)} (first at eps {at:g})")
    return f"\nFewest available frames under attack: {', '.join(parts)}.\n" if parts else ""


def _regions(stanford: dict[str, int]) -> dict[str, int]:
    """A Stanford-ESA row's counts in the order of pipeline.evaluation.measures.REGIONS."""
    from pipeline.evaluation.measures import REGIONS

    return {r: stanford.get(r, 0) for r in REGIONS}


def _available_share(stanford: dict[str, int]) -> float | None:
    """The share of frames available (nominal, MI or HMI) among a Stanford-ESA row's frames (None: no frames):
    at one eps itself, every attacker summed (not nested: a larger eps may abort more), from each attack's first
    frame."""
    total = sum(stanford.values())
    return sum(stanford.get(r, 0) for r in ("nominal", "MI", "HMI")) / total if total else None


def _available(stanford: dict[str, int]) -> str:
    """A Stanford-ESA row's available frames as "k of n" ("-": no frames)."""
    total = sum(stanford.values())
    return f"{sum(stanford.get(r, 0) for r in ('nominal', 'MI', 'HMI'))} of {total}" if total else "-"


def _per_trajectory(chains: dict[str, Any]) -> str:
    """Each chain's table per trajectory at the target eps (errors over AL / PL, final error in m; the flags and
    availability of the attack that found them), or "" when no chain flew that eps."""
    from pipeline.report.markdown import markdown_table

    eps, rows = f"{TARGET_SHIPPED_EPS:g}", []
    for key, chain in chains.items():
        at = chain["summary"]["per_eps"].get(eps)
        for w in [] if at is None else at["per_trajectory"]:
            records = (
                chain["summary"].get("attackers", {}).get((w["worst_attacker"] or "").split(" = ")[0], {}).get(eps, [])
            )
            attack = next((t for t in records if t["trajectory"] == w["trajectory"]), None)
            rows.append(
                {
                    "chain": key,
                    "trajectory": w["trajectory"],
                    "max error / AL": _m(w["max_error_al"]),
                    "single-frame": _m(w["max_error_al_single"]),
                    "max error / PL": _m(w["max_error_pl"]),
                    "final error (m)": _m(w["final_error"]),
                    "worst attacker": attacker_names(w["worst_attacker"] or "-"),
                    "failed": "**yes**" if w["failed"] else "no",
                    "flagged frames": "-" if attack is None else attack["flags"],
                    "available (%)": "-" if attack is None else f"{100 * attack['availability']:.1f}",
                }
            )
    return (
        ""
        if not rows
        else f"\nEach chain per trajectory at eps {eps} (worst over attackers, nested in eps; flagged frames and "
        "availability: of the attack that found that worst, over its attacked frames):\n\n" + markdown_table(rows)
    )


def _kind(integrity: dict[str, Any], p: Params) -> str:
    """The AL the rows judge against, in words, with its values at the goal and at 15 m."""
    from pipeline.defense.integrity import alert_limit
    from stages.config.build import alert_limit_settings

    if integrity.get("alert_limit_m") is not None:
        return f"a fixed {integrity['alert_limit_m']:g} m (`integrity.alert_limit_m`)"
    s = alert_limit_settings(p)
    at = f"{float(alert_limit(s.goal_range, s)):g} m at the goal, {float(alert_limit(15.0, s)):g} m at 15 m"
    if integrity["alert_limit_kind"] == "persistent":
        return (
            f"the persistent-bias AL, tol + max(range - goal range, 0), the largest error a bias that may stay to "
            f"docking can have (derived in pipeline/defense/integrity.py): {at}"
        )
    return f"the single-frame AL (pipeline/defense/integrity.py): {at}"


def _where_unavailable(integrity: dict[str, Any]) -> str:
    """Where the shipped chain's clean availability is lost, by true-range band (`availability_by_range` of
    pipeline/evaluation/campaign.py): an unavailable frame is never judged, so the measure is blind there."""
    bands = integrity["chains"]["robust"]["summary"]["clean"].get("availability_by_range")
    if not bands:
        return ""
    shares = ", ".join(
        ("beyond " if b["to_m"] is None else "")
        + (f"{b['from_m']:g} m" if b["to_m"] is None else f"{b['from_m']:g}-{b['to_m']:g} m")
        + f" {100 * b['available']:.0f}% of {b['frames']}"
        for b in bands
        if b["frames"]
    )
    return (
        f"\n  Without attack, the shipped chain's frames available by true range: {shares}. An unavailable frame is "
        "never judged: where the PL exceeds AL (which falls to the docking tolerance at the goal) the measure cannot "
        "fail, and the chain declares itself unavailable (the guidance holds) rather than fail."
        + _availability_parts(integrity["chains"]["robust"]["summary"]["clean"].get("availability_parts"))
        + _tolerances(integrity["chains"]["robust"]["summary"]["clean"].get("availability_by_tolerance"))
    )


def _availability_parts(parts: dict[str, Any] | None) -> str:
    """What the clean availability would be with parts of the PL left out (pipeline/evaluation/availability.py):
    which part costs it, measured."""
    if not parts:
        return ""
    (flown, full), *rest = parts.items()
    shares = "; ".join(f"{name} {percent_of(v)}" for name, v in rest)
    return (
        f"\n  Which part of the PL costs the availability, measured on the same clean frames (a PL with a part left "
        f"out bounds nothing; pipeline/evaluation/availability.py): {flown} {percent_of(full)}; {shares}."
    )


def _tolerances(record: dict[str, Any] | None) -> str:
    """The clean availability of the same PL against the alert limit of other docking tolerances (m; the record's
    `mission_tolerance_m` the mission's): what a looser docking requirement would buy
    (pipeline/evaluation/availability.py `tolerance_availability`)."""
    if not record or not record["availability"]:
        return ""
    by = sorted(record["availability"].items(), key=lambda kv: float(kv[0]))  # JSON may hold "10" before "2"
    tolerance = record["mission_tolerance_m"]
    met = [t for t, r in by if r["value"] is not None and r["value"] >= TARGET_AVAILABILITY]
    verdict = (
        f"the {100 * TARGET_AVAILABILITY:g}% target is met from a {met[0]} m tolerance on"
        if met
        else f"the {100 * TARGET_AVAILABILITY:g}% target is met at none of them"
    )
    shares = "; ".join(f"{t} m {percent_of(r)}" for t, r in by)
    return (
        f"\n  The same PL on the same clean frames against the alert limit of another docking tolerance (the mission's "
        f"is {tolerance:g} m; the limit falls to it at the goal): {shares}; {verdict}. A wider tolerance is a mission "
        "decision, not a tuning of the chain."
    )


def assumptions(integrity: dict[str, Any], p: Params) -> str:
    """The assumptions every integrity row rests on, in words (metrics `integrity.assumptions`)."""
    a, cap, d = integrity["assumptions"], integrity["capture"], integrity["drift"]
    starts = _starts(d["start"])
    x = a["execution"]
    attackers = ", ".join(attacker_names(n) for n in integrity["attackers"])
    return f"""
Assumptions of every row below:
- **Trajectories and dynamics**: the {integrity["chains"]["robust"]["trajectories"]} eval_render approaches, 60 m to
  10 m, each planned step flown open loop with the thrusters' execution error ({100 * x["scale_std"]:g}% of the step
  and {100 * x["noise_std_m"]:g} cm per axis, 1-sigma per step) and Clohessy-Wiltshire motion (mean motion
  {x["mean_motion_rad_s"]:g} rad/s, {x["approach"]}); the chain is told the commands only. The standard chain and the
  control fly the first {integrity["chains"]["control"]["trajectories"]}.
- **Noise model and process noise**: {a["noise_model"]}; the filter's process noise per frame, std per axis,
  {process_noise(a["position_noise_m"], a.get("position_noise_scale", 0.0))}; the CUSUM reference c = {
        a["cusum_reference"]:g}; integrity risk {a["integrity_risk"]:g} per frame.
- **Trusted start**: the protection level assumes no fault on the {a["trusted_start_frames"]} frames after the
  filter's first start (assumption A, pipeline/defense/protection.py), and claims none (PL inf, unavailable) on
  them once the detector has flagged a frame of the run, until they are past; the captures and a drift from
  acquisition attack inside them.
- **Detector**: the shipped chain's SHAP + LSTM detector at its calibrated threshold
  {a["detector"]["threshold"]:.4g} (models/defense.json), fused with the filter's checks (`defense.fusion`
  {a["detector"]["fusion"]}); it alone guards the trusted-start frames, and every attacker knows it and carries its
  margin in the objective (an adaptive attack, not the paper's FGSM it was trained on). The undefended control has
  none.
- **AL and availability**: {_kind(integrity, p)}; a frame is available when the guidance flies on it (mode track or
  coast) and PL <= AL at the true range; failure = error / AL > 1 on an available frame. The single-frame AL is the
  second column.{_where_unavailable(integrity)}
- **Attackers** ({attackers}): the captures hold a world-frame bias of {", ".join(f"{b:g}" for b in cap["initial_m"])}
  m from the first frame (growth {cap["rate_m"]:g} m per frame), the drifts grow from {starts} as far as keeps
  every innovation under {d["gate_fraction"]:g} of the gate and every CUSUM statistic under half its threshold
  ({d["undefended_rate_m"]:g} m per frame against the control); each frame a targeted PGD of
  {integrity["frame_steps"]} steps from the background-lifting start with BPDA through the clamp, warm-started from
  the previous frame's perturbation, the detector's margin against its doubt level; each attacker nested in eps.
  {
        "Each chain stops after the eps at which it breaks (`integrity.stop_at_break`)."
        if integrity["stop_at_break"]
        else "Every eps is flown on every chain."
    } The full grid (`rpod integrity`, optional/dvc.yaml) flies every
  attacker of the schema on every chain, trajectory and eps.
"""


def integrity_table(rows: list[dict[str, Any]], with_mi: bool) -> str:
    """Per attacker and eps: what the attack caused beside the same frames unattacked."""
    from pipeline.report.markdown import markdown_table

    out = []
    for r in rows:
        cells = {
            "attacker": attacker_names(r["attacker"]),
            "eps": f"{r['eps']:g}",
            "frames": r["frames"],
            "HMI caused (%)": percent_of(r["hmi"]),
            "HMI without attack (%)": percent_of(r["hmi_clean"]),
        }
        if with_mi:
            cells["MI caused (%)"] = percent_of(r["mi"])
        cells |= {
            "attacked frames flagged (%)": percent_of(r["detected"]),
            "same frames flagged without attack (%)": percent_of(r["detected_clean"]),
            "availability (%)": percent_of(r["availability"]),
            "availability without attack (%)": percent_of(r["availability_clean"]),
            "trusted error mean / max (m)": f"{_m(r['trusted_error_mean_m'])} / {_m(r['trusted_error_max_m'])}",
            "without attack (m)": f"{_m(r['clean_error_mean_m'])} / {_m(r['clean_error_max_m'])}",
        }
        out.append(cells)
    return markdown_table(out)


def _bursts(rows: list[dict[str, Any]]) -> str:
    """A line: bursts whose worst case has an HMI frame, per eps (the nested attacker's own count)."""
    from pipeline.stats import wilson

    counts = [(r["eps"], r["bursts_with_hmi"]) for r in rows if "bursts_with_hmi" in r]
    if not counts:
        return ""
    return (
        "\nBursts whose worst case holds at least one HMI frame (the burst attacker's own count, on the real "
        "chain and defense): "
        + "; ".join(f"eps {e:g}: {wilson(k, n).pct()}% ({k}/{n})" for e, (k, n) in counts)
        + ".\n"
    )


def in_order(integrity: dict[str, Any]) -> dict[str, Any]:
    """`integrity` (metrics) with its per-chain dicts in the order of CHAINS and the shipped chain's availability parts
    in the order of pipeline.evaluation.availability.PARTS, so a page drawn from the metrics JSON (whose keys are
    sorted) is the page the stage drew."""
    from pipeline.evaluation.availability import PARTS

    def chain_order(d: dict[str, Any]) -> dict[str, Any]:
        return {k: d[k] for k in sorted(d, key=lambda k: (list(CHAINS).index(k) if k in CHAINS else len(CHAINS), k))}

    out = integrity | {
        "chains": chain_order(integrity["chains"]),
        "breaking_eps": chain_order(integrity["breaking_eps"]),
    }
    clean = integrity["chains"].get("robust", {}).get("summary", {}).get("clean", {})
    if clean.get("availability_parts"):
        parts = {k: clean["availability_parts"][k] for k in PARTS if k in clean["availability_parts"]}
        robust = out["chains"]["robust"]
        summary = robust["summary"] | {"clean": clean | {"availability_parts": parts | clean["availability_parts"]}}
        out["chains"] = out["chains"] | {"robust": robust | {"summary": summary}}
    return out


def integrity_page(integrity: dict[str, Any], p: Params) -> str:
    """reports/integrity_full.md (`rpod integrity`): the full grid's evidence and descriptive rows."""
    return grid_head(integrity, p) + lead(integrity, p) + integrity_section(integrity, p, figure=False)


def grid_head(integrity: dict[str, Any], p: Params) -> str:
    """The full grid page's title and first paragraph: what it flies and how many of the evaluation trajectories
    (`--trajectories N` flies the first N)."""
    flown = max(c["trajectories"] for c in integrity["chains"].values())
    total = p.evaluate.trajectories
    which = (
        "every trajectory"
        if flown >= total
        else f"the first {flown} of the {total} eval_render trajectories only (`--trajectories {flown}`)"
    )
    return (
        "# The full integrity grid (`rpod integrity`)\n\nEvery attacker on the shipped chain, the standard one and "
        f"the undefended robust control, {which} and every eps (the default profile's `rpod robustness` flies fewer "
        "attackers on fewer trajectories and stops each chain at its breaking point: reports/robustness.md).\n\n"
    )


def integrity_section(integrity: dict[str, Any], p: Params, figure: bool = True) -> str:
    """Markdown: the descriptive rows of every chain (HMI and MI the attack caused beside the same frames
    unattacked, detection, availability, trusted error) and, with `figure`, the integrity figure."""
    parts = []
    for key, chain in in_order(integrity)["chains"].items():
        c = chain["clean"]
        parts.append(f"""### {CHAINS[key][0].upper() + CHAINS[key][1:]}

Without any attack, on all {c["frames"]} frames of its {c["trajectories"]} trajectories: availability
{percent_of(c["availability"])}%, HMI {percent_of(c["hmi"])}%, trusted error mean {_m(c["trusted_error_mean_m"])} m, max
{_m(c["trusted_error_max_m"])} m.

{integrity_table(chain["rows"], bool(c.get("has_pl")))}{_bursts(chain["rows"])}""")
    return f"""## What each attack caused (descriptive)

Each attacked trajectory beside the same trajectory unattacked, frame by frame: "HMI caused" counts only the
frames that are HMI (available, error > AL) with the attack and not without it; MI = error > PL. Counted frames:
from a trajectory's first attacked frame to its end; flagged: over the attacked frames. Rates are percent with 95%
percentile-bootstrap intervals over trajectories; where the bootstrap has no spread, the Wilson interval of the
trajectories as trials. These counts speak only of the attacks tried; the section above is the evidence.

{chr(10).join(parts)}
{FIGURE if figure else ""}
"""


FIGURE = (
    "![trusted error against its bound (Stanford diagram) on the shipped chain at the largest eps at which an "
    "attacked frame keeps a finite PL (past it the chain declares every attacked frame unavailable), and one "
    "trajectory over frames](figures/integrity.png)\n"
)

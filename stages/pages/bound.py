"""reports/integrity_bound.md, the page of `rpod bound` (issue 40): per chain and eps the integrity bound's worst
trusted error against the alert limit AL, the replayed (real-chain) worst error, the share of target frames whose bound
exceeds AL with its 95% interval, the attacker sparing the protection level's trusted frames, the interval-bound
certificate beside the capacity, and every assumption the bound rests on."""

from __future__ import annotations

from typing import Any

from pipeline.stats import percent_of

CHAINS = {"robust": "robust (shipped)", "standard": "standard (paper's reproduction)"}

ASSUMPTIONS = """\
- **The capacity is an empirical overbound, not a certificate.** F(eps, range) is, per range bin, a quantile of the
  shifts the strongest-attack suite reached on validation frames times (1 + margin) (datasets/capacity/,
  pipeline/attacks/capacity.py): an attack stronger than the suite, or a frame beyond the quantile, can exceed it.
  An eps between measured ones takes the capacity of the next larger measured eps; the cross-track capacity bounds
  each cross axis separately (a square about the measured disk: conservative by up to sqrt(2)); the attitude is
  left at its clean value.
- **The certificate is vacuous.** Interval bound propagation through the pose network (pipeline/pose/certify.py)
  certifies shifts far beyond the range itself (table below), so nothing here is certified: the bound is exact only
  relative to the capacity.
- **The detector is modelled as blind**: every frame keeps its clean-run detector probability (its doubt and flags).
  The attacker is neither caught by it nor slowed by it. The worst sequence realised in images (above) measures what
  the live detector changes on it.
- **The attacker is white-box and starts at the first frame**: it knows the clean run (the pose network's noise,
  every gain and choice of the filter) and may shift every frame, the start and the trusted-start frames included
  (column "bound"). Column "sparing the PL's trusted frames" is the attacker the protection level's assumption A
  bounds (no fault up to the trusted-start count); its replayed error / PL above 1 is misleading information the PL
  should have covered.
- **The filter's structure is fixed**: the program keeps the clean run's accept / reject / alarm choices (the gate,
  the Huber zone and the sequential test as constraints, pipeline/defense/bound.py); an attack that changes them, or
  triggers a restart, is not searched (targets after the first restart are unmodelled and counted). Within that
  structure the bound is the program's upper bound (first order in the range terms of the noise model); the worst
  sequence is replayed through the real defense ("replayed").
- **Targets** are every `stride`-th frame from the filter's start and the last frame: the share of frames over AL
  is over those target frames, its interval bootstrapped over trajectories (frames of one trajectory resample
  together).
- The protection level's own assumptions (its risk allocated per frame, not per approach; the fault-free noise
  model white in time but for the share of one measurement's variance it holds as shared by the start frames,
  calibrated on validation) are pipeline/defense/protection.py's.
"""


def _x(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _rows(chain: dict[str, Any], label: str, stride: int) -> list[dict[str, str]]:
    """One row per eps: the bound's indices (from the first frame on) and the attacker sparing the trusted frames."""
    rows = []
    for e, row in chain["per_eps"].items():
        b, s = row["bound"], row["spared"]
        cap = next(t["per_eps"][e]["capacity_eps"] for t in chain["tracks"]) if chain["tracks"] else None
        rows.append(
            {
                "chain": label,
                "eps": e,
                "capacity measured at eps": _x(cap, 3),
                "max upper / AL": _x(b["max_error_al"]),
                "worst trajectory": b["worst_trajectory"] or "-",
                "max upper (m)": _x(b["max_error_m"]),
                "replayed worst error (m)": _x(b["max_achieved_m"]),
                "replayed / AL": _x(b["max_achieved_al"]),
                f"target frames (1 in {stride}) with upper > AL (%)": percent_of(b["frames_over_al"]),
                "max upper / PL": _x(b["max_error_pl"]),
                "max replayed / PL": _x(b["max_achieved_pl"]),
                "sparing the PL's trusted frames: max upper / AL": _x(s["max_error_al"]),
                "... max replayed / PL": _x(s["max_achieved_pl"]),
                "image attacks' worst error / AL": _x(chain.get("empirical", {}).get(e)),
                "replays reproducing the program (%)": _x(None if b["exact"] is None else 100 * b["exact"], 0),
                "unmodelled targets": str(b["unmodelled"]),
            }
        )
    return rows


def _certificates(chains: dict[str, Any]) -> list[dict[str, str]]:
    """Per chain and eps: the IBP certificate's median shift along the line of sight beside the capacity's."""
    rows = []
    for model, c in chains.items():
        cert = c.get("certificate")
        for e, r in (cert or {}).get("per_eps", {}).items():
            rows.append(
                {
                    "chain": CHAINS[model],
                    "eps": e,
                    "frames": str(len(cert["frames"])),
                    "certified shift along the LOS, median (m)": f"{r['certified_along_median_m']:.3g}",
                    "capacity along the LOS, median (m)": _x(r["capacity_along_median_m"]),
                    "certificate / capacity": f"{r['ratio_median']:.3g}",
                    "vacuous (beyond the range on every frame)": "yes" if r["vacuous"] else "no",
                }
            )
    return rows


def _available(fly: dict[str, Any]) -> str:
    """Whether a replay's target frame is available (PL <= AL, flown) and its PL: "yes (0.84)"; "-" for a replay
    recorded before availability was."""
    if "available" not in fly:
        return "-"
    return ("yes" if fly["available"] else "no") + ("" if fly["pl_m"] is None else f" ({fly['pl_m']:.2f})")


def _breaking_lines(chains: dict[str, Any]) -> list[str]:
    """Per chain: the smallest eps at which the worst sequence realised in images fails the real chain (error / AL
    > 1 on an available frame), the campaign's measure of reports/robustness.md."""
    out = []
    for model, c in chains.items():
        done = sorted((float(e), r) for e, r in c.get("realized", {}).items() if r.get("modelled"))
        if not done or "failed" not in done[0][1]["live"]:
            continue
        broke = next((e for e, r in done if r["live"]["failed"]), None)
        flown = ", ".join(f"{e:g}" for e, _ in done)
        out.append(
            f"- {CHAINS[model]}: "
            + (f"fails the real chain from eps {broke:g}" if broke is not None else "no failure on an available frame")
            + f" (eps flown {flown}; one trajectory per eps, the bound's worst){_unjudged(done)}"
        )
    return out


def _unjudged(done: list[tuple[float, dict[str, Any]]]) -> str:
    """Where the realised sequences' target frames were unavailable on the real chain (PL > AL): the error there is
    not judged by the measure, and the sentence says so with the PLs, the AL and the largest error it leaves."""
    off = [r for _, r in done if not r["live"]["available"]]
    if not off:
        return ""
    pls = [r["live"]["pl_m"] for r in off if r["live"]["pl_m"] is not None]
    return (
        f"; its target frame is unavailable at {len(off)} of {len(done)} eps ("
        + (f"PL {_span(pls, 1)}" if pls else "no PL")
        + f" against AL {_span([r['alert_m'] for r in off], 2)}), so the error there (up to "
        f"{max(r['live']['error_m'] for r in off):.2f} m) is not judged: the chain declares itself unavailable "
        "there rather than fail"
    )


def _span(values: list[float], digits: int) -> str:
    """ "8.5-11.2 m", or "1.00 m" when the values round alike."""
    lo, hi = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
    return f"{lo} m" if lo == hi else f"{lo}-{hi} m"


def _realized_rows(chains: dict[str, Any]) -> list[dict[str, str]]:
    """Per chain and eps: the worst sequence realised in images (`realized`), beside the bound and its replay."""
    rows = []
    for model, c in chains.items():
        for e, r in c.get("realized", {}).items():
            if not r.get("modelled"):
                continue
            fl = "/".join(str(r[k]["flagged"]) for k in ("clean", "blind", "live"))
            rows.append(
                {
                    "chain": CHAINS[model],
                    "eps": e,
                    "trajectory, frame (range m)": f"{r['trajectory']}, {r['frame']} ({r['range_m']:.1f})",
                    "AL (m)": _x(r["alert_m"]),
                    "upper (m)": _x(r["bound_m"]),
                    "requested sequence replayed (m)": _x(r["requested"]["error_m"]),
                    "in images, detector blind (m)": _x(r["blind"]["error_m"]),
                    "in images, real chain (m)": _x(r["live"]["error_m"]),
                    "real chain / AL": _x(r["live"]["error_m"] / r["alert_m"]),
                    "target available, real chain (PL m)": _available(r["live"]),
                    "real chain: max error / AL, available frames": _x(r["live"].get("max_error_al_available")),
                    "real chain / upper": _x(r["live"]["error_m"] / r["bound_m"]),
                    "frames attacked": str(r["attacked_frames"]),
                    "shift requested, median (m)": _x(r["requested_length_median_m"]),
                    "reached along it, median (%)": _x(
                        None if r["reached_share_median"] is None else 100 * r["reached_share_median"], 0
                    ),
                    "residual median / 90th pct (m)": f"{r['residual_median_m']:.2f} / {r['residual_p90_m']:.2f}",
                    "frames flagged clean / blind / real (detector)": f"{fl} ({r['live']['detector_flagged']})",
                }
            )
    return rows


def _realized_lines(chains: dict[str, Any]) -> list[str]:
    """Per chain at its largest realised eps: the measured steps from the bound to the real chain's error in images."""
    out = []
    for model, c in chains.items():
        done = [(float(e), r) for e, r in c.get("realized", {}).items() if r.get("modelled")]
        if not done:
            continue
        e, r = max(done, key=lambda t: t[0])
        image = c.get("empirical", {}).get(f"{e:g}")
        out.append(
            f"- {CHAINS[model]}, eps {e:g}: the worst sequence realised in images ends {r['live']['error_m']:.2f} m "
            f"off through the real chain ({r['live']['error_m'] / r['alert_m']:.2f} x AL, "
            f"{100 * r['live']['error_m'] / r['bound_m']:.0f}% of the bound's {r['bound_m']:.2f} m)"
            + ("" if image is None else f", against {image:.2f} x AL for the image attackers of reports/robustness.md")
            + f". Measured steps: bound {r['bound_m']:.2f} m -> its feasible sequence replayed "
            f"{r['requested']['error_m']:.2f} m (the program's upper bound against its attack) -> in images, detector "
            f"blind {r['blind']['error_m']:.2f} m (shifts the images did not reach: residual over 90th percentile "
            f"{r['residual_p90_m']:.2f} m; {r['blind']['flagged'] - r['clean']['flagged']} more frames flagged by the "
            f"motion checks) -> real chain {r['live']['error_m']:.2f} m (the detector flags "
            f"{r['live']['detector_flagged']} frames)."
        )
    return out


REALIZED_INTRO = (
    "Per chain and eps, the worst trajectory's worst sequence (its largest upper / AL) pursued frame by frame by a "
    "targeted attack of the same eps (APGD on the distance to the requested position, every frame stored as 8 bits; "
    "pipeline/evaluation/bound_images.py), then flown through the real chain with the detector blind (its clean "
    "probabilities, as the bound models it) and live. Each step from the bound to the real chain is measured: the "
    "program's feasible sequence replayed, the images' reach of each requested shift, the detector."
)


CHECKS_INTRO = (
    "An attacker limited by the checks alone: no capacity (a box as wide as the true range on every axis), the "
    "detector blind, the frames the PL trusts spared (assumption A), the worst sequence per target frame replayed "
    "through the real defense with the clean run's flags. A protection level sound against that attacker with these "
    "checks must be at least its replayed error, so where that error exceeds AL no such PL can make the frame "
    "available: the share of target frames within AL is a ceiling on the clean availability of any capacity-free "
    "PL of this filter and its checks, beside what the chain's PL makes available on the same frames. Targets: every "
    "frame whose AL is below the clean run's largest PL, the others every stride-th frame standing for the frames up "
    "to the next (every frame from the filter's start counts once)."
)


def _checks_rows(chains: dict[str, Any]) -> list[dict[str, str]]:
    """Per chain: the checks-only attacker's availability ceiling beside the PL's, and its error at the goal."""
    rows = []
    for model, c in chains.items():
        k = c.get("checks_only")
        if not k:
            continue
        goal, pl = k["goal_achieved_m"], k["goal_pl_m"]
        rows.append(
            {
                "chain": CHAINS[model],
                "frames (targets)": f"{k['ceiling']['n']} ({k['targets']})",
                "availability ceiling, any sound PL (%)": percent_of(k["ceiling"]),
                "the chain's PL, same frames (%)": percent_of(k["pl"]),
                "replayed error at the last frame, median / max (m)": f"{_x(goal['median'])} / {_x(goal['max'])}",
                "largest AL there (m)": _x(k["goal_alert_m"]),
                "PL there, range (m)": f"{_x(pl['min'])}-{_x(pl['max'])}",
                "max replayed / AL": _x(k["max_achieved_al"]),
                "largest shift / range": _x(k["largest_shift_range"]),
            }
        )
    return rows


def _first_lines(chains: dict[str, Any]) -> list[str]:
    """Per chain: the eps at which the bound first exceeds AL (and the eps its capacity was measured at, if larger)."""
    out = []
    for m, c in chains.items():
        e = c["first_over_al_eps"]
        if e is None:
            out.append(f"- {CHAINS[m]}: the bound stays within AL at every eps")
            continue
        measured = min((v for v in c["capacity"]["eps"] if v >= e), default=e)
        borrowed = "" if measured == e else f" (on the capacity measured at eps {measured:g}: none at {e:g})"
        out.append(f"- {CHAINS[m]}: the bound first exceeds AL at eps {e:g}{borrowed}")
    return out


def _capacity_lines(chains: dict[str, Any]) -> list[str]:
    """Per chain: the eps the capacity was measured at and its overbound (quantile, margin, range bins)."""
    return [
        f"- {CHAINS[m]}: measured at eps {', '.join(f'{e:g}' for e in c['capacity']['eps'])}; the "
        f"{c['capacity']['quantile']:g} quantile x (1 + {c['capacity']['margin']:g}) per range bin "
        f"({', '.join(f'{v:g}' for v in c['capacity']['edges'])} m)"
        for m, c in chains.items()
    ]


def bound_page(metrics: dict[str, Any]) -> str:
    """The whole page from reports/metrics/bound.json's content."""
    from pipeline.report.markdown import markdown_table

    chains, stride = metrics["chains"], metrics["stride"]
    rows = [r for model, c in chains.items() for r in _rows(c, CHAINS[model], stride)]
    certs, realized = _certificates(chains), _realized_rows(chains)
    return "\n".join(
        [
            "# Integrity bound under the attacker's capacity",
            "",
            "The worst trusted error of fault sequences within the attacker's capacity F(eps, range) that pass every "
            f"check of the chain's defense, on {metrics['trajectories']} evaluation trajectories ({metrics['frames']} "
            f"frames; every {stride}th frame from the filter's start and the last is a target), against the alert limit "
            "AL at the true range. upper: the program's bound; replayed: the worst sequence flown through the real "
            "chain's defense; image attacks: the largest error / AL the image-space attackers of reports/robustness.md "
            'reached on the same chain at that eps (its own trajectories; "-" where it did not fly the eps). The next '
            "section measures how much of the bound images reach.",
            "",
            markdown_table(rows),
            "Where the bound first exceeds AL:",
            "",
            *_first_lines(chains),
            "",
            "## What availability any sound PL can have with these checks",
            "",
            CHECKS_INTRO,
            "",
            markdown_table(checks) if (checks := _checks_rows(chains)) else "Not run.\n",
            "## The worst sequence in images",
            "",
            REALIZED_INTRO,
            "",
            *([markdown_table(realized), *_realized_lines(chains), ""] if realized else ["Not run.", ""]),
            *(
                ["Where the worst sequence realised in images fails the real chain:", "", *lines, ""]
                if (lines := _breaking_lines(chains))
                else []
            ),
            "## The capacity",
            "",
            *_capacity_lines(chains),
            "",
            "## Certificate",
            "",
            markdown_table(certs) if certs else "Not computed (bound.certify_frames = 0).\n",
            "## Assumptions",
            "",
            ASSUMPTIONS,
        ]
    )

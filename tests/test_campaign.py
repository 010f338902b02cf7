"""The integrity campaign (pipeline/evaluation/campaign.py) and its pages on test_capture's toy chain: a planted
persistent bias (a capture held from acquisition) fails the measures and sets the breaking point at the eps that
can deliver it, per chain (the defended toy and the undefended control); the ladder stops after the breaking point
when asked; the summary nests each attacker in eps, takes the worst over attackers per trajectory and counts HMI
trajectories with Clopper-Pearson intervals; the robustness page leads with the breaking point and the targets;
the closed loop's docking table and breaking point per variant."""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import numpy as np
import pytest
from test_capture import EXACT, IDENTITY6, NOISE, ToyOnboard, ToyPose, encode, shift

from pipeline.attackers.capture import CaptureSettings
from pipeline.attackers.drift import DriftSettings
from pipeline.defense.chain import Defended
from pipeline.defense.integrity import AlertLimitSettings, alert_limit
from pipeline.defense.settings import DefenseSettings
from pipeline.evaluation.campaign import Campaign, Plan, fly_campaign, safety_summary
from pipeline.evaluation.integrity_runs import Track
from pipeline.evaluation.measures import TrajectoryMeasures

PERSISTENT, SINGLE = AlertLimitSettings(kind="persistent"), AlertLimitSettings()


@pytest.fixture(scope="module")
def tracks() -> list[Track]:
    """Two 40-frame toy approaches 60 m -> 10 m (camera = world axes), 0.1 m of seeded noise on the estimates."""
    out = []
    for k in range(2):
        n = 40
        rel = np.column_stack([np.linspace(6.0 - 3 * k, 0.0, n), np.linspace(-4.0, 0.0, n), np.linspace(60.0, 10.0, n)])
        images = np.stack([encode(t) for t in rel + np.random.default_rng(k).normal(size=(n, 3)) * 0.1])
        out.append(Track(f"t{k}", images, np.column_stack([rel, np.tile(IDENTITY6, (n, 1))])))
    return out


def _campaign(eps: list[float], stop: bool, defended: bool) -> Campaign:
    plans = [
        Plan("capture/lateral 2 m", CaptureSettings("lateral", initial=2.0), 0),
        Plan("drift/los", DriftSettings("los", max_rate=None if defended else 0.02), 21),
    ]
    return Campaign(eps, plans, shift, 0, None, [], PERSISTENT, SINGLE, 8, 1.0, 0, stop)


def _fly(tracks: list[Track], eps: list[float], stop: bool, defended: bool):
    d = Defended(DefenseSettings(), EXACT, NOISE) if defended else None
    return fly_campaign(ToyOnboard(ToyPose()), ToyPose(), d, tracks, _campaign(eps, stop, defended))


@pytest.mark.parametrize("defended", [True, False])
def test_a_planted_persistent_bias_breaks_each_chain_at_the_eps_that_delivers_it(tracks, defended: bool) -> None:
    """One 8-bit level per pixel (eps 0.004) moves the toy estimate 0.29 m: the 2 m capture is not delivered and the
    trajectories hold; at eps 0.03 (7 levels, 2.06 m) it is, held from acquisition to the goal: error / AL_p > 1 on
    an available frame (the defended toy's checks cannot see a bias consistent with the commands), the breaking
    point of either chain. The clean flights hold, the control has no PL."""
    flights = _fly(tracks, [0.004, 0.03], stop=False, defended=defended)
    s = safety_summary(flights)
    assert s["breaking_eps"] == 0.03 and s["eps_flown"] == [0.004, 0.03] and s["stopped_at"] is None
    small, large = s["per_eps"]["0.004"], s["per_eps"]["0.03"]
    assert small["failed"] == 0 and small["max_error_al"] < 1
    assert large["failed"] == 2 and large["max_error_al"] > 1.5 and large["worst_attacker"] == "capture/lateral 2 m"
    assert large["final_error_max_m"] > 1.8 and large["max_error_al_single"] < large["max_error_al"]
    assert (large["max_error_pl"] is None) == (not defended)
    assert s["clean"]["failed"] == 0 and s["clean"]["max_error_al"] < 1 and s["trajectories"] == 2
    assert s["clean"]["availability"]["value"] > 0.5 and sum(large["stanford"].values()) > 0
    assert large["hmi_trajectories"]["ci_method"] == "Clopper-Pearson over trajectories"
    assert set(s["attackers"]) == {"capture/lateral 2 m", "drift/los"}
    rows = {(r["attacker"], r["eps"]) for r in flights.rows}
    assert rows == {(a, e) for a in s["attackers"] for e in (0.004, 0.03)}


def test_the_ladder_stops_after_the_breaking_point(tracks) -> None:
    flights = _fly(tracks, [0.03, 0.05], stop=True, defended=False)
    s = safety_summary(flights)
    assert s["breaking_eps"] == 0.03 and s["eps_flown"] == [0.03] and s["stopped_at"] == 0.03
    assert "0.05" not in s["per_eps"] and all(e == 0.03 for _, e, _, _ in flights.runs)


def _measures(name: str, al: float, final: float = 0.5, hmi: int = 0) -> TrajectoryMeasures:
    return TrajectoryMeasures(name, 10, al, al / 3, float("nan"), final, 0, hmi, 0, 1.0)


def test_the_summary_nests_each_attacker_in_eps_and_takes_the_worst_over_attackers() -> None:
    """An attacker that found less at a larger eps keeps its smaller eps's worst case (nested); per trajectory the
    worst over attackers; the breaking point is the smallest eps with a failure; HMI trajectories with
    Clopper-Pearson intervals."""
    from pipeline.evaluation.campaign import Flights
    from pipeline.stats import Rate

    measures = {
        "a": {
            0.01: [_measures("t0", 0.5), _measures("t1", 1.2, hmi=2)],
            0.05: [_measures("t0", 0.3), _measures("t1", 0.4)],
        },
        "b": {
            0.01: [_measures("t0", 0.2), _measures("t1", 0.1)],
            0.05: [_measures("t0", 0.9, final=2.0), _measures("t1", 0.2)],
        },
    }
    rate = {"value": 1.0, "ci": [0.9, 1.0], "n": 20}
    flights = Flights([], Rate(0.0, 0.0, 0.0, 20), [], [], {"availability": rate}, [], measures, [], {}, {}, None, {})
    s = safety_summary(flights)
    assert s["breaking_eps"] == 0.01
    at = s["per_eps"]["0.05"]
    assert at["max_error_al"] == 1.2 and at["failed"] == 1 and at["final_error_max_m"] == 2.0  # t1 nested from 0.01
    assert [w["worst_attacker"] for w in at["per_trajectory"]] == ["b", "a"]
    assert at["hmi_trajectories"]["value"] == 0.5 and at["hmi_trajectories"]["ci"][1] > 0.9
    assert s["attackers"]["a"]["0.05"][1]["max_error_al"] == 1.2 and s["per_eps"]["0.01"]["max_error_pl"] is None


def _integrity(breaking: dict[str, float | None], shipped_failed: int = 0, availability: float = 0.999) -> dict:
    """A minimal metrics `integrity` block as rpod robustness writes it (stages/engine/campaigns.py)."""

    def chain(b: float | None, failed: int) -> dict:
        per = {
            f"{e:g}": {
                "max_error_al": 1.5 if failed and e >= 0.05 else 0.4,
                "max_error_al_single": 0.2,
                "max_error_pl": 0.9,
                "final_error_max_m": 0.3,
                "failed": failed if e >= 0.05 else 0,
                "trajectories": 10,
                "worst_attacker": "capture/lateral 2 m",
                "hmi_trajectories": {"value": 0.0, "ci": [0.0, 0.31], "n": 10},
                "stanford": {"nominal": 5, "unavailable": 5 if e >= 0.05 else 0},
                "per_trajectory": [
                    {
                        "trajectory": "t0",
                        "max_error_al": 0.4,
                        "max_error_al_single": 0.2,
                        "max_error_pl": 0.9,
                        "final_error": 0.3,
                        "worst_attacker": "drift/los",
                        "failed": False,
                    }
                ],
            }
            for e in (0.01, 0.05)
        }
        clean = {
            "availability": {"value": availability, "ci": [0.99, 1.0], "n": 2000},
            "false_alarms": {"value": 0.001, "ci": [0.0, 0.004], "n": 2000},
            "max_error_al": 0.3,
            "max_error_pl": 0.5,
            "stanford": {"nominal": 100},
        }
        record = {"trajectory": "t0", "flags": 7, "availability": 0.625, "frames": 200}
        attackers = {"drift/los": {f"{e:g}": [record] for e in (0.01, 0.05)}}
        return {
            "trajectories": 10,
            "summary": {
                "breaking_eps": b,
                "eps_flown": [0.01, 0.05],
                "per_eps": per,
                "clean": clean,
                "attackers": attackers,
            },
        }

    return {
        "chains": {k: chain(b, shipped_failed if k == "robust" else 0) for k, b in breaking.items()},
        "breaking_eps": breaking,
        "eps": [0.01, 0.05],
        "alert_limit_m": None,
        "alert_limit_kind": "persistent",
        "attackers": ["capture/lateral", "drift/los"],
        "capture": {"initial_m": [2.0], "rate_m": 0.0},
        "drift": {"start": "acquisition", "gate_fraction": 0.5, "undefended_rate_m": 0.05},
        "frame_steps": 3,
        "stop_at_break": True,
        "assumptions": {
            "trusted_start_frames": 20,
            "position_noise_m": 0.01,
            "position_noise_scale": 0.02,
            "noise_model": "fitted",
            "detector": {"fusion": "or", "threshold": 0.61},
            "execution": {
                "scale_std": 0.02,
                "noise_std_m": 0.01,
                "mean_motion_rad_s": 0.0011,
                "frame_interval_s": 10.0,
                "approach": "vbar",
            },
            "integrity_risk": 1e-5,
            "cusum_reference": 1.0,
        },
    }


def test_the_robustness_page_leads_with_the_breaking_point_and_says_which_targets_are_missed() -> None:
    from stages.config import params as params_mod
    from stages.pages.integrity import lead, targets

    p = params_mod.build(params_mod.compose("default"))
    held = _integrity({"robust": None, "standard": 0.01, "control": 0.02})
    assert [v for _, v, _ in targets(held)] == ["met", "met", "met", "met", "met", "met"]
    page = lead(held, p)
    assert page.startswith("## Safety evidence that can fail") and "Every target is met" in page
    assert "**Trusted start**" in page and "**Detector**" in page and "threshold\n  0.61" in page
    assert (
        "**Breaking point (smallest eps at which an attacker fails a trajectory): shipped none in the grid, "
        "standard 0.01, undefended robust control 0.02.**" in page.splitlines()[2]
    )
    broken = _integrity({"robust": 0.05, "standard": 0.01, "control": 0.05}, shipped_failed=2, availability=0.946)
    verdicts = dict((t.split(":")[0] if ":" in t else t, v) for t, v, _ in targets(broken))
    first = lead(broken, p).splitlines()[2]
    assert "Targets not met" in first and "clean availability" in first and "shipped 0.05" in first
    assert list(verdicts.values()).count("**missed**") == 2  # shipped at eps <= 0.05, availability
    assert verdicts["shipped breaking eps >= 2 x the control's"] == "not shown"  # both in (0.01, 0.05]: cannot tell
    leaky = _integrity({"robust": None, "standard": 0.01, "control": 0.02})
    leaky["chains"]["standard"]["summary"]["clean"]["max_error_pl"] = 1.15  # seed 1's failure, before the share
    target, verdict, evidence = targets(leaky)[-1]
    assert target.startswith("clean: the PL bounds") and verdict == "**missed**"
    assert evidence == "largest clean error / PL: shipped 0.50, standard 1.15"
    assert "clean: the PL bounds" in lead(leaky, p).splitlines()[2]  # named in the first lines
    no_control = _integrity({"robust": None, "standard": 0.01, "control": None})
    assert targets(no_control)[0][1] == "**missed**" and targets(no_control)[2][1] == "not shown"


def test_the_closed_loop_breaking_point_and_docking_table_per_variant() -> None:
    """pipeline/evaluation/closed_loop.py on a faked plan: each shipped-chain run judged by where it docks; a failed
    attacked run sets its variant's breaking point, a failed no-attack run makes it 0; the paper chain is left out;
    the guidance page leads with it."""
    from types import SimpleNamespace

    from pipeline.evaluation.closed_loop import closed_loop_outcomes
    from pipeline.guidance.grid import GridPlan, InLoopRun
    from pipeline.guidance.law import GuidanceSettings
    from stages.config import params as params_mod
    from stages.pages.guidance import closed_loop_section

    s = GuidanceSettings(variant="true_state")
    plan = GridPlan(s, ((0.05, 20.0, 5, None),), 10, ("true_state",), ("recover",), ((0.01, "capture", 60.0),))

    def run(end: tuple[float, float, float], attacked: int = 0, held: bool = False, lateral: float = 0.0) -> Any:
        positions = np.array([[0.0, 0.0, 60.0], end])
        return SimpleNamespace(
            positions=positions,
            estimates=np.zeros((1, 3)),
            held=np.array([held]),
            modes=None,
            protection=None,  # made without the PL's record: no final_hold
            acted=np.array([[0.0, 0.0, 60.0]]) + [lateral, 0.0, 0.0],  # what the guidance flew on
            outcome="",
            attacked_frames=attacked,
            closest_range=float(np.linalg.norm(end)),
        )

    runs = plan.runs()
    results = {("paper", None): run((0, 0, 30)), ("paper", 0): run((0, 0, 30), 5)}
    results |= {
        ("undefended", None): run((0, 0, 10.2)),
        ("undefended", 0): run((3.0, 0, 10.0), 5, lateral=102.0),  # error / AL 2 at 60 m (AL 51 m)
        ("recover", None): run((0, 0, 13.0), held=True),
        ("recover", 0): run((0, 0, 13.0), 5, held=True),
    }
    order = [
        results.get(
            (d if c != "paper" else "paper", k if not isinstance(k, InLoopRun) else "loop"), run((0.0, 2.0, 10.0), 30)
        )
        for c, _, d, k in runs
    ]
    out = closed_loop_outcomes(plan, order, 5.0, partial(alert_limit, settings=AlertLimitSettings(kind="persistent")))
    v = out["variants"]["true_state"]
    assert {r["defense"] for r in out["runs"]} == {"undefended", "recover"}
    assert v["undefended"]["clean"]["outcome"] == "docked" and v["undefended"]["breaking_eps"] == 0.01
    assert v["undefended"]["per_eps"]["0.05"] == {
        "met": 1,
        "failed": 1,
        "largest_miss_m": 3.0,
        "outcomes": {"missed": 1},
        "largest_error_al": 2.0,
        "largest_error_pl": None,
    }
    assert v["undefended"]["clean"]["max_error_al"] == 0.0 and v["undefended"]["clean"]["frames_flown"] == 1
    assert v["recover"]["clean"]["outcome"] == "held" and v["recover"]["breaking_eps"] == 0.01  # the capture's miss
    page = closed_loop_section(out, params_mod.build(params_mod.compose("default")))
    assert page.startswith("# Closed-loop rendezvous: where the shipped chain docks")
    assert "undefended 0.01; detect-and-recover 0.01" in page.splitlines()[2] and "Targets not met" in page
    assert "nan" not in page  # a variant without runs at an eps shows "-"
    index = page[page.index("Safety index per dynamics and variant") :]
    assert "| 2.00 / -" in index  # the undefended run's planted 102 m error at 60 m (AL 51 m), no PL
    v["undefended"]["breaking_eps"] = 0.0  # failing without attack says nothing about the attacks
    page = closed_loop_section(out, params_mod.build(params_mod.compose("default")))
    assert "not shown" in next(line for line in page.splitlines() if line.startswith("| falsifiable"))


def test_a_campaign_on_the_undefended_control_needs_a_drift_rate(tracks) -> None:
    c = dataclasses.replace(_campaign([0.03], False, False), plans=[Plan("drift/los", DriftSettings("los"), 0)])
    with pytest.raises(ValueError, match="max_rate"):
        fly_campaign(ToyOnboard(ToyPose()), ToyPose(), None, tracks, c)


def test_per_track_shares_assemble_into_the_campaign_over_every_track(tracks) -> None:
    """The toy's frame attack draws nothing, so each track flown alone (`fly_track`, a resumable share) and joined
    (`assemble`) gives the same rows, measures and summary as one campaign over both tracks; a campaign that stops
    at the breaking point cannot be split, and shares of different campaigns do not join."""
    from pipeline.evaluation.campaign import assemble, fly_track

    d = Defended(DefenseSettings(), EXACT, NOISE)
    c = _campaign([0.004, 0.03], False, True)
    whole = fly_campaign(ToyOnboard(ToyPose()), ToyPose(), d, tracks, c)
    shares = [fly_track(ToyOnboard(ToyPose()), ToyPose(), d, t, c) for t in tracks]
    joined = assemble(tracks, shares, c)
    assert joined.rows == whole.rows and joined.clean_row == whole.clean_row
    assert safety_summary(joined) == safety_summary(whole) and joined.stanford == whole.stanford
    with pytest.raises(ValueError, match="must not stop"):
        fly_track(ToyOnboard(ToyPose()), ToyPose(), d, tracks[0], dataclasses.replace(c, stop_at_break=True))
    other = fly_track(ToyOnboard(ToyPose()), ToyPose(), d, tracks[1], dataclasses.replace(c, eps=[0.004]))
    with pytest.raises(ValueError, match="different attackers or eps"):
        assemble(tracks, [shares[0], other], c)


def test_clean_availability_is_split_by_true_range_and_the_page_says_where_it_is_lost() -> None:
    """Frames whose PL exceeds AL near the goal: the split puts the lost availability in the nearest band, and the
    assumptions say an unavailable frame is never judged."""
    from pipeline.defense.integrity import IntegrityFrames
    from pipeline.evaluation.campaign import availability_by_range
    from stages.pages.integrity import _where_unavailable

    rng = np.linspace(60.0, 10.0, 200)
    truth = np.stack([np.zeros(200), np.zeros(200), rng], axis=1)
    alert = 1.0 + (rng - 10.0)  # the persistent AL
    frames = IntegrityFrames(
        np.zeros(200), np.arange(200), truth + 0.1, truth, np.full(200, "track"), alert, np.full(200, 9.0)
    )
    bands = availability_by_range([frames, frames])
    assert [b["frames"] for b in bands] == [
        2 * int(((rng >= lo) & (rng < hi)).sum()) for lo, hi in [(0, 15), (15, 20), (20, 30), (30, np.inf)]
    ]
    assert bands[0]["available"] == 0.0 and bands[2]["available"] == 1.0 and bands[3]["to_m"] is None
    assert 0 < bands[1]["available"] < 1  # AL passes the PL (9 m) at 18 m
    integrity = {"chains": {"robust": {"summary": {"clean": {"availability_by_range": bands}}}}}
    text = _where_unavailable(integrity)
    assert "0-15 m 0% of 40" in text and "beyond 30 m 100%" in text and "never judged" in text
    assert _where_unavailable({"chains": {"robust": {"summary": {"clean": {}}}}}) == ""  # older metrics: nothing


def test_the_page_shows_availability_under_attack_and_each_chain_per_trajectory_and_reads_back_from_json() -> None:
    """The safety-index table's "available frames" (a Stanford-ESA row's nominal, MI and HMI over its frames) and the
    lowest of them per chain; every chain per trajectory with the flags and availability of the attack that found
    its worst; and the page drawn from the metrics JSON (keys sorted) is the page drawn from the stage's dict."""
    import json

    from stages.config import params as params_mod
    from stages.pages.integrity import lead

    p = params_mod.build(params_mod.compose("default"))
    m = _integrity({"robust": None, "standard": 0.05, "control": 0.05})
    page = lead(m, p)
    index = [line for line in page.splitlines() if line.startswith("| robust   | 0.05")][0]
    assert index.rstrip(" |").endswith("5 of 10")  # 5 nominal, 5 unavailable
    assert "Fewest available frames under attack: shipped 5 of 10 (first at eps 0.05)" in page
    rows = [line for line in page.splitlines() if "| t0 " in line]
    assert [r.split("|")[1].strip() for r in rows] == ["robust", "standard", "control"]
    assert all(r.split("|")[-3].strip() == "7" and r.split("|")[-2].strip() == "62.5" for r in rows)
    assert lead(json.loads(json.dumps(m, sort_keys=True)), p) == page


def test_the_full_grid_page_says_how_many_trajectories_it_flew() -> None:
    from stages.config import params as params_mod
    from stages.pages.integrity import grid_head

    p = params_mod.build(params_mod.compose("default"))
    m = _integrity({"robust": None, "standard": 0.05, "control": 0.05})
    assert "control, every trajectory and every eps" in grid_head(m, p)
    for chain in m["chains"].values():
        chain["trajectories"] = 1
    head = grid_head(m, p)
    assert f"the first 1 of the {p.evaluate.trajectories} eval_render trajectories only (`--trajectories 1`)" in head


def test_an_eps_a_chain_did_not_fly_is_a_row_of_dashes_not_nan() -> None:
    """The safety-index table: the eps after a chain broke say so, with "-" in every other column."""
    from pipeline.report.markdown import markdown_table
    from stages.pages.integrity import INDEX_COLUMNS, _safety_index

    flown = {
        "max_error_al": 1.4,
        "max_error_al_single": 0.3,
        "max_error_pl": 2.0,
        "final_error_max_m": 1.5,
        "failed": 1,
        "trajectories": 2,
        "worst_attacker": "capture",
        "hmi_trajectories": {"value": 0.5, "ci": [0.01, 0.99]},
        "stanford": {"nominal": 10},
    }
    summary = {"per_eps": {"0.05": flown}, "breaking_eps": 0.05, "clean": {"stanford": {"nominal": 12}}}
    index, _ = _safety_index({"eps": [0.05, 0.1]}, {"standard": {"summary": summary}})
    assert list(index[0]) == list(INDEX_COLUMNS) and list(index[1]) == list(INDEX_COLUMNS)
    table = markdown_table(index)
    assert "nan" not in table and "not flown (broken at 0.05)" in table


def test_a_breaking_point_is_a_bracket_and_a_ratio_is_judged_only_where_the_brackets_agree() -> None:
    """(survived, broke] from the eps flown; "met" needs the shipped chain to have survived twice the eps where the other
    broke, "missed" needs it to have broken at or below twice the eps where the other held (the other's breaking point
    lies above its survived eps, so the ratio is then below two); otherwise "not shown"."""
    from stages.pages.integrity import bracket_text, breaking_bracket, ratio_verdict

    assert breaking_bracket({"0.01": {}, "0.05": {}, "0.1": {}}, 0.1) == (0.05, 0.1)
    assert breaking_bracket({"0.01": {}, "0.2": {}}, None) == (0.2, None)  # never broke: survived the last eps
    assert breaking_bracket({"0.01": {}}, 0.01) == (None, 0.01)  # broke at the first eps
    assert [bracket_text(b) for b in ((0.07, 0.1), (0.2, None), (None, 0.01))] == [
        "(0.07, 0.1]",
        "none (survived 0.2)",
        "<= 0.01",
    ]
    assert ratio_verdict((0.07, 0.1), (0.07, 0.1), 2.0) == ("**missed**", "ratio above 0.70, below 1.43")
    assert ratio_verdict((0.1, 0.14), (0.07, 0.1), 2.0) == (
        "**missed**",
        "ratio above 1.00, below 2.00",
    )  # 0.14 <= 2 x 0.07
    assert ratio_verdict((0.1, 0.15), (0.07, 0.1), 2.0)[0] == "not shown"
    assert ratio_verdict((0.2, None), (0.07, 0.1), 2.0) == ("met", "ratio above 2.00")
    verdict, text = ratio_verdict((0.14, 0.2), (0.07, 0.1), 2.0)  # the point values alone (0.2 vs 0.1) would say met
    assert verdict == "not shown" and "above 1.40, below 2.86" in text
    assert ratio_verdict((0.2, None), (0.2, None), 2.0)[0] == "not shown"  # the other never broke


def test_the_pl_parts_replay_the_flown_pl_and_leaving_a_part_out_only_adds_availability(tracks) -> None:
    """pipeline/evaluation/availability.py on the toy defended chain's clean flights: the first part is the trace's
    PL exactly (the replay is the flight) and its availability the clean row's; each part left out lowers the PL
    frame by frame (the ramp and the transients are >= 0), so the availability can only grow; the page names every
    part with its interval."""
    from pipeline.evaluation.availability import PARTS, availability_parts, pl_parts
    from stages.pages.integrity import _availability_parts

    d = Defended(DefenseSettings(), EXACT, NOISE, PERSISTENT)
    flights = fly_campaign(ToyOnboard(ToyPose()), ToyPose(), d, tracks, _campaign([0.004], False, True))
    parts = [pl_parts(d, fl.pose, fl.prob, t.R_cam, t.u) for fl, t in zip(flights.clean, tracks)]
    for fl, p in zip(flights.clean, parts):
        assert np.array_equal(p[PARTS[0]], fl.trace.pl)
        started = np.isfinite(p[PARTS[0]])
        assert started.sum() > 30
        for key in PARTS[1:]:
            assert (p[key][started] <= p[PARTS[0]][started]).all()
        assert (p[PARTS[3]][started] <= p[PARTS[1]][started]).all()
        assert (p[PARTS[1]] < p[PARTS[0]])[started][-5:].all()  # the ramp has grown by the goal
    out = availability_parts([fl.frames for fl in flights.clean], parts, 0)
    assert out[PARTS[0]] == flights.clean_row["availability"]
    values = [out[k]["value"] for k in PARTS]
    assert values[0] <= min(values[1:]) and values[3] >= max(values[1:3])
    text = _availability_parts(out)
    assert all(k in text for k in PARTS) and "bounds nothing" in text
    with pytest.raises(ValueError, match="1 flights' records for 2"):
        availability_parts([flights.clean[0].frames], parts)


def test_a_wider_docking_tolerance_only_adds_availability_and_the_mission_s_is_the_clean_row(tracks) -> None:
    """tolerance_availability on the toy defended chain's clean flights: at the mission's tolerance it is the clean
    row's availability, it never falls as the tolerance widens (the AL only grows) and reaches 100% once the
    tolerance exceeds every PL; a fixed AL has no tolerance to widen; the page says from which tolerance the target
    is met, sorted by value even where the JSON holds "10" before "2"."""
    import dataclasses

    from pipeline.evaluation.availability import tolerance_availability
    from stages.pages.integrity import _tolerances

    d = Defended(DefenseSettings(), EXACT, NOISE, PERSISTENT)
    flights = fly_campaign(ToyOnboard(ToyPose()), ToyPose(), d, tracks, _campaign([0.004], False, True))
    frames = [fl.frames for fl in flights.clean]
    worst = max(float(np.nanmax(np.where(np.isfinite(f.pl), f.pl, np.nan))) for f in frames)
    grid = (0.02, PERSISTENT.tolerance, worst + 1.0)
    out = tolerance_availability(frames, PERSISTENT, grid)
    assert out[f"{PERSISTENT.tolerance:g}"] == flights.clean_row["availability"]
    values = [out[f"{t:g}"]["value"] for t in grid]
    assert values == sorted(values) and values[0] < values[-1]
    unbounded = [dataclasses.replace(f, alert=np.full(len(f.pl), np.inf)).available for f in frames]
    assert values[-1] == pytest.approx(np.concatenate(unbounded).mean())  # only what no AL makes available is not
    assert tolerance_availability(frames, dataclasses.replace(PERSISTENT, fixed=5.0)) == {}
    with pytest.raises(ValueError, match="must be > 0"):
        tolerance_availability(frames, PERSISTENT, (0.0,))
    record = {"mission_tolerance_m": 1.0, "availability": {k: out[k] for k in reversed(list(out))}}
    text = _tolerances(record)
    assert text.index(f"{grid[0]:g} m") < text.index(f"{grid[-1]:g} m") and "the mission's is 1 m" in text
    assert ("target is met from" in text) == any(v >= 0.99 for v in values)
    ten = {"10": {"value": 1.0, "ci": [1.0, 1.0], "n": 2}, "2": {"value": 0.5, "ci": [0.4, 0.6], "n": 2}}
    assert "from a 10 m tolerance" in _tolerances({"mission_tolerance_m": 1.0, "availability": ten})
    assert _tolerances(None) == "" and _tolerances({"mission_tolerance_m": 1.0, "availability": {}}) == ""


def test_how_a_defended_chain_broke_says_whether_it_failed_inside_the_trusted_start(tracks) -> None:
    """The planted 2 m capture breaks the defended toy at eps 0.03 where AL_p falls below 2 m, near the goal: its
    first failing frame lies long after the filter's start, outside a 20-frame trusted start and inside a 1000-frame
    one; at an eps where nothing failed, or with no breaking point, there is nothing to say; the page names them."""
    from pipeline.evaluation.campaign import how_it_broke
    from stages.pages.integrity import _how_it_broke

    flights = _fly(tracks, [0.004, 0.03], stop=False, defended=True)
    rows = how_it_broke(flights, 0.03, 20)
    assert {r["trajectory"] for r in rows} == {"t0", "t1"} and {r["attacker"] for r in rows} >= {"capture/lateral 2 m"}
    for r in rows:
        assert r["start_frame"] == 0 and r["first_failure_frame"] > 25 and not r["inside_trusted_start"]
    assert all(r["inside_trusted_start"] for r in how_it_broke(flights, 0.03, 1000))
    assert how_it_broke(flights, 0.004, 20) == [] and how_it_broke(flights, None, 20) == []
    summary = {"breaking_eps": 0.03, "how_it_broke": rows}
    text = _how_it_broke({"robust": {"summary": summary}, "control": {"summary": {"breaking_eps": 0.1}}})
    assert (
        f"0 of {len(rows)} failed flights first fail inside the trusted-start frames" in text and "t0 (capture" in text
    )
    assert _how_it_broke({"robust": {"summary": {"breaking_eps": None}}}) == ""


def test_the_recover_hold_script_splits_the_pl_as_the_library_does(tracks) -> None:
    """scripts/recover_hold.py's per-frame record on the toy defended chain's clean flight: no PL before the filter
    starts, afterwards every part >= 0 and together no more than the PL (the bias adds the ramp and the transients
    over the world axes in quadrature: each part is what leaving it out removes), the same split as
    pipeline/evaluation/availability.py's pl_parts (its PL without the ramp, without the transients)."""
    from script_loader import load_script

    from pipeline.evaluation.availability import PARTS, pl_parts
    from pipeline.geometry.rotations import sixd_to_matrix

    record = load_script("recover_hold")._record
    d = Defended(DefenseSettings(), EXACT, NOISE, PERSISTENT)
    flight = fly_campaign(ToyOnboard(ToyPose()), ToyPose(), d, tracks, _campaign([0.004], False, True)).clean[0]
    t = tracks[0]
    parts, live = pl_parts(d, flight.pose, flight.prob, t.R_cam, t.u), d.defense()
    rows = []
    for i, pose in enumerate(np.asarray(flight.pose, np.float64)):
        out = live.step(pose[:3], float(flight.prob[i]), t.R_cam[i], t.u[i], sixd_to_matrix(pose[None, 3:])[0])
        rows.append(record(live, out))
    started = [i for i, r in enumerate(rows) if r["pl"] is not None]
    assert started and all(not np.isfinite(parts[PARTS[0]][i]) for i in range(started[0]))
    assert sum(r["ramp"] > 0 for r in rows if r["pl"] is not None) > 10
    for i in started:
        r = rows[i]
        assert min(r["noise"], r["ramp"], r["transients"], r["offset"]) >= 0
        assert -1e-9 <= r["pl"] - (r["noise"] + r["ramp"] + r["transients"] + r["offset"]) <= 1e-9 + 0.05 * r["pl"]
        assert r["pl"] == pytest.approx(parts[PARTS[0]][i])
        assert r["pl"] - r["ramp"] == pytest.approx(parts[PARTS[1]][i])
        assert r["pl"] - r["transients"] == pytest.approx(parts[PARTS[2]][i])


def test_the_recover_hold_script_refuses_a_json_path_in_a_missing_folder(monkeypatch, tmp_path, capsys) -> None:
    """`--json` into a folder that does not exist stops with one line naming it, before anything is flown."""
    from script_loader import load_script

    script = load_script("recover_hold")
    monkeypatch.setattr("sys.argv", ["recover_hold.py", "--json", str(tmp_path / "nowhere" / "rows.json")])
    with pytest.raises(SystemExit) as stop:
        script.main()
    assert stop.value.code == 2 and f"the folder {tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err

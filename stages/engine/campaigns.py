"""The integrity campaign of `rpod robustness` (the default profile's ladder) and `rpod integrity` (optional/dvc.yaml:
the full grid): the eval_render trajectories as Tracks told their commands, a Campaign per chain from params.integrity,
and pipeline.evaluation.campaign flown on three chains: the shipped one (robust model, its detector and defense), the
standard one (its own detector and defense) and the undefended robust control (the shipped pose network alone); each
chain's safety evidence (`safety_summary`), its descriptive integrity rows, the assumptions they rest on, and the
integrity figure (the shipped chain at the largest eps it flew).
"""

from __future__ import annotations

import dataclasses
import json
import time
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import file_hash
from pipeline.seeds import seed_for
from stages.artifacts.models import load_chain
from stages.artifacts.paths import PAPER, SHIPPED
from stages.artifacts.readers import chaser_motion, read_eval_render
from stages.config.evaluation import IntegrityAttacker
from stages.config.params import fingerprint
from stages.config.schema import Params
from stages.errors import StageError

CONTROL = "control"  # the undefended robust chain: the shipped pose network, no detector, no defense


def integrity_campaign(
    p: Params,
    shipped: Any,
    seed: int,
    full: bool = False,
    trajectories: int | None = None,
    shards: Path | None = None,
    fan_out: FanOut | None = None,
) -> dict[str, Any]:
    """The integrity campaign (pipeline.evaluation.campaign) on the three chains: the shipped one (`shipped`, a
    SafetyChain) on the first `integrity.trajectories` eval_render ones, the standard one and the undefended robust
    control on the first `integrity.comparison_trajectories` of those; each chain's safety evidence
    (`safety_summary`), its descriptive integrity rows, and the figure's data (the shipped chain). `full`: every
    attacker of the schema on every chain and trajectory at every eps (no stop at the breaking point);
    `trajectories` (with `full` only): the first N eval_render ones (None: all); `shards` (with `full` only): fly
    each chain one trajectory at a time, each trajectory's share kept in that folder, and reuse the shares a killed
    run left (`_fly_shards`); `fan_out` (with `shards` only): the engine that flies the missing shares, one
    `ShardWorker` job per trajectory (stages/integrity.py: stages/engine/pool.py `run` on the stage's engine settings;
    None: flown here, one after another).
    Returns {"fused_rows", "fused" (facts about the shipped defense), "integrity" (the metrics), "figure"}."""

    from pipeline.evaluation.integrity_runs import diagram_eps

    t0 = time.perf_counter()
    if full:
        p = full_grid(p)
    i = p.integrity
    if shards is not None and not full:
        raise ValueError("integrity_campaign: shards need the full grid (a ladder that stops cannot be split)")
    if fan_out is not None and shards is None:
        raise ValueError("integrity_campaign: fan_out flies shards: give the shards folder")
    tracks, bursts, info = integrity_tracks(p, shipped)
    trajectories = trajectories if full else i.trajectories
    tracks, bursts = tracks[:trajectories], bursts[:trajectories]
    paper = load_chain(p, PAPER)
    n = i.comparison_trajectories
    chains = [
        (SHIPPED.value, shipped, shipped.defended, len(tracks)),
        (PAPER.value, paper, paper.defended, n),
        (CONTROL, shipped, None, n),
    ]
    out: dict[str, Any] = {}
    figure = None
    for key, safety, defended, count in chains:
        k = len(tracks) if count is None else min(count, len(tracks))
        target = attack_target(safety.onboard, defended)
        out[key], flown = _fly_chain(p, seed, key, safety, defended, target, tracks[:k], bursts[:k], shards, fan_out)
        if key == SHIPPED.value:
            info.update(false_alarm_rate=flown.alarms.value, ci95_false_alarm=flown.alarms.ci())
            fused_rows = flown.fused_rows
            top = diagram_eps(flown.runs)
            figure = (flown.clean, [(a, runs, masks) for a, e, runs, masks in flown.runs if e == top], top)
    return {
        "fused_rows": fused_rows,
        "fused": info,
        "integrity": _integrity_metrics(p, shipped, out, info, time.perf_counter() - t0),
        "figure": figure,
    }


def full_grid(p: Params) -> Params:
    """The params of the full grid (`rpod integrity`): every attacker of the schema, the drifts from acquisition and
    from the end of the trusted start, no stop at a chain's breaking point, every trajectory on every chain."""
    i = dataclasses.replace(
        p.integrity,
        attackers=list(typing.get_args(IntegrityAttacker)),
        drift_start="both",
        stop_at_break=False,
        comparison_trajectories=None,
    )
    return dataclasses.replace(p, integrity=i)


def _fly_chain(
    p: Params,
    seed: int,
    key: str,
    safety: Any,
    defended: Any,
    target: Any,
    tracks: list[Any],
    bursts: list[Any],
    shards: Path | None = None,
    fan_out: FanOut | None = None,
) -> tuple[dict[str, Any], Any]:
    """One chain's campaign on `tracks` (with a progress bar) -> (its metrics record, the flown campaign); with
    `shards` (a folder) one trajectory at a time, each share kept there and reused by a later run (`_fly_shards`),
    the missing ones flown on `fan_out` (one `ShardWorker` job per trajectory) or, without it, here."""
    from tqdm import tqdm

    from pipeline.evaluation.campaign import assemble, fly_campaign, fly_track

    k = len(tracks)
    campaign = campaign_for(p, seed, defended, bursts)
    steps = len(campaign.eps) * sum(len(t) for t in tracks) if campaign.plans else 0
    fly_all = None if fan_out is None else _on_engine(fan_out, shard_setup(p, safety, defended, seed), tracks, bursts)
    with tqdm(  # the plans step every track's frame together; shards one track at a time (`_steps`)
        total=k * ("burst" in p.integrity.attackers) + (steps // max(k, 1) if shards is None else steps),
        desc=f"robustness (integrity, {key})" if shards is None else f"integrity ({key}, shards in {shards})",
        unit="step",
        dynamic_ncols=True,
    ) as bar:
        if shards is None:
            flown = fly_campaign(safety.onboard, target, defended, tracks, campaign, lambda: bar.update(1))
        else:  # one trajectory at a time, each on item g of the attacks' streams
            shares = _fly_shards(
                _shard_base(p, seed, key, safety),
                tracks,
                lambda g: campaign_for(p, seed, defended, [bursts[g]], index=g),
                lambda t, c: fly_track(safety.onboard, target, defended, t, c, lambda: bar.update(1)),
                shards,
                bar,
                fly_all,
            )
            flown = assemble(tracks, shares, campaign)
    return _record(safety, defended, flown, tracks, seed), flown


def _record(safety: Any, defended: Any, flown: Any, tracks: list[Any], seed: int) -> dict[str, Any]:
    """A chain's metrics record of its flown campaign: the safety summary (with, for a defended chain, where its
    clean availability goes: the PL's parts replayed on the clean flights), the descriptive rows, the clean row."""
    from pipeline.evaluation.availability import clean_availability_parts, tolerance_availability
    from pipeline.evaluation.campaign import how_it_broke, safety_summary
    from pipeline.evaluation.integrity_runs import worst_hmi

    summary = safety_summary(flown)
    if defended is not None:
        summary["clean"]["availability_parts"] = clean_availability_parts(defended, flown.clean, tracks, seed)
        if defended.alert is not None:
            frames = [fl.frames for fl in flown.clean]
            summary["clean"]["availability_by_tolerance"] = {
                "mission_tolerance_m": defended.alert.tolerance,
                "availability": tolerance_availability(frames, defended.alert, seed=seed),
            }
        summary["how_it_broke"] = how_it_broke(flown, summary["breaking_eps"], defended.motion.trusted_start)
    return {
        "model": safety.name,
        "model_hash": safety.pose_hash,
        "defended": defended is not None,
        "trajectories": len(tracks),
        "summary": summary,
        "rows": flown.rows,
        "worst_hmi": worst_hmi(flown.rows),
        "clean": flown.clean_row,
        "false_alarm_rate": flown.alarms.value,
        "ci95_false_alarm": flown.alarms.ci(),
        "calibration_unmet": [] if defended is None else list(safety.calibration.unmet),
    }


def _shard_base(p: Params, seed: int, key: str, safety: Any) -> dict[str, Any]:
    """What every share of chain `key` depends on besides its trajectory: the params, the chain's files, the seed."""
    return {
        "params": json.loads(json.dumps(dataclasses.asdict(p), default=str)),
        "files": [file_hash(f) for f in safety.files if f is not None],
        "chain": key,
        "seed": seed,
    }


def _fly_shards(
    base: dict[str, Any],
    tracks: list[Any],
    campaign_of: Callable[[int], Any],
    fly: Callable[[Any, Any], Any],
    folder: Path,
    bar: Any,
    fly_all: Callable[[list[int], Callable[[int, Any], None]], None] | None = None,
) -> list[Any]:
    """Each track's share of a chain's campaign, in order: read from `folder` when its key (`base`, the track's
    name, index and data) matches (stages/artifacts/shards.py: a killed run resumes), else flown and written there
    as soon as it is (a kill loses only the shares in flight): by `fly_all(missing, done)` (the engine, `_on_engine`:
    it flies the tracks at the indices `missing` in any order and calls `done(g, share)` here as each finishes), or
    without it by `fly(track, campaign_of(g))` one after another. `bar` advances by a whole trajectory's steps for a
    share read or flown by `fly_all` (`fly` advances it itself)."""
    import hashlib

    from stages.artifacts.shards import read_shard, shard_path, write_shard

    shares: list[Any] = [None] * len(tracks)
    keys: dict[int, tuple[Path, str]] = {}
    for g, track in enumerate(tracks):
        data = hashlib.sha256(track.images.tobytes() + np.asarray(track.labels).tobytes() + track.u.tobytes())
        name = fingerprint({**base, "track": track.name, "index": g, "data": data.hexdigest()})
        path = shard_path(folder, base["chain"], track.name)
        shares[g] = read_shard(path, name)
        if shares[g] is None:
            keys[g] = (path, name)
        else:
            bar.update(_steps(campaign_of(g), track))

    def done(g: int, share: Any) -> None:
        write_shard(*keys[g], share)
        shares[g] = share

    missing = list(keys)
    if fly_all is None:
        for g in missing:
            done(g, fly(tracks[g], campaign_of(g)))
    else:

        def finished(g: int, share: Any) -> None:
            done(g, share)
            bar.update(_steps(campaign_of(g), tracks[g]))

        fly_all(missing, finished)
    return shares


def _steps(campaign: Any, track: Any) -> int:
    """A trajectory's steps on the progress bar: one for the burst, one per attacked frame and eps of the plans."""
    return int(campaign.burst is not None) + (len(campaign.eps) * len(track) if campaign.plans else 0)


FanOut = Callable[[Callable[[Any], Any], Any, list[Any], Callable[[int, Any], None]], list[Any]]
"""The engine `rpod integrity` flies its missing shares on: `fan_out(worker_cls, setup, jobs, progress)` builds
`worker_cls(setup)` once per worker, runs every job and calls `progress(i, result)` in the driver as job i finishes
(stages/engine/pool.py `run` on the stage's engine settings, bound by stages/integrity.py)."""


@dataclass(frozen=True)
class ShardSetup:
    """What one ShardWorker holds: where the chain's model files are, its defense, the campaign's params and seed."""

    params: Params  # the campaign's typed params (the full grid's `integrity`; `device`: where the chain runs)
    root: str  # the folder holding the chain's models/, as an absolute path (a worker may run elsewhere)
    model: str  # the chain's pose model: "robust" (the shipped chain and the undefended control) or "standard"
    defended: Any  # pipeline.defense.chain.Defended as the driver loaded it; None: the undefended control
    seed: int  # the campaign's seed (each trajectory's attacks draw on item `ShardJob.index` of its streams)
    torch_threads: int | None = None  # torch threads of this worker; None: left as set up

    def on_ray(self, threads: int) -> ShardSetup:
        """This setup for a Ray worker: the chain on the CPU (Ray workers hold no GPU), `threads` torch threads."""
        return dataclasses.replace(self, params=dataclasses.replace(self.params, device="cpu"), torch_threads=threads)


@dataclass(frozen=True)
class ShardJob:
    """One trajectory of a chain's campaign: its index among the eval_render ones, the track and its bursts."""

    index: int  # g: the trajectory's place (its attacks' seed streams, its shard's key)
    track: Any  # pipeline.evaluation.integrity_runs.Track
    bursts: list[tuple[int, int]]  # the (start, stop) frames of its bursts


def shard_setup(p: Params, safety: Any, defended: Any, seed: int) -> ShardSetup:
    """The ShardSetup of a chain the driver loaded (`safety`, a SafetyChain from ROOT/models/) flown against
    `defended` (None: the undefended control): the workers load the same model files."""
    return ShardSetup(p, str(Path(safety.files[0]).resolve().parent.parent), safety.name, defended, seed)


class ShardWorker:
    """One chain (pose network, SHAP and detector, loaded once per engine worker on its setup's device):
    `run(ShardJob)` flies that trajectory's share of the campaign (pipeline.evaluation.campaign.fly_track, every
    eps of the ladder) on the Campaign of its index, as the driver would -> the TrackFlights pickled (`_on_engine`
    unpickles it: Ray hands numpy arrays back read-only, zero-copy, and a read-only array pickles to other bytes,
    so the shards written would differ from the in-process ones)."""

    def __init__(self, setup: ShardSetup) -> None:
        if setup.torch_threads:
            import torch

            torch.set_num_threads(setup.torch_threads)
        chain = load_chain(setup.params, setup.model, setup.root, defended=False)
        self.onboard, self.defended = chain.onboard, setup.defended
        self.target = attack_target(chain.onboard, setup.defended)
        self.params, self.seed = setup.params, setup.seed

    def run(self, job: ShardJob) -> bytes:
        import pickle

        from pipeline.evaluation.campaign import fly_track

        track = job.track
        if not track.images.flags.writeable:  # a Ray job's arrays arrive read-only: torch takes a writable copy
            track = dataclasses.replace(track, images=np.array(track.images), labels=np.array(track.labels))
        campaign = campaign_for(self.params, self.seed, self.defended, [job.bursts], index=job.index)
        share = fly_track(self.onboard, self.target, self.defended, track, campaign)
        return pickle.dumps(share, protocol=pickle.HIGHEST_PROTOCOL)

    def close(self) -> None:
        pass


def _on_engine(
    fan_out: FanOut, setup: ShardSetup, tracks: list[Any], bursts: list[Any]
) -> Callable[[list[int], Callable[[int, Any], None]], None]:
    """`_fly_shards`' `fly_all` on `fan_out`: one ShardJob per missing trajectory, each share handed to `done` as
    its job finishes (the engine's progress call, in the driver)."""

    import pickle

    def fly_all(missing: list[int], done: Callable[[int, Any], None]) -> None:
        if missing:
            jobs = [ShardJob(g, tracks[g], bursts[g]) for g in missing]
            fan_out(ShardWorker, setup, jobs, lambda i, share: done(missing[i], pickle.loads(share)))

    return fly_all


def attack_target(onboard: Any, defended: Any) -> Any:
    """What a chain's attacks differentiate (`onboard`: an OnboardChain): the defended chain's pose network and
    detector frame by frame (a PerFrameChain), the undefended control's (`defended` None) pose network alone."""
    from pipeline.attacks.adaptive import PerFrameChain

    return onboard.model if defended is None else PerFrameChain(onboard.model, onboard.shap, onboard.detector)


def _integrity_metrics(
    p: Params, shipped: Any, out: dict[str, Any], info: dict[str, Any], seconds: float
) -> dict[str, Any]:
    """robustness.json's "integrity": every chain's record (`out`), the breaking points, the shipped chain's rows,
    worst HMI and clean run, and the campaign's settings and assumptions."""
    i = p.integrity
    return {
        "chains": out,
        "breaking_eps": {key: v["summary"]["breaking_eps"] for key, v in out.items()},
        "rows": out[SHIPPED.value]["rows"],
        "worst_hmi": out[SHIPPED.value]["worst_hmi"],
        "clean": out[SHIPPED.value]["clean"],
        "eps": [float(e) for e in i.eps],
        "attackers": list(i.attackers),
        "assumptions": _assumptions(p, shipped),
        "alert_limit_m": i.alert_limit_m,
        "alert_limit_kind": i.alert_limit_kind,
        "collision_range_m": i.collision_range_m,
        "burst": {
            "steps": i.burst_steps,
            "restarts": i.burst_restarts,
            "lambdas": [float(v) for v in i.burst_lambdas],
            "cap": i.burst_cap,
            "objective": i.burst_objective,
            "hinge": i.burst_hinge,
            "bursts": info["bursts"],
            "burst_length": info["burst_length"],
        },
        "capture": {"initial_m": [float(b) for b in i.capture_initial], "rate_m": i.capture_rate},
        "drift": {
            "start": i.drift_start,
            "gate_fraction": i.drift_gate_fraction,
            "undefended_rate_m": i.undefended_drift_rate,
        },
        "frame_steps": i.frame_steps,
        "stop_at_break": i.stop_at_break,
        "seconds": seconds,
    }


def campaign_for(p: Params, seed: int, defended: Any, bursts: list[list[tuple[int, int]]], index: int = 0) -> Any:
    """The Campaign of params.integrity against `defended` (None: the undefended control, whose drift grows by
    integrity.undefended_drift_rate per frame): the captures per direction and initial bias from frame 0, the
    drifts from integrity.drift_start (both: one from each start, named "drift/<direction> <start>"), the burst on
    `bursts`, the AL of integrity.alert_limit_kind beside the single-frame one; its attacks draw on item `index` of
    their streams (a trajectory's own in the sharded grid)."""
    import dataclasses as dc

    from pipeline.attackers.drift import STARTS, start_frame
    from pipeline.evaluation.campaign import Campaign, Plan
    from stages.config.build import (
        alert_limit_settings,
        burst_attacker,
        capture_settings,
        defense_settings,
        drift_settings,
        frame_attack,
    )

    i = p.integrity
    motion = defense_settings(p.defense, 0.5)[1]  # the filter settings (trusted_start) the drift's start counts on
    starts = STARTS if i.drift_start == "both" else (i.drift_start,)
    plans = []
    for name in i.attackers:
        kind, _, direction = name.partition("/")
        if kind == "capture":
            plans += [Plan(f"{name} {b:g} m", capture_settings(p, direction, b), 0) for b in i.capture_initial]
        elif kind == "drift":
            drift = drift_settings(p, direction)
            if defended is None:
                drift = dc.replace(drift, max_rate=float(i.undefended_drift_rate))
            named = len(starts) > 1
            plans += [Plan(f"{name} {s}" if named else name, drift, start_frame(s, motion)) for s in starts]
    return Campaign(
        [float(e) for e in i.eps],
        plans,
        frame_attack(p),
        seed_for(seed, "robustness.drift", index),
        burst_attacker(p, seed_for(seed, "robustness.burst", index)) if "burst" in i.attackers else None,
        bursts,
        alert_limit_settings(p),
        alert_limit_settings(p, "single_frame"),
        p.robustness.batch_size,
        p.robustness.harm_m,
        seed,
        i.stop_at_break,
    )


def _assumptions(p: Params, shipped: Any) -> dict[str, Any]:
    """What every integrity row rests on, for the reports: the trusted-start frames, the shipped detector (fusion,
    threshold), the noise model, the dynamics and execution error of the trajectories, the AL kind."""
    x, d = p.guidance.execution, p.defense
    return {
        "trusted_start_frames": d.trusted_start,
        "position_noise_m": d.position_noise,
        "position_noise_scale": d.position_noise_scale,
        "detector": {"fusion": d.fusion, "threshold": float(shipped.defended.settings.threshold)},
        "noise_model": "pose-network noise and bias per range bin fitted on the validation trajectories "
        f"(defense.noise_bins = {d.noise_bins}), inflated x{shipped.calibration.inflation:g}, the PL holding "
        f"{shipped.defended.motion.correlated_error:g} of one measurement's variance as shared by the start frames "
        "(rpod calibrate)",
        "execution": {
            "scale_std": x.scale_std,
            "noise_std_m": x.noise_std,
            "mean_motion_rad_s": x.mean_motion,
            "frame_interval_s": x.frame_interval,
            "approach": x.approach,
        },
        "dynamics": "open loop: each evaluation trajectory flown along its planned commands with execution error "
        "and Clohessy-Wiltshire motion; the chain is told the commands only",
        "alert_limit_kind": p.integrity.alert_limit_kind,
        "integrity_risk": d.integrity_risk,
        "cusum_reference": d.cusum_reference,
    }


def integrity_tracks(p: Params, safety: Any) -> tuple[list[Any], list[list[tuple[int, int]]], dict[str, Any]]:
    """(the eval_render trajectories as Tracks told their commands, the bursts of each, facts about the shipped
    chain's defense `safety`)."""
    from pipeline.evaluation.integrity_runs import Track
    from pipeline.evaluation.robustness import burst_schedule

    images, poses, _ = read_eval_render(p)
    labels = poses[TARGET].to_numpy(np.float64)
    _, commands = chaser_motion(poses)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])]
    tracks = [Track(f"t{g}", images[ix], labels[ix], commands[ix]) for g, ix in enumerate(trajs)]
    # the chain's defense as `rpod calibrate` recorded it (the noise model fitted on validation trajectories)
    defended, cal = safety.defended, safety.calibration
    length, r = p.integrity.burst_length, p.robustness
    try:
        bursts = [burst_schedule(len(ix), length, r.burst_every) for ix in trajs]
    except ValueError as e:
        raise StageError(f"params.yaml robustness.burst_every / integrity.burst_length: {e}") from None
    info = {
        "trajectories": len(trajs),
        "bursts": sum(len(b) for b in bursts),
        "burst_length": length,
        "burst_every": r.burst_every,
        "noise_model": defended.noise.as_dict(),
        "gate": defended.motion.gate,
        "gate_false_alarm": defended.motion.false_alarm,
        "noise_inflation": cal.inflation,
        "fusion": defended.settings.fusion,
        "calibration_unmet": list(cal.unmet),
        "noise_fitted_on": "validation trajectories (models/defense.json, rpod calibrate)",
    }
    return tracks, bursts, info

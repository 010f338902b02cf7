"""`rpod bound`: issue 40's integrity bound under the attacker's capacity -> reports/integrity_bound.md and
reports/metrics/bound.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of the default
`dvc repro`: on the default profile (10 trajectories, 3 eps, 2 attackers and the checks-only one, 2 chains, stride 10)
its programs took 27 minutes and the whole stage 31 on the 2-core machine while the test suite shared it for 12 of
them (reports/metrics/bound.json, seconds per chain; the checks-only attacker adds about 5 of the 27).

Per chain of `bound.models` (loaded through the one door, stages/artifacts/models.py `load_chain`) and each of the
first `bound.trajectories` eval_render trajectories: pipeline/evaluation/integrity_bound.py `bound_track` at each eps
of `bound.eps`, with the chain's attacker capacity F(eps, range) read from datasets/capacity/ (`rpod train --robust`,
pipeline/formats/capacity.py), the detector blind, the alert limit of params (the one the defense file records); then
the largest indices over trajectories, the share of target frames whose bound exceeds AL (95% interval bootstrapped
over trajectories) and, on `bound.certify_frames` frames of the first trajectory, the interval-bound certificate
beside the capacity; once per trajectory the attacker limited by the checks alone (no capacity, the trusted frames
spared), whose replayed errors give the ceiling on the availability of any protection level sound against it;
beside the bound, the largest error / AL the image-space attackers of `rpod robustness` reached
(reports/metrics/robustness.json, when present); and per eps the worst trajectory's worst sequence pursued in images by
a targeted attack (the lean suite's APGD budget, `suite.steps`) and flown through the real chain
(pipeline/evaluation/bound_images.py), which measures how much of the bound images reach.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import typer

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import atomic_write_text, read_json
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import BOUND_METRICS, BOUND_REPORT, CAPACITY, ROBUSTNESS_METRICS
from stages.artifacts.readers import read_eval_render
from stages.config.build import alert_limit_settings
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.bound import bound_page


def main(params: Params) -> None:
    """The integrity bound of each chain of bound.models on the eval_render trajectories; its page and metrics."""
    from pipeline.evaluation.integrity_runs import Track

    b = params.bound
    images, poses, _ = read_eval_render(params)
    labels = poses[TARGET].to_numpy(np.float64)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])]
    tracks = [Track(f"t{g}", images[ix], labels[ix]) for g, ix in enumerate(trajs[: b.trajectories])]
    eps = sorted(float(e) for e in b.eps)
    chains = {model: _chain(params, model, tracks, eps) for model in b.models}
    for model, chain in chains.items():
        chain["empirical"] = _empirical(model, eps)
        chain["realized"] = _realized(params, model, chain, tracks, eps)
    metrics = {
        "eps": eps,
        "stride": b.stride,
        "trajectories": len(tracks),
        "frames": int(sum(len(t) for t in tracks)),
        "chains": chains,
    }
    write_metrics(BOUND_METRICS, metrics, params.profile_name)
    atomic_write_text(BOUND_REPORT, bound_page(metrics))
    seconds = sum(c["seconds"] for c in chains.values())
    typer.echo(
        f"bound: {len(chains)} chains x {len(tracks)} trajectories x {len(eps)} eps in {seconds:.0f} s "
        f"-> {BOUND_REPORT}"
    )


def _empirical(model: str, eps: list[float]) -> dict[str, float | None]:
    """Per eps ("%g"): the largest trusted error / AL the image-space attackers of `rpod robustness` reached on the
    chain (reports/metrics/robustness.json, its integrity campaign; None where it did not fly that eps or the file is
    absent), to set beside the bound."""
    if not ROBUSTNESS_METRICS.exists():
        return {f"{e:g}": None for e in eps}
    chains = read_json(ROBUSTNESS_METRICS).get("integrity", {}).get("chains", {})
    flown = chains.get(model, {}).get("summary", {}).get("per_eps", {})
    return {f"{e:g}": flown.get(f"{e:g}", {}).get("max_error_al") for e in eps}


def _realized(params: Params, model: str, chain: dict[str, Any], tracks: list[Any], eps: list[float]) -> dict[str, Any]:
    """Per eps ("%g"): the worst trajectory's worst sequence (the largest upper / AL) realised in images by the
    targeted attack (the lean suite's APGD budget: suite.steps, restarts and starts) and flown through the real chain
    (pipeline/evaluation/bound_images.py `realize_worst`)."""
    from tqdm import tqdm

    from pipeline.evaluation.bound_images import RealizeSettings, realize_worst
    from pipeline.seeds import seed_for

    caps, _ = _capacities(model, eps)
    safety, limit, out = load_chain(params, model), alert_limit_settings(params), {}
    by_name = {t.name: t for t in tracks}
    s = params.suite
    with tqdm(total=len(eps), desc=f"bound in images ({model})", unit="eps") as bar:
        for i, e in enumerate(eps):
            seed = seed_for(params.seed, "bound", len(eps) * params.bound.models.index(model) + i)
            settings = RealizeSettings(s.steps, s.restarts, tuple(s.starts), params.bound.batch_size, seed)
            worst = chain["per_eps"][f"{e:g}"]["bound"]["worst_trajectory"]
            if worst is None:
                bar.update(1)
                continue
            row = next(t for t in chain["tracks"] if t["name"] == worst)
            out[f"{e:g}"] = realize_worst(
                safety.onboard,
                safety.defended,
                by_name[worst],
                caps,
                e,
                limit,
                int(row["per_eps"][f"{e:g}"]["bound"]["frame"]),
                settings,
            )
            bar.update(1)
    return out


def _capacities(model: str, eps: list[float]) -> tuple[list[Any], dict[str, Any]]:
    """The fitted capacities F(eps, range) of `model` in datasets/capacity/ and their meta; a StageError when the
    files are missing or measured below the largest eps asked."""
    from pipeline.formats.capacity import capacity_paths, read_capacity

    if not capacity_paths(CAPACITY, model)[1].is_file():
        raise StageError(f"{CAPACITY}: no capacity of the {model} model; run `rpod train --robust` (dvc repro robust)")
    _, caps, meta = read_capacity(CAPACITY, model)
    if max(eps) > max(c.eps for c in caps):
        raise StageError(
            f"params.yaml bound.eps: {max(eps):g} is above every eps the {model} model's capacity was "
            f"measured at ({', '.join(f'{c.eps:g}' for c in caps)}; suite.capacity.eps)"
        )
    return caps, meta


def _chain(params: Params, model: str, tracks: list[Any], eps: list[float]) -> dict[str, Any]:
    """One chain's per-trajectory bounds, summary per eps and certificate (JSON-ready)."""
    from pipeline.evaluation.integrity_bound import certificate, checks_only_rates, first_over

    b = params.bound
    caps, meta = _capacities(model, eps)
    safety = load_chain(params, model)
    limit = alert_limit_settings(params)
    t0 = time.perf_counter()
    rows = _bound_tracks(params, model, safety, tracks, caps, eps, limit)
    per_eps = _per_eps(rows, eps)
    cert = certificate(safety.model, tracks[0], caps, eps, b.certify_frames) if b.certify_frames and tracks else None
    return {
        "model_hash": safety.pose_hash,
        "capacity": {
            "eps": [c.eps for c in caps],
            "quantile": caps[0].quantile,
            "margin": caps[0].margin,
            "edges": caps[0].edges.tolist(),
            "meta": meta,
        },
        "per_eps": per_eps,
        "first_over_al_eps": first_over(per_eps),
        "checks_only": checks_only_rates(rows),
        "tracks": rows,
        "certificate": cert,
        "seconds": time.perf_counter() - t0,
    }


def _bound_tracks(
    params: Params, model: str, safety: Any, tracks: list[Any], caps: list[Any], eps: list[float], limit: Any
) -> list[dict[str, Any]]:
    """`bound_track` of the chain `safety` on every trajectory (a progress bar over its programs); a StageError
    naming the trajectory when a range lies outside the capacity's bins or the solver finds no solution."""
    from tqdm import tqdm

    from pipeline.evaluation.integrity_bound import ATTACKERS, bound_track

    b = params.bound
    rows = []
    with tqdm(total=len(tracks) * (len(eps) * len(ATTACKERS) + 1), desc=f"bound ({model})", unit="program") as bar:
        for track in tracks:
            try:
                rows.append(
                    bound_track(
                        safety.onboard,
                        safety.defended,
                        track,
                        caps,
                        eps,
                        b.stride,
                        limit,
                        b.batch_size,
                        lambda: bar.update(1),
                    )
                )
            except ValueError as e:  # a range outside the capacity's bins
                raise StageError(
                    f"{CAPACITY} ({model}) on eval_render {track.name}: {e}; widen suite.capacity.edges"
                ) from None
            except RuntimeError as e:  # the conic solver gave no solution (pipeline/defense/bound.py)
                raise StageError(
                    f"rpod bound ({model}) on eval_render {track.name}: {e}; no bound for this chain (a larger "
                    f"bound.stride changes the target frames)"
                ) from None
    return rows


def _per_eps(rows: list[dict[str, Any]], eps: list[float]) -> dict[str, Any]:
    """Per eps (its %g name) the worst bound over the trajectories per attacker, with the rate of its frames over
    the alert limit (value, interval, frames)."""
    from pipeline.evaluation.integrity_bound import ATTACKERS, over_al_rate, worst_over_trajectories

    per_eps = {}
    for e in (f"{v:g}" for v in eps):
        worst = worst_over_trajectories(rows, e)
        for who in ATTACKERS:
            r = over_al_rate(rows, e, who)
            worst[who]["frames_over_al"] = {"value": r.value if r.n else None, "ci": r.ci(), "n": r.n}
        per_eps[e] = worst
    return per_eps

"""The integrity bound (pipeline/defense/bound.py) on evaluation trajectories with the shipped chain's defense.

For the first `--trajectories` eval_render trajectories (datasets/eval_render), the shipped chain
(models/pose_robust.pt, detector_robust.pt) reads every frame once; models/defense.json's defense runs
over them; then, at each eps, `worst_case` finds the worst trusted error at every `--stride`-th frame
(and the last) over shift sequences within a capacity F(eps, range) that pass every check (the
detector blind), replayed through the real defense. Prints per frame the bound (upper, achieved),
AL, PL and the safety indices, then a summary per eps: max upper / AL, max achieved / PL, the clean
filter's structure (restarts, Huber frames), and the cost per trajectory on this CPU. Beside it, the same
attacker sparing the frames the protection level assumes fault-free (its assumption A: the start and the
trusted-start frames), whose achieved / PL above 1 would mean the PL fails under its own assumptions;
and on a sample of frames the certified shift of interval bound propagation (pipeline/pose/certify.py)
against the capacity.

The capacity is a PLACEHOLDER until the strongest attack suite measures per-frame shifts
(pipeline/attacks/capacity.py `fit_capacity`): a range-proportional box whose value at the test set's
mean range (36 m) is the robust model's mean PGD-50 position error in reports/pose_robust.md (0.67 m at
eps 0.01, 0.83 m at 0.02, 1.46 m at 0.05), on every axis (along and across the line of sight): an
average, not an overbound, and all of it taken as the attack's shift.

    .venv/bin/python benchmarks/integrity_bound.py [--trajectories 3] [--stride 10] [--eps 0.01 0.05]
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.attacks.capacity import capacity_at, proportional_capacity  # noqa: E402
from pipeline.defense.bound import ACCEPT, ALARM, HUBER, RESTART, Recording, WorstCase, record, worst_case  # noqa: E402
from pipeline.defense.calibration import CleanRun  # noqa: E402
from pipeline.defense.integrity import alert_limit  # noqa: E402
from pipeline.evaluation.integrity_runs import Track  # noqa: E402
from pipeline.evaluation.robustness import pose_estimates  # noqa: E402
from pipeline.geometry.labels import TARGET  # noqa: E402
from pipeline.pose.certify import certified_shift  # noqa: E402
from stages.artifacts.models import load_chain  # noqa: E402
from stages.artifacts.paths import SHIPPED  # noqa: E402
from stages.artifacts.readers import read_eval_render  # noqa: E402
from stages.config.params import load  # noqa: E402

PGD_MEAN_ERROR_M = {0.01: 0.67, 0.02: 0.83, 0.05: 1.46}  # reports/pose_robust.md, robust model, PGD-50
MEAN_RANGE_M = 36.0  # the test frames' mean range there
EDGES = np.arange(0.0, 85.0, 5.0)  # m: the capacity's range bins


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectories", type=int, default=3)
    ap.add_argument("--stride", type=int, default=10, help="every stride-th frame is a target (and the last)")
    ap.add_argument("--eps", type=float, nargs="+", default=sorted(PGD_MEAN_ERROR_M))
    args = ap.parse_args()
    params = load()
    images, poses, _ = read_eval_render(params)
    labels = poses[TARGET].to_numpy(np.float64)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])]
    safety = load_chain(params, SHIPPED)
    chain, d = safety.onboard, safety.defended
    limit = partial(alert_limit, settings=d.alert)
    caps = [
        proportional_capacity(e, EDGES, PGD_MEAN_ERROR_M[e] / MEAN_RANGE_M, PGD_MEAN_ERROR_M[e] / MEAN_RANGE_M)
        for e in sorted(PGD_MEAN_ERROR_M)
    ]
    print(
        f"shipped defense: gate {d.motion.gate:.2f} (soft {d.motion.soft_gate}), CUSUM c {d.motion.cusum_reference} "
        f"h {d.motion.cusum_threshold}, trusted start {d.motion.trusted_start}, fusion {d.settings.fusion}; "
        f"{len(trajs)} eval trajectories, first {args.trajectories}"
    )
    summary: dict[float, list[dict[str, float]]] = {e: [] for e in args.eps}
    spared: dict[float, list[float]] = {e: [] for e in args.eps}
    for g, ix in enumerate(trajs[: args.trajectories]):
        track = Track(f"t{g}", images[ix], labels[ix])
        truth, n = track.truth, len(ix)
        run, rng, al, clean, err = _clean_run(chain, d, limit, track, truth)
        targets = sorted(set(range(0, n, args.stride)) | {n - 1})
        solve = partial(worst_case, d.settings, d.motion, d.noise, run, truth, alert_limit=limit)
        for e in args.eps:
            cap = capacity_at(caps, e, rng)
            w = _worst(solve, cap, al, targets, e, rng, err)
            spared[e].append(_spared(solve, cap, al, targets, clean, d.motion.trusted_start))
            summary[e].append(
                {
                    "upper_al": float(np.nanmax(w.ratio)),
                    "achieved_pl": float(np.nanmax(w.pl_index)),
                    "upper_m": float(np.nanmax(w.upper)),
                    "exact": float(np.mean(w.exact)),
                    "seconds": w.seconds,
                    "per_target": w.seconds / len(targets),
                    "all_targets": w.seconds / len(targets) * (n - clean.start),
                }
            )
    _print_summary(summary, spared)
    certify(safety.model, Track("t0", images[trajs[0]], labels[trajs[0]]), caps, args.eps)


def _clean_run(
    chain: Any, d: Any, limit: Callable[[float], float], track: Track, truth: np.ndarray
) -> tuple[CleanRun, np.ndarray, np.ndarray, Recording, np.ndarray]:
    """(the chain's clean run of `track` (true rel `truth` (N, 3), world, m), range (N,) (m), AL (N,) (m), its
    recording through the defense `d`, the trusted error (N,) (m)); prints the clean run's structure."""
    t0 = time.perf_counter()
    est, prob = pose_estimates(chain, track.images, 32)
    chain_s = time.perf_counter() - t0
    run, n = CleanRun(est, prob, track.R_cam, track.u), len(track)
    rng, al = np.linalg.norm(truth, axis=1), alert_limit(np.linalg.norm(truth, axis=1), d.alert)
    clean = record(d.settings, d.motion, d.noise, run, alert_limit=limit)
    err = np.linalg.norm(clean.trace.trusted - truth, axis=1)
    print(
        f"\n{track.name}: {n} frames, range {rng[0]:.1f} -> {rng[-1]:.1f} m; chain {chain_s:.1f} s; clean: "
        f"start frame {clean.start}, restart at {clean.horizon if clean.horizon < n else 'none'}, "
        f"{int((clean.kind == HUBER).sum())} Huber, {int(clean.trace.flag.sum())} flags, "
        f"{int(clean.trace.available.sum())} available, max error {np.nanmax(err):.2f} m, "
        f"max error/PL {np.nanmax(err / clean.trace.pl):.2f}, restarts {int((clean.kind == RESTART).sum())}"
    )
    return run, rng, al, clean, err


def _worst(
    solve: Callable[..., WorstCase],
    cap: np.ndarray,
    al: np.ndarray,
    targets: list[int],
    e: float,
    rng: np.ndarray,
    err: np.ndarray,
) -> WorstCase:
    """`solve` (`worst_case` on the clean run) at the target frames within the capacity `cap` (N, 3) (m) of eps `e`,
    AL `al` (N,) (m); prints it per frame beside the range `rng` and the clean error `err` (m)."""
    w = solve(cap, al, targets=targets)
    print(
        f"  eps {e}: {w.seconds:.1f} s for {len(targets)} targets "
        f"({w.seconds / len(targets):.2f} s per target); capacity at the start {cap[0, 0]:.2f} m"
    )
    print("    frame  range  AL    clean  upper  achieved  PL     upper/AL  achieved/PL  exact  available")
    for t, j in enumerate(w.targets):
        print(
            f"    {j:5d}  {rng[j]:5.1f}  {w.alert[t]:4.1f}  {err[j]:5.2f}  {w.upper[t]:5.2f}  "
            f"{w.achieved[t]:8.2f}  {w.pl[t]:5.2f}  {w.ratio[t]:8.2f}  {w.achieved[t] / w.pl[t]:11.2f}  "
            f"{str(bool(w.exact[t])):5s}  {bool(w.available[t])}"
        )
    return w


def _spared(
    solve: Callable[..., WorstCase],
    cap: np.ndarray,
    al: np.ndarray,
    targets: list[int],
    clean: Recording,
    trusted_start: int,
) -> float:
    """Max achieved / PL of `solve` (`worst_case` on the clean run) sparing the frames the PL assumes fault-free
    (assumption A: up to the `trusted_start`-th trusted frame of `clean`), at the targets after them; printed."""
    trusted = np.flatnonzero(np.isin(clean.kind, (ACCEPT, HUBER, ALARM)))[trusted_start - 1]
    assumed = cap.copy()
    assumed[: trusted + 1] = 0.0  # the PL's assumption A: those frames fault-free
    later = [j for j in targets if j > trusted]
    a = solve(assumed, al, targets=later)
    print(
        f"    sparing frames <= {trusted} (assumption A): max achieved {np.nanmax(a.achieved):.2f} m, "
        f"max achieved/PL {np.nanmax(a.pl_index):.2f}"
    )
    return float(np.nanmax(a.pl_index))


def _print_summary(summary: dict[float, list[dict[str, float]]], spared: dict[float, list[float]]) -> None:
    """Print per eps the maxima over the trajectories and the mean cost per trajectory (s)."""
    print(
        "\neps    trajectories  max upper (m)  max upper/AL  max achieved/PL  (sparing A)  exact  s/trajectory  "
        "s/trajectory at every frame (est.)"
    )
    for e, rows in summary.items():
        print(
            f"{e:<6} {len(rows):12d}  {max(r['upper_m'] for r in rows):13.2f}  "
            f"{max(r['upper_al'] for r in rows):12.2f}  "
            f"{max(r['achieved_pl'] for r in rows):15.2f}  {max(spared[e]):11.2f}  "
            f"{np.mean([r['exact'] for r in rows]):5.2f}  {np.mean([r['seconds'] for r in rows]):12.1f}  "
            f"{np.mean([r['all_targets'] for r in rows]):10.0f}"
        )


def certify(model: object, track: Track, caps: list, eps: list[float], every: int = 20) -> None:
    """Interval bound propagation's certified shift along the line of sight on every `every`-th frame of
    `track` beside the capacity there (m)."""
    import torch

    ix = np.arange(0, len(track), every)
    x = track.frames(ix)
    los = track.labels[ix, :3] / np.linalg.norm(track.labels[ix, :3], axis=1, keepdims=True)
    rng = np.linalg.norm(track.labels[ix, :3], axis=1)
    print(
        f"\ninterval bound propagation on {len(ix)} frames of {track.name} (camera frame; along the LOS: "
        f"sum_i |los_i| max shift_i)"
    )
    for e in eps:
        t0 = time.perf_counter()
        with torch.no_grad():
            m = certified_shift(model, x, e).numpy()
        along = np.einsum("ni,ni->n", np.abs(los), m)
        cap = capacity_at(caps, e, rng)[:, 0]
        print(
            f"  eps {e}: certified along-LOS shift median {np.median(along):.3g} m (min {along.min():.3g}, "
            f"max {along.max():.3g}); capacity there median {np.median(cap):.2f} m: the certificate is "
            f"{np.median(along / cap):.3g}x the capacity; {time.perf_counter() - t0:.1f} s"
        )


if __name__ == "__main__":
    main()

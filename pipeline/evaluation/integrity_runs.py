"""The chain-level attackers on recorded trajectories, judged by integrity (issue 26; `rpod robustness`).

Each trajectory (`Track`: uint8 frames (N, H, W, 3), labels (N, 9): camera-frame position (m) and 6-D
rotation) is flown open loop along its planned commands (`pipeline.evaluation.robustness.world_motion`):
the shipped chain reads every frame, a fresh defense runs over the whole trajectory, and its trace
gives the integrity records of the trusted estimate (`pipeline.defense.integrity`: AL at the true
range, available, HMI; PL when the defense has one). The same trajectory without the attack is the
clean counterpart, frame for frame, so harm counts only what the attack caused.
- burst (`burst_attack`): `BurstAttacker.nested` on each trajectory through the increasing eps, its
  bursts at the given frames;
- drift and capture (`plan_attack`): the planner of each (pipeline/attackers/drift.py, capture.py) and a
  targeted per-frame attack, run in lockstep over every trajectory and plan so that each PGD step is one
  batch of all of them: the `DriftAttacker` and `CaptureAttacker`, batched, each plan from its own first
  frame to the end of the trajectory, with the detector's margin taken against the probability at which
  the defense stops updating its filter (its doubt level `update_below`, else the threshold), any
  per-frame `FrameAttack`, warm-started from the previous frame's perturbation.
The undefended control (`defended` None): the chain's raw estimate is what the guidance flies on (the
trusted estimate is the raw one, every frame tracked and available, no flags, no PL).
A track's commands (`Track.commands`) are what the chaser commanded and its chain is told; by default
the flown motion read from the labels (exact execution), with execution error the planned steps.
An attacked flight reads through the chain only the frames the attack changed (`fly` with `base`):
the chain is stateless, so the other frames' estimates are the clean flight's.
Counted frames (`counted`): from a trajectory's first attacked frame to its end, every frame the attack
can reach; detection is over the attacked frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch

from pipeline.defense.integrity import AlertLimitSettings, IntegrityFrames, concat, defense_frames, integrity_rates
from pipeline.stats import Rate, bootstrap_rate


@dataclass(frozen=True)
class Track:
    """One recorded trajectory: `name`, uint8 frames (N, H, W, 3), labels (N, 9) [m, 6-D]; R_cam (N, 3,
    3) camera -> world and u (N, 3) the commanded displacement of rel (world, m): `commands` when given
    (the steps the chaser commanded, e.g. `pipeline.geometry.trajectories.Sequence.commands` of a
    trajectory flown with execution error), else the flown motion read from the labels."""

    name: str
    images: np.ndarray
    labels: np.ndarray
    commands: np.ndarray | None = None
    R_cam: np.ndarray = field(init=False)
    u: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        from pipeline.evaluation.robustness import world_motion

        R_cam, u = world_motion(np.asarray(self.labels, np.float64))
        if self.commands is not None:
            if np.shape(self.commands) != u.shape:
                raise ValueError(
                    f"track {self.name}: commands must be (N, 3) = {u.shape}, got {np.shape(self.commands)}"
                )
            u = np.asarray(self.commands, np.float64)
        object.__setattr__(self, "R_cam", R_cam)
        object.__setattr__(self, "u", u)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def truth(self) -> np.ndarray:
        """(N, 3) the true rel, world frame (m)."""
        return np.einsum("nij,nj->ni", self.R_cam, np.asarray(self.labels[:, :3], np.float64))

    def frames(self, index: Any = slice(None)) -> torch.Tensor:
        """Frames `index` as floats on the 8-bit grid, (n, 3, H, W)."""
        return torch.from_numpy(np.ascontiguousarray(self.images[index])).permute(0, 3, 1, 2).float() / 255.0


@dataclass(frozen=True)
class Flown:
    """One trajectory through the real chain and defense: pose (N, 9), prob (N,), the `DefenseTrace`
    and the integrity records."""

    pose: np.ndarray
    prob: np.ndarray
    trace: Any
    frames: IntegrityFrames


def undefended_trace(t_pred: np.ndarray, R_cam: np.ndarray) -> Any:
    """The DefenseTrace of the undefended chain over camera-frame estimates t_pred (N, 3) (m): trusted =
    the raw estimate in world axes (R_cam (N, 3, 3) camera -> world), every frame tracked and available,
    no flags, no protection level."""
    from pipeline.defense.fusion import TRACK, DefenseTrace

    n = len(t_pred)
    no = np.zeros(n, bool)
    return DefenseTrace(
        no,
        no,
        no,
        np.einsum("nij,nj->ni", R_cam, np.asarray(t_pred, np.float64)),
        np.full(n, TRACK),
        np.full(n, np.nan),
        np.full(n, np.nan),
        no,
        None,
        np.ones(n, bool),
    )


def fly(
    chain: Any,
    defended: Any,
    track: Track,
    limit: AlertLimitSettings,
    batch_size: int,
    images: np.ndarray | None = None,
    base: Flown | None = None,
) -> Flown:
    """`track` (or its frames replaced by `images`, uint8 (N, H, W, 3)) through the OnboardChain `chain`
    and a fresh defense (`defended`: pipeline.evaluation.robustness.Defended; None: the undefended
    control, `undefended_trace`); with `base` (the clean flight of `track`) only the frames that differ
    from the track's are read through the chain."""
    from pipeline.defense.fusion import run_defense
    from pipeline.evaluation.robustness import pose_estimates
    from pipeline.geometry.rotations import sixd_to_matrix

    if base is None or images is None:
        pose, prob = pose_estimates(chain, track.images if images is None else images, batch_size)
    else:
        changed = np.flatnonzero((images != track.images).reshape(len(images), -1).any(1))
        pose, prob = base.pose.copy(), base.prob.copy()
        pose[changed], prob[changed] = pose_estimates(chain, images[changed], batch_size)
    if defended is None:
        trace = undefended_trace(pose[:, :3], track.R_cam)
    else:
        d = defended.defense()
        trace = run_defense(
            d.settings,
            d.filter.settings,
            d.filter.noise,
            pose[:, :3],
            prob,
            track.R_cam,
            track.u,
            sixd_to_matrix(pose[:, 3:]),
            d.alert_limit,
        )
    return Flown(pose, prob, trace, defense_frames(trace, track.truth, track.name, limit))


def burst_attack(
    target: Any,
    defended: Any,
    tracks: Sequence[Track],
    masks: Sequence[np.ndarray],
    attacker: Any,
    eps: Sequence[float],
    done: Callable[[], None] = lambda: None,
) -> tuple[dict[float, list[Any]], ...]:
    """(eps -> the stored frames (uint8 (N, H, W, 3)) of each track, eps -> each track's bursts' worst cases
    (`BurstOutcome`s in time order)), its bursts (`masks` (N,) bool) crafted by `attacker` (a BurstAttacker)
    through `target` (a DifferentiableChain), nested through the increasing `eps` (`defended` None: the
    undefended control); `done()` after each track."""
    from pipeline.attackers.base import AttackRun

    stored: dict[float, list[Any]] = {float(e): [] for e in eps}
    worst: dict[float, list[Any]] = {float(e): [] for e in eps}
    for track, mask in zip(tracks, masks):
        run = AttackRun(
            track.frames(),
            torch.as_tensor(track.labels, dtype=torch.float32),
            track.R_cam,
            track.u,
            np.asarray(mask, bool),
        )
        res = attacker.nested(target, None if defended is None else defended.defense(), run, [float(e) for e in eps])
        for e, images, bursts in zip(res.eps, res.images, res.bursts):
            stored[e].append(images.permute(0, 2, 3, 1).numpy())
            worst[e].append(bursts)
        done()
    return stored, worst


def plan_attack(
    target: Any,
    defended: Any,
    tracks: Sequence[Track],
    clean: Sequence[Flown],
    plans: Sequence[tuple[Any, int]],
    eps: float,
    seed: int,
    frame_attack: Any = None,
    warm: bool = True,
    done: Callable[[], None] = lambda: None,
) -> list[list[np.ndarray]]:
    """Per plan of `plans` ((settings, first attacked frame): DriftSettings or CaptureSettings, anything with
    `planner(defense)`), the stored frames (uint8 (N, H, W, 3)) of each track attacked at `eps` from that frame to
    the end: every plan and track in lockstep, one batched per-frame attack over the pairs attacking a frame
    (`frame_attack`, a pipeline.attackers.drift.FrameAttack; default targeted PGD), seeded `seed`; `warm`: each
    pair's attack starts from its previous frame's perturbation (consecutive frames differ little) once every
    pair of the frame has one. `defended` None: the undefended control (no detector margin); `clean` the tracks'
    clean flights (the estimates the planners start from and are fed before a plan's first frame); `done()` after
    each attacked frame."""
    from pipeline.attackers.base import chain_outputs, doubt_logit
    from pipeline.attackers.drift import TargetedPGD
    from pipeline.geometry.rotations import sixd_to_matrix

    attack = TargetedPGD() if frame_attack is None else frame_attack
    logit = None if defended is None else doubt_logit(defended.defense())
    pairs = [(j, i) for j in range(len(plans)) for i in range(len(tracks))]  # (plan, track)
    planners = [plans[j][0].planner(None if defended is None else defended.defense()) for j, _ in pairs]
    stored = [[t.images.copy() for t in tracks] for _ in plans]
    generator = torch.Generator().manual_seed(int(seed))
    shift: dict[int, torch.Tensor] = {}  # pair -> its last perturbation (3, H, W), floats
    for k in range(max(len(t) for t in tracks)):
        active = _active_pairs(k, planners, pairs, plans, tracks, clean)
        if not active:
            continue
        wanted = []
        for n in active:
            c, t = clean[pairs[n][1]], tracks[pairs[n][1]]
            wanted.append(np.concatenate([planners[n].target(c.pose[k, :3], t.R_cam[k], t.u[k]), c.pose[k, 3:]]))
        x = torch.cat([tracks[pairs[n][1]].frames(slice(k, k + 1)) for n in active])
        goal = torch.as_tensor(np.stack(wanted), dtype=x.dtype)
        if warm and all(n in shift for n in active):
            adv = attack(target, x, goal, eps, logit, generator, start=x + torch.stack([shift[n] for n in active]))
        else:
            adv = attack(target, x, goal, eps, logit, generator)
        pose, prob = chain_outputs(target, adv.float() / 255.0)
        for row, n in enumerate(active):
            j, i = pairs[n]
            t = tracks[i]
            stored[j][i][k] = adv[row].permute(1, 2, 0).numpy()
            shift[n] = adv[row].float() / 255.0 - x[row]
            planners[n].deliver(pose[row, :3], float(prob[row]), t.R_cam[k], t.u[k], sixd_to_matrix(pose[row, 3:]))
        done()
    return stored


def _active_pairs(
    k: int,
    planners: list[Any],
    pairs: list[tuple[int, int]],
    plans: Sequence[tuple[Any, int]],
    tracks: Sequence[Track],
    clean: Sequence[Flown],
) -> list[int]:
    """The indices of the pairs (plan, track) that attack frame k (plan started, track that long); a pair whose
    plan starts later is fed its track's clean estimate of frame k instead."""
    from pipeline.geometry.rotations import sixd_to_matrix

    active = []
    for n, (p, (j, i)) in enumerate(zip(planners, pairs)):
        c, t = clean[i], tracks[i]
        if k >= len(t):
            continue
        if k < plans[j][1]:
            p.deliver(c.pose[k, :3], float(c.prob[k]), t.R_cam[k], t.u[k], sixd_to_matrix(c.pose[k, 3:]))
        else:
            active.append(n)
    return active


def counted(attacked: np.ndarray) -> np.ndarray:
    """(N,) the frames from the first attacked frame of `attacked` (N,) bool to the end (none without one)."""
    attacked = np.asarray(attacked, bool)
    return np.cumsum(attacked) > 0


def as_json(r: Rate, trajectories: int) -> dict[str, Any]:
    """A Rate as the metrics JSON holds it: {"value", "ci": [lo, hi], "n", "ci_method"} (value None when n
    is 0). A bootstrap over trajectories without spread (no hit or only hits on every trajectory: [0, 0]
    or [1, 1]) bounds nothing; its interval is then the Wilson interval of the `trajectories` as trials,
    all without a hit (or all with hits): a conservative bound of the frame rate, since a trajectory
    with a hit has at least the frame's chance of one."""
    from pipeline.stats import wilson

    method = "bootstrap over trajectories"
    if r.n and r.lo == r.hi and r.value in (0.0, 1.0):
        w = wilson(int(r.value) * trajectories, trajectories)
        r, method = Rate(r.value, w.lo, w.hi, r.n), "Wilson over trajectories (the bootstrap had no spread)"
    return {"value": None if r.n == 0 else float(r.value), "ci": r.ci(), "n": int(r.n), "ci_method": method}


def _errors(frames: IntegrityFrames, mask: np.ndarray) -> tuple[float, float]:
    err = frames.error[mask]
    err = err[np.isfinite(err)]
    return (float(err.mean()), float(err.max())) if err.size else (float("nan"), float("nan"))


def integrity_row(
    attacker: str,
    eps: float,
    attacked: Sequence[Flown],
    clean: Sequence[Flown],
    masks: Sequence[np.ndarray],
    seed: int = 0,
) -> dict[str, Any]:
    """One attacker at one eps over every track (attacked flights, their clean counterparts, the attacked
    frames (N,) of each): the HMI the attack caused and the rest of `integrity_rates` over the counted
    frames, detection over the attacked frames, and the same frames without the attack beside them."""
    a, c = concat([f.frames for f in attacked]), concat([f.frames for f in clean])
    hit = np.concatenate([np.asarray(m, bool) for m in masks])
    keep = np.concatenate([counted(m) for m in masks])
    r = integrity_rates(a, c, keep, seed=seed)
    groups = a.trajectory.astype(str)
    flag = np.concatenate([f.trace.flag for f in attacked])
    clean_flag = np.concatenate([f.trace.flag for f in clean])
    (mean, worst), (clean_mean, clean_worst) = _errors(a, keep), _errors(c, keep)
    return {
        "attacker": attacker,
        "eps": float(eps),
        "frames": int(keep.sum()),
        "attacked_frames": int(hit.sum()),
        "trajectories": len(attacked),
        "ci_method": "bootstrap over trajectories",
        **{
            k: as_json(r[k], len(attacked))
            for k in ("hmi", "hmi_attacked", "hmi_clean", "mi", "availability", "availability_clean")
        },
        "detected": as_json(bootstrap_rate(flag[hit], groups[hit], seed=seed), len(attacked)),
        "detected_clean": as_json(bootstrap_rate(clean_flag[hit], groups[hit], seed=seed), len(attacked)),
        "trusted_error_mean_m": mean,
        "trusted_error_max_m": worst,
        "clean_error_mean_m": clean_mean,
        "clean_error_max_m": clean_worst,
    }


def worst_hmi(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per eps ("%g") of `integrity_row`s: the attacker whose caused HMI is highest, with its rate ({"value", "ci",
    "n"}); attackers that tie are named together ("drift/los = capture/los 2 m"), the widest interval kept."""
    out: dict[str, dict[str, Any]] = {}
    for r in rows:
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


def clean_row(clean: Sequence[Flown], seed: int = 0) -> dict[str, Any]:
    """The clean trajectories' integrity: availability, HMI, MI (bootstrap over trajectories), frames, error (m)."""
    from pipeline.defense.integrity import clean_rates

    r = clean_rates(concat([f.frames for f in clean]), seed=seed)
    return {
        **{k: as_json(r[k], len(clean)) for k in ("availability", "hmi", "mi")},
        "frames": r["frames"],
        "trajectories": len(clean),
        "trusted_error_mean_m": r["trusted_error_mean_m"],
        "trusted_error_max_m": r["trusted_error_max_m"],
        "has_pl": bool(clean[0].frames.pl is not None),
    }


def raw_errors(flown: Sequence[Flown], tracks: Sequence[Track], masks: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Over the attacked frames of every track: (raw position error (M,) of the CNN estimate, camera frame
    (m); flag (M,); trajectory id (M,)): the per-frame view of pipeline.evaluation.robustness.fused_row."""
    err, flag, group = [], [], []
    for g, (f, t, m) in enumerate(zip(flown, tracks, masks)):
        m = np.asarray(m, bool)
        err.append(np.linalg.norm(f.pose[m, :3] - np.asarray(t.labels[m, :3], np.float64), axis=1))
        flag.append(f.trace.flag[m])
        group.append(np.full(int(m.sum()), g))
    return tuple(np.concatenate(v) for v in (err, flag, group))


def diagram_eps(runs: Sequence[tuple[str, float, Sequence[Flown], Sequence[np.ndarray]]]) -> float | None:
    """The eps the integrity figure shows, of a campaign's attacked `runs` (attacker, eps, flights, attacked masks):
    the largest at which some attacker's counted frame has a point on the Stanford diagram (`diagram_points`: a
    finite bound), else the largest flown (where every attacked frame lost its PL, the chain declared itself
    unavailable and the diagram would show the clean frames alone); None without runs."""
    if not runs:
        return None
    plotted = [e for _, e, flights, masks in runs if diagram_points(flights, masks)["bound"]]
    return max(plotted) if plotted else max(e for _, e, _, _ in runs)


def diagram_points(flown: Sequence[Flown], masks: Sequence[np.ndarray]) -> dict[str, list[float]]:
    """For the integrity figure: over the counted frames with an estimate and a finite bound, the bound (PL where
    the frames have one, else AL; m), the trusted error (m) and whether the frame was available. A frame whose PL
    is inf (a trusted start the detector doubted: unavailable, no bound to plot) is left out."""
    fr = concat([f.frames for f in flown])
    bound = fr.alert if fr.pl is None else fr.pl
    keep = np.concatenate([counted(m) for m in masks]) & np.isfinite(fr.error) & np.isfinite(bound)
    return {
        "bound": bound[keep].tolist(),
        "error": fr.error[keep].tolist(),
        "available": fr.available[keep].tolist(),
        "bound_is": "AL" if fr.pl is None else "PL",
    }

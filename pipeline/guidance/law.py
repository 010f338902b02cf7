"""Closed-loop rendezvous guided by the pose estimator, with an optional attack window.

Frames (those of pipeline/geometry/trajectories.py). The world frame is target-centred with the approach
along +z; the state `rel` (target position relative to the chaser, world axes, metres) starts at
(0, 0, 60) and the goal is (0, 0, 10), the label position t of an image taken by a camera looking
along +z. The camera attitude R_c (camera -> world, OpenCV camera axes, `look_at`) changes: after
every step the chaser re-points its camera at where it believes the target is. The image shows
the target at t = R_c^T rel with attitude R_c^T R_target; the estimator's camera-frame t_pred
becomes the world estimate R_c t_pred.

Control law (per axis): cmd = clip(est - goal, -max_step, max_step).
- variant "paper": the next true state is computed from the estimate, rel <- est - cmd (the
  paper's simplification: the chaser ends up where it believes it goes; prediction = truth by
  construction);
- variant "true_state": the command is applied to the true state, rel <- rel - cmd, or, with
  `GuidanceSettings.execution`, as the thrusters and the orbit execute it (pipeline/guidance/dynamics.py:
  a few percent of scale error and centimetres of noise per step, Clohessy-Wiltshire motion over the
  frame interval); the defense is still told the command.
Defense (`GuidanceSettings.defense`, the chain inside the loop; pipeline/defense/fusion.py):
- "undefended": the law acts on every estimate (the paper);
- "hold": a flagged frame's estimate is not used: the chaser holds (no command) for that frame;
- "recover": the law acts on the defense's trusted estimate (the motion filter's state, its
  prediction on flagged frames) where the defense declares it available; elsewhere the chaser
  holds: in the defense's hold mode, and where the protection level exceeds the alert limit (PL >
  AL: the defense cannot bound its error within what the guidance absorbs; the Defense's
  `alert_limit`, pipeline/defense/fusion.py).
A hold sends no command: the chaser stays where it is and keeps its camera pointing. The defense
gets the displacement of `rel` (-cmd, or 0 in a hold; in the paper variant the believed point minus
its trusted estimate) to drive its motion filter.
A run lasts `max_steps` steps (the nominal approach 60 m -> 10 m takes 50); it is judged at the
end: within `tolerance` of the goal or not. It stops early when the target's centre leaves the
image ("target lost"). The attack starts at the first step whose true range is at or below S
and lasts K consecutive frames (fewer if the run ends first). An attacker in the loop may watch it:
`observe` gets the loop's state (`LoopState`) before every frame is estimated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.defense.fusion import Defense
from pipeline.geometry.camera import Intrinsics
from pipeline.geometry.trajectories import look_at, pose_in_camera
from pipeline.guidance.dynamics import Executor
from pipeline.guidance.settings import ExecutionSettings

VARIANTS = ("paper", "true_state")
DEFENSES = ("undefended", "hold", "recover")
DOCKED = "docked"
SUCCEEDED = "attack succeeded"
LOST = "target lost"
MISSED = "missed without attack"

PROTECTION = ("pl", "al", "noise", "ramp", "transients", "offset")  # RendezvousResult.protection's columns (m)

RenderFn = Callable[[np.ndarray, np.ndarray], Any]
"""render(R, t) -> image (passed as is to the estimator): target attitude R (target -> camera),
position t (camera frame, m)."""


@dataclass(frozen=True)
class Estimate:
    """The chain's output for one frame: t camera-frame position (m), prob the detector's attack
    probability, R the target -> camera attitude estimate (optional)."""

    t: np.ndarray
    prob: float = 0.0
    R: np.ndarray | None = None


EstimateFn = Callable[[Any, bool, tuple[np.ndarray, np.ndarray]], "np.ndarray | Estimate"]
"""estimate(image, attacked, (R, t) true pose) -> t_pred (3,) camera frame (m), or an Estimate."""


@dataclass(frozen=True)
class AttackWindow:
    """Attack the K = `length` frames from the first one at true range <= `start_range` (m)."""

    start_range: float
    length: int


@dataclass(frozen=True)
class GuidanceSettings:
    """Start and goal of `rel` (world frame, metres), tolerance (m), per-axis step limit (m); `execution`:
    how the true_state variant executes a command (None: exactly; the paper variant takes none)."""

    start: tuple[float, float, float] = (0.0, 0.0, 60.0)
    goal: tuple[float, float, float] = (0.0, 0.0, 10.0)
    tolerance: float = 1.0
    max_step: float = 1.0
    max_steps: int = 60
    variant: str = "paper"
    defense: str = "undefended"
    execution: ExecutionSettings | None = None

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown guidance variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.defense not in DEFENSES:
            raise ValueError(f"unknown guidance defense {self.defense!r}; choose one of {', '.join(DEFENSES)}")
        if self.tolerance <= 0 or self.max_step <= 0 or self.max_steps < 1:
            raise ValueError(
                "guidance tolerance and max_step must be positive and max_steps >= 1, got "
                f"{self.tolerance}, {self.max_step}, {self.max_steps}"
            )
        if np.linalg.norm(self.goal) >= np.linalg.norm(self.start):
            raise ValueError(f"the guidance goal {self.goal} must be closer to the target than the start {self.start}")
        if self.execution is not None and self.variant == "paper":
            raise ValueError(
                "execution error applies to the true_state dynamics; the paper variant flies the chaser "
                "to its estimate (prediction = truth by construction)"
            )

    def window(self, start_range: float, length: int) -> AttackWindow:
        """A validated attack window: S between the goal range and the start range, K >= 1."""
        lo, hi = float(np.linalg.norm(self.goal)), float(np.linalg.norm(self.start))
        if not lo <= start_range <= hi:
            raise ValueError(
                f"attack start range S={start_range} m is outside the trajectory: the range goes "
                f"from {hi:g} m to {lo:g} m"
            )
        if int(length) < 1:
            raise ValueError(f"attack length K must be at least 1 frame, got {length}")
        return AttackWindow(float(start_range), int(length))


@dataclass(frozen=True)
class LoopState:
    """What the loop shows an attacker who watches it, before frame `step` is estimated: the true rel
    (world, m), the camera attitude R_c (camera -> world), the commanded displacement of rel since the
    last frame (world, m; what the defense will be given), the live defense (None: undefended; read
    it, never step it) and the run's settings."""

    step: int
    rel: np.ndarray
    R_c: np.ndarray
    u: np.ndarray
    defense: Defense | None
    settings: "GuidanceSettings"


@dataclass
class RendezvousResult:
    """One closed-loop run. positions: (n+1, 3) true rel after each step (first row = start);
    estimates: (n, 3) world-frame estimates; attacked: (n,) bool; miss: final ||rel - goal|| (m);
    with a defense: flags (n,) bool and modes (n,) str of pipeline/defense/fusion.py, else None;
    held: (n,) bool, the steps that sent no command (the chaser held), None in results made without it;
    believed: (n, 3) the rel each step's command aimed to reach by the chaser's own estimate (world, m; NaN rows
    where it held), None in results made without it; protection: (n, 6) per frame the defense's PL, the AL it was
    judged against and the PL's parts (`protection_parts`; columns PROTECTION, m; NaN where there is none), None
    undefended or in results made without it; acted: (n, 3) the estimate each step's command was computed from, what
    the guidance flew on (world, m: the raw estimate, or with "recover" the trusted one; NaN rows where it held),
    None in results made without it."""

    positions: np.ndarray
    estimates: np.ndarray
    attacked: np.ndarray
    outcome: str
    miss: float
    attack_start: int | None
    flags: np.ndarray | None = None
    modes: np.ndarray | None = None
    held: np.ndarray | None = None
    believed: np.ndarray | None = None
    protection: np.ndarray | None = None
    acted: np.ndarray | None = None

    @property
    def attacked_frames(self) -> int:
        return int(self.attacked.sum())

    @property
    def closest_range(self) -> float:
        """The least true range over the run (m): the distance from the target to the path between
        consecutive positions (a step may jump past the target under the paper dynamics)."""
        return float(
            min(segment_range(a, b) for a, b in zip(self.positions[:-1], self.positions[1:]))
            if len(self.positions) > 1
            else np.linalg.norm(self.positions[0])
        )


def segment_range(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (m) from the target (the origin of rel) to the segment from rel `a` to rel `b`."""
    d = np.asarray(b, np.float64) - a
    s = 0.0 if not d @ d > 0 else float(np.clip(-(np.asarray(a, np.float64) @ d) / (d @ d), 0.0, 1.0))
    return float(np.linalg.norm(a + s * d))


def in_view(t: np.ndarray, K: Intrinsics) -> bool:
    """Whether a camera-frame point (m) is in front of the camera and projects inside the image."""
    if t[2] <= 0:
        return False
    u, v = K.fx * t[0] / t[2] + K.cx, K.fy * t[1] / t[2] + K.cy
    return bool(-0.5 <= u <= K.width - 0.5 and -0.5 <= v <= K.height - 0.5)


def arrival_step(
    result: "RendezvousResult", goal: tuple[float, float, float] | np.ndarray, tolerance: float
) -> int | None:
    """Steps after which the chaser is within `tolerance` (m) of `goal` and stays there to the end of
    the run, or None when the run does not end there."""
    inside = np.linalg.norm(result.positions - np.asarray(goal, dtype=np.float64), axis=1) <= tolerance
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return int(outside[-1] + 1) if len(outside) else 0


def guidance_step(
    est: np.ndarray, rel: np.ndarray, goal: np.ndarray, max_step: float, variant: str
) -> tuple[np.ndarray, np.ndarray]:
    """One application of the control law -> (next true rel, rel the chaser believes it reaches)."""
    cmd = np.clip(est - goal, -max_step, max_step)
    believed = est - cmd
    return (believed if variant == "paper" else rel - cmd), believed


def outcome(lost: bool, miss: float, tolerance: float, attacked: np.ndarray) -> str:
    """How a run ended: target lost, docked (final miss (m) within `tolerance` (m)), else attack
    succeeded when any frame was attacked, missed without attack when none was."""
    if lost:
        return LOST
    if miss <= tolerance:
        return DOCKED
    return SUCCEEDED if attacked.any() else MISSED


def run_rendezvous(
    render: RenderFn,
    estimate: EstimateFn,
    K: Intrinsics,
    settings: GuidanceSettings,
    window: AttackWindow | None = None,
    target_attitude: np.ndarray | None = None,
    defense: Defense | None = None,
    observe: Callable[[LoopState], None] | None = None,
) -> RendezvousResult:
    """Fly the closed loop: render the true pose, estimate it (attacked inside the window), move.

    `target_attitude` is the target -> world rotation (identity by default). `defense` (a fresh
    pipeline.defense.fusion.Defense per run) is required unless settings.defense is "undefended".
    `observe` (an attacker in the loop) is shown the `LoopState` before each frame is estimated.
    The defense is told the chaser's displacement u (world, m) since the previous frame: -cmd in the
    true_state variant (the command, never the executed step of `settings.execution`); in the paper
    variant the chaser lands where it believes it goes (act - cmd), so u is that point minus the
    defense's trusted estimate, and a biased estimate is not read as motion.
    """
    _check_defense(settings.defense, defense)
    R_tw = np.eye(3) if target_attitude is None else np.asarray(target_attitude, dtype=np.float64)
    goal = np.asarray(settings.goal, dtype=np.float64)
    rel = np.asarray(settings.start, dtype=np.float64)
    R_c = look_at(rel)
    executor = None if settings.execution is None else Executor(settings.execution)
    positions, estimates, attacked, held, believed, acted = [rel], [], [], [], [], []
    defended: tuple[list[Any], list[Any], list[Any]] = ([], [], [])  # flags, modes, PROTECTION rows
    attack_start: int | None = None
    lost = False
    u = np.zeros(3)
    for k in range(settings.max_steps):
        R, t = pose_in_camera(rel, R_c, R_tw)
        if window is not None and attack_start is None and np.linalg.norm(rel) <= window.start_range + 1e-6:
            attack_start = k
        hit = attack_start is not None and k < attack_start + window.length
        if observe is not None:
            observe(LoopState(k, rel.copy(), R_c.copy(), u.copy(), defense, settings))
        out = estimate(render(R, t), hit, (R, t))
        out = out if isinstance(out, Estimate) else Estimate(np.asarray(out, dtype=np.float64))
        est = R_c @ np.asarray(out.t, dtype=np.float64)
        act: np.ndarray | None = est
        trusted: np.ndarray | None = None
        if defense is not None:
            act, trusted = _defend(defense, settings.defense, out, R_c, u, est, defended)
        rel, u, R_c, aim = _move(act, trusted, rel, goal, R_c, settings, executor)
        acted.append(np.full(3, np.nan) if act is None else act)
        positions.append(rel)
        believed.append(aim)
        estimates.append(est)
        attacked.append(hit)
        held.append(act is None)
        if not in_view(R_c.T @ rel, K):
            lost = True
            break
    miss = float(np.linalg.norm(rel - goal))
    logs = (positions, estimates, attacked, held, believed, acted, None if defense is None else defended)
    return _result(logs, lost, miss, settings.tolerance, attack_start)


def _check_defense(mode: str, defense: Defense | None) -> None:
    """A ValueError unless a Defense is given exactly when the guidance defense `mode` is not "undefended"."""
    if (mode == "undefended") != (defense is None):
        raise ValueError(
            f"guidance defense {mode!r} needs "
            + ("no Defense" if defense is not None else "a Defense (pipeline/defense/fusion.py)")
        )


def protection_parts(defense: Defense) -> tuple[float, float, float, float]:
    """The parts of `defense`'s protection level now (m; pipeline/defense/protection.py): the noise term, the slow
    ramp c sum|W|, the transients h TV+ (each what leaving it out removes: the bias adds them over the world axes
    in quadrature, so the parts add up to a little less than the PL) and a restart's carried offset; NaN before
    the PL exists."""
    f = defense.filter
    if not math.isfinite(f.protection_level):
        return (math.nan,) * 4
    pr = f.protection
    bias = pr.bias()
    return f.pl_noise_term, bias - pr.bias(reference=0.0), bias - pr.bias(threshold=0.0), pr.offset


def _defend(
    defense: Defense,
    mode: str,
    out: Estimate,
    R_c: np.ndarray,
    u: np.ndarray,
    est: np.ndarray,
    logs: tuple[list[Any], list[Any], list[Any]],
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """One frame through the defense (its flag, mode and PROTECTION row appended to `logs`): (what the law acts
    on: the estimate `est` (world, m) or, with "recover", the trusted estimate; None to hold; the trusted estimate
    (world, m), None where it is not finite)."""
    d = defense.step(out.t, out.prob, R_c, u, out.R)
    trusted = d.trusted if np.isfinite(d.trusted).all() else None
    flags, modes, protection = logs
    flags.append(d.flag)
    modes.append(d.mode)
    limit = defense.alert_limit
    al = math.nan if limit is None or trusted is None else float(limit(float(np.linalg.norm(trusted))))
    protection.append((d.pl if math.isfinite(d.pl) else math.nan, al, *protection_parts(defense)))
    if mode == "hold":
        act = None if d.flag else est
    else:
        act = d.trusted if d.available else None
    return act, trusted


def _move(
    act: np.ndarray | None,
    trusted: np.ndarray | None,
    rel: np.ndarray,
    goal: np.ndarray,
    R_c: np.ndarray,
    settings: GuidanceSettings,
    executor: Executor | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The chaser's step on the estimate `act` (world, m; None: hold): (the next rel (world, m), the displacement
    u told to the defense (world, m), the camera attitude R_c (camera -> world), re-pointed at the believed
    target, and the rel the command aimed to reach by the chaser's estimate (world, m; NaN in a hold))."""
    believed = np.full(3, np.nan)
    if act is None:  # hold: no command, the chaser and its camera stay as they are
        u = np.zeros(3)
        if executor is not None:  # station kept; its draws keep the errors aligned with the steps
            executor.step(rel, u)
    else:
        nxt, believed = guidance_step(act, rel, goal, settings.max_step, settings.variant)
        rel = nxt if executor is None else executor.step(rel, act - believed, R_c)
        u = believed - (act if trusted is None or settings.variant != "paper" else trusted)
        if np.linalg.norm(believed) > 1e-6:
            R_c = look_at(believed)
    return rel, u, R_c, believed


def _result(
    logs: tuple[list[Any], list[Any], list[bool], list[bool], list[Any], list[Any], tuple[list[Any], ...] | None],
    lost: bool,
    miss: float,
    tolerance: float,
    attack_start: int | None,
) -> RendezvousResult:
    """The run's `RendezvousResult` from its per-frame logs (positions, estimates, attacked, held, the believed
    rel per step, the estimate each command was computed from, and the defense's (flags, modes, PROTECTION rows) or
    None undefended) and its end (lost, miss distance (m))."""
    positions, estimates, attacked, held, believed, acted, defended = logs
    attacked_arr = np.array(attacked, dtype=bool)
    return RendezvousResult(
        np.array(positions),
        np.array(estimates).reshape(-1, 3),
        attacked_arr,
        outcome(lost, miss, tolerance, attacked_arr),
        miss,
        attack_start,
        None if defended is None else np.array(defended[0], dtype=bool),
        None if defended is None else np.array(defended[1]),
        np.array(held, dtype=bool),
        np.array(believed, dtype=np.float64).reshape(-1, 3),
        None if defended is None else np.array(defended[2], dtype=np.float64).reshape(-1, len(PROTECTION)),
        np.array(acted, dtype=np.float64).reshape(-1, 3),
    )


class CachedCamera:
    """The chaser's camera and pose CNN (or the whole safety chain) for `run_rendezvous`, with an image cache.

    Every attacked run follows the no-attack baseline until its attack starts, and Cycles and the CNN
    are deterministic, so each rendered pose's image and clean estimate are kept. `render` and
    `estimate` are the RenderFn and EstimateFn; attacked frames go through `attack(x, y)` (images
    (1, 3, H, W) in [0, 1], labels (1, 9): metres, 6-D) which `self.attack` may be changed to between
    runs. With `chain` (a pipeline.defense.chain.OnboardChain over `model`) `estimate` returns an `Estimate`
    (position, the detector's probability, attitude) for the defended variants; without it the
    camera-frame position (m). `images`: the rendered images by pose, a dict that cameras of other chains
    over the same scene may share (each pose is rendered once). `counts`: guidance steps, frames this camera
    rendered, attacked frames.
    """

    def __init__(
        self,
        render_image: Callable[[np.ndarray, np.ndarray], np.ndarray],
        model: Any,
        attack: Callable[[Any, Any], Any] | None = None,
        chain: Any | None = None,
        images: dict[bytes, np.ndarray] | None = None,
    ):
        self.render_image, self.model, self.attack, self.chain = render_image, model, attack, chain
        self.images = {} if images is None else images
        self.cache: dict[bytes, np.ndarray | Estimate] = {}  # pose -> this chain's clean estimate
        self.counts = {"steps": 0, "renders": 0, "attacked": 0}
        self.keys: set[bytes] = set()  # the poses rendered (or read from the cache) since it was last cleared

    @staticmethod
    def _input(image: np.ndarray) -> Any:
        import torch

        return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255

    def _position(self, x: Any) -> np.ndarray | Estimate:
        import torch

        if self.chain is not None:
            from pipeline.geometry.rotations import sixd_to_matrix

            out = self.chain(x)
            pose = out.pose[0].numpy().astype(np.float64)
            return Estimate(pose[:3], float(out.prob[0]), sixd_to_matrix(pose[3:9]))
        with torch.no_grad():
            return self.model(x)[0, :3].numpy().astype(np.float64)

    def render(self, R: np.ndarray, t: np.ndarray) -> tuple[bytes, np.ndarray]:
        key = np.round(np.concatenate([R.ravel(), t]), 9).tobytes()
        if key not in self.images:
            self.images[key] = self.render_image(R, t)
            self.counts["renders"] += 1
        if key not in self.cache:
            self.cache[key] = self._position(self._input(self.images[key]))
        self.counts["steps"] += 1
        self.keys.add(key)
        return key, self.images[key]

    def estimate(
        self, rendered: tuple[bytes, np.ndarray], attacked: bool, pose: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray | Estimate:
        import torch

        from pipeline.geometry.rotations import matrix_to_6d

        key, image = rendered
        if not attacked:
            return self.cache[key]
        if self.attack is None:
            raise ValueError("an attacked frame but no attack was given")
        self.counts["attacked"] += 1
        y = torch.as_tensor(np.concatenate([pose[1], matrix_to_6d(pose[0])])[None], dtype=torch.float32)
        return self._position(self.attack(self._input(image), y))

"""Closed-loop rendezvous guided by the pose estimator (SPEC 5), with an optional attack window.

Frames (those of pipeline/trajectories.py). The world frame is target-centred with the approach
along +z; the state `rel` (target position relative to the chaser, world axes, metres) starts at
(0, 0, 60) and the goal is (0, 0, 10), the label position t of an image taken by a camera looking
along +z. The camera attitude R_c (camera -> world, OpenCV camera axes, `look_at`) changes: after
every step the chaser re-points its camera at where it believes the target is. The image shows
the target at t = R_c^T rel with attitude R_c^T R_target; the estimator's camera-frame t_pred
becomes the world estimate R_c t_pred.

Control law (per axis): cmd = clip(est - goal, -max_step, max_step).
- variant "paper": the next true state is computed from the estimate, rel <- est - cmd (the
  paper's simplification: the chaser ends up where it believes it goes);
- variant "true_state": the command is applied to the true state, rel <- rel - cmd.
A run lasts `max_steps` steps (the nominal approach 60 m -> 10 m takes 50); it is judged at the
end: within `tolerance` of the goal or not. It stops early when the target's centre leaves the
image ("target lost"). The attack starts at the first step whose true range is at or below S
and lasts K consecutive frames (fewer if the run ends first).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.camera import Intrinsics
from pipeline.trajectories import look_at, pose_in_camera

VARIANTS = ("paper", "true_state")
HELD = "rendezvous held"
SUCCEEDED = "attack succeeded"
LOST = "target lost"
MISSED = "missed without attack"

RenderFn = Callable[[np.ndarray, np.ndarray], Any]
"""render(R, t) -> image (passed as is to the estimator): target attitude R (target -> camera),
position t (camera frame, m)."""
EstimateFn = Callable[[Any, bool, tuple[np.ndarray, np.ndarray]], np.ndarray]
"""estimate(image, attacked, (R, t) true pose) -> t_pred (3,), camera frame, metres."""


@dataclass(frozen=True)
class AttackWindow:
    """Attack the K = `length` frames from the first one at true range <= `start_range` (m)."""

    start_range: float
    length: int


@dataclass(frozen=True)
class GuidanceSettings:
    """Start and goal of `rel` (world frame, metres), tolerance (m), per-axis step limit (m)."""

    start: tuple[float, float, float] = (0.0, 0.0, 60.0)
    goal: tuple[float, float, float] = (0.0, 0.0, 10.0)
    tolerance: float = 1.0
    max_step: float = 1.0
    max_steps: int = 60
    variant: str = "paper"

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown guidance variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.tolerance <= 0 or self.max_step <= 0 or self.max_steps < 1:
            raise ValueError("guidance tolerance and max_step must be positive and max_steps >= 1, got "
                             f"{self.tolerance}, {self.max_step}, {self.max_steps}")
        if np.linalg.norm(self.goal) >= np.linalg.norm(self.start):
            raise ValueError(f"the guidance goal {self.goal} must be closer to the target than the start {self.start}")

    def window(self, start_range: float, length: int) -> AttackWindow:
        """A validated attack window: S between the goal range and the start range, K >= 1."""
        lo, hi = float(np.linalg.norm(self.goal)), float(np.linalg.norm(self.start))
        if not lo <= start_range <= hi:
            raise ValueError(f"attack start range S={start_range} m is outside the trajectory: the range goes "
                             f"from {hi:g} m to {lo:g} m")
        if int(length) < 1:
            raise ValueError(f"attack length K must be at least 1 frame, got {length}")
        return AttackWindow(float(start_range), int(length))


@dataclass
class RendezvousResult:
    """One closed-loop run. positions: (n+1, 3) true rel after each step (first row = start);
    estimates: (n, 3) world-frame estimates; attacked: (n,) bool; miss: final ||rel - goal|| (m)."""

    positions: np.ndarray
    estimates: np.ndarray
    attacked: np.ndarray
    outcome: str
    miss: float
    attack_start: int | None

    @property
    def attacked_frames(self) -> int:
        return int(self.attacked.sum())


def in_view(t: np.ndarray, K: Intrinsics) -> bool:
    """Whether a camera-frame point (m) is in front of the camera and projects inside the image."""
    if t[2] <= 0:
        return False
    u, v = K.fx * t[0] / t[2] + K.cx, K.fy * t[1] / t[2] + K.cy
    return bool(-0.5 <= u <= K.width - 0.5 and -0.5 <= v <= K.height - 0.5)


def arrival_step(result: "RendezvousResult", goal: tuple[float, float, float] | np.ndarray,
                 tolerance: float) -> int | None:
    """Steps after which the chaser is within `tolerance` (m) of `goal` and stays there to the end of
    the run, or None when the run does not end there."""
    inside = np.linalg.norm(result.positions - np.asarray(goal, dtype=np.float64), axis=1) <= tolerance
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return int(outside[-1] + 1) if len(outside) else 0


def guidance_step(est: np.ndarray, rel: np.ndarray, goal: np.ndarray, max_step: float,
                  variant: str) -> tuple[np.ndarray, np.ndarray]:
    """One application of the control law -> (next true rel, rel the chaser believes it reaches)."""
    cmd = np.clip(est - goal, -max_step, max_step)
    believed = est - cmd
    return (believed if variant == "paper" else rel - cmd), believed


def run_rendezvous(render: RenderFn, estimate: EstimateFn, K: Intrinsics, settings: GuidanceSettings,
                   window: AttackWindow | None = None,
                   target_attitude: np.ndarray | None = None) -> RendezvousResult:
    """Fly the closed loop: render the true pose, estimate it (attacked inside the window), move.

    `target_attitude` is the target -> world rotation (identity by default).
    """
    R_tw = np.eye(3) if target_attitude is None else np.asarray(target_attitude, dtype=np.float64)
    goal = np.asarray(settings.goal, dtype=np.float64)
    rel = np.asarray(settings.start, dtype=np.float64)
    R_c = look_at(rel)
    positions, estimates, attacked = [rel], [], []
    attack_start: int | None = None
    lost = False
    for k in range(settings.max_steps):
        R, t = pose_in_camera(rel, R_c, R_tw)
        if window is not None and attack_start is None and np.linalg.norm(rel) <= window.start_range + 1e-6:
            attack_start = k
        hit = attack_start is not None and k < attack_start + window.length
        t_pred = np.asarray(estimate(render(R, t), hit, (R, t)), dtype=np.float64)
        est = R_c @ t_pred
        rel, believed = guidance_step(est, rel, goal, settings.max_step, settings.variant)
        if np.linalg.norm(believed) > 1e-6:
            R_c = look_at(believed)
        positions.append(rel)
        estimates.append(est)
        attacked.append(hit)
        if not in_view(R_c.T @ rel, K):
            lost = True
            break
    attacked_arr = np.array(attacked, dtype=bool)
    miss = float(np.linalg.norm(rel - goal))
    if lost:
        outcome = LOST
    elif miss <= settings.tolerance:
        outcome = HELD
    else:
        outcome = SUCCEEDED if attacked_arr.any() else MISSED
    return RendezvousResult(np.array(positions), np.array(estimates).reshape(-1, 3), attacked_arr,
                            outcome, miss, attack_start)


class CachedCamera:
    """The chaser's camera and pose CNN for `run_rendezvous`, with an image cache.

    Every attacked run follows the no-attack baseline until its attack starts, and Cycles and the CNN
    are deterministic, so each rendered pose's image and clean position estimate are kept. `render`
    and `estimate` are the RenderFn and EstimateFn; attacked frames go through `attack(x, y)` (images
    (1, 3, H, W) in [0, 1], labels (1, 9): metres, 6-D) which `self.attack` may be changed to between
    runs. `counts`: guidance steps, rendered frames, attacked frames.
    """

    def __init__(self, render_image: Callable[[np.ndarray, np.ndarray], np.ndarray], model: Any,
                 attack: Callable[[Any, Any], Any] | None = None):
        self.render_image, self.model, self.attack = render_image, model, attack
        self.cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
        self.counts = {"steps": 0, "renders": 0, "attacked": 0}

    @staticmethod
    def _input(image: np.ndarray) -> Any:
        import torch

        return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255

    def _position(self, x: Any) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.model(x)[0, :3].numpy().astype(np.float64)

    def render(self, R: np.ndarray, t: np.ndarray) -> tuple[bytes, np.ndarray]:
        key = np.round(np.concatenate([R.ravel(), t]), 9).tobytes()
        if key not in self.cache:
            image = self.render_image(R, t)
            self.cache[key] = (image, self._position(self._input(image)))
            self.counts["renders"] += 1
        self.counts["steps"] += 1
        return key, self.cache[key][0]

    def estimate(self, rendered: tuple[bytes, np.ndarray], attacked: bool,
                 pose: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        import torch

        from pipeline.rotations import matrix_to_6d

        key, image = rendered
        if not attacked:
            return self.cache[key][1]
        if self.attack is None:
            raise ValueError("an attacked frame but no attack was given")
        self.counts["attacked"] += 1
        y = torch.as_tensor(np.concatenate([pose[1], matrix_to_6d(pose[0])])[None], dtype=torch.float32)
        return self._position(self.attack(self._input(image), y))

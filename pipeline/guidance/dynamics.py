"""The chaser's executed motion: the commanded displacement as the thrusters and the orbit carry it out.

Frames (pipeline/geometry/trajectories.py). `rel` is the target relative to the chaser camera, world
axes, metres; a command moves the chaser by `cmd` (world, m), so without error rel <- rel - cmd. The
motion filter and the protection level (pipeline/defense/kalman.py, protection.py) are told the
command only; this module is the truth they do not know.

Execution error (per step, per thruster axis; Gates 1963). A maneuver's execution error is a part
proportional to the commanded velocity change (thrust level / shut-off, magnitude and pointing) plus
a fixed part independent of it (Gates, "A Simplified Model of Midcourse Maneuver Execution Errors",
JPL TR 32-504, 1963; the model as CNES's PATRIUS implements it, `GatesModel`, magnitude and direction
errors proportional to the delta-v, Gaussian). Per step k and per thruster axis i (the chaser's body
axes, `axes` below: the camera axes, boresight along the line of sight), the executed chaser
displacement along that axis is
    d_i = (1 + scale_std * a_i) c_i + noise_std * b_i,      a, b ~ N(0, 1), drawn afresh every step,
with c_i the command along the axis (m).
Defaults and where they come from:
- scale_std = 0.02 (2 % 1-sigma per axis, ~6 % 3-sigma): "a thruster may generate a slightly different
  thrust than commanded ... in the order of percents (e.g. 1 % - 5 %)", simulated as a normal error on
  the thrust magnitude (Okapi:Orbits, "Space debris: can CubeSats be used sustainably? (continued)",
  https://okapiorbits.space/space-debris-can-cubesats-be-used-sustainably-continued/); Monte Carlo
  tools take the same form, a 3-sigma percentage on the delta-v magnitude and direction, e.g. 5 %
  (nyx-space `mc::helpers`, https://docs.rs/nyx-space/1.1.0/nyx_space/mc/helpers/index.html). Cold-gas
  systems are chosen for the repeatability of their impulse bit (Spacecraft Propulsion Systems,
  chapter 1, cold gas: impulse bits down to 1e-5 N s); a monopropellant RCS in short pulses sits at the
  upper end of that range.
- noise_std = 0.01 m per axis per step: the fixed (Gates) part. A step is started and stopped by
  pulses; what remains is of the order of one minimum impulse bit per axis. For a ~150 kg chaser (the
  PRISMA main spacecraft's class, SSC, "PRISMA - Swedish in-orbit testbed for rendezvous and formation
  flying") an impulse bit of 0.01-0.1 N s (1 N-class cold-gas or monopropellant thrusters in pulse
  mode; our assumption, not a datasheet figure) leaves 0.07-0.7 mm/s, i.e. 0.7-7 mm over a 10 s step:
  1 cm 1-sigma per axis is the conservative end.
- relative orbital motion (Clohessy-Wiltshire) over the frame interval: mean motion n (rad/s; LEO
  ~0.0011 rad/s, a 95-minute orbit) and frame interval dt (s, default 10 s: 1 m steps at 0.1 m/s, the
  speed of a final approach). Each step is a stop-and-go hop: the chaser starts it at rest relative to
  the target (the previous step's braking pulse nulled its velocity; the braking error is part of the
  execution error), leaves with velocity d / dt (d the executed displacement above, world) and coasts
  dt under the CW equations, so it arrives at Phi_rr p + Phi_rv d / dt instead of p + d (p = -rel the
  chaser's position relative to the target). World axes map to the Hill frame (x radial, y
  along-track, z orbit normal) of a V-bar approach (the chaser behind the target, the approach along
  the orbital velocity: world z = along-track, world y = nadir = -radial, world x = -orbit normal) or an
  R-bar approach (the chaser below the target: world z = radial, world y = along-track, world x =
  -orbit normal). With the defaults the CW term is millimetres per step near the V-bar (radial offsets
  drift most): the truth's motion is dominated by the thrusters' errors.
A hold (no command) keeps station: the chaser stays where it is (its controller nulls the drift).

Per step the error's std per axis is about sqrt((scale_std c)^2 + noise_std^2): 2.2 cm for a 1 m step,
1.1 cm for a 0.25 m one: the filter's process noise takes the same form (`MotionSettings.position_noise`
and `position_noise_scale`, its `step_variance`; the library defaults, 5 mm and 0, are a filter's without
a thruster model): it must not be told the truth, only how uncertain the commands are.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.geometry.trajectories import look_at
from pipeline.guidance.settings import ExecutionSettings

# Hill (x radial, y along-track, z orbit normal) <- world, per approach: rows are the Hill axes in world axes
_HILL_FROM_WORLD = {
    "vbar": np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]),
    "rbar": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
}


def cw_matrices(mean_motion: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Phi_rr, Phi_rv) (3, 3) of the Clohessy-Wiltshire equations in the Hill frame (x radial, y
    along-track, z orbit normal) over dt (s) at mean motion n (rad/s): position after dt = Phi_rr p0 +
    Phi_rv v0 (m, m/s). n = 0: free motion (I, dt I)."""
    n, t = float(mean_motion), float(dt)
    if n == 0.0:
        return np.eye(3), t * np.eye(3)
    s, c = math.sin(n * t), math.cos(n * t)
    rr = np.array([[4 - 3 * c, 0.0, 0.0], [6 * (s - n * t), 1.0, 0.0], [0.0, 0.0, c]])
    rv = np.array([[s / n, 2 * (1 - c) / n, 0.0], [-2 * (1 - c) / n, (4 * s - 3 * n * t) / n, 0.0], [0.0, 0.0, s / n]])
    return rr, rv


class Executor:
    """Executes commanded steps one after another (`step`), drawing the errors from `settings.draws()`
    in step order, so two runs with the same settings see the same errors step for step."""

    def __init__(self, settings: ExecutionSettings):
        self.settings = settings
        self.rng = settings.draws()
        H = _HILL_FROM_WORLD[settings.approach]
        rr, rv = cw_matrices(settings.mean_motion, settings.frame_interval)
        self._rr, self._rv = H.T @ rr @ H, H.T @ rv @ H / settings.frame_interval  # world axes; rv per metre of step

    def step(self, rel: np.ndarray, cmd: np.ndarray, axes: np.ndarray | None = None) -> np.ndarray:
        """The next true rel (world, m) after commanding the chaser to move by `cmd` (world, m) from
        `rel`; `axes` (3, 3) thruster (body) axes -> world, by default the camera pointing at `rel`
        (`look_at`). Six normals are drawn whether or not the step moves, so the errors stay aligned
        with the step count; a zero command (a hold) keeps station."""
        rel, cmd = np.asarray(rel, np.float64), np.asarray(cmd, np.float64)
        a, b = self.rng.standard_normal(3), self.rng.standard_normal(3)
        if not cmd.any():
            return rel.copy()
        A = look_at(rel) if axes is None else np.asarray(axes, np.float64)
        s = self.settings
        body = A.T @ cmd
        executed = A @ ((1.0 + s.scale_std * a) * body + s.noise_std * b)
        return -(self._rr @ -rel + self._rv @ executed)


def execute_plan(planned: np.ndarray, settings: ExecutionSettings) -> np.ndarray:
    """The rel actually flown (n, 3) (world, m) when the chaser starts at `planned[0]` and commands each
    planned step planned[k] - planned[k-1] open loop (no feedback: the evaluation trajectories, whose
    commands the chain is told), the body axes pointing at the planned rel."""
    planned = np.asarray(planned, np.float64)
    if planned.ndim != 2 or planned.shape[1] != 3 or len(planned) < 1 or not np.isfinite(planned).all():
        raise ValueError(f"execute_plan needs a finite planned rel of shape (n, 3), got {planned.shape}")
    ex = Executor(settings)
    flown = [planned[0]]
    for k in range(1, len(planned)):
        # rel <- rel - cmd: the chaser moves by cmd = -(planned step of rel)
        flown.append(ex.step(flown[-1], planned[k - 1] - planned[k], look_at(planned[k - 1])))
    return np.array(flown)

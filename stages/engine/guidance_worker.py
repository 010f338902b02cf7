"""The guidance stage's engine worker: one Blender scene and two safety chains per worker (the paper grid's,
the standard model's, which also flies as the defended "standard" chain; and the shipped one, the robust model's:
stages.artifacts.paths.PAPER, SHIPPED), one flight of the grid (pipeline.guidance.grid.GridPlan) per job;
stages/guidance.py builds the jobs.

Each attacked run's attack is seeded by its place in the grid, and each rendered pose's background
(render.background) by the pose itself, so the flights do not depend on which worker flies which run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from stages.artifacts.models import load_chain
from stages.artifacts.paths import PAPER, SHIPPED
from stages.config.build import capture_settings, in_loop_attack, in_loop_settings, make_attack
from stages.config.schema import Params


@dataclass(frozen=True)
class GuidanceSetup:
    """What one GuidanceWorker holds: the camera, the scene, where the chains' model files are and the grid."""

    params: Params  # typed params (device, `attack` section, `guidance.method`, the in-loop attacker's `integrity`)
    K: Any  # pipeline.geometry.camera.Intrinsics: the pose model's input size (pixels)
    scene: Any  # pipeline.render.scene.SceneSettings, checked by stages.engine.chunks.prepare
    root: str  # the folder holding models/, as an absolute path (a worker may run elsewhere)
    defense: Any  # pipeline.defense.chain.Defended of the shipped chain: a fresh Defense per run
    plan: Any  # pipeline.guidance.law.GridPlan: every run of the grid
    seed: int  # the attack seed of run 0 (params seed + the stage's offset); the backgrounds'
    torch_threads: int | None  # torch threads of this worker; None: left as set up
    standard_defense: Any = None  # the standard chain's Defended (models/defense_standard.json); None: not flown


@dataclass(frozen=True)
class Flight:
    """One guidance job: one run of the plan."""

    chain: str  # "paper" (the paper grid), "shipped" or "standard" (pipeline.guidance.grid.CHAINS)
    dynamics: str  # the chaser's dynamics (a name of guidance.dynamics)
    defense: str  # "undefended" or a name of guidance.defenses
    cell: Any  # index of the (eps, S, K) attack window in plan.grid, an InLoopRun, or None: the no-attack run


def flights(plan: Any) -> list[Flight]:
    """Every run of a GridPlan as a job, in plan order (the paper grid first)."""
    return [Flight(chain=chain, dynamics=dyn, defense=defense, cell=cell) for chain, dyn, defense, cell in plan.runs()]


class GuidanceWorker:
    """One Blender scene and the two safety chains, built once per engine worker: `run(Flight)` flies that
    run of the plan (pipeline.guidance.grid.GridPilot) -> (result, keys of the poses it rendered)."""

    def __init__(self, setup: GuidanceSetup) -> None:
        from pipeline.attacks.gradient import attack_loss, stored_attack
        from pipeline.guidance.grid import GridPilot
        from pipeline.guidance.law import CachedCamera
        from pipeline.render.scene import Renderer

        if setup.torch_threads:
            import torch

            torch.set_num_threads(setup.torch_threads)
        chains = {
            "paper": load_chain(setup.params, PAPER, setup.root, defended=False),
            "shipped": load_chain(setup.params, SHIPPED, setup.root, defended=False),
        }
        losses = {name: attack_loss(setup.params.attack.loss, chain.loss) for name, chain in chains.items()}
        a, method, seed = setup.params.attack, setup.params.guidance.method, setup.seed

        def attack_at(name: str, eps: float, i: int) -> Any:
            return stored_attack(chains[name].model, losses[name], eps, make_attack(a, method, seed + i))

        self.renderer = Renderer(setup.K, setup.scene)
        images: dict[bytes, Any] = {}  # both chains see the same rendered poses: each is rendered once
        render_image = pose_renderer(self.renderer, setup.seed)
        cameras = {
            name: CachedCamera(render_image, c.model, chain=c.onboard, images=images) for name, c in chains.items()
        }
        cameras["standard"] = cameras["paper"]  # the same model and detector; the defense is the run's
        defenses = {"shipped": setup.defense, "standard": setup.standard_defense}
        in_loop = in_loop_attackers(setup.params, {"shipped": chains["shipped"], "standard": chains["paper"]}, seed)
        self.pilot = GridPilot(cameras, setup.K, setup.plan, attack_at, defenses, in_loop)

    def run(self, job: Flight) -> tuple[Any, frozenset[bytes]]:
        return self.pilot.fly(job.chain, job.dynamics, job.defense, job.cell)

    def close(self) -> None:
        self.renderer.close()


def in_loop_attackers(p: Params, chains: dict[str, Any], seed: int) -> dict[str, Callable[[float, str, int], Any]]:
    """Per chain name (of `chains`: the loaded chains it attacks) `in_loop_at(eps, goal, i)`: the in-loop attacker
    of run i (pipeline/attackers/in_loop.py; goal capture: pipeline/attackers/capture.py), seeded `seed` + i, on that
    chain's pose model, SHAP explainer and detector."""
    from pipeline.attackers.capture import CaptureInLoop
    from pipeline.attackers.in_loop import InLoopAttacker
    from pipeline.attacks.adaptive import PerFrameChain

    capture = (
        capture_settings(p, "lateral", p.integrity.capture_initial[0])
        if "capture" in p.integrity.in_loop_goals
        else None
    )

    def on(chain: Any) -> Callable[[float, str, int], Any]:
        target = PerFrameChain(chain.onboard.model, chain.onboard.shap, chain.onboard.detector)

        def in_loop_at(eps: float, goal: str, i: int) -> Any:
            if goal == "capture":
                return CaptureInLoop(target, eps, capture, frame_attack=in_loop_attack(p), seed=seed + i)
            return InLoopAttacker(target, eps, in_loop_settings(p, goal), seed + i)

        return in_loop_at

    return {name: on(chain) for name, chain in chains.items()}


def pose_renderer(renderer: Any, seed: int) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """`renderer.render` (a pipeline.render.scene.Renderer) for poses rendered on demand: each pose (R target ->
    camera, t in metres) over its background draw of the renderer's settings.background from `seed`, keyed by the
    pose itself. The grid flies the target at rest (pipeline.guidance.law.run_rendezvous: identity target
    attitude), so the camera -> world rotation is R^T."""
    from pipeline.render.backgrounds import draw, pose_key

    background = renderer.settings.background

    def render(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        return renderer.render(R, t, draw(background, R.T, seed, pose_key(R, t)))

    return render

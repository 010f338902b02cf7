"""The attack stage's engine worker: one pose model per worker, one batch of test images per job.

Each batch's attack is seeded by its place (`AttackSetup.seed` + first row // batch), so the stored
adversarial images do not depend on which worker attacks which batch (stages/attack.py builds the jobs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from stages.artifacts.models import load_pose
from stages.config.build import make_attack
from stages.config.schema import Params


@dataclass(frozen=True)
class AttackSetup:
    """What one AttackWorker holds: the pose model and the attack settings."""

    params: Params  # typed params (the pose model's device and `attack` section)
    pose_path: str  # models/pose.pt as an absolute path (a worker may run elsewhere)
    eps: tuple[float, ...]  # L-inf budgets, in units of the [0, 1] pixel range
    batch: int  # images per job (the last may hold fewer)
    seed: int  # the attack seed of the first batch (params seed + the stage's offset)
    torch_threads: int | None  # torch threads of this worker; None: left as set up


@dataclass(frozen=True)
class AttackBatch:
    """One attack job: test rows first .. first + B - 1."""

    first: int  # test row of the first image (a multiple of the batch size)
    images: np.ndarray  # (B, H, W, 3) uint8 test images
    labels: Any  # torch.Tensor (B, 9) float32: position (camera frame, metres), 6-D rotation


class AttackWorker:
    """The pose model (loaded once per engine worker): `run(AttackBatch)` attacks one batch at every
    eps -> {"clean": pose outputs (B, 9) on the clean images, eps: (stored uint8 images (B, H, W, 3),
    pose outputs on them, pose outputs on the float adversarial images, their stored L-inf)}."""

    def __init__(self, setup: AttackSetup) -> None:
        import torch

        from pipeline.attacks.gradient import attack_loss

        if setup.torch_threads:
            torch.set_num_threads(setup.torch_threads)
        pose = load_pose(setup.params, setup.pose_path)
        self.model, self.loss_fn = pose.model.eval(), attack_loss(setup.params.attack.loss, pose.loss)
        self.a, self.seed, self.eps_list, self.batch = setup.params.attack, setup.seed, setup.eps, setup.batch

    def run(self, job: AttackBatch) -> dict[str, Any]:
        from pipeline.attacks.every_eps import attack_every_eps

        attack = make_attack(self.a, self.a.method, self.seed + job.first // self.batch)
        return attack_every_eps(self.model, self.loss_fn, attack, job.images, job.labels, self.eps_list)

    def close(self) -> None:
        pass

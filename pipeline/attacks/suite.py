"""The chain-level attackers by name (their interface: pipeline/attacks/base.py); a new attacker adds its class here."""
from __future__ import annotations

from typing import Callable

from pipeline.attacks.base import SequenceAttacker
from pipeline.attacks.drift import DriftAttacker

ATTACKERS: dict[str, Callable[..., SequenceAttacker]] = {DriftAttacker.name: DriftAttacker}


def get_attacker(name: str, **options: object) -> SequenceAttacker:
    """The attacker `name` of ATTACKERS, built with `options` (its constructor's keywords)."""
    if name not in ATTACKERS:
        raise ValueError(f"unknown attacker {name!r}; choose one of {', '.join(sorted(ATTACKERS))}")
    return ATTACKERS[name](**options)

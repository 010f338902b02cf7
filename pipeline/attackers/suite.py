"""The chain-level attackers by name (their interface: pipeline/attackers/base.py); a new attacker adds its class here."""

from __future__ import annotations

import inspect
from typing import Callable

from pipeline.attackers.base import SequenceAttacker
from pipeline.attackers.burst import BurstAttacker
from pipeline.attackers.capture import CaptureAttacker
from pipeline.attackers.drift import DriftAttacker

ATTACKERS: dict[str, Callable[..., SequenceAttacker]] = {
    DriftAttacker.name: DriftAttacker,
    BurstAttacker.name: BurstAttacker,
    CaptureAttacker.name: CaptureAttacker,
}


def get_attacker(name: str, **options: object) -> SequenceAttacker:
    """The attacker `name` of ATTACKERS, built with `options` (its constructor's keywords); an unknown
    name or option is a one-line ValueError naming it."""
    if name not in ATTACKERS:
        raise ValueError(f"unknown attacker {name!r}; choose one of {', '.join(sorted(ATTACKERS))}")
    known = list(inspect.signature(ATTACKERS[name]).parameters)
    unknown = [k for k in options if k not in known]
    if unknown:
        raise ValueError(f"unknown {name} option {unknown[0]!r}; choose from {', '.join(known)}")
    return ATTACKERS[name](**options)

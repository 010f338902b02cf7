"""Params -> library objects: the one place where typed params (stages.config.schema) become the settings
pipeline/ takes (Intrinsics, SceneSettings, the attack, TrainConfig, AdversarialConfig, AugmentConfig, DefenseSettings,
MotionSettings, AlertLimitSettings, ExecutionSettings, the chain-level attackers, EngineSettings) and the lab mock-up
policy. Bad values raise a StageError naming the key.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any

from pipeline.settings import as_type, part
from stages.config.evaluation import Defense
from stages.config.params import given
from stages.config.schema import Params
from stages.config.sections import Adversarial, Attack, Augment, Guidance, Render, Train
from stages.config.suite import Suite
from stages.errors import StageError


def settings_of(cls: type, section: Any, library_defaults: tuple[str, ...] = (), **extra: Any) -> Any:
    """`cls` (a library settings dataclass) from the fields of a params `section` (a schema dataclass) of the
    same names and `extra` for the others; a value is converted to the library field's type (a whole number to
    float, a list to a tuple of it). A field of `cls` that neither gives keeps its library default only when
    named in `library_defaults` (a setting params.yaml does not set): any other gap, or a name there that `cls`
    lacks, is a TypeError, so a field renamed on one side fails loudly instead of falling back to its default
    (tests/test_architecture.py checks every section of `SECTION_SETTINGS` against its classes)."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    missing = sorted(names - set(extra) - {n for n in names if hasattr(section, n)} - set(library_defaults))
    if missing or not set(library_defaults) <= names:
        raise TypeError(
            f"{cls.__name__} from params section {type(section).__name__}: no value for {missing}, "
            f"unknown library defaults {sorted(set(library_defaults) - names)}"
        )
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in extra:
            values[f.name] = extra[f.name]
        elif hasattr(section, f.name):
            values[f.name] = as_type(getattr(section, f.name), hints[f.name])
    return cls(**values)


# params section still declared beside its library settings (the sections composed of theirs, render.background,
# train.augment, defense and guidance.execution, are built back with pipeline.settings `part`) -> the library settings
# dataclasses `settings_of` builds from it, and the section's fields that no library settings take (the stages read
# them themselves: sizes, counts, file and calibration params)
SECTION_SETTINGS: dict[str, tuple[str, ...]] = {
    "render": ("pipeline.render.scene:SceneSettings",),
    "train": ("pipeline.pose.train:TrainConfig",),
    "train.adversarial": ("pipeline.pose.adversarial:AdversarialConfig",),
    "suite": ("pipeline.attacks.strongest:SuiteConfig",),
    "suite.full": ("pipeline.attacks.strongest:SuiteConfig",),
}
STAGE_ONLY: dict[str, tuple[str, ...]] = {
    "render": (
        "chunk",
        "end_range",
        "frames_per_sequence",
        "height",
        "max_target_rotation_deg",
        "pointing_jitter_deg",
        "previews",
        "source",
        "source_test",
        "start_range",
        "target_attitude",
        "width",
    ),
    "train": ("adversarial", "augment", "compile", "dropout", "range_bins", "val_fraction", "width"),
    "train.adversarial": ("ablation", "black_level", "epochs", "init", "lr_max", "warmup_epochs"),
    "suite": ("capacity", "check_frames", "eps", "frames", "full", "full_frames"),
    "suite.full": (),
}


def intrinsics(params: Params) -> Any:
    """The render camera: K from params.camera at its reference size, scaled to render.width x height."""
    from pipeline.geometry.camera import Intrinsics

    c, r = params.camera, params.render
    try:
        return Intrinsics(c.ref_width, c.ref_height, c.fx, c.fy, c.cx, c.cy).scaled(r.width, r.height)
    except ValueError as e:
        raise StageError(f"params.yaml camera/render: {e}") from None


def scene_settings(render: Render) -> Any:
    """The Blender scene settings of a `render` params section (mesh None = the procedural target), with its
    background (`render.background`)."""
    from pipeline.render.scene import SceneSettings
    from pipeline.render.settings import BackgroundSettings

    return settings_of(
        SceneSettings,
        render,
        ("ambient", "max_bounces"),
        mesh=given(render.mesh),
        background=part(render.background, BackgroundSettings),
    )


def check_attack_params(section: Attack | Guidance, where: str) -> None:
    """Check the eps list and attack method of a section (`<where>.eps`, `<where>.method`) before any work."""
    from pipeline.attacks.gradient import ATTACKS, check_eps

    eps, method = section.eps, section.method
    if not eps:
        raise StageError(f"params.yaml {where}.eps must be a non-empty list of numbers in (0, 1]")
    for e in eps:
        try:
            check_eps(e)
        except (TypeError, ValueError):
            raise StageError(f"params.yaml {where}.eps: {e!r} is not in (0, 1] (pixels are in [0, 1])") from None
    if method not in ATTACKS:
        raise StageError(f"params.yaml {where}.method: unknown attack {method!r}; choose one of {', '.join(ATTACKS)}")


def make_attack(attack: Attack, method: str, seed: int) -> Any:
    """The attack named `method` with the iterative options of the `attack` params section."""
    import torch

    from pipeline.attacks.gradient import LOSSES, get_attack

    if attack.loss not in LOSSES:
        raise StageError(f"params.yaml attack.loss: unknown loss {attack.loss!r}; choose one of {', '.join(LOSSES)}")
    try:
        return get_attack(
            method,
            steps=attack.steps,
            step_size=attack.step_size,
            random_start=attack.random_start,
            momentum=float(attack.momentum),
            generator=torch.Generator().manual_seed(seed),
        )
    except ValueError as e:
        raise StageError(f"params.yaml attack: {e}") from None


def train_config(train: Train, epochs: int, seed: int) -> Any:
    """The TrainConfig of a `train` params section (ValueError on a bad value)."""
    from pipeline.pose.train import TrainConfig

    return settings_of(TrainConfig, train, epochs=epochs, seed=seed)


def robust_train_config(train: Train, seed: int) -> Any:
    """The TrainConfig of `rpod train --robust` (train.adversarial): the train recipe for adversarial.epochs
    epochs; fine-tuning (init: standard) on a cosine schedule warming up from min(train.lr_base, lr_max) to
    adversarial.lr_max over adversarial.warmup_epochs (ValueError on a bad value)."""
    from pipeline.pose.train import TrainConfig

    adv = train.adversarial
    if adv.init == "scratch":
        return settings_of(TrainConfig, train, epochs=adv.epochs, seed=seed)
    return settings_of(
        TrainConfig,
        train,
        epochs=adv.epochs,
        seed=seed,
        schedule="cosine",
        lr_base=min(float(train.lr_base), float(adv.lr_max)),
        lr_max=float(adv.lr_max),
        warmup_epochs=float(adv.warmup_epochs),
    )


def adversarial_config(adversarial: Adversarial) -> Any:
    """The AdversarialConfig of the `train.adversarial` params section."""
    from pipeline.pose.adversarial import AdversarialConfig

    try:
        return settings_of(AdversarialConfig, adversarial)
    except ValueError as e:
        raise StageError(f"params.yaml: bad train.adversarial ({e})") from None


def suite_config(suite: Suite, seed: int, full: bool = False) -> Any:
    """The SuiteConfig of the `suite` params section seeded `seed`: its members, steps, restarts and starts, or
    with `full` the full suite (pipeline/attacks/strongest.py FULL's members and starts) at the sizes of suite.full."""
    from pipeline.attacks.strongest import FULL, SuiteConfig

    try:
        if full:
            return settings_of(
                SuiteConfig,
                suite.full,
                ("p_init",),
                members=FULL.members,
                starts=FULL.starts,
                seed=seed,
            )
        return settings_of(SuiteConfig, suite, ("queries", "p_init", "square_eps"), seed=seed)
    except ValueError as e:
        raise StageError(f"params.yaml: bad suite section ({e})") from None


def augment_config(augment: Augment) -> Any:
    """The AugmentConfig of the `train.augment` params section."""
    from pipeline.pose.settings import AugmentConfig

    try:
        return part(augment, AugmentConfig)
    except ValueError as e:
        raise StageError(f"params.yaml: bad train.augment ({e})") from None


def defense_settings(defense: Defense, threshold: float, update_below: float | None = None) -> tuple[Any, Any]:
    """(DefenseSettings, MotionSettings) of params.defense with the detector's `threshold` and doubt level
    `update_below` (calibrated from `defense.doubt_share`; None: no doubt zone); a doubt level above the
    threshold starts at it."""
    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.settings import DefenseSettings

    doubt = None if update_below is None else min(float(update_below), threshold)
    try:
        return (
            part(defense, DefenseSettings, threshold=threshold, update_below=doubt),
            part(defense, MotionSettings),
        )
    except ValueError as e:
        raise StageError(f"params.yaml: {e}") from None


def execution_settings(params: Params, seed: int, step: float | None = None) -> Any:
    """The ExecutionSettings of params.guidance.execution with the errors' `seed` (pipeline/seeds.py); `step` (m per
    frame, e.g. an evaluation trajectory's 0.25 m): the frame interval of that step at the closed loop's speed
    (guidance.max_step per guidance.execution.frame_interval); None: the closed loop's own."""
    from pipeline.guidance.settings import ExecutionSettings

    x, g = params.guidance.execution, params.guidance
    interval = float(x.frame_interval) * (1.0 if step is None else float(step) / float(g.max_step))
    try:
        return part(x, ExecutionSettings, seed=int(seed), frame_interval=interval)
    except ValueError as e:
        raise StageError(f"params.yaml guidance.execution: {e}") from None


# AlertLimitSettings field -> the param that feeds it (the guidance law's constants are guidance's own)
ALERT_LIMIT_KEYS = {
    "tolerance": "guidance.tolerance",
    "max_step": "guidance.max_step",
    "slack_steps": "guidance.slack_steps",
    "collision_range": "integrity.collision_range_m",
    "fixed": "integrity.alert_limit_m",
    "goal_range": "guidance.target",
    "kind": "integrity.alert_limit_kind",
}


def alert_limit_settings(params: Params, kind: str | None = None) -> Any:
    """The AlertLimitSettings of pipeline.defense.integrity: the guidance law's tolerance, step limit, slack and goal
    range |guidance.target| (params.guidance) with params.integrity's collision range and AL kind (`kind` instead
    when given: the reports' second column), or integrity.alert_limit_m (m) when set."""
    from pipeline.defense.integrity import AlertLimitSettings

    g, i = params.guidance, params.integrity
    goal = sum(float(v) ** 2 for v in g.target) ** 0.5
    try:
        return AlertLimitSettings(
            float(g.tolerance),
            float(g.max_step),
            g.slack_steps,
            float(i.collision_range_m),
            None if i.alert_limit_m is None else float(i.alert_limit_m),
            goal,
            i.alert_limit_kind if kind is None else kind,
        )
    except ValueError as e:
        name = next((k for k in ALERT_LIMIT_KEYS if f" {k} must" in str(e)), "kind")
        raise StageError(f"params.yaml {ALERT_LIMIT_KEYS[name]}: {e}") from None


def burst_attacker(params: Params, seed: int) -> Any:
    """The BurstAttacker of params.integrity (AL as a function of the true range, as the integrity rows judge it;
    its objective and hinge margins)."""
    from pipeline.attackers.suite import get_attacker
    from pipeline.defense.integrity import alert_limit

    i, limit = params.integrity, alert_limit_settings(params)
    al = lambda rng: alert_limit(rng, limit)  # noqa: E731
    try:
        return get_attacker(
            "burst",
            alert_limit=al,
            cap=float(i.burst_cap),
            steps=i.burst_steps,
            restarts=i.burst_restarts,
            lambdas=tuple(float(v) for v in i.burst_lambdas),
            seed=seed,
            objective=i.burst_objective,
            hinge=None if i.burst_hinge is None else float(i.burst_hinge),
        )
    except ValueError as e:
        raise StageError(f"params.yaml integrity: {e}") from None


def drift_settings(params: Params, direction: str) -> Any:
    """The DriftSettings of params.integrity for `direction` (los or lateral)."""
    from pipeline.attackers.drift import DriftSettings

    try:
        return DriftSettings(direction=direction, gate_fraction=float(params.integrity.drift_gate_fraction))
    except ValueError as e:
        raise StageError(f"params.yaml integrity.attackers / drift_gate_fraction: {e}") from None


def capture_settings(params: Params, direction: str, initial: float) -> Any:
    """The CaptureSettings of params.integrity for `direction` (los or lateral) and the held bias `initial` (m)."""
    from pipeline.attackers.capture import CaptureSettings

    i = params.integrity
    try:
        return CaptureSettings(
            direction=direction,
            initial=float(initial),
            rate=float(i.capture_rate),
            gate_fraction=float(i.drift_gate_fraction),
        )
    except ValueError as e:
        raise StageError(f"params.yaml integrity.capture_initial / capture_rate: {e}") from None


def frame_attack(params: Params) -> Any:
    """The per-frame attack of the drift and the capture: targeted PGD of integrity.frame_steps steps from the
    background-lifting start, with BPDA through the robust model's black-level clamp (pipeline/attacks/starts.py,
    bpda.py; a model without a clamp gets a random start and its plain gradient)."""
    from pipeline.attackers.drift import TargetedPGD

    return TargetedPGD(steps=params.integrity.frame_steps, start="lift", bpda=True)


def in_loop_attack(params: Params) -> Any:
    """The per-frame attack of the in-loop capture: targeted PGD of integrity.in_loop_steps steps from the lifting
    start with BPDA through the clamp (as `frame_attack`)."""
    from pipeline.attackers.drift import TargetedPGD

    return TargetedPGD(steps=params.integrity.in_loop_steps, start="lift", bpda=True)


def in_loop_settings(params: Params, goal: str) -> Any:
    """The InLoopSettings of params.integrity for `goal` (collide or miss); its stealth is the drift's gate fraction."""
    from pipeline.attackers.in_loop import InLoopSettings

    i = params.integrity
    try:
        return InLoopSettings(goal=goal, steps=i.in_loop_steps, gate_fraction=float(i.drift_gate_fraction))
    except ValueError as e:
        raise StageError(f"params.yaml integrity.in_loop_goals / in_loop_steps: {e}") from None


def mockup(params: Params) -> tuple[str | None, float]:
    """(mesh file or None = procedural target, metres per mesh unit) of the mock-up rendered at lab.scale x
    its size, i.e. at the size of the real target. Relative paths are resolved against the working folder."""
    lab, r = params.lab, params.render
    if given(lab.mesh) is None:  # the main target, built at 1/scale: rendered at scale x it is the main mesh
        mesh, unit = given(r.mesh), float(r.mesh_scale)
    else:
        mesh, unit = lab.mesh, float(lab.mesh_scale) * float(lab.scale)
    if mesh is None:
        return None, unit
    path = Path(mesh).resolve()
    if not path.is_file():
        key = "render.mesh" if given(lab.mesh) is None else "lab.mesh"
        raise StageError(f"params.yaml {key}: mock-up mesh file {mesh} not found")
    return str(path), unit


def retrain_reason(params: Params) -> str | None:
    """Why the lab stage must train its own models, or None when it may reuse the main ones."""
    lab, r = params.lab, params.render
    if lab.retrain == "always":
        return "lab.retrain is always"
    mesh, unit = mockup(params)
    main = None if given(r.mesh) is None else str(Path(r.mesh).resolve())
    if mesh != main or abs(unit - float(r.mesh_scale)) > 1e-9 * max(unit, 1.0):
        return (
            f"the mock-up (lab.mesh {lab.mesh}, {lab.mesh_scale:g} m per unit, x{lab.scale:g}) is not "
            f"the main target (render.mesh {r.mesh}, {r.mesh_scale:g} m per unit)"
        )
    return None

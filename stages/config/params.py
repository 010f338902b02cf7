"""Params: compose profiles into params.yaml, load it typed for a stage, and the fingerprints of its sections."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import json
from pathlib import Path
from typing import Any, Callable

import yaml

from pipeline.io.atomic import atomic_write_text
from pipeline.io.files import read_yaml
from pipeline.seeds import run_base
from stages.config.schema import Params, build
from stages.config.sections import ParamsError, Render

ROOT = Path(__file__).resolve().parents[2]  # the repository (package) root: code-side files only
CONF_DIR = ROOT / "conf"  # the source of params.yaml: config.yaml and profile/*.yaml
PARAMS_FILE = Path("params.yaml")  # in the working folder, like every output

# The value of an unset external input (render.mesh, render.source, lab.mesh, lab.real_data): a tracked
# folder, because dvc.yaml lists these params' paths as deps and a dep must exist (null cannot be one).
NONE = "inputs/none"


def profiles() -> list[str]:
    """Names of the profiles in conf/profile/."""
    return sorted(p.stem for p in (CONF_DIR / "profile").glob("*.yaml"))


def compose(profile: str = "default", overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose conf/config.yaml with one profile (and optional Hydra overrides) via Hydra."""
    if profile not in profiles():
        raise ParamsError(f"unknown profile {profile!r}; choose one of {', '.join(profiles())} (conf/profile/)")
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra_compose(config_name="config", overrides=[f"profile={profile}", *(overrides or [])])
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


# The envelope trajectory generator (stages/eval_render.py `trajectories`) of the detector split and the envelope
# validation frames: in the fingerprints of those renders, so a render made before it (issue 27) is refused.
ENVELOPE = "operational-envelope-1"


def render_record(render: Render) -> dict[str, Any]:
    """The `render` params section as a mapping (meta.json's `render`), its `background` left out while it is off
    (share 0), the default target attitude (per_frame) and the default Cycles device (cpu) left out: the renders
    made before these options existed keep their meta.json and fingerprints."""
    r = dataclasses.asdict(render)
    if render.background.share == 0:
        r.pop("background")
    if r["target_attitude"] == "per_frame":
        r.pop("target_attitude")
    if r["device"] == "cpu":
        r.pop("device")
    return r


def render_key(params: Params) -> dict[str, Any]:
    """The `render` params as fingerprints hash them (`render_record`): unset external inputs (null or inputs/none)
    as null and an unset SPEED source left out (the mapping params.yaml holds: stages.config.schema)."""
    r = render_record(params.render)
    r["mesh"] = given(r["mesh"])
    if given(r["source"]) is None:
        r.pop("source"), r.pop("source_test")
    return r


def fingerprint(key: dict[str, Any]) -> str:
    """16 hex digits of the SHA-256 of `key` as JSON with sorted keys."""
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


def render_fingerprint(params: Params) -> str:
    """Hash of everything that decides the rendered images (`seed`, `camera`, `render`): the render
    stage stamps it into datasets/render/meta.json; every reader of the renders compares it."""
    return fingerprint({"seed": params.seed, "camera": dataclasses.asdict(params.camera), "render": render_key(params)})


def evaluation_seed(params: Params) -> int:
    """The base seed of the evaluation trajectories (their paths, pointing jitter, execution errors and attack
    schedules): it follows `seed` (pipeline/seeds.py run_base: hashed from `seed` and the set's name)."""
    return run_base(params.seed, "evaluate")


def validation_seed(params: Params) -> int:
    """The base seed of the defense's validation trajectories (datasets/val_render, val_envelope): it follows `seed`
    (pipeline/seeds.py run_base: hashed from `seed` and the set's name), never the evaluation's."""
    return run_base(params.seed, "validation")


def heldout_seed(params: Params) -> int:
    """The base seed of the final held-out trajectories (`rpod heldout`): it follows `seed` (pipeline/seeds.py
    run_base: hashed from `seed` and the set's name), never the evaluation's or the validation's, and no choice or
    calibration reads them."""
    return run_base(params.seed, "heldout")


def _execution_key(params: Params) -> dict[str, Any]:
    """What decides the flown motion of the evaluation and validation trajectories: guidance.execution and the
    closed loop's step (their frame interval is taken at its speed)."""
    return {**dataclasses.asdict(params.guidance.execution), "max_step": params.guidance.max_step}


def eval_render_fingerprint(params: Params) -> str:
    """Hash of the params that decide the `eval_render` images (so a stale render is refused)."""
    e = params.evaluate
    return fingerprint(
        {
            "seed": params.seed,
            "camera": dataclasses.asdict(params.camera),
            "render": render_key(params),
            "evaluate": {
                "trajectories": e.trajectories,
                "frames": e.frames,
                "lateral_range": e.lateral_range,
                "seed": evaluation_seed(params),
            },
            "execution": _execution_key(params),
        }
    )


def heldout_fingerprint(params: Params) -> str:
    """Hash of the params that decide a held-out set's images (datasets/heldout/<camera>: the evaluation's kind of
    approach from the held-out base, with `params`' camera)."""
    e = params.evaluate
    return fingerprint(
        {
            "seed": params.seed,
            "camera": dataclasses.asdict(params.camera),
            "render": render_key(params),
            "evaluate": {"trajectories": e.trajectories, "frames": e.frames, "lateral_range": e.lateral_range},
            "heldout": heldout_seed(params),
            "execution": _execution_key(params),
        }
    )


def val_render_fingerprint(params: Params) -> str:
    """Hash of the params that decide the defense's validation images (datasets/val_render)."""
    e, d = params.evaluate, params.defense
    return fingerprint(
        {
            "seed": params.seed,
            "camera": dataclasses.asdict(params.camera),
            "render": render_key(params),
            "evaluate": {"frames": e.frames, "lateral_range": e.lateral_range},
            "defense": {"val_trajectories": d.val_trajectories, "val_seed": validation_seed(params)},
            "execution": _execution_key(params),
        }
    )


def val_envelope_fingerprint(params: Params) -> str:
    """Hash of the params that decide the envelope validation images (datasets/val_envelope: views, not a flown
    approach, so no execution error)."""
    e, d = params.evaluate, params.defense
    return fingerprint(
        {
            "seed": params.seed,
            "camera": dataclasses.asdict(params.camera),
            "render": render_key(params),
            "evaluate": {"frames": e.frames, "lateral_range": e.lateral_range},
            "defense": {"val_trajectories": d.val_trajectories, "val_seed": validation_seed(params)},
            "envelope": ENVELOPE,
        }
    )


def detect_render_fingerprint(params: Params) -> str:
    """Hash of the params that decide the detector split's images (datasets/detect_render)."""
    s = params.shap
    return fingerprint(
        {
            "seed": params.seed,
            "camera": dataclasses.asdict(params.camera),
            "render": render_key(params),
            "evaluate": {"lateral_range": params.evaluate.lateral_range},
            "shap": {"frames": s.frames, "seed": s.seed, "trajectories": detector_trajectories(params)},
            "envelope": ENVELOPE,
        }
    )


def detector_trajectories(params: Params) -> int:
    """Trajectories of the detector split: enough `shap.frames`-frame ones for the SHAP sample plan's
    source images (pipeline.shap.plan_sources)."""
    s = params.shap
    return -(-max(s.normal, s.per_eps * len(s.eps)) // s.frames)


def check_render_fingerprint(meta: dict[str, Any], params: Params, path: Path | str) -> None:
    """Refuse renders (meta.json at `path`) made with other `seed`/`camera`/`render` params than params.yaml."""
    if meta.get("fingerprint") != render_fingerprint(params):
        raise ParamsError(
            f"{path} was rendered with other seed/camera/render params than params.yaml "
            f"(fingerprint {meta.get('fingerprint')!r}, params give {render_fingerprint(params)!r}); "
            f"re-run `rpod render` (or `dvc repro`)"
        )


def write_params(params: dict[str, Any], path: Path = PARAMS_FILE) -> None:
    atomic_write_text(path, yaml.safe_dump(params, sort_keys=False, default_flow_style=None, width=100))


# The key of params.yaml that stamps the conf/ it was composed from (`conf_sha`): `rpod params` and `dvc exp run`
# write it, every stage checks it, so an edit of conf/ without composing params.yaml again is refused, not ignored.
CONF_STAMP = "conf_sha"
CONF = Path("conf")  # conf/ in the working folder (the repository DVC composes in), relative like params.yaml


def conf_sha(conf: Path = CONF) -> str | None:
    """16 hex digits of the SHA-256 over the YAML files of `conf` (relative names and bytes, sorted): what
    params.yaml's `conf_sha` records; None where the working folder has no conf/config.yaml."""
    if not (conf / "config.yaml").is_file():
        return None
    h = hashlib.sha256()
    for f in sorted(conf.rglob("*.yaml")):
        h.update(f.relative_to(conf).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def stamped(params: dict[str, Any], conf: Path = CONF) -> dict[str, Any]:
    """`params` with `conf_sha` (after `profile_name`) of the conf/ they were composed from; unchanged without it."""
    sha = conf_sha(conf)
    if sha is None:
        return params
    out = {k: v for k, v in params.items() if k != CONF_STAMP}
    keys = list(out)
    at = keys.index("profile_name") + 1 if "profile_name" in keys else 0
    return dict([*list(out.items())[:at], (CONF_STAMP, sha), *list(out.items())[at:]])


def check_stamp(params: dict[str, Any], path: Path, conf: Path = CONF) -> None:
    """Refuse a params.yaml whose `conf_sha` is not the working folder's conf/ (edited since `rpod params`); one
    without the stamp, or a folder without conf/, is not checked."""
    stamp, now = params.get(CONF_STAMP), conf_sha(conf)
    if stamp is not None and now is not None and stamp != now:
        profile = params.get("profile_name", "default")
        raise ParamsError(
            f"{path} is stale: conf/ changed since it was composed (conf_sha {stamp}, conf/ now "
            f"{now}); run `rpod params {profile}` (with your -S overrides) to compose it again"
        )


def load(path: Path = PARAMS_FILE) -> Params:
    """Read params.yaml and check it against stages.config.schema (unknown keys refused with a suggestion) and
    against conf/ (`check_stamp`): the typed params every stage command reads."""
    path = Path(path)
    if not path.exists():
        raise ParamsError(f"{path} not found: run `rpod params default` (or another profile) first")
    params = read_yaml(path)  # a FIFO, invalid YAML or a key given twice: one DataError naming the file
    if not isinstance(params, dict):
        raise ParamsError(f"{path} must hold a mapping of sections")
    check_stamp(params, path)
    params.pop(CONF_STAMP, None)
    return build(params)  # unknown keys, types and ranges of every section (stages.config.schema), checked once here


def with_params(command: Callable[..., None]) -> Callable[..., None]:
    """A stage command `command(params, ...)` as the CLI registers it: params.yaml loaded once (`load`) and
    passed in; Typer sees the command's other options (signature, --help text) unchanged."""
    signature = inspect.signature(command, eval_str=True)  # real annotations: Typer reads Annotated options

    @functools.wraps(command)
    def run(*args: Any, **kwargs: Any) -> None:
        return command(load(), *args, **kwargs)

    options = list(signature.parameters.values())[1:]
    run.__signature__ = signature.replace(parameters=options)  # type: ignore[attr-defined]
    return run


def given(value: str | None) -> str | None:
    """An external-input param's path, or None when it is unset: null, or a path ending in `inputs/none`."""
    if value is None or Path(value).parts[-2:] == tuple(NONE.split("/")):
        return None
    return str(value)

"""Params: compose profiles into params.yaml, load and validate it for a stage."""
from __future__ import annotations

import difflib
import hashlib
import json
from pathlib import Path
from typing import Any

import yaml

from stages.io import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
CONF_DIR = ROOT / "conf"
PARAMS_FILE = Path("params.yaml")


class ParamsError(ValueError):
    """A params problem the user can fix; the message names the file and the key."""


def profiles() -> list[str]:
    """Names of the profiles in conf/profile/."""
    return sorted(p.stem for p in (CONF_DIR / "profile").glob("*.yaml"))


def compose(profile: str = "default", overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose conf/config.yaml with one profile (and optional Hydra overrides) via Hydra."""
    if profile not in profiles():
        raise ParamsError(f"unknown profile {profile!r}; choose one of {', '.join(profiles())} (conf/profile/)")
    from hydra import compose as hydra_compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra_compose(config_name="config", overrides=[f"profile={profile}", *(overrides or [])])
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def render_fingerprint(params: dict[str, Any]) -> str:
    """Hash of everything that decides the rendered images (`seed`, `camera`, `render`): the render
    stage stamps it into datasets/render/meta.json; every reader of the renders compares it."""
    key = json.dumps({"seed": params["seed"], "camera": params["camera"], "render": params["render"]}, sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def check_render_fingerprint(meta: dict[str, Any], params: dict[str, Any], path: Path | str) -> None:
    """Refuse renders (meta.json at `path`) made with other `seed`/`camera`/`render` params than params.yaml."""
    if meta.get("fingerprint") != render_fingerprint(params):
        raise ParamsError(f"{path} was rendered with other seed/camera/render params than params.yaml "
                          f"(fingerprint {meta.get('fingerprint')!r}, params give {render_fingerprint(params)!r}); "
                          f"re-run `rpod render` (or `dvc repro`)")


def write_params(params: dict[str, Any], path: Path = PARAMS_FILE) -> None:
    atomic_write_text(path, yaml.safe_dump(params, sort_keys=False, default_flow_style=None, width=100))


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def load(path: Path = PARAMS_FILE) -> dict[str, Any]:
    """Read params.yaml and refuse unknown keys (typos) with a suggestion."""
    path = Path(path)
    if not path.exists():
        raise ParamsError(f"{path} not found: run `rpod params default` (or another profile) first")
    try:
        params = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ParamsError(f"{path} is not valid YAML: {e}") from None
    if not isinstance(params, dict):
        raise ParamsError(f"{path} must hold a mapping of sections")
    schema = _flat(compose("default"))
    known = set(schema)
    prefixes = {k.rsplit(".", 1)[0] for k in known if "." in k}
    for key in _flat(params):
        if key in known or any(key.startswith(p + ".") for p in known if schema[p] in ({}, None)):
            continue
        if key in prefixes:
            raise ParamsError(f"{path}: {key!r} must be a section of parameters, got {_flat(params)[key]!r}")
        hint = difflib.get_close_matches(key, sorted(known), n=1)
        raise ParamsError(f"{path}: unknown parameter {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else ""))
    return params

"""Composition checked against the params schema, for both entry points: `rpod params` (stages/cli.py) and
DVC's `dvc exp run -S` (stages/config/hydra_plugins/rpod_params.py); and the profile conf/config.yaml
composes from, which `rpod params NAME` sets so a sweep keeps it. No stage imports this module."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Callable

from pipeline.io.atomic import atomic_write_text
from stages.config.params import compose
from stages.config.schema import build
from stages.config.sections import ParamsError

# conf/config.yaml in the working folder (the repository DVC composes in), relative like params.yaml
CONFIG_FILE = Path("conf") / "config.yaml"
# The defaults-list line of conf/config.yaml that picks the profile DVC's Hydra composition starts from.
_PROFILE_LINE = re.compile(r"^(  - profile: )(\w+)", re.M)


def checked(compose_fn: Callable[[list[str]], dict[str, Any]], overrides: list[str]) -> dict[str, Any]:
    """`compose_fn(overrides)` (a Hydra composition: `rpod params`, or DVC's for `dvc exp run -S`) checked
    against the schema (stages.config.schema.build): an override naming a key the profile lacks is refused
    before Hydra sees it, and bad values after composing, with the one-line ParamsError the stages give."""
    groups = [o for o in overrides if _override_key(o) == "profile"]
    base = compose_fn(groups)
    for override in overrides:
        keys = _override_key(override).split(".")
        if override not in groups and not _has(base, keys):
            build(_with_key(base, keys))  # raises the schema's "unknown parameter ... (did you mean ...)"
    composed = compose_fn(list(overrides))
    build(composed)
    return composed


def compose_checked(profile: str, overrides: list[str]) -> dict[str, Any]:
    """`compose(profile, overrides)`, refused with one line (ParamsError) unless it builds typed Params."""
    return checked(lambda some: compose(profile, some), overrides)


def record_profile(profile: str, config: Path = CONFIG_FILE) -> bool:
    """Make `profile` the one conf/config.yaml's defaults list picks (what `dvc exp run -S key=value`
    composes from); False when there is no conf/config.yaml in the working folder (nothing composes there)."""
    if not config.exists():
        return False
    text = config.read_text()
    if len(_PROFILE_LINE.findall(text)) != 1:
        raise ParamsError(f"{config}: its defaults list needs one `  - profile: NAME` line")
    atomic_write_text(config, _PROFILE_LINE.sub(lambda m: m.group(1) + profile, text))
    return True


def _override_key(override: str) -> str:
    """The dotted key of a Hydra override (`+a.b=1`, `~a.b`, `a.b=1` -> `a.b`)."""
    return override.lstrip("~+").split("=", 1)[0]


def _has(tree: Any, keys: list[str]) -> bool:
    for key in keys:
        if not isinstance(tree, dict) or key not in tree:
            return False
        tree = tree[key]
    return True


def _with_key(tree: dict[str, Any], keys: list[str]) -> dict[str, Any]:
    """A copy of `tree` with the (missing) nested key `keys` set to null."""
    out = json.loads(json.dumps(tree))
    node = out
    for key in keys[:-1]:
        node = node.setdefault(key, {})
        if not isinstance(node, dict):  # below a value (train.epochs.x): Hydra's own error says so
            return out
    node[keys[-1]] = None
    return out

"""The params each `rpod` command reads, listed in its --help with their meaning and units.

One source for each: the params of a command are dvc.yaml's `params:` of the stages that run it (so
`dvc repro` re-runs a stage exactly when a param its help lists changes); their meaning and units are
the comments beside them in conf/config.yaml, and a numeric param's range is its `In` in the schema
(stages/config/schema.py `ranges`). Built only when --help is asked for.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import typer.core
from typer._click.exceptions import NoSuchOption, UsageError  # typer 0.29 carries its own click

from stages.artifacts.dvc import dvc_stages
from stages.config.params import CONF_DIR, PARAMS_FILE

CONFIG = CONF_DIR / "config.yaml"
_KEY = re.compile(r"^(?P<indent> *)(?P<key>\w+):(?P<value>[^#]*?)\s*(?:#\s?(?P<comment>.*))?$")


def config_comments(text: str) -> dict[str, tuple[bool, str]]:
    """Dotted key of conf/config.yaml -> (is a leaf, its comment with continuation lines; "" when none)."""
    out: dict[str, tuple[bool, str]] = {}
    path: list[tuple[int, str]] = []  # (indent, key) of the enclosing sections
    last: tuple[int, str] | None = None
    for line in text.splitlines():
        stripped = line.lstrip()
        indent = len(line) - len(stripped)
        if stripped.startswith("#"):
            if last is not None and indent > last[0]:  # a comment continued under the key's own
                leaf, comment = out[last[1]]
                out[last[1]] = (leaf, f"{comment} {stripped.lstrip('#').strip()}".strip())
            continue
        m = _KEY.match(line)
        if m is None:
            last = None
            continue
        path = [(i, k) for i, k in path if i < indent]
        key = ".".join([k for _, k in path] + [m["key"]])
        value = m["value"].strip()
        out[key] = (value not in ("", "{}"), (m["comment"] or "").strip())  # "{}": an empty section
        path.append((indent, m["key"]))
        last = (indent, key)
    out.pop("defaults", None)  # Hydra's composition list, not a param
    return out


def command_stages(command: str) -> list[str]:
    """The dvc.yaml stages whose command is `rpod <command>` (with or without options)."""
    return [name for name, st in dvc_stages().items() if st["cmd"].split()[:2] == ["rpod", command]]


def command_params(command: str, comments: dict[str, tuple[bool, str]]) -> list[str]:
    """Every param (leaf key of conf/config.yaml) that dvc.yaml lists for the stages of `rpod <command>`."""
    listed = {p for name in command_stages(command) for p in dvc_stages()[name].get("params", [])}
    return [
        key for key, (leaf, _) in comments.items() if leaf and any(key == p or key.startswith(p + ".") for p in listed)
    ]


HOW_TO_SET = (
    "Set one with `rpod params PROFILE -S key=value` (rewrites params.yaml; then `dvc repro`) or run an "
    "experiment with `dvc exp run -S key=value`; a stage command takes no --key options."
)


def current_values(path: Path = PARAMS_FILE) -> dict[str, Any]:
    """Dotted key -> value in params.yaml as it stands (empty when it is missing or not a YAML mapping): what a
    command would read now, shown in --help whether or not the file is up to date with conf/."""
    from pipeline.io.errors import DataError
    from pipeline.io.files import read_yaml

    try:
        data = read_yaml(path)  # never blocks on a FIFO; an unreadable file shows no values rather than no help
    except (DataError, OSError):
        return {}

    def flat(node: Any, prefix: str) -> dict[str, Any]:
        if not isinstance(node, dict):
            return {prefix: node}
        return {
            k: v for key, sub in node.items() for k, v in flat(sub, f"{prefix}.{key}" if prefix else str(key)).items()
        }

    return flat(data, "") if isinstance(data, dict) else {}


def _shown(value: Any) -> str:
    """A param's value as YAML writes it inline (null, true, [1, 2])."""
    import json

    return "null" if value is None else json.dumps(value) if not isinstance(value, str) else value


def params_epilog(command: str) -> str:
    """The --help section listing the params a command reads, each with its value in params.yaml now, and how to
    set one (empty when it reads none or dvc.yaml is absent)."""
    if not CONFIG.is_file():
        return ""
    comments = config_comments(CONFIG.read_text())
    keys = command_params(command, comments)
    if not keys:
        return ""
    stages = ", ".join(command_stages(command))
    from stages.config.schema import ranges

    limits = ranges()
    now = current_values()
    lines = [
        f"  {k}"
        + (f" = {_shown(now[k])}" if k in now else "")
        + f": {comments[k][1] or '(no description)'}"
        + (f"; range {limits[k].interval} {limits[k].unit}".rstrip() if k in limits else "")
        for k in keys
    ]
    return (
        f"Params read (params.yaml, from conf/config.yaml; dvc.yaml stage {stages}), with their values now:\n\n"
        + "\n".join(lines)
        + f"\n\n{HOW_TO_SET}"
    )


def param_for_option(command: str, option: str) -> str | None:
    """The param a mistaken `--option` of `rpod <command>` names (`--epochs` -> train.epochs), or None: the
    command's params whose last part (or whole dotted key) is the option, dashes read as underscores."""
    if not CONFIG.is_file():
        return None
    name = option.lstrip("-").replace("-", "_")
    keys = command_params(command, config_comments(CONFIG.read_text()))
    hits = [k for k in keys if k == name or k.split(".")[-1] == name]
    if len(hits) > 1:  # train.epochs before train.adversarial.epochs: the command's own section, shallowest first
        hits = sorted(hits, key=lambda k: (k.split(".")[0] != command, k.count(".")))[:1]
    return hits[0] if hits else None


def stage_map() -> str:
    """`rpod --help`'s map of dvc.yaml stages to the commands that run them (several stages are a flag of one
    command: robust is `rpod train --robust`); export, predict, remote and params are commands only."""
    stages = dvc_stages()
    if not stages:
        return ""
    width = max(map(len, stages))
    rows = [f"  {name:<{width}}  {st['cmd']}" for name, st in stages.items()]
    return "DVC stage -> command (dvc.yaml, optional/dvc.yaml):\n\n" + "\n".join(rows)


def stage_command(name: str) -> str | None:
    """The command a dvc.yaml stage name runs when that name is not itself a command (`robust` -> `rpod train
    --robust`), else None."""
    stage = dvc_stages().get(name)
    if stage is None or stage["cmd"].split()[:2] == ["rpod", name]:
        return None
    return stage["cmd"]


def _escape(text: str) -> str:
    """The text as literal Rich markup (square brackets in units are not styles)."""
    from rich.markup import escape

    return escape(text)


class ParamsHelpCommand(typer.core.TyperCommand):
    """A Typer command whose --help ends with the params it reads (`params_epilog`) and which answers an option
    that is a param (`rpod train --epochs 3`) with how to set that param."""

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self.epilog = _escape(params_epilog(self.name or ""))
        super().format_help(ctx, formatter)

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        try:
            return super().parse_args(ctx, args)
        except NoSuchOption as e:
            key = param_for_option(self.name or "", e.option_name)
            if key is None:
                raise
            now = current_values()
            value = f" (now {_shown(now[key])} in params.yaml)" if key in now else ""
            profile = now.get("profile_name", "PROFILE")
            raise UsageError(
                f"No such option: {e.option_name}. {key} is a param{value}: set it with `rpod params {profile} -S "
                f"{key}=VALUE` (then `dvc repro`) or `dvc exp run -S {key}=VALUE`",
                ctx,
            ) from None


class RootGroup(typer.core.TyperGroup):
    """`rpod` itself: --help ends with the stage -> command map (`stage_map`), and a dvc.yaml stage name that is a
    flag of a command (`rpod robust`) is answered with that command instead of a near-miss suggestion."""

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self.epilog = _escape(stage_map())
        super().format_help(ctx, formatter)

    def resolve_command(self, ctx: Any, args: list[str]) -> Any:
        if args and self.get_command(ctx, args[0]) is None and (cmd := stage_command(args[0])) is not None:
            raise UsageError(f"No such command {args[0]!r}: the dvc.yaml stage {args[0]} runs `{cmd}`", ctx)
        return super().resolve_command(ctx, args)


class ParamsHelpGroup(typer.core.TyperGroup):
    """A Typer command group (e.g. `rpod lab`) whose --help ends with the params it reads."""

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self.epilog = _escape(params_epilog(self.name or ""))
        super().format_help(ctx, formatter)

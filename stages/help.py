"""The params each `rpod` command reads, listed in its --help with their meaning and units.

One source for each: the params of a command are dvc.yaml's `params:` of the stages that run it (so
`dvc repro` re-runs a stage exactly when a param its help lists changes); their meaning and units are
the comments beside them in conf/config.yaml, and a numeric param's range is its `In` in the schema
(stages/config/schema.py `ranges`). Built only when --help is asked for.
"""

from __future__ import annotations

import re
from typing import Any

import typer.core

from stages.artifacts.dvc import dvc_stages
from stages.config.params import CONF_DIR

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


def params_epilog(command: str) -> str:
    """The --help section listing the params a command reads (empty when it reads none or dvc.yaml is absent)."""
    if not CONFIG.is_file():
        return ""
    comments = config_comments(CONFIG.read_text())
    keys = command_params(command, comments)
    if not keys:
        return ""
    stages = ", ".join(command_stages(command))
    from stages.config.schema import ranges

    limits = ranges()
    lines = [
        f"  {k}: {comments[k][1] or '(no description)'}"
        + (f"; range {limits[k].interval} {limits[k].unit}".rstrip() if k in limits else "")
        for k in keys
    ]
    return f"Params read (params.yaml, from conf/config.yaml; dvc.yaml stage {stages}):\n\n" + "\n".join(lines)


def _escape(text: str) -> str:
    """The text as literal Rich markup (square brackets in units are not styles)."""
    from rich.markup import escape

    return escape(text)


class ParamsHelpCommand(typer.core.TyperCommand):
    """A Typer command whose --help ends with the params it reads (`params_epilog`)."""

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self.epilog = _escape(params_epilog(self.name or ""))
        super().format_help(ctx, formatter)


class ParamsHelpGroup(typer.core.TyperGroup):
    """A Typer command group (e.g. `rpod lab`) whose --help ends with the params it reads."""

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self.epilog = _escape(params_epilog(self.name or ""))
        super().format_help(ctx, formatter)

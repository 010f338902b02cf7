"""`rpod`: one command per DVC stage. Each command reads params.yaml, calls pipeline/, writes artifacts.

Set RPOD_DEBUG=1 to see full tracebacks instead of one-line errors.
"""
from __future__ import annotations

import os
import sys

import typer

from stages import params as params_mod
from stages.io import StageError

app = typer.Typer(
    help="rpodguard: render a target satellite, train a pose CNN, attack it, explain it with SHAP, "
    "detect the attacks, and report. Each command is one DVC stage (see dvc.yaml); run `dvc repro` "
    "to run them all in order.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


@app.callback()
def _root() -> None:
    """rpodguard: render, train, attack, explain (SHAP), detect, evaluate and report.

    Each command is one DVC stage (see dvc.yaml); `dvc repro` runs them all in order.
    """


@app.command("params")
def params_cmd(
    profile: str = typer.Argument("default", help="Profile in conf/profile/: default, smoke or paper."),
    set_: list[str] = typer.Option([], "--set", "-S", help="Hydra override, e.g. train.epochs=5 (repeatable)."),
) -> None:
    """Write params.yaml from conf/config.yaml and a profile (what `dvc exp run -S profile=NAME` does)."""
    composed = params_mod.compose(profile, set_)
    params_mod.write_params(composed)
    typer.echo(f"params.yaml <- conf/config.yaml + conf/profile/{profile}.yaml" + (f" + {set_}" if set_ else ""))


# Stage modules keep heavy imports (bpy, torch) inside their commands so `rpod --help` is fast.
# A module exposes `main` (one command) or `app` (a command group, e.g. `rpod lab rescale`).
STAGES = ["render", "label", "train", "attack", "guidance", "shap", "detect", "evaluate", "robustness", "lab", "report"]


def _register() -> None:
    import importlib

    for name in STAGES:
        try:
            mod = importlib.import_module(f"stages.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"stages.{name}":
                continue  # stage not written yet
            raise
        if hasattr(mod, "app"):
            app.add_typer(mod.app, name=name)
        else:
            app.command(name)(mod.main)


_register()


def main() -> None:
    """Console entry point: one clear line for user errors, a traceback only with RPOD_DEBUG=1."""
    try:
        app()
    except (StageError, ValueError, FileNotFoundError) as e:
        if os.environ.get("RPOD_DEBUG"):
            raise
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        sys.exit(2)

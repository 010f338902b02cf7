"""`rpod`: one command per DVC stage. Each command reads params.yaml, calls pipeline/, writes artifacts.

Known errors (bad params, missing or corrupt artifacts, a refused training run) print one line and exit
with status 1; `rpod --debug COMMAND` (or RPOD_DEBUG=1) shows the full traceback instead.
"""

from __future__ import annotations

import os
import sys

# Before torch (and its OpenMP runtime) loads: idle OpenMP threads sleep instead of spinning. On a
# shared 2-core machine spinning threads made training 10-20x slower (7-12 vs ~146 img/s measured with
# one other process running); the variable is only a default, a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numpy's and torch's CPU kernels are capped at AVX2 by `import stages` ($RPOD_CPU_ISA: avx2 | native; a
# variable the user set wins), so that a seed gives the same results on machines with and without AVX-512
# (stages/config/cpu.py); a bad $RPOD_CPU_ISA is reported here, in one line.
from stages.config.cpu import pin_cpu_isa  # noqa: E402

try:
    pin_cpu_isa()
except ValueError as _e:
    sys.exit(f"error: {_e}")

import typer  # noqa: E402

from pipeline.io.errors import DataError  # noqa: E402
from stages.config import compose as compose_mod  # noqa: E402
from stages.config import params as params_mod  # noqa: E402
from stages.help import RootGroup  # noqa: E402

app = typer.Typer(
    help="rpodguard: render a target satellite, train a pose CNN, attack it, explain it with SHAP, "
    "detect the attacks, and report. Each DVC stage runs one command (some with a flag: the map below); "
    "`dvc repro` runs them all in order. params, predict, export and remote are commands only.",
    cls=RootGroup,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


_DEBUG = {"on": bool(os.environ.get("RPOD_DEBUG"))}
# errors raised inside these libraries are about their input (a damaged store or table, a bad override)
_LIBRARIES = ("zarr", "numcodecs", "google_crc32c", "pyarrow", "hydra", "omegaconf", "yaml")


def _version(show: bool) -> None:
    """--version: print the installed rpodguard's version and stop."""
    if show:
        from importlib.metadata import version

        typer.echo(f"rpodguard {version('rpodguard')}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show the full traceback of an error."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print rpodguard's version and exit."
    ),
) -> None:
    """rpodguard: render a target satellite, train a pose CNN, attack it, explain it with SHAP, detect the
    attacks, and report. Each DVC stage runs one command (some with a flag: the map below); `dvc repro` runs them
    all in order. params, predict, export and remote are commands only."""
    _DEBUG["on"] = _DEBUG["on"] or debug


@app.command("params")
def params_cmd(
    profile: str = typer.Argument("default", help="Profile in conf/profile/: default, smoke or paper."),
    set_: list[str] = typer.Option([], "--set", "-S", help="Hydra override, e.g. train.epochs=5 (repeatable)."),
    check: bool = typer.Option(False, "--check", help="Only check that params.yaml is up to date with conf/."),
) -> None:
    """Write params.yaml from conf/config.yaml and a profile, checked against the params schema and stamped with
    conf/'s hash (conf_sha: stages refuse it once conf/ is edited), and make the profile the one conf/config.yaml
    composes from (so `dvc exp run -S key=value` keeps it). --check: only check params.yaml (`make repro` does)."""
    if check:
        params_mod.load()
        typer.echo("params.yaml is up to date with conf/")
        return
    composed = compose_mod.compose_checked(profile, set_)
    recorded = compose_mod.record_profile(profile)
    params_mod.write_params(params_mod.stamped(composed))
    typer.echo(
        f"params.yaml <- conf/config.yaml + conf/profile/{profile}.yaml"
        + (f" + {set_}" if set_ else "")
        + (f"; conf/config.yaml now composes {profile!r} (dvc exp run -S)" if recorded else "")
    )


# Stage modules keep heavy imports (bpy, torch) inside their commands so `rpod --help` is fast.
# A module exposes `main` (one command) or `app` (a command group, e.g. `rpod lab rescale`).
# export, predict, remote: not DVC stages
STAGES = [
    "render",
    "label",
    "train",
    "attack",
    "guidance",
    "shap",
    "detect",
    "eval_render",
    "calibrate",
    "evaluate",
    "robustness",
    "lab_models",
    "lab",
    "report",
    "ablation",
    "pose_trial",
    "attitude",
    "gaps",
    "heldout",
    "suite",
    "bound",
    "integrity",
    "export",
    "predict",
    "remote",
]


def _register() -> None:
    import importlib

    from stages.config.params import with_params
    from stages.help import ParamsHelpCommand, ParamsHelpGroup

    for name in STAGES:
        try:
            mod = importlib.import_module(f"stages.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"stages.{name}":
                continue  # stage not written yet
            raise
        if hasattr(mod, "app"):
            app.add_typer(mod.app, name=name, cls=ParamsHelpGroup)
        else:
            app.command(name, cls=ParamsHelpCommand)(with_params(mod.main) if _takes_params(mod.main) else mod.main)


def _takes_params(command: object) -> bool:
    """Whether a stage command takes the typed params first (`main(params: Params, ...)`): the CLI loads them."""
    import inspect

    first = next(iter(inspect.signature(command).parameters), None)  # type: ignore[arg-type]
    return first == "params"


_register()


def known_error(e: BaseException) -> str | None:
    """The one-line message for an error the user can act on, or None for a bug (shown as a traceback)."""
    text = " ".join(str(e).split())
    if isinstance(e, KeyError):
        return f"missing field {e.args[0]!r} in params.yaml or an input artifact (rpod --debug shows where)"
    if isinstance(e, (DataError, ValueError, OSError)):  # a StageError is a DataError
        return text or type(e).__name__
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    where = [type(e).__module__, tb.tb_frame.f_globals.get("__name__", "") if tb is not None else ""]
    if any(w.split(".")[0] in _LIBRARIES for w in where):
        return f"{type(e).__name__}: {text}"
    return None


def main() -> None:
    """Console entry point: one line and exit status 1 for known errors (a traceback with --debug), one line and exit
    status 130 when SIGINT (Ctrl-C) or SIGTERM stops a command (pipeline/interrupt.py: temporaries and locks are
    removed on the way out, and under DVC the git-tracked outputs it deleted before the stage come back)."""
    from pipeline import interrupt
    from pipeline.io.store import release_zarr

    interrupt.install()
    try:
        _run()
    except SystemExit as e:
        release_zarr()
        if e.code == interrupt.EXIT_STATUS and interrupt.requested() is not None:
            # Stopped: every clean-up ran in the `finally` blocks on the way here; leave without the interpreter's
            # finalization, where Ray's core worker, interrupted inside ray.wait, crashed (exit -11 after the line)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(interrupt.EXIT_STATUS)
        raise
    finally:
        release_zarr()


def _run() -> None:
    """`app()` with the error, interrupt and restore paths of `main`."""
    from pipeline.interrupt import EXIT_STATUS, Interrupted
    from stages.artifacts.dvc import restore_tracked_outputs

    command = " ".join(["rpod", *[a for a in sys.argv[1:] if not a.startswith("-")][:1]])
    try:
        app()
    except SystemExit as e:
        if e.code not in (0, None):
            _note_restored(restore_tracked_outputs())
        raise
    except Interrupted as e:
        restored = restore_tracked_outputs()
        under_dvc = "; DVC records nothing" if os.environ.get("DVC_STAGE") else ""
        back = f" (put back from git: {', '.join(restored)})" if restored else ""
        typer.secho(
            f"{command}: stopped by {e}; no half-written output left{under_dvc}{back}", fg=typer.colors.RED, err=True
        )
        sys.exit(EXIT_STATUS)
    except Exception as e:
        message = known_error(e)
        if message is None or _DEBUG["on"]:
            _note_restored(restore_tracked_outputs())
            raise
        typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
        _note_restored(restore_tracked_outputs())
        sys.exit(1)


def _note_restored(restored: list[str]) -> None:
    """Say which git-tracked outputs a failed stage put back (none: nothing said)."""
    if restored:
        typer.secho(
            f"note: put back from git the outputs DVC deleted before the stage: {', '.join(restored)}", err=True
        )


if __name__ == "__main__":
    main()

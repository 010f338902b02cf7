"""dvc.yaml lists, for every stage, each project module whose code its command can run: a missing
one means `dvc repro` would not re-run the stage when that code changes.

The code a command can run is derived from the source, function by function: start from every
function of stages/<command>.py (stages/cli.py only dispatches to it) and of stages/__init__.py (the CPU pin every
command runs first), follow the names each function
uses (module-level and in-function imports, `module.attr` references, calls to functions of the
same module), and collect the files reached. Function granularity keeps, e.g., `rpod render` off
pipeline/attacks/gradient.py although stages/config/build.py (which it uses) has an attack helper.
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("pipeline", "stages")
TOP = "<module>"  # the unit of a module's top-level statements


def module_file(name: str) -> Path | None:
    """The file of a dotted module name in pipeline/ or stages/ (None for other modules)."""
    if name.split(".")[0] not in PACKAGES:
        return None
    base = REPO / Path(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.exists():
            return path
    return None


@lru_cache(maxsize=None)
def parse(path: Path) -> tuple[dict[str, list[ast.AST]], dict[str, tuple[Path, str]]]:
    """A module's units (TOP and each top-level function/class -> AST nodes) and its module-level
    bindings of imported project names (local name -> (file, attribute or TOP))."""
    tree = ast.parse(path.read_text())
    units: dict[str, list[ast.AST]] = {TOP: []}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            units[node.name] = [node]
        else:
            units[TOP].append(node)
    return units, bindings(units[TOP])


def bindings(nodes: list[ast.AST]) -> dict[str, tuple[Path, str]]:
    """Imported project names bound by the import statements in `nodes` (searched recursively)."""
    out: dict[str, tuple[Path, str]] = {}
    for root in nodes:
        for node in ast.walk(root):
            if isinstance(node, ast.Import):
                for a in node.names:
                    f = module_file(a.name)
                    if f is not None:
                        out[a.asname or a.name.split(".")[0]] = (f, TOP)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                base = module_file(node.module)
                for a in node.names:
                    sub = module_file(f"{node.module}.{a.name}")
                    if sub is not None:  # `from stages import params`
                        out[a.asname or a.name] = (sub, TOP)
                    elif base is not None:  # `from stages.errors import StageError`
                        out[a.asname or a.name] = (base, a.name)
    return out


def reached(path: Path, unit: str) -> set[tuple[Path, str]]:
    """Units that `unit` of `path` uses directly (its module's TOP is always one of them)."""
    units, module_names = parse(path)
    nodes = units.get(unit, [])
    names = {**module_names, **bindings(nodes)}
    out = {(path, TOP)} | {(f, TOP) for f, _ in bindings(nodes).values()}
    for root in nodes:
        for node in ast.walk(root):
            if isinstance(node, ast.Name):
                if node.id in names:
                    out.add(names[node.id])
                elif node.id in units and node.id != unit:
                    out.add((path, node.id))
            elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in names:
                f, attr = names[node.value.id]
                if attr == TOP:  # module.attr
                    out.add((f, node.attr))
    return out


def files_of(entry: Path) -> set[Path]:
    """Every project file whose code the functions of `entry` can run."""
    todo = [(entry, u) for u in parse(entry)[0]]
    seen = set(todo)
    while todo:
        for nxt in reached(*todo.pop()) - seen:
            seen.add(nxt)
            todo.append(nxt)
    return {f for f, _ in seen if f.name != "__init__.py"}


# the default pipeline (`dvc repro`), then the stages run only on demand (`dvc repro optional/dvc.yaml`, wdir: the root)
PIPELINES = ("dvc.yaml", "optional/dvc.yaml")
STAGES = {name: st for f in PIPELINES for name, st in yaml.safe_load((REPO / f).read_text())["stages"].items()}


# commands that run other commands as subprocesses (stages/engine/subrun.py): lab_models with lab.retrain, pose_trial
SUBPROCESSES = {
    "lab_models": ("render", "label", "train", "shap", "detect"),
    "pose_trial": ("render", "label", "train"),
}


# every `rpod` command first runs the stages package's __init__: the CPU pin (stages/config/cpu.py), which sets
# the kernels numpy and torch compute with, and the missing-input hint
ENTRY = REPO / "stages" / "__init__.py"


def stage_files(name: str) -> set[Path]:
    cmd = STAGES[name]["cmd"].split()
    assert cmd[0] == "rpod", f"stage {name}: command {cmd} is not an rpod command"
    files = files_of(REPO / "stages" / f"{cmd[1]}.py") | files_of(ENTRY) | {ENTRY}
    for sub in SUBPROCESSES.get(cmd[1], ()):
        files |= files_of(REPO / "stages" / f"{sub}.py")
    return files


def covered(path: Path, deps: list[str]) -> bool:
    return any(path == REPO / d or REPO / d in path.parents for d in deps)


@pytest.mark.parametrize("name", sorted(STAGES))
def test_every_module_a_stage_runs_is_a_dependency(name):
    deps = STAGES[name].get("deps", [])
    missing = sorted(str(f.relative_to(REPO)) for f in stage_files(name) if not covered(f, deps))
    assert not missing, f"dvc.yaml stage {name} lacks deps on the code it runs: {', '.join(missing)}"


def test_the_derivation_follows_functions_not_whole_modules():
    render = {str(f.relative_to(REPO)) for f in stage_files("render")}
    assert {
        "pipeline/render/scene.py",
        "stages/config/build.py",
        "stages/artifacts/readers.py",
        "pipeline/geometry/trajectories.py",
    } <= render
    assert "pipeline/attacks/gradient.py" not in render  # build.make_attack is not used by render
    for later in ("evaluate", "lab"):  # editing the detector's code or page does not re-run them
        assert "stages/detect.py" not in {str(f.relative_to(REPO)) for f in stage_files(later)}


def test_no_stage_imports_another_stage():
    shared = {
        "artifacts",
        "errors",
        "params",
        "schema",
        "cli",
        "checkpoint",
        "data",
        "help",
        "speed",
        "engine",
        "chunks",
    }
    for path in sorted((REPO / "stages").glob("*.py")):
        _, top = parse(path)
        imported = {f for f, _ in top.values()} | {f for u in parse(path)[0].values() for f, _ in bindings(u).values()}
        for f in imported:
            assert f.parent.name != "stages" or f.stem in shared or f == path, (
                f"{path.name} imports the stage module {f.name}"
            )

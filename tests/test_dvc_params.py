"""dvc.yaml lists, as a stage's `params:`, only keys its command reads, so `dvc exp run -S key=value` does not
re-run a stage that never reads `key` (e.g. `train.epochs` and the surrogate, which trains for
`robustness.surrogate_epochs`).

The keys a command reads are derived from the source: from the stage's `main(params, ...)`, follow the attribute
chains on `params` (`params.train.width`), names bound to them (`e = params.evaluate`), calls that pass them to
project functions (into those functions, argument to parameter), the library settings built from a section
(`settings_of(TrainConfig, params.train, epochs=...)` and `part(params.defense, MotionSettings)` read the
settings' fields but the ones given), and take only the branch a command-line flag selects (`--surrogate`). A
chain passed to anything else counts as read whole. The derivation over-approximates, so it can only show a
listed key unread, which is what these tests check (tests/test_dvc_deps.py does the same for code deps).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml
from test_dvc_deps import REPO, STAGES, TOP, bindings, parse

Key = tuple[str, ...]
PARAMS = yaml.safe_load((REPO / "params.yaml").read_text())


class Reads:
    """The params keys (tuples of names) that functions read, given the flags that are set."""

    def __init__(self, flags: frozenset[str] = frozenset(), off: frozenset[str] = frozenset()):
        self.flags, self.off, self.keys, self.seen = flags, off, set[Key](), set()

    def function(self, path: Path, name: str, env: dict[str, Key]) -> None:
        if (path, name, tuple(sorted(env.items()))) in self.seen:
            return
        self.seen.add((path, name, tuple(sorted(env.items()))))
        node = parse(path)[0][name][0]
        scope, env = {**parse(path)[1], **bindings([node])}, dict(env)
        for stmt in node.body:
            self.visit(stmt, env, path, scope)

    def visit(self, node: ast.AST, env: dict[str, Key], path: Path, scope: dict) -> None:
        if isinstance(node, (ast.If, ast.IfExp)) and (taken := self._flag(node.test)) is not None:
            branch = node.body if taken else node.orelse
            for child in branch if isinstance(branch, list) else [branch]:
                self.visit(child, env, path, scope)
            return
        if (
            isinstance(node, ast.Assign)
            and len(node.targets) == 1
            and isinstance(node.targets[0], ast.Name)
            and (key := _rooted(node.value, env)) is not None
        ):
            env[node.targets[0].id] = key
            return
        if (key := _rooted(node, env)) is not None:
            self.keys.add(key)
            return
        if isinstance(node, ast.Call) and self.call(node, env, path, scope):
            return
        for child in ast.iter_child_nodes(node):
            self.visit(child, env, path, scope)

    def call(self, node: ast.Call, env: dict[str, Key], path: Path, scope: dict) -> bool:
        """Follow a call that passes params chains into a project function (or settings_of); False: not one."""
        target = _resolve(node.func, path, scope)
        if target is None:
            return False
        file, name = target
        if name in ("settings_of", "part"):  # settings_of(cls, section, ...), part(section, cls, ...)
            at = (1, 0) if name == "settings_of" else (0, 1)
            section, given = _rooted(node.args[at[0]], env), {k.arg for k in node.keywords}
            cls = _resolve(node.args[at[1]], path, scope)
            if section is None or cls is None:
                return False
            self.keys |= {section + (f,) for f in _fields(*cls) if f not in given}
            return True
        fn = parse(file)[0].get(name, [None])[0]
        if not isinstance(fn, ast.FunctionDef):
            return False
        names = [a.arg for a in fn.args.posonlyargs + fn.args.args]
        bound = {names[i]: k for i, a in enumerate(node.args) if i < len(names) and (k := _rooted(a, env)) is not None}
        bound |= {kw.arg: k for kw in node.keywords if kw.arg and (k := _rooted(kw.value, env)) is not None}
        for arg in [*node.args, *(kw.value for kw in node.keywords)]:
            if _rooted(arg, env) is None:
                self.visit(arg, env, path, scope)
        self.function(file, name, bound)
        return True

    def _flag(self, test: ast.AST) -> bool | None:
        if isinstance(test, ast.Name) and test.id in self.flags | self.off:
            return test.id in self.flags
        if isinstance(test, ast.UnaryOp) and isinstance(test.op, ast.Not) and self._flag(test.operand):
            return False
        return None


def _rooted(node: ast.AST, env: dict[str, Key]) -> Key | None:
    """The params key an expression names (`params.train.width` -> ('train', 'width')), or None."""
    if isinstance(node, ast.Name):
        return env.get(node.id)
    if isinstance(node, ast.Attribute) and (base := _rooted(node.value, env)) is not None:
        return base + (node.attr,)
    return None


def _resolve(node: ast.AST, path: Path, scope: dict) -> tuple[Path, str] | None:
    """(file, top-level name) of a called or named project function or class."""
    if isinstance(node, ast.Name):
        if node.id in scope:
            file, attr = scope[node.id]
            return (file, node.id if attr == TOP else attr) if attr != TOP else None
        return (path, node.id) if node.id in parse(path)[0] else None
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in scope:
        file, attr = scope[node.value.id]
        return (file, node.attr) if attr == TOP else None
    return None


def _fields(file: Path, name: str) -> set[str]:
    """The annotated fields of a dataclass (followed through a module that re-exports it)."""
    units, imported = parse(file)
    if name not in units:
        return _fields(imported[name][0], imported[name][1])
    cls = units[name][0]
    return {s.target.id for s in cls.body if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)}


def command_reads(stage: str) -> set[Key]:
    """The params keys the stage's command reads (its flags select branches)."""
    cmd = STAGES[stage]["cmd"].split()
    flags = frozenset(a.removeprefix("--") for a in cmd[2:] if a.startswith("--"))
    main = parse(REPO / "stages" / f"{cmd[1]}.py")[0]["main"][0]
    # the command's other boolean flags (parameters defaulting to False) are off
    off = (
        frozenset(
            a.arg
            for a, d in zip(main.args.args[::-1], main.args.defaults[::-1])
            if isinstance(d, ast.Constant) and d.value is False
        )
        - flags
    )
    reads = Reads(flags, off)
    reads.function(REPO / "stages" / f"{cmd[1]}.py", "main", {"params": ()})
    return reads.keys


def listed(stage: str) -> set[Key]:
    return {tuple(p.split(".")) for p in STAGES[stage].get("params", [])}


def leaves(key: Key) -> list[Key]:
    """The keys of params.yaml (the default profile) at or below `key`: a listed section is every key in it."""
    node = PARAMS
    for name in key:
        node = node[name]
    return [leaf for name in node for leaf in leaves(key + (name,))] if isinstance(node, dict) else [key]


def unread(stage: str, reads: set[Key]) -> list[str]:
    """Keys in the stage's `params:` (a section: each key in it) that no derived read covers (a read covers a
    key when it is the key or a section holding it)."""
    return sorted(
        ".".join(leaf) for k in listed(stage) for leaf in leaves(k) if not any(leaf[: len(r)] == r for r in reads)
    )


def test_the_surrogate_lists_only_what_it_reads():
    reads = command_reads("surrogate")
    assert ("robustness", "surrogate_epochs") in reads and ("train", "lr_max") in reads
    assert ("train", "epochs") not in reads and ("train", "range_bins") not in reads  # the --surrogate branch
    assert not unread("surrogate", reads)
    train_read = {leaf for k in reads if k[0] == "train" for leaf in leaves(k)}
    assert train_read == {leaf for k in listed("surrogate") if k[0] == "train" for leaf in leaves(k)}


def test_lab_models_lists_only_what_it_and_its_sub_pipeline_read():
    """With lab.retrain, stages/lab_models.py runs render, label, train, shap and detect on a params.yaml
    derived from the main one (all of it: the derivation reads the whole params there): what they list is
    read too, so the train stage's keys (train.epochs included) stay deps; train.adversarial (the robust
    stage's, which the sub-pipeline does not run) is not listed."""
    from stages.lab_models import STEPS

    assert () in command_reads("lab_models")
    sub_pipeline = {k for step in STEPS for k in listed(step)}
    assert ("train", "epochs") in sub_pipeline and not unread("lab_models", command_reads("lab_models") | sub_pipeline)
    assert listed("lab_models") >= {k for k in listed("train") if k[0] == "train"}
    assert not any(k[:2] == ("train", "adversarial") or k == ("train",) for k in listed("lab_models"))


@pytest.mark.parametrize("stage", sorted(set(STAGES) - {"lab_models"}))
def test_every_stage_lists_no_key_it_does_not_read(stage):
    assert not unread(stage, command_reads(stage))


def test_the_derivation_finds_an_unread_key():
    assert "train.epochs" in unread("train", {("train", "width")}) and not unread("train", {()})

"""Layering of the code: the library (pipeline/) and the public API (rpodguard/) never import the
commands (stages/); the packages of each are declared in one order, lowest first, and a package imports
only the packages below it (so no two packages import each other); no modules import each other in a cycle.

Every import statement counts, also those inside functions (a deferred import is still a dependency).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("pipeline", "stages", "rpodguard")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}

# The layers, lowest first: a unit (a subpackage, or a module directly under pipeline/) imports only units
# before it. The library: files and errors; the stop flag of signals; typed settings (ranges, checks); every seed;
# intervals; frames and cameras; image operations; whether a frame shows the target; the Blender scene; the SHAP
# closed form; attacks on images (FGSM, PGD, the adaptive one) and their schedules;
# the pose network (its adversarial training uses the attacks); the detectors; the defense (filter, fusion,
# protection level, integrity, calibration, the onboard chain); the guidance law; the attackers of the
# defended chain (burst, drift, in-loop: they model the defense and the guidance); evaluation campaigns;
# file formats (a chain's files and the one door that loads a chain); report building blocks.
PIPELINE_ORDER = (
    "io",
    "interrupt",
    "settings",
    "seeds",
    "stats",
    "geometry",
    "images",
    "visibility",
    "render",
    "shap",
    "attacks",
    "pose",
    "detectors",
    "defense",
    "guidance",
    "attackers",
    "evaluation",
    "formats",
    "report",
)
# The commands' support, lowest first: errors; params (schema, composition, params -> library settings);
# artifacts (paths, readers, checks); the Ray engine and its workers; report pages; then the commands
# (one module per stage, the CLI and its --help), which no other unit imports.
STAGES_ORDER = ("errors", "config", "artifacts", "engine", "pages")
COMMANDS = "stages.<commands>"
ORDER = (*(f"pipeline.{u}" for u in PIPELINE_ORDER), "rpodguard", *(f"stages.{u}" for u in STAGES_ORDER), COMMANDS)


def unit(name: str) -> str:
    """The layer unit of a module: pipeline.X / stages.X (a subpackage or a module under the package),
    rpodguard, or the stages' commands (every other module directly under stages/, and stages/__init__)."""
    parts = name.split(".")
    if parts[0] == "rpodguard":
        return "rpodguard"
    if parts[0] == "stages" and (len(parts) == 1 or (len(parts) == 2 and parts[1] not in STAGES_ORDER)):
        return COMMANDS
    return ".".join(parts[:2])


def imports(name: str) -> set[str]:
    """The project modules that module `name` imports anywhere in its source."""
    path = MODULES[name]
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in MODULES}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package[: len(package) - node.level + 1], *([base] if base else [])])
            for a in node.names:
                sub = f"{base}.{a.name}"
                out |= {sub} if sub in MODULES else ({base} if base in MODULES else set())
    return out - {name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_library_and_api_never_import_the_stages() -> None:
    bad = [
        f"{name} imports {dep}"
        for name in MODULES
        if not name.startswith("stages")
        for dep in sorted(imports(name))
        if dep.split(".")[0] == "stages"
    ]
    assert not bad, bad


def test_the_api_imports_the_library_only() -> None:
    deps = {dep for name in MODULES if name.startswith("rpodguard") for dep in imports(name)}
    assert deps and all(d.split(".")[0] in ("pipeline", "rpodguard") for d in deps), deps


def test_the_api_imports_no_evaluation_helper() -> None:
    """The public API (rpodguard) runs the chain; judging it (pipeline.evaluation, pipeline.report) is the stages'.
    A helper the API needs from there belongs in a lower layer (issue 36: resize and alert_limit were moved)."""
    deps = {dep for name in MODULES if name.startswith("rpodguard") for dep in imports(name)}
    bad = sorted(d for d in deps if d.startswith(("pipeline.evaluation", "pipeline.report")))
    assert not bad, bad


def test_every_unit_has_its_place_in_the_order() -> None:
    units = {unit(name) for name in MODULES if name != "pipeline"}
    assert units - set(ORDER) == set(), "declare the new package in PIPELINE_ORDER or STAGES_ORDER"
    assert set(ORDER) - units == set(), "a declared layer has no module"


def test_packages_import_only_the_layers_below() -> None:
    rank = {u: i for i, u in enumerate(ORDER)}
    bad = sorted(
        f"{name} ({unit(name)}) imports {dep} ({unit(dep)})"
        for name in MODULES
        if name != "pipeline"
        for dep in imports(name)
        if rank[unit(dep)] > rank[unit(name)]
    )
    assert not bad, bad


def test_a_command_imports_no_other_command() -> None:
    commands = {name for name in MODULES if unit(name) == COMMANDS and name != "stages"}
    bad = sorted(f"{name} imports {dep}" for name in commands - {"stages.cli"} for dep in imports(name) & commands)
    assert not bad, bad


SEED_ARITHMETIC = re.compile(r"seed\w*\s*\+\s*\d|\d\s*\+\s*\w*seed\b|SEED_OFFSET")


def test_seeds_have_one_home() -> None:
    """Only pipeline/seeds.py holds seed offsets: no other module adds a literal number to a seed."""
    files = [p for pkg in (*PACKAGES, "scripts", "benchmarks") for p in sorted((REPO / pkg).rglob("*.py"))]
    bad = [
        f"{p.relative_to(REPO)}:{i}: {line.strip()}"
        for p in files
        if p != REPO / "pipeline" / "seeds.py"
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if SEED_ARITHMETIC.search(line)
    ]
    assert not bad, bad
    assert SEED_ARITHMETIC.search("rng(self.seed + 1)") and SEED_ARITHMETIC.search("seed=p.seed + SEED_OFFSET[x]")
    assert not SEED_ARITHMETIC.search("seed_for(seed, 'lab.schedule', i)")


def test_seeds_are_hashed_from_base_stream_and_index_and_never_shared() -> None:
    """A stream's seed depends on its name (guidance and shap, which shared one under the old offset table, now
    differ), on the base and on the index; every declared stream's first items and every seed run's trajectory
    bases (the stream's seed on the run's seed) are distinct, in [0, 2**31), and the same on every call; an unknown
    stream or a negative base is refused."""
    import pytest

    from pipeline.seeds import RUN_STREAMS, STREAMS, run_base, seed_for

    assert seed_for(7, "guidance") != seed_for(7, "shap") and seed_for(7, "shap") == seed_for(7, "shap")
    assert seed_for(7, "guidance", 1) != seed_for(7, "guidance") != seed_for(8, "guidance")
    drawn = [seed_for(b, s, i) for b in range(3) for s in sorted(STREAMS) for i in range(50)]
    drawn += [run_base(seed, s) for seed in range(3, 100) for s in RUN_STREAMS]  # seeds 0-2: seed_for(seed, s) above
    assert run_base(2, "heldout") == seed_for(2, "heldout")
    assert len(set(drawn)) == len(drawn) and all(0 <= d < 2**31 for d in drawn)
    assert seed_for(0, "evaluate.schedule", 2) == 1646237154  # the hash is part of the outputs: a change fails here
    with pytest.raises(KeyError, match="declare it in pipeline/seeds.py"):
        seed_for(0, "guidence")
    with pytest.raises(ValueError, match="non-negative"):
        seed_for(-1, "guidance")


def test_no_import_cycles() -> None:
    assert cycles({name: imports(name) for name in MODULES}) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def _section(path: str) -> type:
    """The schema dataclass of a dotted params section (e.g. "train.adversarial")."""
    import typing

    from stages.config.schema import Params

    cls = Params
    for name in path.split("."):
        cls = typing.get_type_hints(cls)[name]
    return cls


def test_every_schema_field_maps_to_a_library_field() -> None:
    """Each params section built into library settings (stages/config/build.py SECTION_SETTINGS) holds only fields
    of those settings, under their names, and the fields the stages read themselves (STAGE_ONLY, which no library
    settings of the section take); settings_of refuses a library field that nothing gives."""
    import dataclasses
    import importlib

    from stages.config.build import SECTION_SETTINGS, STAGE_ONLY

    for path, classes in SECTION_SETTINGS.items():
        library: set[str] = set()
        for spec in classes:
            module, name = spec.split(":")
            library |= {f.name for f in dataclasses.fields(getattr(importlib.import_module(module), name))}
        schema = {f.name for f in dataclasses.fields(_section(path))}
        assert schema - library == set(STAGE_ONLY[path]), (path, sorted(schema - library))
        assert not set(STAGE_ONLY[path]) & library, path
        assert schema & library, path


def _composed_sections() -> dict[str, type]:
    """Dotted params path -> each params section composed of library settings (pipeline.settings `composed`)."""
    import dataclasses
    import typing

    from stages.config.schema import Params

    out: dict[str, type] = {}

    def walk(cls: type, prefix: str) -> None:
        for name, hint in typing.get_type_hints(cls).items():
            if dataclasses.is_dataclass(hint):
                if hasattr(hint, "__parts__"):
                    out[prefix + name] = hint
                walk(hint, f"{prefix}{name}.")

    walk(Params, "")
    return out


def test_a_composed_section_declares_each_knob_once() -> None:
    """A section composed of library settings takes each library field's type (with its range) and default as
    declared there, leaves out only the fields named runtime (set by the caller, never params), and declares on
    itself only fields that no part has; the sections that still mirror library settings are the rest."""
    import dataclasses
    import typing

    from stages.config.build import SECTION_SETTINGS

    composed = _composed_sections()
    assert set(composed) == {"render.background", "train.augment", "defense", "guidance.execution"}
    assert not set(composed) & set(SECTION_SETTINGS)
    for path, section in composed.items():
        fields = {f.name: f for f in dataclasses.fields(section)}
        hints = typing.get_type_hints(section, include_extras=True)
        library: set[str] = set()
        for cls in section.__parts__:
            own = typing.get_type_hints(cls, include_extras=True)
            for f in dataclasses.fields(cls):
                library.add(f.name)
                if f.name in section.__runtime__:
                    assert f.name not in fields, (path, f.name)
                    continue
                assert hints[f.name] == own[f.name], (path, f.name)
                assert fields[f.name].default == f.default, (path, f.name)
        assert set(section.__runtime__) <= library, path


def test_a_composed_section_refuses_what_its_parts_refuse() -> None:
    """Built from a params mapping, a composed section runs its parts' own checks (a bad value is one ParamsError
    naming the key), and `part` builds each part back with the runtime fields the caller gives."""
    import dataclasses

    import pytest

    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.settings import DefenseSettings
    from pipeline.settings import part
    from stages.config import params as params_mod
    from stages.config.sections import ParamsError

    p = params_mod.build(params_mod.compose("default"))
    motion = part(p.defense, MotionSettings)
    assert motion.trusted_start == p.defense.trusted_start and isinstance(motion.position_noise, float)
    assert part(p.defense, DefenseSettings, threshold=0.3).threshold == 0.3
    with pytest.raises(TypeError, match="not composed of"):
        part(p.guidance.execution, MotionSettings)
    bad = dataclasses.asdict(p)
    bad["defense"]["reacquire_after"] = 1
    with pytest.raises(ParamsError, match=r"^params.yaml defense.reacquire_after must be >= 2 frames, got 1$"):
        params_mod.build(bad)


def test_settings_of_refuses_a_library_field_that_nothing_gives() -> None:
    import dataclasses

    import pytest

    from stages.config.build import settings_of

    @dataclasses.dataclass(frozen=True)
    class Library:
        kept: float = 1.0
        renamed: int = 2

    @dataclasses.dataclass(frozen=True)
    class Section:
        kept: int
        old_name: int

    assert settings_of(Library, Section(3, 4), ("renamed",)) == Library(3.0, 2)
    with pytest.raises(TypeError, match=r"no value for \['renamed'\]"):
        settings_of(Library, Section(3, 4))
    with pytest.raises(TypeError, match=r"unknown library defaults \['typo'\]"):
        settings_of(Library, Section(3, 4), ("renamed", "typo"))


def test_the_registry_literals_of_the_schema_are_the_registries() -> None:
    """The schema's Literal types mirror the library's registries (generating them there would import torch into
    every params load, the Hydra plugin DVC runs included): each must name exactly the registry's entries."""
    import typing

    from pipeline.attackers.in_loop import GOALS
    from pipeline.attackers.suite import ATTACKERS
    from pipeline.attacks.gradient import ATTACKS, LOSSES
    from pipeline.defense.settings import FUSIONS
    from pipeline.guidance.law import DEFENSES, VARIANTS
    from stages.config.evaluation import AttackLoss, AttackMethod, Defense, InLoopGoal, IntegrityAttacker
    from stages.config.sections import Guidance

    hints = {name: typing.get_type_hints(cls) for name, cls in (("defense", Defense), ("guidance", Guidance))}
    attackers = {a for a in typing.get_args(IntegrityAttacker)}
    assert set(typing.get_args(AttackMethod)) == set(ATTACKS) and set(typing.get_args(AttackLoss)) == set(LOSSES)
    assert {a.split("/")[0] for a in attackers} == set(ATTACKERS) and set(typing.get_args(InLoopGoal)) == set(GOALS)
    assert set(typing.get_args(hints["defense"]["fusion"])) == set(FUSIONS)
    assert set(typing.get_args(typing.get_args(hints["guidance"]["dynamics"])[0])) == set(VARIANTS)
    assert set(typing.get_args(typing.get_args(hints["guidance"]["defenses"])[0])) == set(DEFENSES) - {"undefended"}
    standard = typing.get_args(typing.get_args(hints["guidance"]["standard_defenses"])[0])
    assert set(standard) == set(DEFENSES) - {"undefended"}


def test_the_schema_s_other_choice_literals_are_their_registries() -> None:
    """The rest of the schema's Literal choices that name a library registry: the integrity campaign's alert-limit
    kind, burst objective and drift start, the execution's approach, the adversarial training's objectives and
    starts. A value added to one side only would pass params validation and fail deep inside a stage, or the
    reverse."""
    import typing

    from pipeline.attackers.burst import OBJECTIVES as BURST_OBJECTIVES
    from pipeline.attackers.drift import STARTS as DRIFT_STARTS
    from pipeline.attacks.objectives import OBJECTIVES
    from pipeline.attacks.starts import STARTS
    from pipeline.defense.integrity import KINDS
    from pipeline.guidance.settings import APPROACHES
    from stages.config.evaluation import Integrity
    from stages.config.sections import Adversarial, Execution

    integrity, adversarial = typing.get_type_hints(Integrity), typing.get_type_hints(Adversarial)
    assert set(typing.get_args(integrity["alert_limit_kind"])) == set(KINDS)
    assert set(typing.get_args(integrity["burst_objective"])) == set(BURST_OBJECTIVES)
    assert set(typing.get_args(integrity["drift_start"])) == {*DRIFT_STARTS, "both"}  # both: one drift from each
    assert set(typing.get_args(typing.get_type_hints(Execution)["approach"])) == set(APPROACHES)
    assert set(typing.get_args(typing.get_args(adversarial["objectives"])[0])) == set(OBJECTIVES)
    assert set(typing.get_args(adversarial["start"])) == set(STARTS)


# a chain built from files goes through the one door; these build one from models in memory (a detector just
# trained, random models for a benchmark)
CHAIN_BUILDERS = {"pipeline/formats/chain.py", "stages/detect.py", "benchmarks/chain_latency.py"}


def _calls(path: Path) -> set[str]:
    """The names of the functions and methods a file calls."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            out.add(f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", ""))
    return out


def test_a_chain_has_one_door() -> None:
    """Only pipeline/formats/chain.py reads a chain's detector and defense files (stages, rpodguard, benchmarks
    and scripts call its `load_chain`), and only the door and the in-memory builders assemble an OnboardChain."""
    files = {
        str(p.relative_to(REPO)): p
        for pkg in (*PACKAGES, "scripts", "benchmarks")
        for p in sorted((REPO / pkg).rglob("*.py"))
    }
    calls = {name: _calls(path) for name, path in files.items()}
    readers = sorted(n for n, c in calls.items() if c & {"read_detector", "read_defense"})
    assert readers == ["pipeline/formats/chain.py"], readers
    builders = {n for n, c in calls.items() if c & {"from_model", "OnboardChain"}}
    assert builders <= CHAIN_BUILDERS, builders - CHAIN_BUILDERS
    doors = {n for n, c in calls.items() if "open_chain" in c or "load_chain" in c}
    assert {
        "rpodguard/api.py",
        "stages/artifacts/models.py",
        "scripts/bundle_weights.py",
        "benchmarks/explain_speed.py",
    } <= doors


MAX_FUNCTION_LINES = 60  # issue 36: a function, def line to last line (decorators excluded), reads on one screen


def long_functions(source: str, name: str) -> list[str]:
    """`name:line function (n lines)` of every function and method of `source`, nested ones included, longer
    than MAX_FUNCTION_LINES."""
    return [
        f"{name}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(ast.parse(source))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]


def test_no_function_is_longer_than_60_lines() -> None:
    """Every function of the library, the API, the commands, the benchmarks and the scripts: split a longer one
    into helpers."""
    files = [p for pkg in (*PACKAGES, "benchmarks", "scripts") for p in sorted((REPO / pkg).rglob("*.py"))]
    bad = [line for p in files for line in long_functions(p.read_text(), str(p.relative_to(REPO)))]
    assert not bad, bad


def test_the_length_check_finds_a_long_function() -> None:
    body = "    x = 1\n"
    nested = "class A:\n    def f(self):\n        def g():\n" + "            pass\n" * 60 + "        return g\n"
    assert long_functions("@decorator\ndef f():\n" + body * 59, "a.py") == []
    assert long_functions("@decorator\ndef f():\n" + body * 60, "a.py") == ["a.py:2 f (61 lines)"]
    assert long_functions(nested, "b.py") == ["b.py:2 f (63 lines)", "b.py:3 g (61 lines)"]


def test_contributing_prints_the_layer_order_the_test_enforces() -> None:
    """CONTRIBUTING's "Layers" paragraph names every unit of PIPELINE_ORDER and STAGES_ORDER, in that order."""
    import re

    text = (REPO / "CONTRIBUTING.md").read_text()
    para = text[text.index("- **Layers.**") : text.index("### How to add")]
    said = [n for n in re.findall(r"`([a-z_]+)`", para) if n in PIPELINE_ORDER or n in STAGES_ORDER]
    assert said == [*PIPELINE_ORDER, *STAGES_ORDER], said


# Where the default profile's value (conf/config.yaml) and the library dataclass's default differ, and why. Every
# other field a params section shares with its library settings has one value in both (the test below), so a default
# changed on one side only fails here instead of drifting apart in silence. The stages pass every field from
# params.yaml (settings_of refuses a gap), so the library default never reaches a run.
LIBRARY_DEFAULTS_DIFFER: dict[str, str] = {  # reasons: conf/config.yaml's comments, the library docstrings
    "train.cycle_epochs": "the cyclic schedule's half cycle; the default profile flies cosine",
    "train.schedule": "the library's is the cyclic LR (triangular2); the default profile chose cosine with warm-up",
    "train.warmup_epochs": "cosine's warm-up, which the library's cyclic default does not use",
    "train.ema": "no weight averaging unless asked; the default profile validates and saves the average (0.998)",
    "train.adversarial.position_weight": "the profile's inner loss is position only (the harm is position)",
    "train.adversarial.fraction": "profile 0.5: validation attitude 4.4 deg against 6.9 at 1.0 (conf comment)",
    "train.adversarial.eps": "the library's plain PGD recipe (0.05); the profile ships benchmarks/robust_recipes.py's c6",
    "train.adversarial.objectives": "as train.adversarial.eps: the profile attacks position and attitude",
    "train.adversarial.objective_eps": "as train.adversarial.eps: attitude at 0.03",
    "train.adversarial.start": "as train.adversarial.eps: past the clamp the profile starts from the lifted background",
    "train.adversarial.bpda": "as train.adversarial.start",
    "train.adversarial.trades": "as train.adversarial.eps: TRADES beta 0.3",
    "render.background": "SceneSettings' background is off; the default profile renders a quarter of the frames over the Earth",
    "render.background.share": "BackgroundSettings is off (every frame black) unless asked; the profile: a quarter",
    "render.background.stars": "as render.background.share: the profile's frames over the Earth carry stars",
    "render.background.black_offset": "as render.background.stars: a sensor black offset (0.02, below the clamp)",
    "render.background.noise_std": "as render.background.stars: sensor read noise",
    "train.augment.p": "profile 0.3: lighter than 0.5, the 160x90 default underfits (conf comment)",
    "train.augment.blur_sigma": "the profile's lighter augmentation, with train.augment.p",
    "train.augment.jpeg_quality": "the profile's lighter augmentation, with train.augment.p",
    "suite.steps": "SuiteConfig's default is the full suite's strength (FULL); the default profile's lean suite: 50",
    "suite.restarts": "as suite.steps",
    "suite.starts": "as suite.steps",
    "suite.full.square_eps": "the library's None runs Square at every eps; suite.full names 0.05, FULL's",
    "suite.full.batch_size": "rpod suite attacks every test frame in one batch (a GPU's best); the library's 32",
    "defense.position_noise": "MotionSettings' 5 mm per frame without a step scale; the profile's: the thrusters'",
    "defense.position_noise_scale": "as defense.position_noise",
    "guidance.max_steps": "GuidanceSettings' 60 steps (the nominal 50-step approach and 10 more); the profile's 100",
}


def test_a_library_default_equals_the_default_profiles_value_or_says_why_not() -> None:
    """For each section of SECTION_SETTINGS, every field its library settings share has the default profile's value
    as the library default (and so has every field of a composed section), except the LIBRARY_DEFAULTS_DIFFER fields
    (which must still differ: a list that lies fails); fields without a library default (required) and the mesh
    sentinel are not defaults."""
    import dataclasses
    import importlib

    from stages.config import params as params_mod
    from stages.config.build import SECTION_SETTINGS

    p = params_mod.build(params_mod.compose("default"))

    def plain(v: object) -> object:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return tuple(plain(x) for x in v)
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v

    differ = set()
    for path, classes in SECTION_SETTINGS.items():
        section = p
        for name in path.split("."):
            section = getattr(section, name)
        for spec in classes:
            module, name = spec.split(":")
            for f in dataclasses.fields(getattr(importlib.import_module(module), name)):
                if not hasattr(section, f.name) or (path, f.name) == ("render", "mesh"):
                    continue
                if f.default is not dataclasses.MISSING:
                    default = f.default
                elif f.default_factory is not dataclasses.MISSING:
                    default = f.default_factory()
                else:
                    continue
                if plain(default) != plain(getattr(section, f.name)):
                    differ.add(f"{path}.{f.name}")
    for path, section in _composed_sections().items():  # their defaults are the library's, field by field
        value = p
        for name in path.split("."):
            value = getattr(value, name)
        for f in dataclasses.fields(section):
            if f.default is not dataclasses.MISSING and plain(f.default) != plain(getattr(value, f.name)):
                differ.add(f"{path}.{f.name}")
    from pipeline.guidance.law import GuidanceSettings  # built by hand in stages/guidance.py (target -> goal; its
    # execution is the guidance.execution section above)

    for f in dataclasses.fields(GuidanceSettings):
        name = "target" if f.name == "goal" else f.name
        value = getattr(p.guidance, name, None)
        if value is not None and not dataclasses.is_dataclass(value) and plain(f.default) != plain(value):
            differ.add(f"guidance.{name}")
    assert differ == set(LIBRARY_DEFAULTS_DIFFER), (
        sorted(differ - set(LIBRARY_DEFAULTS_DIFFER)),
        sorted(set(LIBRARY_DEFAULTS_DIFFER) - differ),
    )

"""One schema rule for every numeric param: finite and inside its documented range (`In`, declared beside
the field in stages/config/{schema,sections,evaluation}.py), refused with one line naming the key, both
when a stage loads params.yaml and when `rpod params` composes it (then nothing is written)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import sys
import types
import typing
from typing import Annotated, Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.settings import In
from stages.config.params import compose
from stages.config.schema import Params, build
from stages.config.sections import ParamsError


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted key, type hint) of every non-dataclass field below `cls`."""
    out = []
    for f in dataclasses.fields(cls):
        hint = typing.get_type_hints(cls, include_extras=True)[f.name]
        if dataclasses.is_dataclass(hint):
            out += _leaves(hint, f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", hint))
    return out


def _number(hint: Any) -> tuple[type, In | None, int] | None:
    """(int or float, its In rule or None, list depth) of a numeric field hint (through Optional and lists)."""
    depth = 0
    while True:
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin in (typing.Union, types.UnionType):
            hint = next(a for a in args if a is not type(None))
        elif origin is list:
            hint, depth = args[0], depth + 1
        elif origin is Annotated:
            return args[0], next((r for r in args[1:] if isinstance(r, In)), None), depth
        else:
            return (hint, None, depth) if hint in (int, float) else None


NUMERIC = [(key, *_number(hint)) for key, hint in _leaves(Params) if _number(hint)]


@functools.cache
def _base() -> dict[str, Any]:
    return compose("smoke")


def _with(key: str, depth: int, value: Any) -> dict[str, Any]:
    """The smoke params with `key` (its first element, for a list) set to `value`."""
    p = copy.deepcopy(_base())
    *path, last = key.split(".")
    section = functools.reduce(lambda d, k: d[k], path, p)
    if depth == 0 or not section[last]:  # null or an empty list ([] = a default, e.g. objective_eps)
        section[last] = value if depth == 0 else [value] * 2 if depth == 1 else [[value] * 2]
    else:
        target = section[last]
        for _ in range(depth - 1):
            target = target[0]
        target[0] = value
    return p


def test_every_numeric_param_declares_a_finite_range():
    assert len(NUMERIC) > 100
    missing = [key for key, _, rule, _ in NUMERIC if rule is None]
    assert not missing, f"numeric params without an In range: {missing}"
    for key, _, rule, _ in NUMERIC:
        low, high = rule.bounds()
        assert math.isfinite(low) and math.isfinite(high) and low < high, key
        assert rule.interval[0] in "[(" and rule.interval[-1] in "])", key


def test_help_shows_each_range():
    from typer.testing import CliRunner

    from stages.cli import app
    from stages.config.schema import ranges

    assert set(ranges()) == {key for key, *_ in NUMERIC}
    out = " ".join(CliRunner().invoke(app, ["render", "--help"], terminal_width=200).output.split())
    assert "image width; range [8, 8192] pixels" in out and "(Blender sun strength); range (0, 10000] W/m^2" in out


def test_every_profile_lies_inside_the_ranges():
    for name in ("default", "smoke", "paper"):
        build(compose(name))


BAD = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, 0.0, -1, -0.5, -1e-9, 1e300, 10**18, -(10**18)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**20), 10**20),
)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(param=st.sampled_from(NUMERIC), value=BAD)
def test_out_of_range_values_are_refused_naming_the_param(param, value):
    key, kind, rule, depth = param
    fits = (
        (kind is float or isinstance(value, int))
        and not (isinstance(value, float) and math.isnan(value))
        and rule.contains(value)
    )
    if fits:
        return  # inside the documented range (other sections' cross-checks aside)
    with pytest.raises(ParamsError) as refused:
        build(_with(key, depth, value))
    message = str(refused.value)
    section, leaf = key.split(".")[0], key.split(".")[-1]
    assert "\n" not in message and message.startswith("params.yaml") and section in message and leaf in message


@pytest.mark.parametrize(
    "override",
    [
        "attack.momentum=nan",
        "attack.step_size=nan",
        "render.max_target_rotation_deg=nan",
        "render.max_target_rotation_deg=-10",
        "render.sun_strength=nan",
        "render.sun_strength=inf",
        "render.sun_strength=0",
        "render.sun_strength=-5",
        "detect.squeeze_bits=0",
        "train.weight_decay=-1",
        "train.max_minutes=0",
        "train.max_minutes=-1",
        "train.max_minutes=nan",
        "render.chunk=0",
        "render.chunk=-5",
        "train.cycle_epochs=nan",
        "render.width=2",
        "engine.timeout_s=nan",
        "attack.eps=[0.5,nan]",
    ],
)
def test_rpod_params_refuses_the_issues_probes_and_writes_nothing(tmp_path, monkeypatch, capsys, override):
    from stages import cli

    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(cli._DEBUG, "on", False)
    monkeypatch.setattr(sys, "argv", ["rpod", "params", "default", "-S", override])
    with pytest.raises(SystemExit) as exit_:
        cli.main()
    err = capsys.readouterr().err.strip()
    key = override.split("=")[0]
    assert exit_.value.code == 1 and len(err.splitlines()) == 1 and f"params.yaml {key}" in err, err
    assert list(tmp_path.iterdir()) == []  # no params.yaml, nothing else

"""Settings read typed: the documented range of a numeric setting (`In`, declared beside its field as
`Annotated[float, In("(0, 1]", "unit")]`) and `typed(cls, values, source)`, a settings dataclass built from a
mapping (a params.yaml section, a JSON file's record) with every value's type, finiteness and range checked
and unknown keys refused, each refusal one line naming the file (`Source.name`) and the dotted key.

A value keeps the type its file gave it: a whole number where a float is expected stays an int (PEP 484's
numeric tower), so `dataclasses.asdict` of the result is the mapping read, as JSON and YAML write it: a list is
read as a tuple where the field is a tuple.

`composed` declares a settings section (a params.yaml section) by the library settings dataclasses it is made of,
so each setting's type, range and default are declared once, beside the code that uses it; `part` builds one back.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Callable, Literal


@dataclass(frozen=True)
class In:
    """The documented range of a number: `interval` with finite bounds ("[" or "]": bound included, "(" or ")":
    excluded) and its unit. `typed` refuses a value outside it, and any NaN or infinity."""

    interval: str
    unit: str = ""

    def bounds(self) -> tuple[float, float]:
        low, high = self.interval[1:-1].split(",")
        return float(low), float(high)

    def contains(self, value: float) -> bool:
        (low, high), (left, right) = self.bounds(), (self.interval[0], self.interval[-1])
        return (low <= value if left == "[" else low < value) and (value <= high if right == "]" else value < high)

    def rule(self, whole: bool) -> str:
        """What a value must be, for a message: "a positive whole number in [1, 10] (frames)"."""
        low = self.bounds()[0]
        kind = ("a positive " if low > 0 or (low == 0 and self.interval[0] == "(") else "a ") + (
            "whole number" if whole else "number"
        )
        return f"{kind} in {self.interval}" + (f" ({self.unit})" if self.unit else "")


@dataclass(frozen=True)
class Source:
    """Where the values come from, for the messages and the rules: `name` (e.g. params.yaml), `error` the
    exception raised (a ValueError subclass), `noun` what a key is called there, `remake` how to write a
    complete file (said when a key is missing) and `required`: every field must be given, but those declared
    `field(..., metadata=OPTIONAL)` (else also a field with a default may be left out: it keeps its default)."""

    name: str
    error: type[ValueError] = ValueError
    noun: str = "key"
    remake: str = ""
    required: bool = True


def typed(cls: type, values: Any, source: Source, key: str = "") -> Any:
    """`cls` (a dataclass) from the mapping `values`, checked field by field (see the module docstring), then by
    `cls`'s own checks (its ValueError becomes one naming `key`), then every number against its `In` range."""
    return _build(cls, values, key, source)


def ranges(cls: type, prefix: str = "") -> dict[str, In]:
    """Dotted key -> the `In` range of each numeric field of `cls` and its nested dataclasses (of each element,
    for a list): e.g. {"render.width": In("[8, 8192]", "pixels"), ...}."""
    out: dict[str, In] = {}
    for name, hint in typing.get_type_hints(cls, include_extras=True).items():
        if dataclasses.is_dataclass(hint):
            out.update(ranges(hint, f"{prefix}{name}."))
            continue
        while typing.get_origin(hint) in (typing.Union, types.UnionType, list):
            hint = next(a for a in typing.get_args(hint) if a is not type(None))
        rule = next((r for r in typing.get_args(hint)[1:] if isinstance(r, In)), None)
        if typing.get_origin(hint) is Annotated and rule is not None:
            out[f"{prefix}{name}"] = rule
    return out


def composed(*parts: type, runtime: tuple[str, ...] = ()) -> Callable[[type], type]:
    """Class decorator: a settings section (a frozen dataclass, keyword-only) declared by the library settings
    dataclasses `parts`: their fields with their types, ranges and defaults, less `runtime` (fields a caller sets
    when it builds a part, never read from a file), then the decorated class's own annotated fields (settings no
    part takes) and its methods. Built, the section runs the class's own `__post_init__`, then builds each part
    from its fields, so every part's own checks refuse a bad value. `part(section, cls, **runtime)` builds one
    back. A name given by two parts, or by a part and the class, is a TypeError."""

    def compose(cls: type) -> type:
        specs: list[tuple[str, Any, Any]] = []
        for owner in parts:
            hints = typing.get_type_hints(owner, include_extras=True)
            for f in dataclasses.fields(owner):
                if f.name not in runtime:
                    specs.append(
                        (f.name, hints[f.name], dataclasses.field(default=f.default, default_factory=f.default_factory))
                    )
        own = typing.get_type_hints(cls, include_extras=True)
        for name in cls.__dict__.get("__annotations__", {}):
            default = cls.__dict__.get(name, dataclasses.MISSING)
            given = default if isinstance(default, dataclasses.Field) else dataclasses.field(default=default)
            specs.append((name, own[name], given))
        names = [name for name, _, _ in specs]
        twice = sorted({n for n in names if names.count(n) > 1})
        unknown = sorted(set(runtime) - {f.name for owner in parts for f in dataclasses.fields(owner)})
        if twice or unknown:
            raise TypeError(f"{cls.__name__}: fields declared twice {twice}, runtime fields no part has {unknown}")
        namespace = {k: v for k, v in vars(cls).items() if k not in ("__dict__", "__weakref__", "__annotations__")}
        namespace = {k: v for k, v in namespace.items() if k not in names}
        namespace.update(
            __parts__=parts,
            __runtime__=runtime,
            __post_init__=_composed_checks(cls.__dict__.get("__post_init__"), parts),
        )
        return dataclasses.make_dataclass(cls.__name__, specs, namespace=namespace, frozen=True, kw_only=True)

    return compose


def _composed_checks(own: Callable[[Any], None] | None, parts: tuple[type, ...]) -> Callable[[Any], None]:
    def __post_init__(self: Any) -> None:
        if own is not None:
            own(self)
        for cls in parts:
            part(self, cls)

    return __post_init__


def part(section: Any, cls: type, **runtime: Any) -> Any:
    """The library settings `cls` (one of the parts a `composed` section was declared by) from `section`'s fields,
    each converted to `cls`'s field type (a whole number to float, a list to a tuple), and `runtime` for the fields a
    caller sets (a runtime value also overrides the section's)."""
    if cls not in getattr(type(section), "__parts__", ()):
        raise TypeError(f"{type(section).__name__} is not composed of {cls.__name__}")
    hints = typing.get_type_hints(cls)
    values = {
        f.name: as_type(getattr(section, f.name), hints[f.name])
        for f in dataclasses.fields(cls)
        if f.name not in runtime and hasattr(section, f.name)
    }
    return cls(**values, **runtime)


def as_type(value: Any, hint: Any) -> Any:
    """`value` as the type `hint` names: float(int) for float, a tuple of converted items for tuple[...]."""
    if value is None:
        return None
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return as_type(value, next(a for a in typing.get_args(hint) if a is not type(None)))
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:  # tuple[X, ...]: every item an X
            return tuple(as_type(v, args[0]) for v in value)
        return tuple(as_type(v, a) for v, a in zip(value, args))
    return float(value) if hint is float else value


OPTIONAL = {"optional": True}  # field metadata: a key a file may leave out (the field keeps its default)
_WHAT = {int: "a whole number", float: "a number", bool: "true or false", str: "a string"}


def _check(value: Any, hint: Any, key: str, source: Source) -> Any:
    """`value` as the type `hint` (ints accepted for floats, lists for tuples), or `source.error` naming `key`."""
    origin, args, fail = typing.get_origin(hint), typing.get_args(hint), source.error
    if hint is Any:
        return value
    if hint is dict or origin is dict:
        if not isinstance(value, dict):
            raise fail(f"{source.name} {key} must be a mapping, got {value!r}")
        return value
    if origin is Annotated:
        rules = [r for r in args[1:] if isinstance(r, In)]
        if rules and isinstance(value, float) and not math.isfinite(value):
            raise fail(f"{source.name} {key} must be {rules[0].rule(args[0] is int)}, got {value!r}")
        return _check(value, args[0], key, source)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _check(value, next(a for a in args if a is not type(None)), key, source)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple) if origin is tuple else list):
            raise fail(f"{source.name} {key} must be a list, got {value!r}")
        items = args if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis) else args[:1] * len(value)
        if len(items) != len(value):
            raise fail(f"{source.name} {key} must be a list of {len(items)}, got {value!r}")
        out = [_check(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, items))]
        return tuple(out) if origin is tuple else out
    if origin is Literal:
        if value not in args:
            raise fail(f"{source.name} {key} must be one of {', '.join(map(str, args))}, got {value!r}")
        return value
    if dataclasses.is_dataclass(hint):
        return value if isinstance(value, hint) else _build(hint, value, key, source)
    ok = {
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        bool: isinstance(value, bool),
        str: isinstance(value, str),
    }[hint]
    if not ok:
        raise fail(f"{source.name} {key} must be {_WHAT[hint]}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise fail(f"{source.name} {key} must be a finite number, got {value!r}")
    return value


def _build(cls: type, section: Any, key: str, source: Source) -> Any:
    if not isinstance(section, dict):
        if key:  # a section replaced by a value (e.g. `-S train=1`)
            raise source.error(f"{source.name}: {key!r} must be a section of {source.noun}s, got {section!r}")
        raise source.error(f"{source.name} top level must be a mapping, got {section!r}")
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    prefix = f"{key}." if key else ""
    for name in section:
        if name not in fields:
            hint = difflib.get_close_matches(str(name), list(fields), n=1)
            raise source.error(
                f"{source.name}: unknown {source.noun} {prefix + str(name)!r}"
                + (f" (did you mean {prefix + hint[0]!r}?)" if hint else "")
            )
    values = {}
    for name, f in fields.items():
        if name not in section:
            defaulted = f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING  # type: ignore[misc]
            if defaulted and (f.metadata.get("optional") or not source.required):
                continue
            raise source.error(
                f"{source.name}: missing {source.noun} {prefix + name!r}"
                + (f" ({source.remake})" if source.remake else "")
            )
        values[name] = _check(section[name], hints[name], prefix + name, source)
    try:
        built = cls(**values)
    except source.error:
        raise  # already names its key in full
    except (TypeError, ValueError) as e:
        raise source.error(f"{source.name} {_keyed(str(e), key)}") from None
    for name, value in values.items():  # after the section's own checks, so their messages come first
        _check_range(value, hints[name], prefix + name, source)
    return built


def _keyed(message: str, key: str) -> str:
    """`message` naming `key` in full: kept when it does ("defense.hold_after must ..."), completed when it names the
    key's last part ("background.share must ..." under render.background), else prefixed ("train: ...")."""
    last = key.rsplit(".", 1)[-1]
    if not key or message.startswith(f"{key}."):
        return message
    if message.startswith(f"{last}."):
        return key + message[len(last) :]
    return f"{key}: {message}"


def _check_range(value: Any, hint: Any, key: str, source: Source) -> None:
    """`source.error` naming `key` when a number (or a list's element) lies outside its field's `In` range."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if value is None or dataclasses.is_dataclass(value):
        return
    if origin in (typing.Union, types.UnionType):
        _check_range(value, next(a for a in args if a is not type(None)), key, source)
    elif origin in (list, tuple):
        items = args if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis) else args[:1] * len(value)
        for i, (v, a) in enumerate(zip(value, items)):
            _check_range(v, a, f"{key}[{i}]", source)
    elif origin is Annotated:
        for rule in args[1:]:
            if isinstance(rule, In) and not rule.contains(value):
                raise source.error(f"{source.name} {key} must be {rule.rule(args[0] is int)}, got {value!r}")

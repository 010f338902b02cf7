"""defense.json as a schema (issue 42, item 1; pipeline/formats/defense.py): every key required, typed, finite and in
range, no unknown key; what calibrate writes reads back equal; a file calibrated under other params is refused naming
both values. Property tests (hypothesis) over the committed shipped chain's defense file, mutated."""

from __future__ import annotations

import copy
import dataclasses
import json
import re
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.defense.chain import Defended
from pipeline.defense.gate import MotionSettings
from pipeline.defense.settings import DefenseSettings
from pipeline.formats.defense import DefenseFile, check_settings, parse_defense, read_defense
from pipeline.io.errors import DataError
from pipeline.settings import ranges
from rpodguard.api import BUNDLE

RECORD = json.loads((BUNDLE / "defense.json").read_text())  # what `rpod calibrate` wrote for the shipped chain
WHERE = "models/defense.json"
EXAMPLES = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CALIBRATED = {"threshold", "update_below", "cusum_threshold", "correlated_error"}  # the settings calibrate chooses


def paths(record: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of the record's typed part (`validation`'s free-form records aside)."""
    out = []
    for key, value in record.items():
        out.append((*prefix, key))
        if isinstance(value, dict) and key in ("noise", "fitted_noise", "settings", "alert_limit"):
            out += paths(value, (*prefix, key))
    return out


def at(record: dict, path: tuple) -> tuple[dict, str]:
    """(the mapping holding the key, the key) of a key path."""
    for key in path[:-1]:
        record = record[key]
    return record, path[-1]


REQUIRED = [p for p in paths(RECORD) if p != ("tightened",)]
LEAVES = [p for p in REQUIRED if p[0] != "validation" and not isinstance(at(RECORD, p)[0][p[-1]], dict)]


def test_the_committed_defense_file_reads_and_writes_back_the_same_record():
    cal = parse_defense(copy.deepcopy(RECORD), WHERE)
    assert cal.to_json() == RECORD and cal.model == "robust"
    assert cal.defended == Defended(cal.settings, cal.motion, cal.noise, cal.alert_limit)
    assert cal.defended.settings.threshold == RECORD["threshold"] == RECORD["settings"]["threshold"]
    read_defense(BUNDLE / "defense.json", RECORD["pose_model_hash"], RECORD["detector_threshold"])


@EXAMPLES
@given(st.sampled_from(REQUIRED))
def test_every_key_is_required(path):
    record = copy.deepcopy(RECORD)
    parent, key = at(record, path)
    del parent[key]
    with pytest.raises(
        DataError,
        match=rf"{WHERE}.*(missing key '{'.'.join(path)}'|is not a rpodguard-defense|"
        rf"settings must be a mapping)",
    ) as e:
        parse_defense(record, WHERE)
    assert "\n" not in str(e.value)


@EXAMPLES
@given(
    st.sampled_from([(), ("settings",), ("alert_limit",), ("noise",), ("fitted_noise",), ("validation",)]),
    st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=12),
)
def test_an_unknown_key_is_refused(where, name):
    record = copy.deepcopy(RECORD)
    parent = record
    for key in where:
        parent = parent[key]
    if name in parent or (where == ("settings",) and name == "motion"):
        return
    parent[name] = 1
    with pytest.raises(DataError, match=rf"{WHERE}: unknown key '{'.'.join((*where, name))}'"):
        parse_defense(record, WHERE)


BAD = [float("nan"), float("inf"), -float("inf"), "5", True, [1.0], {"a": 1}]


@EXAMPLES
@given(st.sampled_from(LEAVES), st.sampled_from(BAD))
def test_a_value_of_the_wrong_type_or_not_finite_is_refused(path, bad):
    record = copy.deepcopy(RECORD)
    parent, key = at(record, path)
    if isinstance(parent[key], list) and isinstance(bad, list) or isinstance(parent[key], str) and isinstance(bad, str):
        return  # a list for a list (its elements are checked below), a string for a string
    parent[key] = bad
    with pytest.raises(DataError, match=WHERE) as e:
        parse_defense(record, WHERE)
    assert "\n" not in str(e.value)


RANGED = {
    **{
        ("settings", k): r
        for k, r in {**ranges(DefenseSettings), **ranges(MotionSettings)}.items()
        if k not in CALIBRATED
    },
    **{("alert_limit", k): None for k in ("tolerance", "max_step", "collision_range", "fixed")},
}


@EXAMPLES
@given(st.sampled_from(sorted(RANGED)), st.sampled_from([-1.0, 0.0, 1e300, -1e-9]))
def test_a_number_out_of_its_range_is_refused(path, bad):
    rule = RANGED[path]
    if rule is not None and rule.contains(bad):
        return
    record = copy.deepcopy(RECORD)
    parent, key = at(record, path)
    parent[key] = int(bad) if isinstance(parent[key], int) and bad == int(bad) and abs(bad) < 1e18 else bad
    with pytest.raises(DataError, match=rf"{WHERE}.*{key}") as e:
        parse_defense(record, WHERE)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "path, value, message",
    [
        (("settings", "hold_after"), 1.5, "settings.hold_after must be a whole number, got 1.5"),
        (("settings", "hold_after"), "5", "settings.hold_after must be a whole number, got '5'"),
        (("alert_limit", "tolerance"), float("inf"), "alert_limit.tolerance must be a finite number"),
        (("alert_limit", "fixed"), 1e300, "alert_limit.fixed must be a positive number in"),
        (("noise", "floor"), 1e6, "noise.floor must be a positive number in"),
        (("detector_threshold",), float("nan"), "detector_threshold must be a positive number in \\(0, 1\\)"),
        (("settings", "threshold"), 1.0, "settings: detector threshold must be in \\(0, 1\\), got 1.0"),
        (("settings", "fusion"), "and", "settings.fusion must be one of paper, motion, or"),
        (("model",), "paper", "model must be one of standard, robust"),
    ],
)
def test_the_probes_of_issue_42_are_refused_with_one_line(path, value, message):
    record = copy.deepcopy(RECORD)
    parent, key = at(record, path)
    parent[key] = value
    with pytest.raises(DataError, match=message) as e:
        parse_defense(record, WHERE)
    assert str(e.value).startswith(WHERE) and "\n" not in str(e.value)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda r: r["settings"].update(threshold=0.5), "must be the calibrated threshold"),
        (
            lambda r: r["noise"]["knot_std"][0].__setitem__(0, -0.5),
            "noise.knot_std\\[0\\]\\[0\\] must be a positive number",
        ),
        (lambda r: r["noise"].update(floor=0.5), "noise is not fitted_noise inflated"),
        (
            lambda r: (r["noise"].update(floor=10.0), r["fitted_noise"].update(floor=10.0 / r["inflation"])),
            "floor 10.0 must lie below its largest standard deviation",
        ),
        (lambda r: r.update(settings={}), "missing key 'settings.fusion'"),
        (lambda r: r.update(alert_limit={}), "missing key 'alert_limit.tolerance'"),
    ],
)
def test_a_record_that_contradicts_itself_or_is_empty_is_refused(change, message):
    record = copy.deepcopy(RECORD)
    change(record)
    with pytest.raises(DataError, match=message):
        parse_defense(record, WHERE)


settings_values = st.fixed_dictionaries(
    {
        "hold_after": st.integers(1, 10_000_000),
        "release_after": st.integers(1, 10_000_000),
        "fusion": st.sampled_from(["paper", "motion", "or"]),
        "false_alarm": st.floats(1e-9, 1 - 1e-9),
        "position_noise": st.floats(1e-6, 1000),
        "position_noise_scale": st.floats(0, 1),
        "soft_gate": st.floats(1e-6, 1),
        "reacquire_after": st.integers(2, 10_000_000),
        "trusted_start": st.integers(0, 10_000_000),
        "cusum_reference": st.floats(0, 100),
    }
)


@EXAMPLES
@given(settings_values, st.floats(1e-3, 1e5), st.integers(0, 1000))
def test_any_valid_record_reads_back_equal_and_flies_what_it_records(values, tolerance, slack):
    record = copy.deepcopy(RECORD)
    record["settings"].update(values)
    record["alert_limit"].update(tolerance=tolerance, slack_steps=slack)
    cal = parse_defense(record, WHERE)
    assert cal.to_json() == record and parse_defense(cal.to_json(), WHERE) == cal
    flown = cal.defended
    assert all(getattr(flown.settings, k, getattr(flown.motion, k, None)) == v for k, v in values.items())
    assert flown.alert.tolerance == tolerance and flown.alert.slack_steps == slack
    assert flown.new() is not flown.new()  # a fresh defense per run


@EXAMPLES
@given(st.sampled_from(sorted(k for k in {**ranges(DefenseSettings), **ranges(MotionSettings)} if k not in CALIBRATED)))
def test_a_file_calibrated_under_other_settings_is_refused_naming_both_values(name):
    cal = parse_defense(copy.deepcopy(RECORD), WHERE)
    wanted = cal.defended
    check_settings(cal, WHERE, wanted, 0.05, "params.yaml", {})  # as calibrated
    part = "settings" if name in {f.name for f in dataclasses.fields(DefenseSettings)} else "motion"
    old = getattr(getattr(wanted, part), name)
    new = old + 1 if isinstance(old, int) and not isinstance(old, bool) else old * 0.5
    other = dataclasses.replace(wanted, **{part: dataclasses.replace(getattr(wanted, part), **{name: new})})
    with pytest.raises(
        DataError,
        match=rf"{WHERE} records settings.{name} = {old!r} but params.yaml gives "
        rf"defense.{name} = {new!r}: calibrated under other settings",
    ):
        check_settings(cal, WHERE, other, 0.05, "params.yaml", {name: f"defense.{name}"})
    doubt = re.escape(repr(wanted.settings.update_below))  # the bundle's calibrated doubt level
    with pytest.raises(DataError, match=rf"records settings.update_below = {doubt} but params.yaml gives doubt = None"):
        check_settings(cal, WHERE, wanted, None, "params.yaml", {})


def test_the_committed_params_fly_exactly_what_the_committed_defense_file_records():
    """The switch to defense.json as the only source changes no number: the settings the stages built from
    params.yaml and the calibrated settings (thresholds, h, the PL's correlated share; before) equal those the file
    records (after), field by field."""
    from stages.config.build import alert_limit_settings, defense_settings
    from stages.config.params import load

    p = load()
    cal = parse_defense(copy.deepcopy(RECORD), WHERE)
    settings, motion = defense_settings(p.defense, cal.threshold, cal.settings.update_below)
    before = Defended(
        settings,
        dataclasses.replace(motion, cusum_threshold=cal.cusum_threshold, correlated_error=cal.motion.correlated_error),
        cal.noise,
        alert_limit_settings(p),
    )
    assert repr(before) == repr(cal.defended)  # equal values of equal types
    check_settings(cal, WHERE, before, p.defense.doubt_share, "params.yaml", {})


def test_the_schema_is_the_dataclass():
    """Every field of DefenseFile is a key of the file (settings and motion share `settings`), nothing else."""
    keys = {f.name for f in dataclasses.fields(DefenseFile)} - {"motion"}
    assert keys == set(RECORD) | {"tightened"}

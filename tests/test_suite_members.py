"""scripts/suite_members.py: the share of the full suite's worst case a subset of its members finds."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.attacks.strongest import ERRORS, SHIFTS, SuiteResult
from pipeline.formats.suite import write_suite_part
from tests.script_loader import load_script

members = load_script("suite_members")
MEMBERS = ("apgd/position", "apgd/range_far", "apgd/attitude", "square/position")


def _part(eps: float, errors: np.ndarray) -> SuiteResult:
    """One eps of a run over 4 frames; `errors` (M, N) is every error kind's value per member and frame."""
    m, n = errors.shape
    values = {k: errors[:, None, :].astype(np.float64) for k in ERRORS}
    return SuiteResult(
        (eps,),
        MEMBERS[:m],
        values,
        {k: np.zeros((m, 1, n)) for k in SHIFTS},
        {k: np.full(n, 0.1) for k in ERRORS},
        np.full(n, 20.0),
        np.ones((m, 1)),
        np.ones((m, 1)),
    )


def _write(folder, model: str, kind: str, key: str, parts: dict[float, np.ndarray]) -> None:
    for e, errors in parts.items():
        write_suite_part(folder / f"{model}-{kind}-{e:g}.npz", _part(e, errors), key, "cpu")


def test_a_subset_s_share_is_its_nested_worst_case_over_the_suite_s(tmp_path) -> None:
    # range_far is the worst member on frames 2 and 3; square ran at the second eps only (NaN at the first)
    small = np.array([[1.0, 1.0, 0.5, 0.5], [0.5, 0.5, 2.0, 2.0], [0.2, 0.2, 0.2, 0.2], [np.nan] * 4])
    large = np.array([[2.0, 2.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0], [0.2, 0.2, 0.2, 0.2], [3.0, 0.1, 0.1, 0.1]])
    _write(tmp_path, "robust", "full", "k1", {0.01: small, 0.05: large})
    full = members.load_run(tmp_path, "robust", "full")
    assert full.eps == (0.01, 0.05)
    every = members.share(full, MEMBERS, "position_m")
    np.testing.assert_allclose(every, [1.0, 1.0])
    # position alone: frames 2, 3 lose range_far's 2.0 (nested: also at eps 0.05); frame 0 loses square's 3.0
    np.testing.assert_allclose(members.share(full, ("apgd/position",), "position_m"), [3.0 / 6.0, 6.0 / 9.0])
    # bpda/x is apgd/x where the model has no clamp (the full suite ran no bpda member)
    np.testing.assert_allclose(members.share(full, ("bpda/range_far",), "position_m"), [5.0 / 6.0, 6.0 / 9.0])
    # the best pair finds the whole worst case at the first eps, where square did not run
    best = members.candidates(full, 2)
    assert ("apgd/position", "apgd/range_far") in best and all("square/position" not in c for c in best)


def test_the_report_prints_the_lean_suite_beside_the_subsets(tmp_path, capsys) -> None:
    errors = np.array([[1.0, 2.0, 3.0, 4.0], [2.0, 1.0, 1.0, 1.0], [0.5, 0.5, 0.5, 0.5]])
    _write(tmp_path, "standard", "full", "k1", {0.01: errors})
    _write(tmp_path, "standard", "lean", "k2", {0.01: errors[:1] * 0.5})
    members.report(tmp_path, [], 2, 1)
    out = capsys.readouterr().out
    assert "standard: 4 frames, eps 0.01" in out
    assert "lean suite as run (apgd/position): 0.455" in out  # (0.5 + 1 + 1.5 + 2) / (2 + 2 + 3 + 4)
    assert "apgd/position, apgd/range_far: 1.000" in out  # the best pair holds every frame's worst


@pytest.mark.parametrize("case", ["empty", "two runs", "unknown member", "damaged", "misnamed"])
def test_bad_input_stops_with_one_line_naming_it(tmp_path, case) -> None:
    errors = np.ones((3, 4))
    if case == "two runs":
        _write(tmp_path, "robust", "full", "k1", {0.01: errors})
        _write(tmp_path, "robust", "full", "k2", {0.02: errors})
    if case == "unknown member":
        _write(tmp_path, "robust", "full", "k1", {0.01: errors})
    if case == "damaged":
        (tmp_path / "robust-full-0.01.npz").write_bytes(b"not a zip")
    if case == "misnamed":
        _write(tmp_path, "robust", "full", "k1", {0.01: errors})
        (tmp_path / "robust-full-0.01.npz").rename(tmp_path / "robust-full-last.npz")
    subsets = [("apgd/lateral",)] if case == "unknown member" else []
    with pytest.raises(SystemExit) as e:
        members.report(tmp_path, subsets, 3, 5)
    expected = {
        "empty": "no full-suite parts",
        "two runs": "parts of 2 runs",
        "unknown member": "not a member",
        "damaged": "robust-full-0.01.npz: not a readable suite part",
        "misnamed": "robust-full-last.npz: not named",
    }[case]
    assert expected in str(e.value) and "\n" not in str(e.value)

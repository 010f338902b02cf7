"""`rpod bound` (stages/bound.py): its params section, its reading of the capacity files, and its page built from
bound_run outputs on a toy filter."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.attacks.capacity import proportional_capacity
from pipeline.defense.integrity import AlertLimitSettings
from pipeline.evaluation.integrity_bound import (
    ATTACKERS,
    bound_run,
    checks_only_rates,
    first_over,
    over_al_rate,
    worst_over_trajectories,
)
from pipeline.formats.capacity import COLUMNS, write_capacity
from stages.config.bound import Bound
from stages.errors import StageError
from stages.pages.bound import bound_page
from tests.test_bound import FLAT, toy
from tests.test_integrity_bound import DEFENDED, caps

GOOD = dict(models=["robust"], eps=[0.01], stride=10, trajectories=None, certify_frames=0, batch_size=8)


def test_the_section_refuses_no_eps_and_a_repeated_chain() -> None:
    Bound(**GOOD)
    with pytest.raises(ValueError, match="at least one"):
        Bound(**{**GOOD, "eps": []})
    with pytest.raises(ValueError, match="repeat"):
        Bound(**{**GOOD, "models": ["robust", "robust"]})


def _write(folder, eps: list[float]) -> None:
    frames = pd.DataFrame([[i, 20.0 + i, e, 0.1, 0.1, 1.0] for e in eps for i in range(3)], columns=COLUMNS)
    write_capacity(folder, "robust", frames, [proportional_capacity(e, [0.0, 100.0], 0.01, 0.01) for e in eps], {})


def test_the_stage_reads_the_capacity_and_refuses_a_missing_one_or_an_eps_above_it(tmp_path, monkeypatch) -> None:
    from stages.artifacts.paths import CAPACITY
    from stages.bound import _capacities

    monkeypatch.chdir(tmp_path)
    with pytest.raises(StageError, match="rpod train --robust"):
        _capacities("robust", [0.01])
    _write(tmp_path / CAPACITY, [0.01, 0.05])
    got, _ = _capacities("robust", [0.01, 0.02])
    assert [c.eps for c in got] == [0.01, 0.05]
    with pytest.raises(StageError, match="bound.eps"):
        _capacities("robust", [0.1])


def _metrics() -> dict:
    """A one-chain metrics dict as stages/bound.py assembles it, from two toy trajectories."""
    tracks = [
        bound_run(DEFENDED, f"t{s}", *toy(40, s, FLAT)[::-1], caps(0.01, 0.01), [0.01, 0.05], 10, AlertLimitSettings())
        for s in (1, 2)
    ]
    per_eps = {}
    for e in ("0.01", "0.05"):
        per_eps[e] = worst_over_trajectories(tracks, e)
        for who in ATTACKERS:
            r = over_al_rate(tracks, e, who)
            per_eps[e][who]["frames_over_al"] = {"value": r.value if r.n else None, "ci": r.ci(), "n": r.n}
    chain = {
        "capacity": {"eps": [0.01, 0.05], "quantile": 0.99, "margin": 0.25, "edges": [0.0, 100.0]},
        "per_eps": per_eps,
        "first_over_al_eps": first_over(per_eps),
        "checks_only": checks_only_rates(tracks),
        "tracks": tracks,
        "certificate": None,
        "seconds": 1.0,
    }
    return {"eps": [0.01, 0.05], "stride": 10, "trajectories": 2, "frames": 80, "chains": {"robust": chain}}


def test_the_page_states_the_bound_its_replay_its_rate_with_an_interval_and_its_assumptions() -> None:
    m = _metrics()
    page = bound_page(m)
    b = m["chains"]["robust"]["per_eps"]["0.05"]["bound"]
    assert f"{b['max_error_al']:.2f}" in page and f"{b['max_achieved_m']:.2f}" in page
    rate = b["frames_over_al"]
    assert rate["n"] > 0 and f"{100 * rate['ci'][1]:.1f}]" in page  # the share comes with its interval
    for words in (
        "empirical overbound, not a certificate",
        "certificate is vacuous",
        "detector is modelled as blind",
        "trusted-start frames",
        "Not computed",
        "What availability any sound PL can have with these checks",
        f"{100 * m['chains']['robust']['checks_only']['ceiling']['value']:.1f} [",
    ):
        assert words in page
    assert np.isfinite(b["max_error_m"])
    assert " s on this machine" not in page and "Cost:" not in page  # no timings in a report (bound.json has them)


def test_the_page_sets_the_image_attacks_worst_beside_the_bound(tmp_path, monkeypatch) -> None:
    """The largest error / AL the robustness campaign's image-space attackers reached, per chain and eps, from
    reports/metrics/robustness.json; "-" for an eps it did not fly or without the file."""
    import json

    from stages import bound

    monkeypatch.chdir(tmp_path)
    assert bound._empirical("robust", [0.01, 0.05]) == {"0.01": None, "0.05": None}
    (tmp_path / "reports" / "metrics").mkdir(parents=True)
    flown = {"integrity": {"chains": {"robust": {"summary": {"per_eps": {"0.01": {"max_error_al": 0.0213}}}}}}}
    (tmp_path / "reports" / "metrics" / "robustness.json").write_text(json.dumps(flown))
    empirical = bound._empirical("robust", [0.01, 0.05])
    assert empirical == {"0.01": 0.0213, "0.05": None}
    m = _metrics()
    m["chains"]["robust"]["empirical"] = empirical
    lines = [line for line in bound_page(m).splitlines() if line.startswith("| robust")]
    header = next(line for line in bound_page(m).splitlines() if line.startswith("| chain") and "image" in line)
    column = [c.strip() for c in header.split("|")].index("image attacks' worst error / AL")
    assert [line.split("|")[column].strip() for line in lines[:2]] == ["0.02", "-"]


def test_the_page_measures_each_step_from_the_bound_to_the_worst_sequence_in_images() -> None:
    """The realised worst sequence (tests/test_bound_images.py's toy network) on the page: its table, and per chain
    the steps bound -> requested -> detector blind -> real chain with their figures."""
    from tests.test_bound_images import _realize

    m = _metrics()
    r = _realize(reach=0.05, along=0.05)
    m["chains"]["robust"]["realized"] = {"0.05": r}
    page = bound_page(m)
    assert "## The worst sequence in images" in page and "Not run" not in page
    line = next(x for x in page.splitlines() if x.startswith("- robust (shipped), eps 0.05: the worst sequence"))
    for v in (r["bound_m"], r["requested"]["error_m"], r["blind"]["error_m"], r["live"]["error_m"]):
        assert f"{v:.2f} m" in line
    assert f"{r['residual_p90_m']:.2f} m" in line


def test_a_solver_failure_stops_the_stage_with_one_line(monkeypatch) -> None:
    """The conic solver's failure (clarabel NumericalError on the default run's standard chain) is one line naming
    the chain and trajectory, not a traceback."""
    import types

    import pipeline.evaluation.integrity_bound as integrity_bound
    import stages.bound as stage
    from stages.config import params as params_mod
    from stages.config.schema import build

    def failing(*args, **kwargs):
        raise RuntimeError("worst-case program of frame 190: NumericalError")

    monkeypatch.setattr(stage, "_capacities", lambda model, eps: ([], {}))
    monkeypatch.setattr(stage, "load_chain", lambda params, model: types.SimpleNamespace(onboard=None, defended=None))
    monkeypatch.setattr(integrity_bound, "bound_track", failing)
    track = types.SimpleNamespace(name="t0")
    with pytest.raises(StageError, match=r"^rpod bound \(standard\) on eval_render t0: .*NumericalError; no bound"):
        stage._chain(build(params_mod.compose("smoke")), "standard", [track], [0.01])


def test_the_first_eps_over_al_names_the_capacity_it_was_measured_on() -> None:
    """An eps between measured capacities borrows the next larger one's: the line says so."""
    from stages.pages.bound import _first_lines

    chain = {"first_over_al_eps": 0.02, "capacity": {"eps": [0.01, 0.05]}}
    line = _first_lines({"robust": chain})[0]
    assert line.endswith("first exceeds AL at eps 0.02 (on the capacity measured at eps 0.05: none at 0.02)")
    chain["capacity"]["eps"] = [0.01, 0.02, 0.05]
    assert _first_lines({"robust": chain})[0].endswith("first exceeds AL at eps 0.02")
    assert _first_lines({"robust": {**chain, "first_over_al_eps": None}})[0].endswith("stays within AL at every eps")

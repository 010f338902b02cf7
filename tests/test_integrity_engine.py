"""`rpod integrity` on the engine (stages/engine/campaigns.py `ShardWorker`, stages/integrity.py `shard_engine`): the
trajectories whose shard is missing fan out as one job each, in any order, on workers that load the chain themselves,
and the shards they write are those the driver writes flying them itself, byte for byte (each trajectory's attacks
draw on its own seed streams; same torch threads per flight; on Ray the values to float rounding: see the last
test); a run that finds some shards flies only the others; the CPU fans out over Ray workers holding the chain on the
CPU, a GPU flies in-process. Tiny random chains on 3 toy trajectories of the full grid (smoke profile); the last test
starts a local Ray with 2 workers (~20 s)."""

from __future__ import annotations

import dataclasses
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from test_chains import _defense, _run
from test_predict import H, W

from pipeline.evaluation.integrity_runs import Track
from pipeline.evaluation.robustness import burst_schedule
from pipeline.io.atomic import write_json
from stages.artifacts.models import load_chain
from stages.artifacts.paths import CHAINS, SHIPPED, Model
from stages.config import params as params_mod
from stages.config.schema import build
from stages.engine import campaigns
from stages.engine import pool as engine

pytestmark = pytest.mark.usefixtures("one_thread")  # the driver's flights on 1 torch thread, as each Ray worker's
SEED = 5
REPO = Path(__file__).resolve().parent.parent
IN_PROCESS = engine.EngineSettings(1, None, 60.0, 0)


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """(full-grid smoke params for the tiny models, root holding models/ with both chains calibrated, 3 tracks of
    12 frames approaching 40 -> 20 m, their bursts)."""
    root = tmp_path_factory.mktemp("run")
    overrides = [f"render.width={W}", f"render.height={H}", "train.width=0.125", "threads=2", "engine.workers=1"]
    p = build(params_mod.compose("smoke", overrides))
    models = _run(root)
    for m in Model:
        write_json(root / CHAINS[m].defense, _defense(models, m, load_chain(p, m, root, defended=False).threshold, p))
    rng, n = np.random.default_rng(0), 12
    labels = np.column_stack(
        [np.linspace(1, -1, n), np.zeros(n), np.linspace(40, 20, n), np.tile([1, 0, 0, 0, 1, 0], (n, 1))]
    )
    tracks = [Track(f"t{g}", rng.integers(0, 255, (n, H, W, 3), dtype=np.uint8), labels) for g in range(3)]
    p = campaigns.full_grid(p)
    bursts = [burst_schedule(n, p.integrity.burst_length, p.robustness.burst_every) for _ in tracks]
    return p, root, tracks, bursts


def fly(grid, key: str, folder, fan_out=None) -> tuple[dict, dict[str, bytes]]:
    """Chain `key` (robust or control) of the full grid on the tracks, shards in `folder`, the missing ones flown on
    `fan_out` (None: by the driver itself) -> (the chain's record, {shard file: its bytes})."""
    p, root, tracks, bursts = grid
    safety = load_chain(p, SHIPPED, root)
    defended = None if key == campaigns.CONTROL else safety.defended
    target = campaigns.attack_target(safety.onboard, defended)
    record, _ = campaigns._fly_chain(p, SEED, key, safety, defended, target, tracks, bursts, folder, fan_out)
    return record, {f.name: f.read_bytes() for f in sorted((folder / key).glob("*.pkl"))}


def results(record: dict) -> tuple:
    """What the page and metrics take from a chain's assembled campaign."""
    return record["rows"], record["summary"], record["worst_hmi"], record["clean"], record["false_alarm_rate"]


@pytest.fixture(scope="module")
def by_driver(grid, tmp_path_factory) -> dict[str, tuple[dict, dict[str, bytes]]]:
    """Each chain flown by the driver itself, one trajectory after another (the path without an engine)."""
    return {key: fly(grid, key, tmp_path_factory.mktemp("driver")) for key in (SHIPPED.value, campaigns.CONTROL)}


@pytest.mark.parametrize("key", [SHIPPED.value, campaigns.CONTROL])
def test_missing_shards_fly_one_job_each_in_any_order_and_match_the_drivers(grid, by_driver, key, tmp_path) -> None:
    calls: list[list[int]] = []

    def backwards(worker_cls, setup, jobs, progress):
        """The in-process engine, the jobs flown last first."""
        calls.append([job.index for job in jobs])
        last = len(jobs) - 1
        return engine.run(worker_cls, setup, jobs[::-1], IN_PROCESS, progress=lambda i, r: progress(last - i, r))

    record, shards = fly(grid, key, tmp_path, backwards)
    want_record, want_shards = by_driver[key]
    assert calls == [[0, 1, 2]] and list(shards) == ["t0.pkl", "t1.pkl", "t2.pkl"]
    assert shards == want_shards  # byte for byte: key and share
    assert same(results(record), results(want_record)) and record["rows"]

    for name in ("t0.pkl", "t2.pkl"):  # a run killed before two trajectories were written
        (tmp_path / key / name).unlink()
    record, shards = fly(grid, key, tmp_path, backwards)
    assert calls[1:] == [[0, 2]] and shards == want_shards and same(results(record), results(want_record))
    fly(grid, key, tmp_path, backwards)
    assert len(calls) == 2  # every shard there: the engine is not called


def test_each_trajectory_flies_on_its_own_seed_streams(grid, by_driver) -> None:
    """A worker built cold flies t1 alone as the driver did (its index, 1), and otherwise on index 0: the test
    above would see a worker that numbered the jobs by their order."""
    p, root, tracks, bursts = grid
    safety = load_chain(p, SHIPPED, root)
    worker = campaigns.ShardWorker(campaigns.shard_setup(p, safety, safety.defended, SEED))
    stored = pickle.loads(by_driver[SHIPPED.value][1]["t1.pkl"])["share"]

    def flown(index: int) -> bytes:
        return worker.run(campaigns.ShardJob(index, tracks[1], bursts[1]))

    assert flown(1) == pickle.dumps(stored, protocol=pickle.HIGHEST_PROTOCOL) != flown(0)


def test_the_cpu_fans_out_over_ray_workers_on_the_cpu_and_a_gpu_flies_in_process(grid, monkeypatch) -> None:
    from stages import integrity

    p, root, tracks, bursts = grid
    p = dataclasses.replace(p, device="auto", engine=dataclasses.replace(p.engine, workers=2))
    seen = []
    monkeypatch.setattr(integrity.engine, "run", lambda *a, **k: seen.append((a[1], a[3], k["num_cpus"])))
    setup = campaigns.ShardSetup(p, str(root), SHIPPED.value, None, SEED)
    for device in (torch.device("cpu"), torch.device("cuda")):
        es, fan_out = integrity.shard_engine(p, device)
        fan_out(campaigns.ShardWorker, setup, [], lambda i, r: None)
    (cpu, es_cpu, cpus), (gpu, es_gpu, _) = seen
    assert es_cpu.workers == 2 and not es_cpu.in_process and cpus == 1  # threads=2 shared out over 2 workers
    assert cpu.params.device == "cpu" and cpu.torch_threads == 1 and cpu.params.integrity == p.integrity
    assert es_gpu.in_process and gpu == setup  # the stage's device (auto: the GPU), its torch threads
    # a job is a whole trajectory: the no-progress guard waits engine.timeout_s per (attacker, eps) run of it
    i = p.integrity
    starts = 2 * sum(a.startswith("drift") for a in i.attackers)
    runs = (sum(a.startswith("capture") for a in i.attackers) * len(i.capture_initial) + starts + 1) * len(i.eps)
    assert es_cpu.timeout_s == es_gpu.timeout_s == p.engine.timeout_s * runs


@pytest.mark.slow
def test_two_ray_workers_write_the_shards_the_driver_writes(grid, by_driver, tmp_path, monkeypatch) -> None:
    from stages import integrity

    pytest.importorskip("ray")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    p = grid[0]
    es, fan_out = integrity.shard_engine(
        dataclasses.replace(p, engine=dataclasses.replace(p.engine, workers=2)), torch.device("cpu")
    )
    assert es.workers == 2 and not es.in_process
    with engine.session(es):
        record, shards = fly(grid, SHIPPED.value, tmp_path, fan_out)
    want_record, want_shards = by_driver[SHIPPED.value]
    # The same keys, the values to float rounding: byte for byte when this file runs alone, but in the full suite a
    # shard differed in its last bits (the driver's process carries torch state that earlier tests set and fresh Ray
    # workers do not; which state was not traced).
    assert list(shards) == list(want_shards)
    assert [pickle.loads(b)["key"] for b in shards.values()] == [pickle.loads(b)["key"] for b in want_shards.values()]
    assert close(results(record), results(want_record)) and record["rows"]


def same(a, b) -> bool:
    """Nested records exactly equal, NaN equal to NaN (the full grid's drift from the end of the trusted start
    attacks no frame of a 12-frame toy track: its rows hold NaN)."""
    return json.dumps(a, sort_keys=True, default=repr) == json.dumps(b, sort_keys=True, default=repr)


def close(a, b) -> bool:
    """Nested records equal, their floats to a relative 1e-5 (float rounding of other kernels)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(close(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(close(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.allclose(a, b, rtol=1e-5, atol=1e-9, equal_nan=True))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-5 * max(abs(a), abs(b)) + 1e-9
    return a == b


def test_the_shards_script_prints_each_share_as_the_campaign_judges_it(by_driver, tmp_path, capsys) -> None:
    """scripts/integrity_shards.py on the shards of a flown chain: one row per (attacker, eps) run and the no-attack
    row; each attacker's "nested" column is the campaign summary's per-trajectory error / AL (nested in eps)."""
    import importlib.util

    from stages.config.build import alert_limit_settings

    spec = importlib.util.spec_from_file_location("integrity_shards", REPO / "scripts" / "integrity_shards.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    record, shards = by_driver[SHIPPED.value]
    for name, data in shards.items():
        (tmp_path / SHIPPED.value).mkdir(exist_ok=True)
        (tmp_path / SHIPPED.value / name).write_bytes(data)
    p = build(params_mod.compose("smoke"))
    attackers = record["summary"]["attackers"]
    for g, name in enumerate(sorted(shards)):
        rows = script.share_rows(pickle.loads(shards[name])["share"], alert_limit_settings(p, "single_frame"))
        assert rows[-1]["attacker"] == "no attack" and len(rows) == 1 + sum(len(v) for v in attackers.values())
        for row in rows[:-1]:
            want = attackers[row["attacker"]][row["eps"]][g]["max_error_al"]
            assert row["nested"] == ("-" if want is None or want != want else f"{want:.2f}"), (name, row)
    assert script.main([str(tmp_path)]) == 0 and capsys.readouterr().out.count("| no attack") == len(shards)
    assert script.main([str(tmp_path / "none")]) == 1
    (tmp_path / SHIPPED.value / "t9.pkl").write_bytes(b"not a shard")
    assert script.main([str(tmp_path)]) == 0 and "t9.pkl: unreadable" in capsys.readouterr().out

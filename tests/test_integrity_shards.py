"""`rpod integrity`'s resumable shards (stages/artifacts/shards.py, stages/engine/campaigns.py `_fly_shards`): a
share is written once flown and read back instead of flown while its key holds; a changed model file, a corrupt or
half-written shard, or another trajectory's data is flown again."""

from __future__ import annotations

import types

import numpy as np
import pytest

from pipeline.evaluation.integrity_runs import Track
from stages.artifacts.shards import read_shard, shard_path, write_shard


def test_a_shard_reads_back_under_its_key_only(tmp_path) -> None:
    path = shard_path(tmp_path, "robust", "t3")
    assert path == tmp_path / "robust" / "t3.pkl" and read_shard(path, "k") is None
    write_shard(path, "k", {"x": np.arange(3)})
    assert read_shard(path, "k")["x"].tolist() == [0, 1, 2]
    assert read_shard(path, "other") is None
    path.write_bytes(path.read_bytes()[:10])  # cut short
    assert read_shard(path, "k") is None
    assert not list(path.parent.glob(".*.tmp"))  # no temporary file left behind


def _tracks(n: int = 3) -> list[Track]:
    rng = np.random.default_rng(0)
    labels = np.column_stack([np.zeros((5, 2)), np.linspace(30, 20, 5), np.tile([1, 0, 0, 0, 1, 0], (5, 1))])
    return [Track(f"t{g}", rng.integers(0, 255, (5, 4, 6, 3), dtype=np.uint8), labels) for g in range(n)]


@pytest.fixture()
def flying(tmp_path):
    """`_fly_shards` over a counting flight, with the key of `_shard_base` (smoke params, one model file)."""
    import stages.engine.campaigns as engine
    from stages.config import params as params_mod
    from stages.config.schema import build

    flown: list[tuple[str, int]] = []
    model = tmp_path / "model.pt"
    model.write_bytes(b"weights")
    safety = types.SimpleNamespace(files=(model, None, None))
    p = build(params_mod.compose("smoke"))
    bar = types.SimpleNamespace(n=0)
    bar.update = lambda k: setattr(bar, "n", bar.n + k)

    def fly(track: Track, c) -> dict:
        flown.append((track.name, c.index))
        return {"track": track.name, "index": c.index}

    def run(tracks: list[Track]) -> list:
        base = engine._shard_base(p, 7, "robust", safety)
        campaign_of = lambda g: types.SimpleNamespace(eps=[0.01], plans=[1], burst=None, index=g)  # noqa: E731
        return engine._fly_shards(base, tracks, campaign_of, fly, tmp_path / "s", bar)

    return run, flown, model, bar


def test_a_rerun_reads_the_finished_shares_and_flies_only_what_is_missing(flying, tmp_path) -> None:
    run, flown, model, bar = flying
    tracks = _tracks()
    first = run(tracks[:2])  # a run killed after two trajectories
    assert flown == [("t0", 0), ("t1", 1)] and [s["index"] for s in first] == [0, 1]
    flown.clear()
    again = run(tracks)
    assert flown == [("t2", 2)] and again == first + [{"track": "t2", "index": 2}]
    assert bar.n == 2 * 5  # the two shares read advance the bar by their steps (1 eps x 5 frames each)
    flown.clear()
    model.write_bytes(b"retrained")  # another model: every share is stale
    run(tracks)
    assert flown == [("t0", 0), ("t1", 1), ("t2", 2)]
    flown.clear()
    shard_path(tmp_path / "s", "robust", "t1").write_bytes(b"half")  # a damaged shard is flown again
    changed = _tracks()
    changed[2].images[0, 0, 0, 0] ^= 1  # so is a trajectory whose frames changed
    run(changed)
    assert flown == [("t1", 1), ("t2", 2)]


def test_a_shards_folder_that_cannot_be_written_stops_rpod_integrity_before_it_flies(tmp_path, monkeypatch) -> None:
    import errno
    import os
    import tempfile

    from pipeline.io.errors import DataError
    from stages import integrity
    from stages.config import params as params_mod
    from stages.config.schema import build

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(integrity, "load_chain", lambda *a, **k: pytest.fail("the chain was loaded"))
    real = tempfile.TemporaryFile

    def read_only(*args, dir=None, **kwargs):  # the shards folder on a read-only mount (root ignores modes)
        if str(dir).endswith("integrity_shards"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    with pytest.raises(DataError, match=r"^datasets/integrity_shards is not writable \(Read-only file system\)"):
        integrity.main(build(params_mod.compose("smoke")))

"""The Ray engine: a two-node local cluster renders the same store as one process, a killed worker's
chunk is retried, and bad engine settings stop with one line (no hang)."""

import socket
import time

import numpy as np
import pytest
import tiny
from faults import exits_once

from pipeline.io.store import open_zarr
from stages.config import params as params_mod
from stages.config.params import load
from stages.config.schema import build
from stages.config.sections import ParamsError
from stages.engine import pool as engine
from stages.engine.chunks import FrameRange, RenderSetup, RenderWorker
from stages.errors import StageError

TINY = tiny.RENDER


def _render(workdir, overrides):
    """`rpod render` in workdir with the tiny params plus overrides -> the images (N, H, W, 3) uint8."""
    from stages import render

    params_mod.write_params(params_mod.compose("smoke", TINY + overrides))
    render.main(load())
    return open_zarr(workdir / "datasets/render/images.zarr")["images"][:]


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def two_nodes(tmp_path_factory, monkeypatch):
    """A local Ray cluster of two nodes with one CPU each, and a marker path for `faults.exits_once`."""
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    marker = tmp_path_factory.mktemp("fault") / "exited"
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        yield cluster, marker
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()


@pytest.mark.slow
def test_two_node_cluster_matches_one_process_and_retries_a_killed_worker(workdir, two_nodes, monkeypatch):
    from stages.engine import chunks

    cluster, marker = two_nodes
    one = _render(workdir, ["engine.workers=1"])
    monkeypatch.setattr(chunks, "RenderWorker", exits_once(RenderWorker, marker, nth=2))  # dies on its 2nd chunk, once
    two = _render(workdir, ["engine.workers=2", f"engine.address={cluster.address}"])
    assert marker.exists()  # one worker died mid-chunk: its chunk was retried
    assert two.shape == one.shape == (26, 18, 32, 3) and one.max() > 0
    assert np.array_equal(one, two)  # image for image, bit for bit
    with pytest.raises(StageError, match="covers no pixels") as err:  # a worker's own error, as one line
        _render(workdir, ["engine.workers=2", f"engine.address={cluster.address}", "render.mesh_scale=0.0001"])
    assert "\n" not in str(err.value) and "Traceback" not in str(err.value)
    with pytest.raises(StageError, match="no chunk finished within engine.timeout_s"):
        es = engine.EngineSettings(workers=1, address=cluster.address, timeout_s=2.0, retries=0)
        setup = RenderSetup(K=None, scene=None, R=np.zeros((4, 3, 3)), t=np.zeros((4, 3)), url="", empty_hint=None)
        engine.run(RenderWorker, setup, [FrameRange(0, 4)], es, num_cpus=8)  # 8 CPUs never free up: no hang


def test_setups_and_jobs_are_frozen_records():
    es = engine.EngineSettings(workers=1, address=None, timeout_s=1.0, retries=0)
    with pytest.raises(TypeError, match="frozen dataclasses, got tuple"):
        engine.run(RenderWorker, (None,) * 6, [FrameRange(0, 4)], es)  # no positional tuples
    with pytest.raises(TypeError, match="frozen dataclasses, got tuple"):
        engine.run(RenderWorker, RenderSetup(None, None, None, None, "", None), [(0, 4)], es)


def test_unreachable_address_stops_at_once(workdir):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(StageError, match="unreachable.*ray start --head"):
        _render(workdir, ["engine.workers=2", f"engine.address=127.0.0.1:{port}"])
    assert time.perf_counter() - t0 < engine.CONNECT_TIMEOUT_S + 5
    assert not (workdir / "datasets/render").exists()


def test_bad_workers_and_store(workdir):
    with pytest.raises(ParamsError, match="engine: workers must be at least 1"):
        build(params_mod.compose("smoke", ["engine.workers=0"]))
    (workdir / "a_file").write_text("not a folder")
    for store, what in [(workdir / "a_file" / "images.zarr", "a path below a file"), ("nosuchproto://x/y.zarr", "")]:
        with pytest.raises(StageError, match="cannot be written.*engine.store"):
            _render(workdir, ["engine.workers=1", f"engine.store={store}"])
        assert not (workdir / "datasets/render").exists(), what


def test_store_elsewhere_is_named_in_meta_and_read_back(workdir):
    import json

    from stages.artifacts.paths import RENDER
    from stages.artifacts.readers import read_render_store

    store = workdir / "shared" / "render.zarr"
    params_mod.write_params(params_mod.compose("smoke", TINY + [f"engine.store={store}"]))
    from stages import render

    render.main(load())
    meta = json.loads((workdir / RENDER / "meta.json").read_text())
    assert meta["store"] == f"{store}/render-{meta['fingerprint']}.zarr"  # one store per render there
    assert not (workdir / RENDER / "images.zarr").exists()
    images, poses, _ = read_render_store(RENDER)
    assert images.shape[0] == len(poses) == 26 and np.asarray(images[:]).max() > 0


def test_a_worker_that_cannot_see_the_store_sends_its_pixels(workdir, monkeypatch):
    from stages.engine import chunks

    direct = _render(workdir, ["engine.workers=1"])
    asked = []
    monkeypatch.setattr(chunks, "visible", lambda fs, root: asked.append(root) and False)  # "another machine"
    sent = _render(workdir, ["engine.workers=1"])
    assert asked and np.array_equal(direct, sent)  # the driver wrote every chunk: same store, same manifest


HOLDER = """
import os, sys
from stages.engine import pool as engine
got = engine.pin_cores(int(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "/a/repository")
print(got, sorted(os.sched_getaffinity(0)), flush=True)
sys.stdin.read()   # hold the cores until the test closes stdin
"""


def test_pin_cores_gives_each_worker_cores_of_its_own(tmp_path):
    """Processes (as Ray workers do) bind to distinct free cores, none when too few are free, and a
    core is free again once its holder has exited. Run in subprocesses: pinning this one would slow the suite."""
    import ast
    import os
    import subprocess
    import sys

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this OS")
    cores = sorted(os.sched_getaffinity(0))
    env = {**os.environ, "TMPDIR": str(tmp_path)}  # lock files of this test only, not of live workers
    procs = []

    def hold(n: int, scope: str = "/a/repository") -> tuple[list[int], list[int]]:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-c", HOLDER, str(n), scope],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                env=env,
            )
        )
        got, bound = procs[-1].stdout.readline().split("] [")
        return ast.literal_eval(got + "]"), ast.literal_eval("[" + bound)

    try:
        first = hold(1)
        assert first == ([cores[0]], [cores[0]])
        assert hold(len(cores)) == ([], cores)  # one core is taken: none bound
        if len(cores) > 1:
            assert hold(1) == ([cores[1]], [cores[1]])
        assert hold(1, "/another/repository") == ([cores[0]], [cores[0]])  # a second pipeline pins its own
        procs[0].communicate("")
        assert hold(1) == ([cores[0]], [cores[0]])  # freed by the exit of its holder
        assert engine.core_locks("/a/repository") != engine.core_locks("/another/repository")
    finally:
        for p in procs:
            p.kill()
            p.wait()

"""Ray faults: a cluster address that answers but is not Ray stops within engine.timeout_s with one line, and
a worker killed mid-run (after its constructor, with a setup large enough for Ray's object store) is
restarted and its job retried, the results equal to those of one process."""

import socket
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest
from faults import exits_once

from stages.config import params as params_mod
from stages.config.schema import build
from stages.engine import pool as engine
from stages.engine.pool import engine_settings
from stages.errors import StageError


@dataclass(frozen=True)
class Setup:
    table: np.ndarray  # 1 MB: above Ray's 100 kB inline limit, so it goes to the object store


@dataclass(frozen=True)
class Job:
    index: int


class TableWorker:
    """A stand-in for a render worker: a heavy setup, a result that depends on all of it and on the job."""

    def __init__(self, setup: Setup) -> None:
        self.table = setup.table

    def run(self, job: Job) -> np.ndarray:
        time.sleep(0.3)  # a job takes a while: Ray has freed what it stored for the constructor
        return np.roll(self.table[:64], job.index) * (job.index + 1)

    def close(self) -> None:
        pass


@pytest.fixture
def not_ray():
    """A plain TCP server on 127.0.0.2 (loopback, which Ray does not rewrite to this machine's address as it
    does 127.0.0.1) that answers every connection with an HTTP line, not Ray -> (address, connections
    served); it stops when the test ends and serves at most 64 connections."""
    srv = socket.create_server(("127.0.0.2", 0))
    srv.settimeout(0.2)
    stop, served = threading.Event(), []

    def serve() -> None:
        while not stop.is_set() and len(served) < 64:
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            with conn:
                conn.sendall(b"HTTP/1.0 200 OK\r\n\r\nnot ray\n")
            served.append(1)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield f"127.0.0.2:{srv.getsockname()[1]}", served
    stop.set()
    thread.join(5)
    srv.close()


def test_a_ray_address_that_is_not_ray_stops_within_timeout(not_ray, monkeypatch):
    pytest.importorskip("ray")
    address, served = not_ray
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.setenv("RAY_ADDRESS", address)
    es = engine_settings(build(params_mod.compose("smoke", ["engine.workers=2", "engine.timeout_s=3"])))
    assert es.address == address
    t0 = time.perf_counter()
    with pytest.raises(StageError, match="is not a Ray head.*engine.timeout_s = 3 s") as err:
        engine.run(TableWorker, Setup(np.zeros(4)), [Job(0)], es)
    assert time.perf_counter() - t0 < es.timeout_s + 5
    assert address in str(err.value) and "\n" not in str(err.value)
    assert len(served) >= 2  # the TCP check and the Ray client both reached it


def test_a_worker_killed_mid_run_is_restarted_and_its_job_retried(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.chdir(tmp_path)  # its own core locks
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the stand-ins live in this test file
    setup = Setup(np.random.default_rng(0).random(1 << 17))
    jobs = [Job(i) for i in range(6)]
    one = engine.run(TableWorker, setup, jobs, engine.EngineSettings(1, None, 60.0, 0))
    marker = tmp_path / "exited"
    two = engine.run(exits_once(TableWorker, marker, nth=2), setup, jobs, engine.EngineSettings(2, None, 60.0, 2))
    assert marker.exists()  # a worker died on its second job: that job ran again
    assert len(two) == len(one) and all(np.array_equal(a, b) for a, b in zip(one, two))

"""Scale-out engine: a stage's chunks run on Ray actors, each holding one heavy state (a Blender scene).

`run(worker_cls, setup, jobs, settings)` builds `worker_cls(setup)` once per worker and returns
`worker.run(job)` for every job, in job order; the setup and each job are frozen dataclasses (named
fields, e.g. `chunks.RenderSetup` and `chunks.FrameRange`), and the caller picks the worker class. With
one worker and no cluster address it runs in this process without starting Ray; otherwise on a local Ray
started for the call (`engine.workers` actors) or on the cluster at `engine.address` / $RAY_ADDRESS. A
worker that dies is restarted and its chunk retried (`engine.retries`); a cluster whose Ray head does not
answer, or no progress, for `engine.timeout_s` seconds stops the stage with one line. Each Ray worker binds
itself to as many cores of its machine as the CPUs it asked for (`pin_cores`), among the cores the workers
of the same pipeline (the driver's working folder: the repository `dvc repro` runs in) hold, so another
pipeline on the machine pins its own workers too.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import socket
import sys
import tempfile
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Protocol

from pipeline import interrupt
from pipeline.io.errors import DataError
from stages.config.schema import Params
from stages.errors import StageError

CONNECT_TIMEOUT_S = 10.0  # seconds to open a TCP connection to a cluster's head before calling it unreachable


def core_locks(scope: str) -> str:
    """The folder of the per-core lock files of one pipeline: `rpod-cores-<16 hex digits of scope>` in this
    machine's temporary folder, scope = the driver's working folder (absolute path), on every node of a cluster."""
    return os.path.join(tempfile.gettempdir(), "rpod-cores-" + hashlib.sha256(scope.encode()).hexdigest()[:16])


class Worker(Protocol):
    """What the engine runs: built once per worker as `worker_cls(setup)` (a frozen dataclass), then
    `run(job)` per job (a frozen dataclass) and `close()` when the worker pool is done."""

    def run(self, job: Any) -> Any: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class EngineSettings:
    """How a stage's jobs fan out (the params `engine` section, resolved by `engine_settings`)."""

    workers: int | None  # actors (1 = in-process); None = every core (of the cluster, with an address)
    address: str | None  # Ray cluster address, None = a local Ray (or in-process)
    timeout_s: float  # seconds without a finished chunk before giving up
    retries: int  # restarts of a dead worker (and retries of its chunk)

    @property
    def in_process(self) -> bool:
        return self.workers == 1 and not self.address

    def threads(self, render_threads: int) -> int:
        """Blender threads per worker: all of render.threads in-process, else shared out (at least 1)."""
        if self.in_process:
            return render_threads
        return max(1, render_threads // (self.workers or (1 if self.address else os.cpu_count() or 1)))


def engine_settings(params: Params) -> EngineSettings:
    """The engine section of params, with address None -> $RAY_ADDRESS; workers None is every core of
    this machine, or of the cluster when there is an address."""
    e = params.engine
    address = e.address or os.environ.get("RAY_ADDRESS") or None
    workers = e.workers if e.workers or address else os.cpu_count() or 1
    return EngineSettings(workers, address, float(e.timeout_s), e.retries)


def run(
    worker_cls: Callable[[Any], Worker],
    setup: Any,
    jobs: list[Any],
    es: EngineSettings,
    num_cpus: float = 1,
    progress: Callable[[int, Any], None] | None = None,
) -> list[Any]:
    """`worker.run(job)` for every job (in order) on workers built as `worker_cls(setup)`, each using
    `num_cpus` CPUs; `progress(i, result)` is called in the driver as each job finishes."""
    _check_records(setup, jobs)
    if es.in_process:
        worker = worker_cls(setup)
        try:
            out = []
            for i, job in enumerate(jobs):
                out.append(worker.run(job))
                if progress:
                    progress(i, out[-1])
            return out
        finally:
            worker.close()
    with session(es):
        return _run_on_ray(worker_cls, setup, jobs, es, num_cpus, progress)


def _check_records(setup: Any, jobs: list[Any]) -> None:
    """Refuse a setup or job that is not a frozen dataclass (named fields, not a positional tuple)."""
    for record in (setup, *jobs):
        params = getattr(record, "__dataclass_params__", None)
        if isinstance(record, type) or params is None or not params.frozen:
            raise TypeError(f"engine setups and jobs are frozen dataclasses, got {type(record).__name__}")


@contextlib.contextmanager
def session(es: EngineSettings) -> Iterator[None]:
    """A Ray session (the cluster at es.address, or a local Ray with es.workers CPUs) kept up for every
    `run` inside it, so a stage with several sets starts Ray once; nothing when in-process or already up."""
    import logging

    if es.in_process:
        yield
        return
    import ray

    if ray.is_initialized():
        yield
        return
    if es.address:
        _check_reachable(es.address, es.timeout_s)
    try:
        with _signal_handlers_kept():
            ray.init(
                address=es.address or "local",
                num_cpus=None if es.address else es.workers,
                include_dashboard=False,
                logging_level=logging.WARNING,
                log_to_driver=True,
            )
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"the Ray cluster at {es.address}" if es.address else "a local Ray"
        raise StageError(
            f"could not start or reach {where} ({type(e).__name__}: {str(e).splitlines()[0]}); "
            f"check engine.address / $RAY_ADDRESS, or set engine.workers: 1 to run in-process"
        ) from None
    except BaseException:  # stopped while Ray started (pipeline/interrupt.py): stop what it started
        ray.shutdown()
        raise
    try:
        yield
    finally:
        ray.shutdown()


def _check_reachable(address: str, timeout_s: float) -> None:
    """Refuse a host:port (or ray://host:port) address whose head does not accept a TCP connection, or (host:port)
    whose Ray head does not answer within timeout_s seconds (ray.init would wait for ever on a port that is not Ray)."""
    if address in ("auto", "local"):
        return
    host, _, port = address.split("://")[-1].rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=min(CONNECT_TIMEOUT_S, timeout_s)).close()
    except (OSError, ValueError) as e:
        raise StageError(
            f"Ray cluster address {address!r} (engine.address or $RAY_ADDRESS) is unreachable "
            f"({type(e).__name__}: {e}); start its head with `ray start --head`, or unset it "
            f"to run on this machine"
        ) from None
    if "://" not in address:  # a Ray Client address (ray://) bounds its own connection attempts
        _check_ray_head(address, timeout_s)


# The Ray head probe, run in a child process: the GCS client ray.init uses retries for ever and logs every retry
# from native code to file descriptor 2, so the child's output is discarded and it ends itself after timeout_s
# (argv[2]) seconds of waiting (os._exit: a client stuck in native code would hold up a normal exit).
_PROBE = """
import os, sys, threading
from ray._private.services import canonicalize_bootstrap_address
from ray._raylet import GcsClient
got = []
def probe():
    try:
        GcsClient(address=canonicalize_bootstrap_address(sys.argv[1]))
        got.append("")
    except Exception as e:
        got.append(f"{type(e).__name__}: {(str(e).splitlines() or [''])[0]}")
thread = threading.Thread(target=probe, daemon=True)
thread.start()
thread.join(float(sys.argv[2]))
print(got[0] if got else "no answer", flush=True)
os._exit(0 if got == [""] else 1)
"""
PROBE_IMPORT_S = 120  # seconds the probe may take to import Ray, beyond engine.timeout_s of waiting for the head


def _check_ray_head(address: str, timeout_s: float) -> None:
    """Refuse a host:port that does not answer as a Ray head (its GCS) within timeout_s seconds (`_PROBE`)."""
    import subprocess

    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE, address, str(timeout_s)],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            timeout=timeout_s + PROBE_IMPORT_S,
        )
        why = done.stdout.strip() or f"probe exit status {done.returncode}" if done.returncode else None
    except subprocess.TimeoutExpired:
        why = "no answer"
    if why is not None:
        raise StageError(
            f"Ray cluster address {address!r} (engine.address or $RAY_ADDRESS) accepts connections but "
            f"is not a Ray head ({why} within engine.timeout_s = {timeout_s:g} s); give the port "
            f"`ray start --head` printed, or unset it to run on this machine"
        )


@contextlib.contextmanager
def _signal_handlers_kept() -> Iterator[None]:
    """Keep this process's SIGINT and SIGTERM handlers through the block (ray.init): Ray sets SIGTERM's to
    `sys.exit` (the driver exited with status 15 and no line, also when the signal came while Ray was starting),
    where the command line's stop path (pipeline/interrupt.py) ends the stage with one line and exit 130 and
    `ray.shutdown` stops the workers. Ray's setter (ray._private.utils.set_sigterm_handler, ray 2.x) does nothing
    within the block, and the handlers are put back after it in case Ray set them otherwise."""
    import signal
    import threading

    import ray._private.utils as ray_utils

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    kept = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    setter = ray_utils.set_sigterm_handler
    ray_utils.set_sigterm_handler = lambda handler: None
    try:
        yield
    finally:
        ray_utils.set_sigterm_handler = setter
        for sig, handler in kept.items():
            if handler is not None:
                signal.signal(sig, handler)


def _run_on_ray(
    worker_cls: Callable[[Any], Worker],
    setup: Any,
    jobs: list[Any],
    es: EngineSettings,
    num_cpus: float,
    progress: Callable[[int, Any], None] | None,
) -> list[Any]:
    """Dispatch jobs to idle actors as they free up; results come back in job order."""
    import ray

    actor = ray.remote(Pinned).options(num_cpus=num_cpus, max_restarts=es.retries, max_task_retries=es.retries)
    workers = es.workers or max(1, int(ray.cluster_resources().get("CPU", 1) // num_cpus))
    cores = int(num_cpus) if float(num_cpus).is_integer() else 0
    scope = os.path.abspath(os.getcwd())  # the pipeline: its workers share one set of core locks
    # The constructor state by reference, held here until the actors are gone: Ray frees an argument it
    # stored itself once the first constructor ran, so a restarted actor could not be rebuilt (ray#53727).
    state = ray.put((worker_cls, setup))
    actors = [actor.remote(state, cores, scope) for _ in range(min(workers, len(jobs)))]
    todo, pending, out = list(range(len(jobs)))[::-1], {}, [None] * len(jobs)
    for a in actors:
        if todo:
            i = todo.pop()
            pending[a.run.remote(jobs[i])] = (a, i)
    try:
        while pending:
            done = _wait_one(list(pending), es.timeout_s)
            if not done:
                raise StageError(
                    f"no chunk finished within engine.timeout_s = {es.timeout_s:g} s on {len(actors)} "
                    f"Ray workers; check `ray status` (free CPUs, live nodes) or raise engine.timeout_s"
                )
            a, i = pending.pop(done[0])
            with interrupt.deferred():
                out[i] = _get(done[0], i, es)
            if progress:
                progress(i, out[i])
            if todo:
                j = todo.pop()
                pending[a.run.remote(jobs[j])] = (a, j)
        with interrupt.deferred():
            ray.get([a.close.remote() for a in actors], timeout=es.timeout_s)  # e.g. a scene's temporary files
    finally:
        for a in actors:
            ray.kill(a)
    return out


POLL_S = 1.0  # seconds one ray.wait blocks before the driver checks for a stop signal


def _wait_one(refs: list[Any], timeout_s: float) -> list[Any]:
    """The first of `refs` to finish within timeout_s seconds ([] if none). Ray's wait runs in its C++ core worker,
    where an exception raised by a signal handler came back as a SystemError: it runs deferred, POLL_S at a time,
    and a stop signal raises between two waits (pipeline/interrupt.py)."""
    import time

    import ray

    end = time.monotonic() + timeout_s
    while True:
        with interrupt.deferred():
            done, _ = ray.wait(refs, num_returns=1, timeout=max(0.0, min(POLL_S, end - time.monotonic())))
        if done or time.monotonic() >= end:
            return done


class Pinned:
    """A Ray actor: binds its process to `cores` cores no other worker of its pipeline (`scope`) holds
    (`pin_cores`), then holds `worker_cls(setup)` (state = (worker_cls, setup))."""

    def __init__(self, state: tuple[Callable[[Any], Worker], Any], cores: int, scope: str) -> None:
        pin_cores(cores, scope)
        worker_cls, setup = state
        self.worker = worker_cls(setup)

    def run(self, job: Any) -> Any:
        return self.worker.run(job)

    def close(self) -> None:
        self.worker.close()


_held: list[int] = []  # lock-file descriptors of the cores this process holds, open until it exits


def pin_cores(n: int, scope: str) -> list[int]:
    """Bind every thread of this process (and those it starts later) to n cores of this machine that no
    other worker of the pipeline `scope` holds: a lock file per core under core_locks(scope), freed when the
    process exits -> the cores, or [] (left unbound) when n < 1, fewer are free, or the OS cannot bind.

    Why: a Blender scene uses both cores of a 2-core machine even at render.threads 1 (its scene sync
    runs on a thread pool sized to the machine), so two unbound 1-thread workers collide; bound, two
    workers render 47 images/s at 160x90 where one 2-thread process renders 41 (benchmarks/render_scale.py)."""
    import fcntl

    if n < 1 or not hasattr(os, "sched_setaffinity"):
        return []
    fds: list[int] = []
    got: list[int] = []
    locks = core_locks(scope)
    try:
        os.makedirs(locks, exist_ok=True)
        for core in sorted(os.sched_getaffinity(0)):
            fd = os.open(os.path.join(locks, f"{core}.lock"), os.O_CREAT | os.O_RDWR, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            fds.append(fd)
            got.append(core)
            if len(got) == n:
                break
        if len(got) < n:
            raise OSError("not enough free cores")
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), got)
            except OSError:  # a thread that has just exited
                pass
    except OSError:
        for fd in fds:
            os.close(fd)
        return []
    _held.extend(fds)
    return got


def _get(ref: Any, i: int, es: EngineSettings) -> Any:
    """The result of job i, or the DataError (or StageError) its worker raised, or one line saying it failed."""
    import ray

    try:
        return ray.get(ref)
    except ray.exceptions.RayError as e:
        err: BaseException = e
        for _ in range(10):  # a task error wraps the worker's own exception in `cause`
            if getattr(err, "cause", None) is None:
                break
            err = err.cause
        if isinstance(err, DataError) and not isinstance(err, ray.exceptions.RayError):
            raise StageError(str(err)) from None
        first = (str(e).strip().splitlines() or [type(e).__name__])[-1]
        raise StageError(f"chunk {i} failed on its Ray worker after {es.retries} retries: {first}") from None

"""Ctrl-C stops a stage: a real SIGINT (or SIGTERM) to a running `rpod render` in a copy of the repository, on the
smoke profile. The render stops between two frames (Blender's Cycles swallows the signal inside a frame:
pipeline/interrupt.py), exits 130 with one line, leaves no lock or temporary; under `dvc repro` nothing is recorded in
dvc.lock and the git-tracked outputs DVC deleted before the stage are back as they were."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "scripts"))
from smoke import copy_repo  # noqa: E402

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        shutil.which("git") is None or not (Path(sys.executable).parent / "dvc").exists(),
        reason="git and dvc (beside python) are needed",
    ),
]
# enough frames that the signal lands while Blender renders (about 0.05 s a frame here), few enough to stay cheap
SLOW_RENDER = ["-S", "render.frames_per_sequence=20", "-S", "render.samples=32"]
STARTED_S = 300  # seconds to wait for the render's progress bar
STOPPED_S = 60  # seconds the command may take to stop once signalled


@pytest.fixture
def copy(tmp_path) -> tuple[Path, dict[str, str]]:
    """A copy of the repository on the smoke profile with a slower render, committed (git status clean)."""
    dst = tmp_path / "repo"
    dst.mkdir()
    env = copy_repo(REPO, dst)
    subprocess.run(["rpod", "params", "smoke", *SLOW_RENDER], cwd=dst, env=env, check=True, capture_output=True)
    subprocess.run(["git", "commit", "-qam", "smoke"], cwd=dst, env=env, check=True)
    return dst, env


def _wait_for_group(pgid: int) -> None:
    """Wait until no process of the group `pgid` is left (the stage may still clean up after DVC exits)."""
    deadline = time.monotonic() + STOPPED_S
    while True:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        if time.monotonic() > deadline:
            left = subprocess.run(["ps", "-eo", "pid,pgid,etime,args"], capture_output=True, text=True).stdout
            raise AssertionError(
                f"the stage never finished its clean-up; left in group {pgid}:\n"
                + "\n".join(line for line in left.splitlines() if line.split()[1] == str(pgid))
            )
        time.sleep(0.1)


def _interrupt(
    args: list[str],
    cwd: Path,
    env: dict[str, str],
    sig: int,
    log: Path,
    delay_s: float = 0.0,
    group: bool = True,
    wait_group: bool = False,
) -> tuple[int, str, float]:
    """Start `args` in its own process group, wait for the render's progress bar and `delay_s` seconds more, send
    `sig` to the whole group (as a terminal's Ctrl-C does) or, `group` False, to the command alone (as `kill` does),
    and, `wait_group`, for every process of the group -> (exit status, stderr, seconds from the signal to the command's exit)."""
    with open(log, "w") as err:
        proc = subprocess.Popen(args, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        deadline = time.monotonic() + STARTED_S
        while "img/s" not in log.read_text() and "img]" not in log.read_text():
            assert proc.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "the render never started"
            time.sleep(0.1)
        time.sleep(delay_s)
        signalled = time.monotonic()
        (os.killpg if group else os.kill)(proc.pid, sig)
        code = proc.wait(timeout=STOPPED_S)
        if wait_group:
            _wait_for_group(proc.pid)
    return code, log.read_text(), time.monotonic() - signalled


def _leftovers(root: Path) -> list[str]:
    """Locks and temporaries beside the outputs (dot files other than git's .gitkeep placeholders)."""
    return sorted(
        str(p.relative_to(root))
        for d in (root / "datasets", root / "reports" / "figures")
        if d.is_dir()
        for p in d.iterdir()
        if p.name.startswith(".") and p.name != ".gitkeep"
    )


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_rpod_render_between_frames_with_one_line(copy, tmp_path, sig):
    root, env = copy
    code, err, seconds = _interrupt(["rpod", "render"], root, env, sig, tmp_path / "err.txt")
    name = signal.Signals(sig).name
    assert code == 130, err[-3000:]
    said = [line for line in err.splitlines() if "stopped by" in line]
    assert said == [f"rpod render: stopped by {name}; no half-written output left"], err[-3000:]
    assert err.rstrip().endswith(said[0]) and "Traceback" not in err and "Error" not in err, err[-3000:]
    assert seconds < STOPPED_S
    assert not (root / "datasets" / "render").exists() and _leftovers(root) == []
    status = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True).stdout
    assert status == "", status  # the tracked outputs (previews, metrics) untouched


@pytest.mark.parametrize("sig, group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_a_signal_stops_a_render_on_ray_workers_with_one_line(copy, tmp_path, sig, group):
    """On Ray (engine.workers 2) the driver waits in Ray's core worker: before issue 41 SIGTERM exited 15 (Ray's own
    handler), or 1 with a SystemError from ray.wait, leaving the lock and a temporary folder; SIGINT crashed at exit."""
    root, env = copy
    subprocess.run(
        ["rpod", "params", "smoke", *SLOW_RENDER, "-S", "engine.workers=2", "-S", "render.frames_per_sequence=40"],
        cwd=root,
        env=env,
        check=True,
        capture_output=True,
    )
    code, err, _ = _interrupt(["rpod", "render"], root, env, sig, tmp_path / "err.txt", delay_s=8.0, group=group)
    assert code == 130, err[-3000:]
    said = [line for line in err.splitlines() if "stopped by" in line]
    assert said == [f"rpod render: stopped by {signal.Signals(sig).name}; no half-written output left"], err[-3000:]
    assert "Traceback" not in err and not (root / "datasets" / "render").exists() and _leftovers(root) == []


@pytest.mark.parametrize("shell", ["/bin/bash", "/bin/sh"])
def test_an_interrupted_dvc_repro_records_nothing_and_leaves_tracked_outputs_as_they_were(copy, tmp_path, shell):
    """DVC runs the stage through $SHELL (/bin/sh where SHELL is unset, as in CI). Bash waits for the stage and passes
    its 130 on; dash (Debian's /bin/sh) dies of the terminal's SIGINT itself, so DVC reports -2 while the stage
    finishes its clean-up: either way DVC records nothing and the outputs are back once the stage has exited."""
    if not Path(shell).exists():
        pytest.skip(f"{shell} is not on this machine")
    root, env = copy
    lock = (root / "dvc.lock").read_bytes()
    previews = {p.name: p.read_bytes() for p in (root / "reports" / "figures" / "previews").iterdir()}
    assert previews
    env = {**env, "SHELL": shell}
    code, err, _ = _interrupt(
        ["dvc", "repro", "render"], root, env, signal.SIGINT, tmp_path / "err.txt", wait_group=True
    )
    assert code != 0, err[-3000:]
    said = [line for line in err.splitlines() if "stopped by" in line]
    assert len(said) == 1 and said[0].startswith(
        "rpod render: stopped by SIGINT; no half-written output left; DVC "
        "records nothing (put back from git: reports/figures/previews"
    ), err
    assert ("exited with 130" in err or "exited with -2" in err) and "Traceback" not in err, err[-3000:]
    assert (root / "dvc.lock").read_bytes() == lock
    assert {p.name: p.read_bytes() for p in (root / "reports" / "figures" / "previews").iterdir()} == previews
    status = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True).stdout
    assert status == "", status
    assert _leftovers(root) == []


@pytest.fixture
def handlers():
    """Restore this process's SIGINT/SIGTERM handlers and the stop flag after a test that installs its own."""
    from pipeline import interrupt

    kept = {sig: signal.getsignal(sig) for sig in interrupt.SIGNALS}
    yield interrupt
    for sig, handler in kept.items():
        signal.signal(sig, handler)
    interrupt._state.update(signal=None, deferred=0, raised=False)


def test_a_deferred_signal_sets_the_flag_and_raises_at_the_end_of_the_block(handlers):
    handlers.install()
    reached = False
    with pytest.raises(handlers.Interrupted, match="SIGTERM"):
        with handlers.deferred():  # as around a Blender call, which would swallow the exception
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            assert handlers.requested() == signal.SIGTERM
            reached = True
    assert reached
    os.kill(os.getpid(), signal.SIGINT)  # a second signal during the clean-up is recorded, not raised
    time.sleep(0.05)


def test_ray_init_does_not_take_the_stop_path_away(handlers):
    """ray.init sets SIGTERM to sys.exit (exit status 15, no line): the engine puts the command's handler back."""
    from stages.engine.pool import _signal_handlers_kept

    handlers.install()
    with _signal_handlers_kept():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))
    assert signal.getsignal(signal.SIGTERM) is handlers._handler

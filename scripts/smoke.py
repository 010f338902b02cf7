"""`make smoke`: the smoke profile end to end in a temporary copy of the repository, so the checkout's
tracked files (params.yaml, conf/config.yaml, reports/, dvc.lock, dvclive/) stay as they were.

    python scripts/smoke.py                              # every stage, in a new temporary folder
    python scripts/smoke.py --dir /tmp/s --stages render label   # those stages (and what they need)
    python scripts/smoke.py --dry                        # `dvc repro --dry --force`: the stages that would run

The copy holds the tracked and untracked-but-not-ignored files (a clean clone plus local edits) as a
one-commit git repository; it is kept, and its path is printed at the end (reports in DIR/reports).
tests/test_e2e_*.py build their copies with `copy_repo` too.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


def run(args: list[str], cwd: Path, env: dict[str, str], timeout: float = 900) -> str:
    """Run a command in `cwd`; its stdout, or AssertionError with the tail of its output when it fails."""
    out = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, (
        f"{' '.join(args)} failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    )
    return out.stdout


def copy_env(dst: Path) -> dict[str, str]:
    """The environment to run this venv's `rpod` and `dvc` on the code of the copy `dst` (and git there)."""
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(dst),
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@example.org",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@example.org",
    }
    env.pop("RPOD_DEBUG", None)
    return env


def copy_repo(src: Path, dst: Path) -> dict[str, str]:
    """Copy `src`'s working-tree files (tracked and untracked-not-ignored) into the folder `dst` as a
    one-commit git repository; returns the environment to run `rpod` and `dvc` there (`copy_env`)."""
    files = (
        subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=src, check=True, capture_output=True)
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, files):
        if (src / name).is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / name, dst / name)
    env = copy_env(dst)
    for args in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "copy"]):
        run(args, dst, env)
    return env


def smoke(dst: Path, stages: list[str], dry: bool) -> None:
    """Copy the checkout into the empty folder `dst`, switch the copy to the smoke profile and run
    `dvc repro` there (only `stages` and what they need, when given), streaming the output; a command
    that fails ends the script with one line (its own message is above it)."""
    env = copy_repo(ROOT, dst)
    # --dry is forced: the copy has no data, every stage of the smoke profile runs there, and an unforced dry run
    # stops at the first stage whose input folder another stage would write ("failed to reproduce 'label'")
    for args in (["rpod", "params", "smoke"], ["dvc", "repro", *(["--dry", "--force"] if dry else []), *stages]):
        done = subprocess.run(args, cwd=dst, env=env)
        if done.returncode != 0:
            sys.exit(f"smoke: `{' '.join(args)}` failed in {dst} (exit {done.returncode})")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, help="empty or new folder for the copy (default: a new temporary one)")
    parser.add_argument("--stages", nargs="*", default=[], help="run only these DVC stages and what they need")
    parser.add_argument("--dry", action="store_true", help="print what `dvc repro` would run, run nothing")
    args = parser.parse_args(argv)
    if shutil.which("git") is None:
        sys.exit("smoke: git is needed to list the repository's files")
    dst = args.dir or Path(tempfile.mkdtemp(prefix="rpodguard-smoke-"))
    if dst.exists() and any(dst.iterdir()):
        sys.exit(f"smoke: --dir {dst} is not empty")
    dst.mkdir(parents=True, exist_ok=True)
    smoke(dst.resolve(), args.stages, args.dry)
    print(f"smoke results: {dst.resolve()} (reports in {dst.resolve() / 'reports'}); the checkout is untouched")


if __name__ == "__main__":
    main()

"""Write the ready-to-use weights bundle from a trained run: the chain that ships, models/{pose_robust.pt,
detector_robust.pt, defense.json}, and the params.yaml they were trained with -> rpodguard/weights/PROFILE/ as
pose.pt, detector.pt, defense.json (pipeline/formats/bundle.py: each file's sha256 and source, the params, the git
commit of the code), which `rpodguard.load_chain()` and `rpod predict` load by default.

    rpod params default && dvc repro calibrate     # pose_robust.pt (robust), detector_robust.pt (detect_robust),
                                                   # defense.json (calibrate)
    python scripts/bundle_weights.py               # -> rpodguard/weights/default/; commit it

--models DIR (default models/) and --params FILE (default params.yaml) may point into another checkout. The
commit recorded is the first one whose dvc.lock records all three files (its code made them), or, for a run
not committed yet, the HEAD of the git repository holding --models with the code files (pipeline/, stages/,
rpodguard/, conf/) that differ from it listed as code_changes. The bundle is loaded back before the script
reports it.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from pipeline.formats.bundle import FILES, SOURCES, write_bundle  # noqa: E402
from pipeline.io.errors import DataError  # noqa: E402
from rpodguard import load_chain  # noqa: E402

CODE = ("pipeline", "stages", "rpodguard", "conf")  # folders whose changes alter what a run trains
REBUILD = (
    "git checkout {commit} -- pipeline stages conf && rpod params {profile} && dvc repro calibrate && "
    "python scripts/bundle_weights.py"
)


def provenance(models: Path) -> tuple[str, list[str]]:
    """(commit, changed code files) for the run in MODELS: the first commit whose dvc.lock records the md5 of all
    three files (that commit's code made them; no changes), else the checkout's HEAD with its changed or
    untracked code files."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=models, capture_output=True, text=True, check=True).stdout

    md5 = [hashlib.md5((models / SOURCES[name]).read_bytes()).hexdigest() for name in FILES]
    try:
        for commit in git("log", "--reverse", "--format=%H", "-S", md5[-1], "--", ":/dvc.lock").split():
            if all(m in git("show", f"{commit}:dvc.lock") for m in md5):
                return commit, []
        status = git(
            "status",
            "--porcelain",
            "--untracked-files=all",
            "--",
            *[f":/{c}" for c in CODE],
            ":(exclude,top)rpodguard/weights",
        )
        return git("rev-parse", "HEAD").strip(), [line[3:] for line in status.splitlines() if line.strip()]
    except (OSError, subprocess.CalledProcessError) as e:
        raise DataError(
            f"{models}: not inside a git checkout with a commit, so the bundle's code commit is unknown ({e})"
        ) from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--models",
        type=Path,
        default=REPO / "models",
        help="a run's models/ folder (pose_robust.pt, detector_robust.pt, defense.json)",
    )
    parser.add_argument(
        "--params", type=Path, default=REPO / "params.yaml", help="the params.yaml they were trained with"
    )
    parser.add_argument("--out", type=Path, default=None, help="bundle folder (default rpodguard/weights/PROFILE)")
    args = parser.parse_args()
    if not args.params.is_file():
        raise DataError(f"{args.params} not found (give the params.yaml the models were trained with)")
    params = yaml.safe_load(args.params.read_text())
    profile = params.get("profile_name", "default")
    out = args.out or REPO / "rpodguard" / "weights" / profile
    commit, changes = provenance(args.models.resolve())
    rebuild = REBUILD.format(commit=commit[:12], profile=profile)
    manifest = write_bundle(out, args.models, params, commit, changes, rebuild)
    chain = load_chain(out)  # the detector must belong to this pose model; the hashes just written must hold
    size = sum(f["bytes"] for f in manifest["files"].values())
    print(
        f"{out}: {', '.join(manifest['files'])} ({size / 1e6:.1f} MB), profile {profile}, commit {commit[:12]}"
        + (f", {len(changes)} changed code files" if changes else "")
        + f"; {chain.rule.describe()}"
    )


if __name__ == "__main__":
    try:
        main()
    except DataError as e:
        sys.exit(f"error: {e}")

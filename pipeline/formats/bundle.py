"""A weights bundle: the files of the chain that ships with their sha256, the params they were trained with and
where they came from, so the chain can be used (and checked) without running the pipeline.

FOLDER/pose.pt (the robust pose model, a run's models/pose_robust.pt: `rpod train --robust`), FOLDER/detector.pt
(its detector, models/detector_robust.pt: `rpod detect --model robust`), FOLDER/defense.json (`rpod calibrate`),
and FOLDER/manifest.json:
    format: "rpodguard-weights/1", profile: the params profile, commit: the git commit of the code that
    trained them, code_changes: code files that differed from that commit (empty for a committed run),
    files: {name: {sha256, bytes}}, sources: {name: the file of a run's models/ it was copied from},
    params: the params.yaml they were trained with, rebuild: how to remake it.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from pipeline.formats.run import BUNDLE_FILES, MODELS_DIR, RUN_FILES, SHIPPED
from pipeline.io.atomic import atomic_dir, file_hash, read_json, write_json
from pipeline.io.errors import DataError

BUNDLE_FORMAT = "rpodguard-weights/1"
MANIFEST = "manifest.json"
FILES = tuple(BUNDLE_FILES)
SOURCES = dict(zip(BUNDLE_FILES, RUN_FILES[SHIPPED]))  # bundle file -> the shipped chain's file in a run's models/


def write_bundle(
    out: Path | str, models: Path | str, params: dict[str, Any], commit: str, code_changes: list[str], rebuild: str
) -> dict[str, Any]:
    """Copy the shipped chain of a run's MODELS folder (`SOURCES`: pose_robust.pt, detector_robust.pt, defense.json)
    into the folder OUT as FILES (replaced whole, atomically) with its manifest; returns the manifest. defense.json
    must name the robust pose model's hash (calibrated on that model)."""
    models, names = Path(models), RUN_FILES[SHIPPED]
    defense, pose = read_json(models / names.defense), models / names.pose
    if defense.get("pose_model_hash") != file_hash(pose):
        raise DataError(
            f"{models / names.defense} was calibrated for another pose model than {pose}; re-run `rpod calibrate`"
        )
    with atomic_dir(out) as tmp:
        for name in FILES:
            shutil.copyfile(models / SOURCES[name], tmp / name)
        manifest = {
            "format": BUNDLE_FORMAT,
            "profile": params.get("profile_name"),
            "commit": commit,
            "code_changes": sorted(code_changes),
            "params": params,
            "rebuild": rebuild,
            "sources": {name: f"{MODELS_DIR}/{SOURCES[name]}" for name in FILES},
            "files": {
                name: {"sha256": file_hash(tmp / name, 64), "bytes": (tmp / name).stat().st_size} for name in FILES
            },
        }
        write_json(tmp / MANIFEST, manifest)
        tmp.chmod(0o755)  # a temporary folder and file are private; a bundle is for everyone
        for path in tmp.iterdir():
            path.chmod(0o644)
    return manifest


def check_bundle(folder: Path | str) -> dict[str, Any]:
    """FOLDER's manifest, once every file it lists is present with its sha256 (else a DataError naming the file)."""
    folder = Path(folder)
    manifest = read_json(folder / MANIFEST)
    files = manifest.get("files") if isinstance(manifest, dict) else None
    if not isinstance(files, dict) or manifest.get("format") != BUNDLE_FORMAT or set(files) != set(FILES):
        raise DataError(f"{folder / MANIFEST} is not a {BUNDLE_FORMAT} manifest listing {', '.join(FILES)}")
    for name, entry in files.items():
        path = folder / name
        if not path.is_file():
            raise DataError(f"{path} is missing from the weights bundle (restore it with `git checkout -- {folder}`)")
        if file_hash(path, 64) != entry.get("sha256"):
            raise DataError(
                f"{path} does not match its sha256 in {folder / MANIFEST} (changed or damaged; restore "
                f"it with `git checkout -- {folder}` or rebuild: {manifest.get('rebuild')})"
            )
    return manifest

"""The weights bundle shipped in git (rpodguard/weights/default/): `load_chain()` and `rpod predict` use it from any
folder with no stage run, its hashes are checked, and scripts/bundle_weights.py rebuilds it identically."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from test_predict import _rpod

from pipeline.formats.bundle import FILES, MANIFEST, SOURCES, check_bundle
from pipeline.io.atomic import file_hash, read_json
from pipeline.io.errors import DataError
from rpodguard import load_chain
from rpodguard.api import BUNDLE

REPO = Path(__file__).resolve().parents[1]


def satellite(scale: float, height: int = 90, width: int = 160) -> np.ndarray:
    """A render-like frame: black space, a lit box (the bus) with two dark-blue panels, centred; SCALE: apparent
    size."""
    image = np.zeros((height, width, 3), np.uint8)
    cy, cx = height // 2, width // 2
    bus, panel, thick = int(6 * scale), int(14 * scale), max(1, int(2 * scale))
    image[cy - bus : cy + bus, cx - bus : cx + bus] = (180, 170, 150)
    image[cy - thick : cy + thick, cx - bus - panel : cx - bus] = (40, 60, 120)
    image[cy - thick : cy + thick, cx + bus : cx + bus + panel] = (40, 60, 120)
    return image


def test_load_chain_with_no_argument_is_the_bundle_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no models/ here: nothing but the bundle to load
    chain = load_chain()
    assert chain.files == (BUNDLE / "pose.pt", BUNDLE / "detector.pt", BUNDLE / "defense.json")
    assert chain.safety.defended is not None and chain.safety.calibration.model == "robust"
    manifest = chain.manifest
    assert manifest["profile"] == "default" and len(manifest["commit"]) == 40
    render = manifest["params"]["render"]  # trained with the params it lists
    assert (chain.height, chain.width) == (render["height"], render["width"])
    assert read_json(BUNDLE / "defense.json")["pose_model_hash"] == file_hash(BUNDLE / "pose.pt")
    out = chain.predict(np.stack([satellite(s, render["height"], render["width"]) for s in (1, 2, 3)]))
    assert out.in_view.all() and np.isfinite(out.position).all()
    z = out.position[:, 2]
    assert (np.diff(z) < 0).all() and z[-1] > 0  # a larger target is nearer: a trained model
    assert (np.abs(out.position[:, :2]) < 0.1 * z[:, None]).all()  # a centred target is on the boresight


def test_rpod_predict_without_models_uses_the_bundle(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    Image.fromarray(satellite(2)).save(tmp_path / "frame.png")
    code, out, err = _rpod(monkeypatch, capsys, "predict", "frame.png")
    assert code == 0 and "frame.png" in out and "z (m)" in out
    assert err.startswith("note: the bundled weights (default profile, commit ") and err.count("\n") == 1


@pytest.fixture
def copy(tmp_path) -> Path:
    folder = tmp_path / "bundle"
    shutil.copytree(BUNDLE, folder)
    return folder


@pytest.mark.parametrize("name", FILES)
def test_a_changed_bundle_file_is_refused_with_one_line(copy, name):
    data = bytearray((copy / name).read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit
    (copy / name).write_bytes(bytes(data))
    with pytest.raises(DataError, match=rf"{name} does not match its sha256 in .*manifest\.json") as info:
        load_chain(copy)
    assert "\n" not in str(info.value)


def test_a_missing_file_or_a_foreign_manifest_is_refused(copy):
    (copy / "detector.pt").unlink()
    with pytest.raises(DataError, match="detector.pt is missing from the weights bundle"):
        check_bundle(copy)
    (copy / MANIFEST).write_text('{"format": "something-else/1", "files": {}}')
    with pytest.raises(DataError, match="is not a rpodguard-weights/1 manifest"):
        check_bundle(copy)


def test_the_bundle_is_the_shipped_chain_the_robust_model_and_its_own_detector():
    """The bundle was copied from a run's shipped chain (models/pose_robust.pt, detector_robust.pt), its pose model
    is the clamped one, and stages.artifacts.paths names the same files as the chain that ships."""
    from pipeline.formats.models import read_detector, read_pose
    from stages.artifacts.paths import CHAINS, SHIPPED, Model

    assert SHIPPED == Model.robust
    shipped = CHAINS[SHIPPED]
    assert {n: f"models/{SOURCES[n]}" for n in FILES} == {
        "pose.pt": str(shipped.pose),
        "detector.pt": str(shipped.detector),
        "defense.json": str(shipped.defense),
    }
    assert read_json(BUNDLE / MANIFEST)["sources"] == {n: f"models/{SOURCES[n]}" for n in FILES}
    assert read_pose(BUNDLE / "pose.pt")["arch"].get("black_level", 0) > 0  # the clamp: the robust model
    assert read_detector(BUNDLE / "detector.pt", model_hash=file_hash(BUNDLE / "pose.pt"))  # its own detector


def test_the_script_rebuilds_the_bundle_naming_the_commit_that_recorded_the_files(copy, tmp_path):
    import hashlib

    git = ["git", "-c", "user.name=t", "-c", "user.email=t@example.org", "-C", str(tmp_path)]
    subprocess.run([*git, "init", "-q"], check=True)
    run = tmp_path / "models"  # a run's models/: the shipped chain under its run names
    run.mkdir()
    for name in FILES:
        shutil.copy(copy / name, run / SOURCES[name])
    copy = run
    md5 = {SOURCES[name]: hashlib.md5((copy / SOURCES[name]).read_bytes()).hexdigest() for name in FILES}
    (tmp_path / "dvc.lock").write_text("".join(f"- path: models/{n}\n  md5: {m}\n" for n, m in md5.items()))
    subprocess.run([*git, "add", "dvc.lock"], check=True)
    subprocess.run([*git, "commit", "-qm", "a run"], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(read_json(BUNDLE / MANIFEST)["params"]))
    done = subprocess.run(
        [
            sys.executable,
            str(REPO / "scripts/bundle_weights.py"),
            "--models",
            str(copy),
            "--params",
            str(params),
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    rebuilt, shipped = read_json(tmp_path / "out" / MANIFEST), read_json(BUNDLE / MANIFEST)
    assert rebuilt["files"] == shipped["files"] and rebuilt["params"] == shipped["params"]
    assert rebuilt["commit"] == commit and rebuilt["code_changes"] == []
    assert "dvc repro calibrate" in rebuilt["rebuild"] and "scripts/bundle_weights.py" in rebuilt["rebuild"]


def test_the_bundle_is_the_chain_of_the_committed_run() -> None:
    """Each bundled file is byte for byte the models/ file that the committed dvc.lock records (md5): a re-run whose
    bundle was not rebuilt (scripts/bundle_weights.py) would have the API and `rpod predict` fly another chain than
    the one reports/ describe (the bundle of d4e9661 outlived two re-calibrations and a new detector)."""
    import hashlib

    manifest = read_json(BUNDLE / MANIFEST)
    lock = yaml.safe_load((REPO / "dvc.lock").read_text())
    recorded = {o["path"]: o["md5"] for s in lock["stages"].values() for o in s.get("outs", [])}
    for name in FILES:
        source = manifest["sources"][name]
        assert source == f"models/{SOURCES[name]}" and source in recorded, source
        md5 = hashlib.md5((BUNDLE / name).read_bytes()).hexdigest()
        assert md5 == recorded[source], f"{name} is not the {source} of dvc.lock: run scripts/bundle_weights.py"


def test_predict_gives_the_shipped_chain_verdict_on_the_bundle(monkeypatch, capsys):
    """On the shipped images (the render previews and the example sequence) the verdict of `load_chain().predict`
    and `rpod predict` is the shipped chain's: its defense file's calibrated threshold and doubt level (read here
    straight from the JSON), not the detector checkpoint's own threshold."""
    chain = load_chain()
    record = read_json(BUNDLE / "defense.json")
    level, doubt = record["threshold"], record["settings"]["update_below"]
    images = sorted((REPO / "reports" / "figures" / "previews").glob("*.png")) + sorted(
        (REPO / "examples" / "approach").glob("*.png")
    )
    assert len(images) >= 4
    out = chain.predict(images)
    assert out.rule.calibrated and out.rule.threshold == level != chain.safety.threshold and out.rule.doubt == doubt
    assert out.in_view.all()
    want = ["attack" if p >= level else "doubt" if p >= doubt else "clean" for p in out.attack_probability]
    assert list(out.verdict) == want
    code, text, _ = _rpod(monkeypatch, capsys, "predict", *map(str, images))
    assert code == 0 and text.splitlines()[0].startswith(
        f"verdict: attack at P(attack) >= {level!r}, doubt at >= {doubt!r} (the chain's calibrated defense, "
    )
    assert [line.split()[-1] for line in text.splitlines()[3:]] == want

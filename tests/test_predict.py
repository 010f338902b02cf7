"""`rpodguard.load_chain` / `Chain.predict` and `rpod predict` on a tiny random pose model and detector."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from pipeline.geometry.camera import reference_intrinsics
from rpodguard import load_chain

H, W = 36, 64  # model input of the tiny checkpoint
CAMERA = reference_intrinsics().scaled(W, H)


def _save_models(folder: Path, K: np.ndarray | None = None, black_level: float = 0.0, seed: int = 0) -> Path:
    """FOLDER/pose.pt and FOLDER/detector.pt as `rpod train` and `rpod detect` write them (random weights drawn with
    `seed`; `K`: the camera matrix `rpod train` stores, None for a checkpoint from before it did; `black_level`: the
    robust model's input clamp, 0 for the standard model)."""
    from pipeline.detectors.lstm import LSTMConfig, LSTMDetector, to_checkpoint
    from pipeline.formats.models import DETECTOR_FORMAT, save_pose
    from pipeline.io.atomic import file_hash
    from pipeline.io.checkpoints import save_torch
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    torch.manual_seed(seed)
    model = PoseNet(width=0.125, black_level=black_level).eval()
    save_pose(folder / "pose.pt", model, PoseLoss(), (H, W), {}, K=K)
    with torch.no_grad():
        background = model.forward_features(torch.rand(6, 3, H, W)).mean(0)
    det = LSTMDetector(LSTMConfig(hidden=8, dense=[4])).eval()
    det.set_normalisation(np.random.default_rng(0).normal(size=(5, 9, 1000)).astype(np.float32) * 0.01)
    save_torch(
        folder / "detector.pt",
        to_checkpoint(
            det,
            {
                "format": DETECTOR_FORMAT,
                "background_mean": background,
                "pose_model_hash": file_hash(folder / "pose.pt"),
            },
        ),
    )
    return folder


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    """A run's models/ without a camera matrix in pose.pt (written before it was stored)."""
    return _save_models(tmp_path_factory.mktemp("run") / "models")


@pytest.fixture(scope="module")
def camera_models(tmp_path_factory) -> Path:
    """A run's models/ whose pose.pt records its camera (`CAMERA`: the paper's printed K at the input size)."""
    return _save_models(tmp_path_factory.mktemp("run") / "models", CAMERA.K)


def _images(n: int, h: int = H, w: int = W, seed: int = 0) -> np.ndarray:
    """N random camera-like frames: blocks of 4 x 4 pixels of one random colour (neighbouring pixels correlate, as
    in a lens image; pixel noise is not a frame: pipeline.visibility.MIN_STRUCTURE)."""
    blocks = np.random.default_rng(seed).integers(0, 256, size=(n, -(-h // 4), -(-w // 4), 3), dtype=np.uint8)
    return np.ascontiguousarray(blocks.repeat(4, axis=1).repeat(4, axis=2)[:, :h, :w])


def _png(path: Path, image: np.ndarray) -> Path:
    Image.fromarray(image).save(path)
    return path


def test_predict_gives_pose_and_flag_per_image(models):
    chain = load_chain(models)
    out = chain.predict(_images(3))
    assert len(out) == 3 and out.sources == ("array[0]", "array[1]", "array[2]")
    assert out.position.shape == (3, 3) and out.quaternion.shape == (3, 4) and out.rotation_6d.shape == (3, 6)
    np.testing.assert_allclose(np.linalg.norm(out.quaternion, axis=1), 1.0, atol=1e-9)
    assert (out.quaternion[:, 0] >= 0).all()
    assert ((out.attack_probability >= 0) & (out.attack_probability <= 1)).all()
    np.testing.assert_array_equal(out.attack_flag, out.attack_probability >= chain.threshold)
    assert len(chain.predict(_images(1)[0])) == 1  # one (H, W, 3) image
    assert load_chain(models.parent).files == chain.files  # a project root holding models/


def test_png_float_and_array_inputs_agree(models, tmp_path):
    chain = load_chain(models)
    images = _images(2, seed=1)
    paths = [_png(tmp_path / f"{k}.png", im) for k, im in enumerate(images)]
    from_files = chain.predict(paths)
    from_arrays = chain.predict(images)
    from_floats = chain.predict(list(images.astype(np.float64) / 255))
    assert from_files.sources == tuple(str(p) for p in paths)
    for other in (from_arrays, from_floats):
        np.testing.assert_allclose(other.position, from_files.position, atol=1e-5)
        np.testing.assert_allclose(other.attack_probability, from_files.attack_probability, atol=1e-5)


def test_other_sizes_are_resized_and_another_aspect_warns(models, tmp_path):
    chain = load_chain(models)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # twice the size, same aspect: no warning
        big = chain.predict(_png(tmp_path / "big.png", _images(1, 2 * H, 2 * W)[0]))
    assert big.position.shape == (1, 3)
    with pytest.warns(UserWarning, match=r"square\.png is 50x50 .*stretched"):
        chain.predict(_png(tmp_path / "square.png", _images(1, 50, 50)[0]))


def test_bad_arrays_are_refused(models):
    chain = load_chain(models)
    with pytest.raises(ValueError, match="float pixels"):
        chain.predict(np.full((H, W, 3), 2.0))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        chain.predict([np.zeros((H, W), np.uint8)])


def _rpod(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    from stages import cli

    monkeypatch.setattr(sys, "argv", ["rpod", *args])
    monkeypatch.setitem(cli._DEBUG, "on", False)
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    captured = capsys.readouterr()
    return exit_info.value.code, captured.out, captured.err


def test_cli_json_and_table(models, tmp_path, monkeypatch, capsys):
    a = _png(tmp_path / "a.png", _images(1)[0])
    b = _png(tmp_path / "b.png", _images(1, 50, 50, seed=2)[0])
    code, out, err = _rpod(monkeypatch, capsys, "predict", str(a), str(b), "--json", "--models", str(models))
    assert code == 0
    records = json.loads(out)
    assert [r["image"] for r in records] == [str(a), str(b)]
    assert len(records[0]["position_m"]) == 3 and len(records[0]["quaternion"]) == 4
    assert len(records[0]["rotation_6d"]) == 6 and isinstance(records[0]["attack_flag"], bool)
    assert err.count("\n") == 1 and err.startswith("warning: ") and "b.png is 50x50" in err
    code, out, err = _rpod(monkeypatch, capsys, "predict", str(a), "--models", str(models))
    assert code == 0 and "a.png" in out and "z (m)" in out and err == ""


def test_cli_bad_inputs_stop_with_one_line(models, tmp_path, monkeypatch, capsys):
    good = _png(tmp_path / "good.png", _images(1)[0])
    (tmp_path / "text.png").write_text("not an image")
    truncated = tmp_path / "cut.png"
    truncated.write_bytes(good.read_bytes()[:200])
    for args, named in (
        ([str(tmp_path / "missing.png")], "missing.png not found"),
        ([str(good), str(tmp_path / "text.png")], "text.png cannot be read as an image"),
        ([str(truncated)], "cut.png cannot be read as an image"),
        ([str(tmp_path)], "is not a file"),
        ([], "no images given"),
    ):
        code, out, err = _rpod(monkeypatch, capsys, "predict", *args, "--models", str(models))
        assert code == 1 and out == "" and err.count("\n") == 1 and err.startswith("error: ") and named in err, err
    code, _, err = _rpod(monkeypatch, capsys, "predict", str(good), "--models", str(tmp_path / "none"))
    assert code == 1 and "pose.pt not found" in err


def test_an_image_that_is_not_a_frame_with_the_target_in_view_gets_no_pose(models, tmp_path, monkeypatch, capsys):
    from rpodguard.api import LIT_LEVEL, MIN_LIT_FRACTION, MIN_STRUCTURE

    dark = np.zeros((H, W, 3), np.uint8)
    speck = dark.copy()
    speck[:2, :2] = 255  # 4 of 2304 lit pixels: under MIN_LIT_FRACTION
    target = dark.copy()
    target[10:20, 20:40] = int(LIT_LEVEL * 255) + 10  # a dim 20x10 target: 8.7% lit
    noise = np.random.default_rng(5).integers(0, 256, size=(H, W, 3), dtype=np.uint8)  # every pixel lit
    grey = np.full((H, W, 3), 128, np.uint8)  # lit, but no structure at all
    assert 4 / (H * W) < MIN_LIT_FRACTION < 200 / (H * W)
    out = load_chain(models).predict(np.stack([dark, speck, target, noise, grey]))
    assert out.verdict[:2] == ("no target", "no target") and out.verdict[3:] == ("not a frame", "not a frame")
    assert out.in_view.tolist() == [False, False, True, False, False]
    assert out.structure[2] > 0.9 and out.structure[3] < 0.1 < MIN_STRUCTURE and out.structure[4] == 0
    seen = out.in_view
    assert np.isnan(out.position[~seen]).all() and np.isnan(out.quaternion[~seen]).all()
    assert not out.attack_flag[~seen].any() and np.isnan(out.attack_probability[~seen]).all()
    assert np.isfinite(out.position[2]).all() and np.isfinite(out.attack_probability[2])
    assert out.records()[0]["position_m"] is None and out.records()[2]["position_m"] is not None
    code, text, err = _rpod(
        monkeypatch,
        capsys,
        "predict",
        str(_png(tmp_path / "dark.png", dark)),
        str(_png(tmp_path / "noise.png", noise)),
        "--models",
        str(models),
    )
    assert code == 0 and "no target in view (0.00% lit pixels" in text and err == ""
    assert "not a camera frame: neighbouring pixels correlate" in text.splitlines()[-1]
    code, text, _ = _rpod(
        monkeypatch, capsys, "predict", str(_png(tmp_path / "dark.png", dark)), "--json", "--models", str(models)
    )
    assert json.loads(text)[0]["in_view"] is False and json.loads(text)[0]["quaternion"] is None


def test_image_paths_are_checked_before_the_models_load(tmp_path, monkeypatch, capsys):
    import rpodguard

    monkeypatch.setattr(rpodguard, "load_chain", lambda *a: pytest.fail("models loaded before the paths were checked"))
    code, out, err = _rpod(monkeypatch, capsys, "predict", str(tmp_path / "typo.png"), "--models", str(tmp_path))
    assert code == 1 and out == "" and err == f"error: {tmp_path / 'typo.png'} not found\n"


def test_the_model_camera_is_read_and_another_camera_warns(camera_models):
    chain = load_chain(camera_models)
    assert chain.camera == CAMERA
    image = _images(1, 2 * H, 2 * W)[0]  # the same camera at twice the resolution: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        chain.predict(image, camera=CAMERA.scaled(2 * W, 2 * H).K)
        chain.predict(image, camera={"Nu": 2 * W, "Nv": 2 * H, "cameraMatrix": CAMERA.scaled(2 * W, 2 * H).K.tolist()})
    wide = CAMERA.K * [[0.5], [0.5], [1]] + [[0, 0, 0.5 * CAMERA.cx], [0, 0, 0.5 * CAMERA.cy], [0, 0, 0]]
    with pytest.warns(UserWarning, match=r"array\[0\]: its camera \(fx 42\.7.* ranges come out about 2\.00 times"):
        chain.predict(_images(1)[0], camera=wide)  # half the focal length: twice the field of view
    with pytest.warns(UserWarning, match=r"array\[0\] is 64x36 but its camera is given at 128x72"):
        chain.predict(
            _images(1)[0], camera={"Nu": 2 * W, "Nv": 2 * H, "cameraMatrix": CAMERA.scaled(2 * W, 2 * H).K.tolist()}
        )


def test_an_older_checkpoint_without_k_loads_and_says_it_cannot_check(models):
    chain = load_chain(models)
    assert chain.camera is None and len(chain.predict(_images(1))) == 1
    with pytest.warns(UserWarning, match="records no camera matrix") as caught:
        chain.predict(_images(3), camera=CAMERA.K)
    assert len(caught) == 1  # once per call, not per image


def test_the_bundled_weights_know_their_camera_from_the_manifest():
    """The bundle's pose.pt predates the stored K: its manifest's params give the synthetic camera."""
    from pipeline.geometry.camera import Intrinsics
    from pipeline.io.atomic import read_json
    from rpodguard.api import BUNDLE
    from rpodguard.camera import model_camera

    manifest = read_json(BUNDLE / "manifest.json")
    c, r = manifest["params"]["camera"], manifest["params"]["render"]
    got = model_camera({"input_size": [r["height"], r["width"]]}, manifest, BUNDLE / "pose.pt")
    assert got == Intrinsics(c["ref_width"], c["ref_height"], c["fx"], c["fy"], c["cx"], c["cy"]).scaled(
        r["width"], r["height"]
    )
    imported = {**manifest, "params": {**manifest["params"], "render": {**r, "source": "/data/speedplus"}}}
    assert model_camera({"input_size": [r["height"], r["width"]]}, imported, BUNDLE / "pose.pt") is None


def test_cli_camera_mismatch_warns_and_a_bad_camera_file_stops_first(camera_models, tmp_path, monkeypatch, capsys):
    image = _png(tmp_path / "a.png", _images(1)[0])
    other = tmp_path / "camera.json"
    other.write_text(json.dumps({"Nu": W, "Nv": H, "cameraMatrix": (CAMERA.K * [[2], [1], [1]]).tolist()}))
    code, out, err = _rpod(
        monkeypatch, capsys, "predict", str(image), "--camera", str(other), "--models", str(camera_models)
    )
    assert code == 0 and "a.png" in out and err.count("\n") == 1 and "ranges come out about 0.50 times" in err
    same = tmp_path / "same.json"
    same.write_text(json.dumps({"Nu": W, "Nv": H, "cameraMatrix": CAMERA.K.tolist()}))
    code, _, err = _rpod(
        monkeypatch, capsys, "predict", str(image), "--camera", str(same), "--models", str(camera_models)
    )
    assert code == 0 and err == ""
    import rpodguard

    monkeypatch.setattr(rpodguard, "load_chain", lambda *a: pytest.fail("models loaded before the camera was checked"))
    (tmp_path / "bad.json").write_text(json.dumps({"cameraMatrix": CAMERA.K.tolist()}))
    for path, named in ((tmp_path / "bad.json", "bad.json: missing key 'Nu'"), (tmp_path / "none.json", "not found")):
        code, out, err = _rpod(monkeypatch, capsys, "predict", str(image), "--camera", str(path))
        assert code == 1 and out == "" and err.count("\n") == 1 and named in err, err


# ----------------------------------------------------------------------------- sequence mode (rpodguard/sequence.py)
def defense_record(pose: Path, detector_threshold: float, model: str = "robust", **changes) -> dict:
    """A whole defense file's record as `rpod calibrate` writes it (pipeline/formats/defense.py) for the pose model
    at `pose` and a detector of that threshold, with made-up calibration results; `changes`: DefenseFile fields."""
    import dataclasses

    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.integrity import AlertLimitSettings
    from pipeline.defense.noise import NoiseModel
    from pipeline.defense.settings import DefenseSettings
    from pipeline.formats.defense import DEFENSE_FORMAT, DefenseFile, Validation
    from pipeline.io.atomic import file_hash

    noise = NoiseModel((0.05, 0.05, 0.1), (0.005, 0.005, 0.01), 1.0, 0.0)
    validation = Validation(
        3,
        1,
        60,
        0.5,
        {"level": None, "share_pct": None, "reached_pct": None},
        {"frames": 10, "detector_pct": 0.0},
        {},
        {},
        {"pct": 100.0, "ci95_pct": [90.0, 100.0]},
        {"pct": 0.0, "ci95_pct": [0.0, 5.0]},
        {},
        {},
    )
    record = DefenseFile(
        DEFENSE_FORMAT,
        model,
        file_hash(pose),
        detector_threshold,
        0.9,
        8.0,
        1.0,
        1.0,
        noise,
        noise,
        DefenseSettings(threshold=0.9),
        MotionSettings(cusum_threshold=8.0),
        AlertLimitSettings(),
        (),
        validation,
    )
    return dataclasses.replace(record, **changes).to_json()


def _calibrate(models: Path) -> None:
    """models/defense.json as `rpod calibrate` writes it (pipeline/formats/defense.py), for the tiny chain."""
    from pipeline.io.atomic import write_json

    write_json(models / "defense.json", defense_record(models / "pose.pt", load_chain(models).safety.threshold))


def test_the_verdict_is_the_calibrated_chain_s_and_a_folder_without_defense_file_says_its_rule(
    models, tmp_path, monkeypatch, capsys
):
    """predict judges at the defense file's calibrated threshold and doubt level (the chain's verdict), printed in
    full; without a defense file at the detector's own threshold, saying so."""
    from pipeline.defense.settings import DefenseSettings
    from pipeline.io.atomic import write_json

    folder = tmp_path / "chain"
    folder.mkdir()
    for name in ("pose.pt", "detector.pt"):
        (folder / name).write_bytes((models / name).read_bytes())
    images = _images(24, seed=6)
    bare = load_chain(folder)
    own = bare.safety.threshold
    out = bare.predict(images)
    assert not out.rule.calibrated and out.rule.threshold == own and out.rule.doubt is None
    assert list(out.verdict) == ["attack" if p >= own else "clean" for p in out.attack_probability]
    paths = [str(_png(tmp_path / f"v{k}.png", image)) for k, image in enumerate(images[:3])]
    code, text, _ = _rpod(monkeypatch, capsys, "predict", *paths, "--models", str(folder))
    assert code == 0 and text.splitlines()[0] == (
        f"verdict: attack at P(attack) >= {own!r} (the detector's own "
        f"threshold, no doubt level: {folder} has no defense.json, which "
        f"`rpod calibrate` writes)"
    )
    probs = np.sort(out.attack_probability)
    threshold, doubt = float(probs[-4]), float(probs[8])  # three levels, each reached by some image
    assert doubt < threshold and threshold != own
    levels = DefenseSettings(threshold=threshold, update_below=doubt)
    write_json(folder / "defense.json", defense_record(folder / "pose.pt", own, threshold=threshold, settings=levels))
    recorded = json.loads((folder / "defense.json").read_text())
    level, below = recorded["threshold"], recorded["settings"]["update_below"]
    calibrated = load_chain(folder).predict(images)
    assert calibrated.rule.calibrated and calibrated.rule.threshold == level and calibrated.rule.doubt == below
    want = ["attack" if p >= level else "doubt" if p >= below else "clean" for p in calibrated.attack_probability]
    assert list(calibrated.verdict) == want and set(want) == {"attack", "doubt", "clean"}
    assert list(calibrated.verdict) != list(out.verdict)  # the detector's own rule differs
    np.testing.assert_array_equal(calibrated.attack_flag, [w == "attack" for w in want])
    code, text, _ = _rpod(monkeypatch, capsys, "predict", *paths, "--json", "--models", str(folder))
    records = json.loads(text)
    assert [r["verdict"] for r in records] == want[:3]
    assert records[0]["threshold"] == level and records[0]["doubt_level"] == below
    assert records[0]["rule"] == "calibrated defense" and records[0]["rule_file"] == str(folder / "defense.json")
    code, text, _ = _rpod(monkeypatch, capsys, "predict", *paths, "--models", str(folder))
    assert text.splitlines()[0] == (
        f"verdict: attack at P(attack) >= {level!r}, doubt at >= {below!r} (the chain's "
        f"calibrated defense, {folder / 'defense.json'})"
    )
    assert [line.split()[-1] for line in text.splitlines()[3:]] == want[:3]


def test_track_gives_the_trusted_estimate_pl_and_availability_per_frame(models, tmp_path):
    from pipeline.defense.integrity import AlertLimitSettings, alert_limit

    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("pose.pt", "detector.pt"):
        (bare / name).write_bytes((models / name).read_bytes())
    n = 8
    images, still, camera = _images(n, seed=3), np.zeros((n, 3)), np.repeat(np.eye(3)[None], n, 0)
    with pytest.raises(Exception, match=r"defense.json not found"):
        load_chain(bare).track(images, still, camera)
    _calibrate(models)
    track = load_chain(models).track(images, still, camera)
    assert track.trusted.shape == (n, 3) and track.pl.shape == (n,) and track.available.dtype == bool
    assert np.isfinite(track.trusted).all() and np.isfinite(track.pl).all() and (track.pl > 0).all()
    rng = np.linalg.norm(track.trusted, axis=1)
    limit = alert_limit(rng, AlertLimitSettings())
    np.testing.assert_array_equal(track.available, (track.mode != "hold") & (track.pl <= limit))
    records = track.records()
    assert len(records) == n and records[0]["image"] == "array[0]" and len(records[0]["trusted_rel_m"]) == 3
    with pytest.raises(ValueError, match=r"commands \(N, 3\) and camera attitudes \(N, 3, 3\)"):
        load_chain(models).track(images, still[:3], camera)


def test_cli_motion_file_gives_one_row_per_frame_and_bad_files_one_line(models, tmp_path, monkeypatch, capsys):
    from rpodguard.sequence import MOTION_COLUMNS

    _calibrate(models)
    paths = [str(_png(tmp_path / f"f{k}.png", image)) for k, image in enumerate(_images(3, seed=4))]
    rows = [",".join(MOTION_COLUMNS)] + ["0,0,-0.1," + ",".join(map(str, np.eye(3).ravel()))] * 3
    (tmp_path / "motion.csv").write_text("\n".join(rows) + "\n")
    code, out, err = _rpod(
        monkeypatch,
        capsys,
        "predict",
        *paths,
        "--motion",
        str(tmp_path / "motion.csv"),
        "--json",
        "--models",
        str(models),
    )
    assert code == 0, err
    records = json.loads(out)
    assert [r["image"] for r in records] == paths and {"trusted_rel_m", "pl_m", "available", "flag", "mode"} <= set(
        records[0]
    )
    code, out, _ = _rpod(
        monkeypatch, capsys, "predict", *paths, "--motion", str(tmp_path / "motion.csv"), "--models", str(models)
    )
    assert code == 0 and "PL (m)" in out and "f2.png" in out
    (tmp_path / "short.csv").write_text("\n".join(rows[:3]) + "\n")
    (tmp_path / "cols.csv").write_text("u_x,u_y\n0,0\n")
    for name, message in (
        ("short.csv", "has 2 rows for 3 images"),
        ("cols.csv", "lacks the column(s) u_z"),
        ("none.csv", "none.csv not found"),
    ):
        code, out, err = _rpod(
            monkeypatch, capsys, "predict", *paths, "--motion", str(tmp_path / name), "--models", str(models)
        )
        assert code == 1 and out == "" and err.count("\n") == 1 and message in err, err

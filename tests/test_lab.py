import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.lab import (
    LabDataError,
    lab_to_synthetic_factor,
    lab_to_synthetic_position,
    match_frames,
    paper_lab_factor,
    relative_pose,
    synthetic_recording,
)
from pipeline.geometry.camera import Intrinsics, project, reference_intrinsics
from pipeline.geometry.rotations import euler_to_matrix, matrix_to_quat, quat_to_matrix
from pipeline.images import domain_shift, segment
from pipeline.pose.metrics import attitude_error_deg
from pipeline.seeds import run_base, seed_for
from stages.config.schema import Params, build

K_ZED = Intrinsics(1920, 1080, 1400.41, 1400.41, 956.29, 557.258)
K_SYN = reference_intrinsics()


def test_rescaling_keeps_the_apparent_size_of_the_target():
    k = lab_to_synthetic_factor(K_SYN, K_ZED, 9.0)
    assert k == pytest.approx(9 * 640 / (1400.41 / 4))
    # a 0.2 m wide mock-up edge seen at lab range d, image resized 1920 -> 480 ...
    K_lab = K_ZED.scaled(480, 270)
    for d in (1.0, 2.0, 3.122):
        lab_px = np.diff(project(np.array([[-0.1, 0, d], [0.1, 0, d]]), K_lab)[:, 0])[0]
        # ... has the same width in pixels as the 9x (1.8 m) target at the rescaled range
        z = d * k
        syn_px = np.diff(project(np.array([[-0.9, 0, z], [0.9, 0, z]]), K_SYN)[:, 0])[0]
        assert syn_px == pytest.approx(lab_px, rel=1e-9)
    # the factor does not depend on the size the two cameras are compared at
    assert lab_to_synthetic_factor(K_SYN.scaled(160, 90), K_ZED, 9.0) == pytest.approx(k)


def test_paper_factor_reproduces_the_printed_range_and_the_039_percent_gap():
    k, k_paper = lab_to_synthetic_factor(K_SYN, K_ZED, 9.0), paper_lab_factor(K_SYN, K_ZED, 9.0)
    assert 3.122 * k_paper == pytest.approx(51.18, abs=0.02)  # the paper's table, 3.122 m -> 51.18 m
    assert 3.122 * k == pytest.approx(51.36, abs=0.01)
    assert k / k_paper == pytest.approx(4 / (956.29 / 240)) and 100 * (k / k_paper - 1) == pytest.approx(
        0.39, abs=0.005
    )


def test_lab_report_shows_the_paper_ranges_beside_ours():
    from stages.pages.lab import paper_ranges

    text = paper_ranges(K_SYN, K_ZED, 9.0, lab_to_synthetic_factor(K_SYN, K_ZED, 9.0))
    row = next(line for line in text.splitlines() if line.startswith("| 3.122 "))
    assert [c.strip() for c in row.strip("|").split("|")] == ["3.122", "51.36", "0.19", "51.17", "51.18"]
    assert "0.39% shorter" in text
    # the paper's equation as printed gives 0.19 m; only its reciprocal gives the printed 51.18 m (issue 38)
    assert "applied to 3.122 m it gives 0.19 m" in text and "only its reciprocal" in text
    assert "only in rounding" not in text and "Only the 3.122 m row is printed" not in text


def test_rescaled_position_projects_to_the_same_pixel():
    t_lab = np.array([[0.05, -0.03, 2.4], [-0.1, 0.08, 1.2]])
    t_syn = lab_to_synthetic_position(t_lab, K_SYN, K_ZED, 9.0)
    np.testing.assert_allclose(project(t_syn, K_SYN), project(t_lab, K_ZED.scaled(480, 270)), atol=1e-9)
    np.testing.assert_allclose(t_syn[:, 2], t_lab[:, 2] * lab_to_synthetic_factor(K_SYN, K_ZED, 9.0))


def test_relative_pose_matches_the_camera_frame_label():
    rng = np.random.default_rng(0)
    R_cam = euler_to_matrix(rng.uniform(-90, 90, 3))
    R_tgt = euler_to_matrix(rng.uniform(-90, 90, 3))
    p_cam, p_tgt = rng.normal(size=3), rng.normal(size=3)
    t, q = relative_pose(p_cam, matrix_to_quat(R_cam), p_tgt, matrix_to_quat(R_tgt))
    # a target point x (target frame) is at p_tgt + R_tgt x in the world, and at R x + t in the camera
    x = rng.normal(size=3)
    world = p_tgt + R_tgt @ x
    np.testing.assert_allclose(R_cam.T @ (world - p_cam), quat_to_matrix(q) @ x + t, atol=1e-12)
    np.testing.assert_allclose(t, -R_cam.T @ (p_cam - p_tgt), atol=1e-12)  # d = p_cam - p_tgt (SPEC 9)


def _hand_made():
    """Two bodies at 120 Hz: camera moving along world x at 1.2 m/s, target still; frames at 30 fps."""
    ts = np.arange(0, 13) / 120.0
    rows = []
    for t in ts:
        rows.append([t, "cam", 1.2 * t, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        rows.append([t, "tgt", 0.0, 0.0, 3.0, 1.0, 0.0, 0.0, 0.0])
    mocap = pd.DataFrame(rows, columns=["timestamp", "body", "x", "y", "z", "qw", "qx", "qy", "qz"])
    camera = pd.DataFrame({"frame": [0, 1, 2, 3], "timestamp": [0.001, 0.034, 0.066, 0.099]})
    return camera, mocap


def test_timestamp_matching_nearest_and_interpolated():
    camera, mocap = _hand_made()
    frames, t, q = match_frames(camera, mocap, "cam", "tgt", "nearest", max_gap=0.005)
    assert frames.tolist() == [0, 1, 2, 3]
    nearest = np.round(camera.timestamp.to_numpy() * 120) / 120
    np.testing.assert_allclose(t[:, 0], -1.2 * nearest)  # t = R^T (p_tgt - p_cam)
    np.testing.assert_allclose(t[:, 2], 3.0)
    _, t_i, q_i = match_frames(camera, mocap, "cam", "tgt", "interpolate", max_gap=0.005)
    np.testing.assert_allclose(t_i[:, 0], -1.2 * camera.timestamp.to_numpy(), atol=1e-12)
    assert np.all(attitude_error_deg(q_i, [1, 0, 0, 0]) < 1e-6)


def test_interpolation_slerps_the_attitude():
    ts = np.array([0.0, 1 / 120])
    qz90 = matrix_to_quat(euler_to_matrix([0, 0, 90]))
    mocap = pd.DataFrame(
        [
            [ts[0], "cam", 0, 0, 0, 1, 0, 0, 0],
            [ts[0], "tgt", 0, 0, 1, 1, 0, 0, 0],
            [ts[1], "cam", 0, 0, 0, 1, 0, 0, 0],
            [ts[1], "tgt", 0, 0, 1, *qz90],
        ],
        columns=["timestamp", "body", "x", "y", "z", "qw", "qx", "qy", "qz"],
    )
    camera = pd.DataFrame({"frame": [0], "timestamp": [0.25 / 120]})
    _, _, q = match_frames(camera, mocap, "cam", "tgt", "interpolate", max_gap=0.01)
    assert attitude_error_deg(q, [1, 0, 0, 0])[0] == pytest.approx(22.5, abs=1e-6)


def test_bad_mocap_and_camera_tables_name_the_line():
    camera, mocap = _hand_made()
    swapped = mocap.copy()
    swapped.iloc[[4, 6]] = swapped.iloc[[6, 4]].to_numpy()  # rows of body 'cam' out of order
    with pytest.raises(LabDataError, match=r"mocap.csv line 8: body 'cam'.*time order"):
        match_frames(camera, swapped, "cam", "tgt", "nearest", 0.005)
    with pytest.raises(LabDataError, match=r"no rows for body 'chaser'"):
        match_frames(camera, mocap, "chaser", "tgt", "nearest", 0.005)
    late = camera.copy()
    late.loc[3, "timestamp"] = 0.5
    with pytest.raises(LabDataError, match=r"camera.csv line 5: no mocap sample of body 'cam' within 0.005 s"):
        match_frames(late, mocap, "cam", "tgt", "nearest", 0.005)
    with pytest.raises(LabDataError, match=r"mocap.csv: missing column"):
        match_frames(camera, mocap.drop(columns="qz"), "cam", "tgt", "nearest", 0.005)
    text = mocap.astype(object)
    text.loc[3, "x"] = "oops"
    with pytest.raises(LabDataError, match=r"mocap.csv line 5: column 'x' is not a number"):
        match_frames(camera, text, "cam", "tgt", "nearest", 0.005)


def test_synthetic_recording_matches_back_to_its_labels():
    q_label = matrix_to_quat(euler_to_matrix([3.0, -5.0, 8.0]))
    rec = synthetic_recording(3.1, 2.6, 40, 30.0, 120.0, q_label, lateral=(0.02, -0.01))
    assert len(rec.camera) == 40 and set(rec.mocap.body) == {"camera", "target"}
    assert np.all(np.diff(rec.mocap[rec.mocap.body == "camera"].timestamp) == pytest.approx(1 / 120))
    speed = (3.1 - 2.6) / (39 / 30)  # lab m/s
    for mode, tol in (("nearest", speed * 0.5 / 120 * 1.001), ("interpolate", 1e-9)):
        frames, t, q = match_frames(rec.camera, rec.mocap, "camera", "target", mode, max_gap=0.01)
        assert np.abs(t - rec.t).max() <= tol
        assert attitude_error_deg(q, rec.q).max() < 1e-5


def test_segmentation_and_domain_shift():
    img = np.zeros((10, 12, 3), np.uint8)
    img[2:5, 3:7] = 200
    img[8, 1] = 10  # faint noise on the background
    seg = segment(img, threshold=0.08)
    assert seg[8, 1].sum() == 0 and np.array_equal(seg[2:5, 3:7], img[2:5, 3:7])
    mask = np.zeros((10, 12), np.uint8)
    mask[2:4, 3:7] = 255
    seg_m = segment(img, mask)
    assert seg_m[4, 3].sum() == 0 and seg_m[2, 3].sum() > 0
    rng = np.random.default_rng(0)
    shifted = domain_shift(img, noise_std=0.02, blur_sigma=0.8, rng=rng)
    assert shifted.dtype == np.uint8 and shifted.shape == img.shape
    assert not np.array_equal(shifted, img)
    assert abs(float(shifted.astype(float).mean()) - float(img.astype(float).mean())) < 3.0


def test_loader_round_trips_a_synthetic_lab_recording(tmp_path):
    from pipeline.formats.recordings import read_recording, write_recording
    from pipeline.io.errors import DataError

    rec = synthetic_recording(1.6, 1.0, 12, 30.0, 120.0, np.array([1.0, 0, 0, 0]), lateral=(0.01, 0.0))
    rng = np.random.default_rng(0)
    images = rng.integers(0, 20, (12, 36, 64, 3), dtype=np.uint8)  # dark, noisy background
    images[:, 10:26, 20:44] = rng.integers(120, 256, (12, 16, 24, 3), dtype=np.uint8)  # the target
    masks = np.zeros((12, 36, 64), np.uint8)
    masks[:, 10:26, 20:44] = 255
    write_recording(tmp_path / "seq", rec.camera, rec.mocap, images, masks)
    bodies = {"camera": "camera", "target": "target"}
    got = read_recording(tmp_path / "seq", 32, 18, bodies, "interpolate", 0.01, 0.08)
    assert got["images"].shape == (12, 18, 32, 3) and got["frames"].tolist() == list(range(12))
    np.testing.assert_allclose(got["t_lab"], rec.t, atol=2e-6)  # CSVs keep 6 decimals
    assert attitude_error_deg(got["q"], rec.q).max() < 1e-3
    assert got["images"][:, :4].max() == 0  # background segmented to black
    assert got["images"][:, 6:12, 11:21].min() > 0
    # without masks the grey-level threshold segments it the same way here
    (tmp_path / "seq" / "masks" / "000003.png").unlink()
    with pytest.raises(DataError, match=r"masks/000003.png cannot be read as a mask \(camera.csv line 5\)"):
        read_recording(tmp_path / "seq", 32, 18, bodies, "nearest", 0.01, 0.08)
    for f in (tmp_path / "seq" / "masks").iterdir():
        f.unlink()
    (tmp_path / "seq" / "masks").rmdir()
    thr = read_recording(tmp_path / "seq", 32, 18, bodies, "interpolate", 0.01, 0.1)
    assert thr["images"][:, :4].max() == 0
    (tmp_path / "seq" / "images" / "000007.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match=r"images/000007.png cannot be read as an image \(camera.csv line 9\)"):
        read_recording(tmp_path / "seq", 32, 18, bodies, "nearest", 0.01, 0.08)
    with pytest.raises(DataError, match="no rows for body 'drone'"):
        read_recording(tmp_path / "seq", 32, 18, {"camera": "drone", "target": "target"}, "nearest", 0.01, 0.08)


def test_rescale_command_prints_the_synthetic_range(monkeypatch):
    from pathlib import Path

    from typer.testing import CliRunner

    from stages.lab import app

    monkeypatch.chdir(Path(__file__).resolve().parent.parent)  # the committed params.yaml
    out = CliRunner().invoke(app, ["rescale", "--z", "3.122"])
    assert out.exit_code == 0, out.output
    k = lab_to_synthetic_factor(K_SYN, K_ZED, 9.0)
    assert f"synthetic z = {3.122 * k:.2f} m" in out.output


def stand_in_models(p):
    """Untrained stand-ins for both chains (in the current folder): models/pose.pt and models/detector.pt (the
    standard model), models/pose_robust.pt (with the black-level clamp) and models/detector_robust.pt."""
    import torch

    from pipeline.detectors.lstm import LSTMConfig, LSTMDetector, to_checkpoint
    from pipeline.formats.models import save_pose
    from pipeline.io.atomic import file_hash
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    torch.manual_seed(0)
    h, w = p.render.height, p.render.width
    for suffix, black_level in (("", 0.0), ("_robust", float(p.train.adversarial.black_level))):
        model = PoseNet(width=p.train.width, dropout=p.train.dropout, black_level=black_level).eval()
        model.set_output_bias((0.0, 0.0, 30.0), (1, 0, 0, 0, 1, 0))
        save_pose(f"models/pose{suffix}.pt", model, PoseLoss(), (h, w), {})
        with torch.no_grad():
            feats = model.forward_features(torch.rand(8, 3, h, w))
        det = LSTMDetector(LSTMConfig(hidden=8, dense=[4]))
        det.set_normalisation((feats - feats.mean(0)).unsqueeze(1).repeat(1, 9, 1).numpy())
        torch.save(
            to_checkpoint(
                det,
                {
                    "format": "rpodguard-detector/1",
                    "pose_model_hash": file_hash(f"models/pose{suffix}.pt"),
                    "background_mean": feats.mean(0),
                    "background_size": 8,
                    "shap_method": "exact",
                },
            ),
            f"models/detector{suffix}.pt",
        )


@pytest.mark.slow
def test_evaluate_and_lab_stages_end_to_end(tmp_path, monkeypatch):
    """eval_render -> evaluate -> lab on the smoke profile with stand-in pose and detector checkpoints."""
    import json

    from typer.testing import CliRunner

    from stages.artifacts.readers import read_eval_render
    from stages.cli import app
    from stages.config import params as params_mod

    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke", ["evaluate.frames=12", "lab.frames=6", "evaluate.eps=[0.5,0.05]"])
    params_mod.write_params(p)
    stand_in_models(build(p))
    runner = CliRunner()
    out = runner.invoke(app, ["evaluate"])
    assert out.exit_code != 0 and "eval_render" in str(out.exception)  # renders not there yet
    assert runner.invoke(app, ["eval_render"]).exit_code == 0
    out = runner.invoke(app, ["evaluate"])
    assert out.exit_code != 0 and "not found" in str(out.exception) and "calibrate" in str(out.exception)
    for args in (["calibrate", "--model", "standard"], ["calibrate"], ["evaluate"], ["lab_models"], ["lab"]):
        out = runner.invoke(app, args)
        assert out.exit_code == 0, (args, out.output, out.exception)
    cal = json.loads((tmp_path / "models/defense.json").read_text())
    assert cal["validation"]["frames"] == 2 * 12 and cal["validation"]["seed"] == run_base(p["seed"], "validation")
    ev = json.loads((tmp_path / "reports/metrics/evaluate.json").read_text())
    assert set(ev["per_eps"]) == {"0.5", "0.05"} and len(ev["rows"]) == 2
    assert set(ev["fused"]["per_eps"]) == {"0.5", "0.05"} and ev["fused"]["per_eps"]["0.5"]["tpr"]["n"] > 0
    assert (tmp_path / "reports/figures/timeline.png").stat().st_size > 1000
    assert "| 0.5 " in (tmp_path / "reports/integrated.md").read_text()
    held = ev["black_level_heldout"]  # the clamp's check on the black-background evaluation frames (fewer than 200)
    _, poses, _ = read_eval_render(params_mod.load())
    black = int((poses["background"] == "black").sum()) if "background" in poses else len(poses)
    assert 0 < black < p["evaluate"]["trajectories"] * 12 and held["images"] == black  # smoke renders a share over sky
    assert held["threshold"] == p["train"]["adversarial"]["black_level"]
    assert "## Held-out check of the black-level clamp" in (tmp_path / "reports/integrated.md").read_text()
    lab = json.loads((tmp_path / "reports/metrics/lab.json").read_text())
    assert lab["factor"] == pytest.approx(9 * 640 / (1400.41 / 4))
    assert max(v["position_max_m"] for v in lab["loader_error"].values()) < 1e-3  # lab metres
    seq = tmp_path / "datasets/lab/seq1"
    assert len(list((seq / "images").glob("*.png"))) == 6 and (seq / "mocap.csv").exists()
    assert lab["reused_models"] and lab["models"]["pose"] == "models/pose.pt" and lab["synthetic_lab"] is None
    assert "## Models: reused" in (tmp_path / "reports/lab.md").read_text()
    # other eps must not re-render: the cached renders are reused as long as their params hold
    params_mod.write_params(params_mod.compose("smoke", ["evaluate.frames=12", "lab.frames=6", "evaluate.eps=[0.3]"]))
    assert runner.invoke(app, ["evaluate"]).exit_code == 0
    params_mod.write_params(params_mod.compose("smoke", ["evaluate.frames=13", "lab.frames=6"]))
    out = runner.invoke(app, ["evaluate"])
    assert out.exit_code != 0 and "rendered with other params" in str(out.exception)


@pytest.mark.slow
def test_lab_stage_retrains_a_synthetic_lab_pose_model_and_detector(tmp_path, monkeypatch):
    """lab.retrain=always on a tiny smoke set: `rpod lab_models` runs render, label, train, shap, detect in
    datasets/lab_models/, then the lab evaluation runs with those models, not the main stand-ins."""
    import json

    import torch
    from typer.testing import CliRunner

    from pipeline.io.atomic import file_hash
    from stages.cli import app
    from stages.config import params as params_mod

    monkeypatch.chdir(tmp_path)
    p = params_mod.compose(
        "smoke",
        [
            "lab.retrain=always",
            "lab.frames=4",
            "lab.train_frames_per_sequence=3",
            "evaluate.eps=[0.5]",
            "attack.eps=[0.5]",
            "shap.normal=12",
            "shap.per_eps=6",
            "shap.eps=[0.5]",
            "shap.background=4",
            "detect.epochs=2",
        ],
    )
    params_mod.write_params(p)
    stand_in_models(build(p))
    main_hash = file_hash("models/pose.pt")
    threads = torch.get_num_threads()
    out = CliRunner().invoke(app, ["lab"])
    assert out.exit_code != 0 and "lab_models" in str(out.exception)  # not trained yet
    for args in (["eval_render"], ["calibrate"], ["lab_models"], ["lab"]):  # lab reads the shipped chain's threshold
        out = CliRunner().invoke(app, args)
        assert out.exit_code == 0, (args, out.output, out.exception)
    assert torch.get_num_threads() == threads
    sub = tmp_path / "datasets/lab_models"
    lab = json.loads((tmp_path / "reports/metrics/lab.json").read_text())
    assert not lab["reused_models"] and lab["retrain_reason"] == "lab.retrain is always"
    assert lab["model_hash"] == file_hash(sub / "models/pose.pt") != main_hash
    assert lab["models"] == {
        "pose": "datasets/lab_models/models/pose.pt",
        "detector": "datasets/lab_models/models/detector.pt",
    }
    det = torch.load(sub / "models/detector.pt", weights_only=True)
    assert det["pose_model_hash"] == lab["model_hash"]
    s = lab["synthetic_lab"]
    assert s["images"] == 13 * 3 and s["size"] == [64, 36] and s["mesh"] is None and s["mesh_scale"] == 1.0
    assert s["seed"] == seed_for(p["lab"]["seed"], "lab_models") and set(s["seconds"]) == {
        "render",
        "label",
        "train",
        "detect_render",
        "shap",
        "detect",
    }
    sub_p = params_mod.load(sub / "params.yaml")  # the same recipe; only the data differ
    assert sub_p.train == build(p).train and sub_p.detect.baselines == []
    assert sub_p.render.frames_per_sequence == 3 and sub_p.render.width == 64
    assert (sub / "reports/pose.md").exists() and (sub / "datasets/shap.zarr").is_dir()
    assert (tmp_path / "datasets/lab/seq1/camera.csv").exists()  # the lab recordings
    text = (tmp_path / "reports/lab.md").read_text()
    assert "## Models: retrained on a synthetic-lab set" in text and lab["model_hash"] in text
    assert "datasets/lab_models/models/detector.pt" in text and "not the main models/pose.pt" in text
    assert "the synthetic-lab model" in text
    assert not (tmp_path / "reports/metrics/train.json").exists()  # the main reports are untouched


@pytest.mark.parametrize(
    "edit, message",
    [
        ({"retrain": "sometimes"}, r"lab.retrain must be one of auto, always, got 'sometimes'"),
        ({"train_frames_per_sequence": 1}, "lab: train_frames_per_sequence must be null or a whole number >= 2"),
        ({"mesh_scale": 0.0}, "lab: scale and mesh_scale must be > 0"),
        ({"sequences": [[1.6, -1.0]]}, r"lab: sequences: each entry must be \[z_start, z_end\] in metres > 0"),
    ],
)
def test_bad_lab_params_are_refused(edit, message):
    from stages.config import params as params_mod
    from stages.config.sections import ParamsError

    p = params_mod.compose("default")
    p["lab"].update(edit)
    with pytest.raises(ParamsError, match=message):
        build(p)


def test_when_the_lab_stage_retrains(tmp_path, monkeypatch):
    from stages.config import params as params_mod
    from stages.config.build import retrain_reason
    from stages.errors import StageError
    from stages.lab_models import sub_params

    def typed(profile: str, overrides: list[str] | None = None) -> Params:
        return build(params_mod.compose(profile, overrides))

    monkeypatch.chdir(tmp_path)
    assert retrain_reason(typed("default")) is None  # default: the main target, reused
    assert retrain_reason(typed("paper")) == "lab.retrain is always"
    (tmp_path / "mockup.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    other = typed("default", ["lab.mesh=mockup.obj", "lab.mesh_scale=0.001"])
    assert "is not the main target" in retrain_reason(other)  # another mock-up: retrain
    sub = sub_params(other)
    assert sub.render.mesh == str(tmp_path / "mockup.obj") and sub.render.mesh_scale == pytest.approx(0.009)
    same = typed("default", ["render.mesh=mockup.obj", "render.mesh_scale=9", "lab.mesh=mockup.obj"])
    assert retrain_reason(same) is None  # the main mesh, built at 1/9
    with pytest.raises(StageError, match="lab.mesh: mock-up mesh file missing.obj not found"):
        retrain_reason(typed("default", ["lab.mesh=missing.obj"]))


def test_a_failing_retrain_step_is_one_clear_error(tmp_path, monkeypatch):
    from pathlib import Path

    from stages import lab_models
    from stages.config import params as params_mod
    from stages.engine import subrun
    from stages.errors import StageError

    def run_step(args: list[str], folder: Path) -> None:
        assert args == ["render"] and (folder / "params.yaml").exists()  # the step runs in the synthetic-lab folder
        raise StageError("params.yaml render: boom")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(subrun, "run_step", run_step)
    with pytest.raises(
        StageError,
        match=r"^lab.retrain \(render on the synthetic-lab set in final/\): params.yaml "
        r"render: boom$",
    ):
        lab_models.retrain(build(params_mod.compose("smoke", ["lab.retrain=always"])), tmp_path / "sub", Path("final"))
    assert Path.cwd() == tmp_path

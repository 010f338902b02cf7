"""`rpod lab`: the lab domain (SPEC 9); `rpod lab rescale --z Z`: lab range -> synthetic range.

`rpod lab` renders lab-like sequences (the ZED camera's geometry, the mock-up at 9x scale, a domain
shift: other sun, sensor blur and noise, a small calibration error), writes each one as a real lab
recording would be stored, reads it back through the real-data loader, and evaluates the pose
model and the safety chain on it: reports/lab.md, reports/metrics/lab.json. With `lab.real_data`
set to a folder, the same evaluation runs on that recording instead.

Models: with `lab.retrain: auto` and the main target as the mock-up, the main models/pose.pt and
models/detector.pt (SPEC 9 allows it); with `lab.retrain: always`, or another mock-up in `lab.mesh`,
a pose model and detector trained first on a synthetic-lab set in datasets/lab/synthetic_lab/
(stages/lab_models.py). The report and metrics (`reused_models`, `models`) say which were used.

Lab recording layout (one folder per sequence; a folder of such folders also works):

    images/000000.png ...     one image per camera frame, any size with the ZED's 16:9 aspect
    masks/000000.png ...      optional: nonzero = target; else a grey-level threshold segments it
    camera.csv                frame,timestamp            (s; optional column `image` = file name,
                              default {frame:06d}.png)
    mocap.csv                 timestamp,body,x,y,z,qw,qx,qy,qz   (s, m, body -> world quaternion)

e.g. camera.csv `0,0.0013` and mocap.csv `0.0000,camera,1.5,0.4,4.3,0.5,-0.5,0.5,-0.5`. The bodies
`lab.bodies.camera` and `lab.bodies.target` must be present; see pipeline/lab.py for the frames.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod
from stages.io import StageError, atomic_dir, atomic_write_text, file_hash, read_json, write_metrics

OUT = Path("datasets/lab")
REPORT = Path("reports/lab.md")
METRICS = Path("reports/metrics/lab.json")
TRAIN_METRICS = Path("reports/metrics/train.json")
MAIN_POSE = Path("models/pose.pt")
MAIN_DETECTOR = Path("models/detector.pt")
SEED_OFFSET = 0
PAPER_ACCURACY = {0.5: 100.0, 0.3: 100.0, 0.1: 100.0, 0.05: 98.44, 0.01: 90.44}
PAPER_AVERAGE = 96.29

app = typer.Typer(help="The lab domain (SPEC 9): lab-like sequences through the real-data loader, pose "
                       "error, FGSM errors and integrated detection; `rpod lab rescale` converts ranges.",
                  pretty_exceptions_enable=False, add_completion=False)


def cameras(p: dict[str, Any]) -> tuple[Any, Any]:
    """(K_syn at the reference size (480x270), K_zed at 1920x1080) from params."""
    from pipeline.camera import Intrinsics

    c, z = p["camera"], p["lab"]["zed"]
    try:
        return (Intrinsics(int(c["ref_width"]), int(c["ref_height"]), c["fx"], c["fy"], c["cx"], c["cy"]),
                Intrinsics(int(z["width"]), int(z["height"]), z["fx"], z["fy"], z["cx"], z["cy"]))
    except ValueError as e:
        raise StageError(f"params.yaml camera / lab.zed: {e}") from None


@app.command("rescale")
def rescale(z: list[float] = typer.Option(..., "--z", help="Lab range(s) in metres (repeatable).")) -> None:
    """Print the equivalent synthetic range of lab ranges (same apparent size in pixels; pinhole model)."""
    from pipeline.lab import lab_to_synthetic_factor

    p = params_mod.load()
    K_syn, K_zed = cameras(p)
    scale = float(p["lab"]["scale"])
    k = lab_to_synthetic_factor(K_syn, K_zed, scale)
    f_eff = K_zed.fx * K_syn.width / K_zed.width
    typer.echo(f"factor = scale * fx_syn / fx_lab_eff = {scale:g} * {K_syn.fx:g} / ({K_zed.fx:g} * "
               f"{K_syn.width}/{K_zed.width} = {f_eff:.2f}) = {k:.4f}")
    for zi in z:
        if zi <= 0:
            raise StageError(f"--z must be a positive range in metres, got {zi}")
        typer.echo(f"lab z = {zi:g} m -> synthetic z = {zi * k:.2f} m")


# ----------------------------------------------------------------------------- recordings on disk
def write_recording(folder: Path, camera: Any, mocap: Any, images: np.ndarray, masks: np.ndarray | None) -> None:
    """Write one recording in the lab layout (PNG images, optional masks, camera.csv, mocap.csv)."""
    import cv2

    (folder / "images").mkdir(parents=True, exist_ok=True)
    if masks is not None:
        (folder / "masks").mkdir(exist_ok=True)
    for k, frame in enumerate(camera["frame"].to_numpy()):
        name = f"{int(frame):06d}.png"
        if not cv2.imwrite(str(folder / "images" / name), images[k][..., ::-1]):
            raise StageError(f"could not write {folder / 'images' / name}")
        if masks is not None and not cv2.imwrite(str(folder / "masks" / name), masks[k]):
            raise StageError(f"could not write {folder / 'masks' / name}")
    camera.to_csv(folder / "camera.csv", index=False, float_format="%.6f")
    mocap.to_csv(folder / "mocap.csv", index=False, float_format="%.6f")


def recording_folders(root: Path) -> list[Path]:
    """`root` itself when it holds camera.csv, else its subfolders that do (sorted)."""
    if not root.is_dir():
        raise StageError(f"lab recording folder {root} not found")
    if (root / "camera.csv").exists():
        return [root]
    subs = sorted(d for d in root.iterdir() if d.is_dir() and (d / "camera.csv").exists())
    if not subs:
        raise StageError(f"{root} holds no lab recording (no camera.csv in it or its subfolders)")
    return subs


def read_recording(folder: Path, width: int, height: int, bodies: dict[str, str], match: str, max_gap: float,
                   threshold: float) -> dict[str, Any]:
    """Load one recording: segmented images resized to width x height (uint8), frames, lab labels t, q.

    Every problem is a StageError naming the file (and line for the CSVs).
    """
    import cv2
    import pandas as pd

    from pipeline.lab import LabDataError, match_frames, resize, segment

    tables = {}
    for name in ("camera.csv", "mocap.csv"):
        path = folder / name
        if not path.exists():
            raise StageError(f"{path} not found (a lab recording needs images/, camera.csv and mocap.csv)")
        try:
            tables[name] = pd.read_csv(path)
        except Exception as e:
            raise StageError(f"{path} is not a readable CSV ({type(e).__name__}: {e})") from None
    try:
        frames, t, q = match_frames(tables["camera.csv"], tables["mocap.csv"], bodies["camera"], bodies["target"],
                                    match, max_gap, str(folder / "camera.csv"), str(folder / "mocap.csv"))
    except LabDataError as e:
        raise StageError(str(e)) from None
    cam = tables["camera.csv"]
    names = (cam["image"].astype(str).tolist() if "image" in cam.columns else [f"{int(f):06d}.png" for f in frames])
    images = np.zeros((len(frames), height, width, 3), np.uint8)
    for k, name in enumerate(names):
        where = f"(camera.csv line {k + 2})"
        bgr = cv2.imread(str(folder / "images" / name), cv2.IMREAD_COLOR)
        if bgr is None:
            raise StageError(f"{folder / 'images' / name} cannot be read as an image {where}")
        h, w = bgr.shape[:2]
        if abs(w / h - width / height) > 0.01 * width / height:
            raise StageError(f"{folder / 'images' / name} is {w}x{h}; the lab images must have the model input's "
                             f"aspect {width}:{height} {where}")
        mask = None
        mpath = folder / "masks" / name
        if (folder / "masks").is_dir():
            mask = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise StageError(f"{mpath} cannot be read as a mask {where}")
            if mask.shape != (h, w):
                raise StageError(f"{mpath} is {mask.shape[1]}x{mask.shape[0]}, its image {w}x{h} {where}")
        images[k] = resize(segment(bgr[..., ::-1], mask, threshold), width, height)
    return {"name": folder.name, "frames": frames, "images": images, "t_lab": t, "q": q}


# ----------------------------------------------------------------------------- synthetic lab sequences
def render_lab(p: dict[str, Any], dest: Path) -> list[dict[str, Any]]:
    """Render lab.sequences with the lab camera and the domain shift into dest/<seq>/ (lab layout).

    Returns per sequence the exact lab labels (for checking the loader round trip).
    """
    from tqdm import tqdm

    from pipeline.lab import domain_shift, synthetic_recording
    from pipeline.rotations import quat_to_matrix
    from pipeline.scene import Renderer
    from stages.lab_models import mockup
    from stages.render import scene_settings

    lab, r = p["lab"], p["render"]
    ds = lab["domain_shift"]
    _, K_zed = cameras(p)
    k_cal = 1.0 + float(ds["calib_error"])       # the true lens differs from the calibration used for labels
    K_lab = K_zed.scaled(int(r["width"]), int(r["height"]))
    K_true = dataclasses.replace(K_lab, fx=K_lab.fx * k_cal, fy=K_lab.fy * k_cal)
    mesh, mesh_scale = mockup(p)                  # the mock-up at scale x its size (= the real target's size)
    settings = dataclasses.replace(scene_settings(r), mesh=mesh, mesh_scale=mesh_scale,
                                   sun_direction=tuple(float(v) for v in ds["sun_direction"]),
                                   sun_strength=float(ds["sun_strength"]))
    rng = np.random.default_rng(int(lab["seed"]) + SEED_OFFSET)
    scale = float(lab["scale"])
    n = int(lab["frames"])
    renderer = Renderer(K_true, settings)
    truth = []
    try:
        with tqdm(total=n * len(lab["sequences"]), desc="lab render", unit="img", dynamic_ncols=True) as bar:
            for i, (z0, z1) in enumerate(lab["sequences"]):
                lateral = tuple(rng.uniform(-0.03, 0.03, 2) * float(z1))   # lab m, target off-centre
                rec = synthetic_recording(float(z0), float(z1), n, float(lab["fps"]), float(lab["mocap_hz"]),
                                          np.array([1.0, 0, 0, 0]), lateral=lateral,
                                          clock_offset=float(rng.uniform(0, 1 / float(lab["mocap_hz"]))),
                                          camera_body=lab["bodies"]["camera"], target_body=lab["bodies"]["target"])
                images = np.zeros((n, K_true.height, K_true.width, 3), np.uint8)
                masks = np.zeros((n, K_true.height, K_true.width), np.uint8)
                for k in range(n):
                    # the 1/scale mock-up at t equals the full-size target at scale * t
                    rgb, alpha = renderer.render_with_alpha(quat_to_matrix(rec.q[k]), scale * rec.t[k])
                    images[k] = domain_shift(rgb, float(ds["noise_std"]), float(ds["blur_sigma"]), rng)
                    masks[k] = np.where(alpha > 0.5, 255, 0)
                    bar.update(1)
                write_recording(dest / f"seq{i + 1}", rec.camera, rec.mocap, images, masks)
                truth.append({"name": f"seq{i + 1}", "t_lab": rec.t, "q": rec.q, "z_range": (float(z0), float(z1))})
    finally:
        renderer.close()
    return truth


# ----------------------------------------------------------------------------- the stage
def check_params(lab: dict[str, Any]) -> None:
    """Refuse bad `lab` params before any work, naming the key."""
    if lab["retrain"] not in ("auto", "always"):
        raise StageError(f"params.yaml lab.retrain must be auto or always, got {lab['retrain']!r}")
    n = lab["train_frames_per_sequence"]
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 2):
        raise StageError(f"params.yaml lab.train_frames_per_sequence must be null or a whole number >= 2, got {n!r}")
    if float(lab["mesh_scale"]) <= 0 or float(lab["scale"]) <= 0:
        raise StageError(f"params.yaml lab: scale and mesh_scale must be > 0, got {lab['scale']} and "
                         f"{lab['mesh_scale']}")
    if lab["match"] not in ("nearest", "interpolate"):
        raise StageError(f"params.yaml lab.match must be nearest or interpolate, got {lab['match']!r}")
    if float(lab["max_gap_s"]) <= 0 or int(lab["frames"]) < 2 or int(lab["attack_length"]) < 1:
        raise StageError("params.yaml lab: need max_gap_s > 0, frames >= 2 and attack_length >= 1")
    for z in lab["sequences"]:
        if len(z) != 2 or min(float(v) for v in z) <= 0:
            raise StageError(f"params.yaml lab.sequences: each entry must be [z_start, z_end] in metres > 0, got {z}")


@app.callback(invoke_without_command=True)
def main(ctx: typer.Context) -> None:
    """Evaluate the pose model and the safety chain in the lab domain (SPEC 9).

    Params: `lab` (sequences, frames, fps, mocap_hz, match, max_gap_s, attack_length, domain_shift,
    real_data, ...), `evaluate.p_start` / `evaluate.eps` for the integrated evaluation, `attack.eps`
    for the FGSM error table.
    """
    if ctx.invoked_subcommand is not None:
        return
    import torch

    from pipeline.lab import lab_to_synthetic_factor, lab_to_synthetic_position
    from pipeline.rotations import attitude_error_deg, quat_to_6d
    from pipeline.schedule import attack_schedule
    from pipeline.training import pose_errors
    from stages.evaluate import evaluate_sequences, fgsm_attack, load_chain, nan_to_none, per_eps_summary
    from stages.lab_models import SUBDIR, retrain, retrain_reason, working_dir

    p = params_mod.load()
    lab, r = p["lab"], p["render"]
    check_params(lab)
    torch.set_num_threads(2)
    K_syn, K_zed = cameras(p)
    scale = float(lab["scale"])
    factor = lab_to_synthetic_factor(K_syn, K_zed, scale)
    reason = retrain_reason(p)
    if reason is None:                             # fail early when the main models are missing
        chain, loss_fn, model_hash = load_chain(p)
    elif lab["real_data"]:
        recording_folders(Path(lab["real_data"]))   # likewise for a missing recording, before training
    t0 = time.perf_counter()
    truth: list[dict[str, Any]] = []
    synthetic_lab: dict[str, Any] | None = None
    source = Path(lab["real_data"]) if lab["real_data"] else OUT
    if reason is not None or not lab["real_data"]:
        with atomic_dir(OUT) as tmp:
            if not lab["real_data"]:
                truth = render_lab(p, tmp)
            if reason is not None:
                typer.echo(f"lab: retraining the pose model and detector on a synthetic-lab set ({reason})")
                synthetic_lab = retrain(p, tmp / SUBDIR, OUT / SUBDIR)
    render_s = time.perf_counter() - t0
    if synthetic_lab is not None:
        torch.set_num_threads(2)
        with working_dir(OUT / SUBDIR):            # load_chain reads models/pose.pt and models/detector.pt
            chain, loss_fn, model_hash = load_chain(p)
        render_s -= sum(synthetic_lab["seconds"].values())
    recs = [read_recording(f, int(r["width"]), int(r["height"]), lab["bodies"], lab["match"], float(lab["max_gap_s"]),
                           float(lab["segment_threshold"])) for f in recording_folders(source)]
    loader_err = {}
    for tr in truth:      # the loader's labels against the exact ones the images were rendered at
        rec = next(x for x in recs if x["name"] == tr["name"])
        loader_err[tr["name"]] = {"position_max_m": float(np.abs(rec["t_lab"] - tr["t_lab"]).max()),
                                  "attitude_max_deg": float(attitude_error_deg(rec["q"], tr["q"]).max())}
    e = p["evaluate"]
    eps_att = [float(x) for x in p["attack"]["eps"]]
    length = int(lab["attack_length"])
    sequences, ranges, clean_rows, fgsm_rows = [], [], [], []
    for i, rec in enumerate(recs):
        t_syn = lab_to_synthetic_position(rec["t_lab"], K_syn, K_zed, scale)
        targets = np.concatenate([t_syn, quat_to_6d(rec["q"])], 1).astype(np.float32)
        sequences.append({"name": rec["name"], "images": rec["images"], "targets": targets,
                          "attacked": attack_schedule(len(targets), float(e["p_start"]), length,
                                                      int(lab["seed"]) + 31 + i)})
        zl = rec["t_lab"][:, 2]
        ranges.append({"sequence": rec["name"], "frames": len(zl), "lab z start (m)": float(zl[0]),
                       "lab z end (m)": float(zl[-1]), "synthetic z start (m)": float(t_syn[0, 2]),
                       "synthetic z end (m)": float(t_syn[-1, 2])})
    # pose error (clean) and FGSM errors on every lab frame
    for s in sequences:
        x = torch.from_numpy(s["images"]).permute(0, 3, 1, 2).float() / 255.0
        y = torch.from_numpy(s["targets"])
        batch = int(e["batch_size"])
        preds = {"clean": np.concatenate([chain.pose_only(x[i:i + batch]).numpy() for i in range(0, len(x), batch)])}
        for eps in eps_att:
            attack = fgsm_attack(chain.model, loss_fn, eps)
            preds[eps] = np.concatenate([chain.pose_only(attack(x[i:i + batch], y[i:i + batch])).numpy()
                                         for i in range(0, len(x), batch)])
        for key, pred in preds.items():
            pos, att = pose_errors(pred, s["targets"])
            row = {"sequence": s["name"], "eps": key, "position_m": float(pos.mean()),
                   "relative_position": float(np.mean(pos / np.linalg.norm(s["targets"][:, :3], axis=1))),
                   "attitude_deg": float(att.mean())}
            (clean_rows if key == "clean" else fgsm_rows).append(row)
    res = evaluate_sequences(chain, loss_fn, sequences, [float(x) for x in e["eps"]], length, int(e["batch_size"]),
                             "lab evaluate")
    summary = per_eps_summary(res["rows"])
    seconds = time.perf_counter() - t0
    train_path = TRAIN_METRICS if synthetic_lab is None else OUT / SUBDIR / TRAIN_METRICS
    train_metrics = read_json(train_path) if train_path.exists() else None
    models = ({"pose": str(MAIN_POSE), "detector": str(MAIN_DETECTOR)} if synthetic_lab is None else
              {"pose": synthetic_lab["pose"], "detector": synthetic_lab["detector"]})
    metrics = {"model_hash": model_hash, "source": str(source), "synthetic": not lab["real_data"], "factor": factor,
               "retrain": lab["retrain"], "reused_models": synthetic_lab is None, "retrain_reason": reason,
               "models": models, "synthetic_lab": synthetic_lab, "ranges": ranges, "loader_error": loader_err,
               "clean": clean_rows, "fgsm": fgsm_rows, "attack_length": length, "threshold": chain.threshold,
               "per_eps": {f"{x['eps']:g}": x for x in summary}, "rows": res["rows"], "clean_detection": res["clean"],
               "accuracy_mean": float(np.mean([x["accuracy"] for x in summary])), "seconds": seconds,
               "render_seconds": render_s}
    write_metrics(METRICS, nan_to_none(metrics), p)
    atomic_write_text(REPORT, report(p, metrics, res["rows"], summary, [s["name"] for s in sequences],
                                     train_metrics, K_syn, K_zed, sequences))
    typer.echo(f"lab: {'reused' if synthetic_lab is None else 'retrained'} models {models['pose']}, "
               f"{models['detector']}; {len(sequences)} sequences from {source}; mean detection accuracy "
               f"{100 * metrics['accuracy_mean']:.2f}% (paper {PAPER_AVERAGE}%) in {seconds:.0f} s -> {REPORT}")


def models_section(p: dict[str, Any], m: dict[str, Any]) -> str:
    """The report's paragraph on which pose model and detector were used, and why."""
    lab, r = p["lab"], p["render"]
    if m["reused_models"]:
        return f"""## Models: reused

The pose model and the detector are the main ones, `{m['models']['pose']}` (hash `{m['model_hash']}`) and
`{m['models']['detector']}` (`lab.retrain: {lab['retrain']}`): the lab mock-up is the main target mesh at
1/{lab['scale']:g} scale and K_blender has the lab images' 16:9 aspect (SPEC 9), so a synthetic-lab training set
would repeat the main one. `lab.retrain: always` (the paper profile), or another mock-up mesh in `lab.mesh`,
trains a synthetic-lab pose model and detector instead.
"""
    s = m["synthetic_lab"]
    t = s["train_test"]
    mesh = "(the procedural Jason-1-like target)" if s["mesh"] is None else f"`{s['mesh']}`"
    return f"""## Models: retrained on a synthetic-lab set

Retrained because {s['reason']}. The pose model and the detector used below are
`{s['pose']}` (hash `{m['model_hash']}`) and `{s['detector']}`, not the main models/pose.pt and
models/detector.pt.

- Synthetic-lab set: {s['images']} images at {s['size'][0]}x{s['size'][1]} with the main camera K_blender (the lab
  images' 16:9 aspect), the 13 approach sequences of SPEC 3 ({s['frames_per_sequence']} frames each, 60 to 10 m,
  base seed {s['seed']}), the mock-up {mesh} rendered at {lab['scale']:g} x its size ({s['mesh_scale']:g} m per mesh
  unit) so the ranges are preserved; sun and render settings of `render`.
- Pose model: the main recipe (`rpod train` with the `train` params, width {p['train']['width']}, input
  {r['width']}x{r['height']}): {s['epochs_run']} epochs, best epoch {s['best_epoch']}; synthetic-lab test split
  ({t['n']} images): {t['pos_mean_m']:.3f} m and {t['att_mean_deg']:.2f} deg mean error.
- SHAP (`rpod shap`, `shap` params) of {s['shap_samples']} clean and FGSM samples with this model, and the LSTM
  detector (`rpod detect`, `detect` params, no baselines) trained on them: test accuracy
  {100 * s['detector_test_accuracy']:.2f}%.

Everything is in `{s['folder']}/` (its own params.yaml, datasets/, models/, reports/pose.md, reports/detector.md);
the time of each step is in reports/metrics/lab.json (`synthetic_lab.seconds`).
"""


PAPER_RANGES = {3.122: 51.18}  # the paper's representative-range table: lab z (m) -> synthetic z (m), as printed


def paper_ranges(K_syn: Any, K_zed: Any, scale: float, factor: float) -> str:
    """The paper's representative-range table beside ours, and why they differ (Markdown)."""
    from pipeline.lab import paper_lab_factor
    from pipeline.report import markdown_table

    k_paper = paper_lab_factor(K_syn, K_zed, scale)
    rows = [{"lab z (m)": f"{z:g}", "ours (m)": z * factor, "paper's formula (m)": z * k_paper,
             "paper, as printed (m)": PAPER_RANGES.get(z, "-")} for z in (3.122, 3.0, 2.5, 2.0, 1.5, 1.0)]
    return f"""Representative ranges beside the paper's. The paper takes the 1920 -> 480 resize as
cx_zed / cx_blender = {K_zed.cx:g} / {K_syn.cx:g} = {K_zed.cx / K_syn.cx:.4f} instead of the exact
{K_zed.width}/{K_syn.width} = {K_zed.width / K_syn.width:g}, so its factor is {k_paper:.3f} against our {factor:.3f} and
its synthetic ranges are {100 * (factor / k_paper - 1):.2f}% shorter; the printed 51.18 m differs from its own
formula only in rounding. Only the 3.122 m row is printed in the paper text we have; the other rows
apply its formula.

{markdown_table(rows, decimals=2)}"""


def report(p: dict[str, Any], m: dict[str, Any], rows: list[dict[str, Any]], summary: list[dict[str, Any]],
           names: list[str], train_metrics: dict[str, Any] | None, K_syn: Any, K_zed: Any,
           sequences: list[dict[str, Any]]) -> str:
    import pandas as pd

    from pipeline.report import markdown_table
    from stages.evaluate import accuracy_table, detail_table

    lab, ds = p["lab"], p["lab"]["domain_shift"]
    f_eff = K_zed.fx * K_syn.width / K_zed.width
    src = ("synthetic lab sequences rendered by this stage and read back through the real-data loader "
           f"(`{OUT}/`)" if m["synthetic"] else f"the real lab recording in `{m['source']}`")
    loader = ""
    if m["loader_error"]:
        worst_p = max(v["position_max_m"] for v in m["loader_error"].values())
        worst_a = max(v["attitude_max_deg"] for v in m["loader_error"].values())
        loader = (f"\nLoader round trip: the labels recovered from mocap.csv/camera.csv ({lab['match']} matching, "
                  f"max gap {lab['max_gap_s']} s) differ from the exact render poses by at most "
                  f"{1000 * worst_p:.2f} mm (lab units) and {worst_a:.4f} deg.\n")
    clean = pd.DataFrame(m["clean"])
    clean_table = [{"sequence": c["sequence"], "position (m)": c["position_m"], "relative position": c["relative_position"],
                    "attitude (deg)": c["attitude_deg"]} for c in m["clean"]]
    fg = pd.DataFrame(m["fgsm"])
    fgsm_table = [{"eps": "clean", "position (m)": float(clean["position_m"].mean()),
                   "relative position": float(clean["relative_position"].mean()),
                   "attitude (deg)": float(clean["attitude_deg"].mean())}]
    for eps, g in fg.groupby("eps", sort=False):
        fgsm_table.append({"eps": f"{eps:g}", "position (m)": float(g["position_m"].mean()),
                           "relative position": float(g["relative_position"].mean()),
                           "attitude (deg)": float(g["attitude_deg"].mean())})
    synth = "not available (run `rpod train`)"
    test = (train_metrics or {}).get("test", {})
    if "pos_mean_m" in test and "att_mean_deg" in test:
        synth = f"{test['pos_mean_m']:.3f} m and {test['att_mean_deg']:.2f} deg mean error"
    which = (f"the main model, `{TRAIN_METRICS}`" if m["reused_models"] else
             f"the synthetic-lab model, `{m['synthetic_lab']['folder']}/{TRAIN_METRICS}`")
    att_frac = np.mean([s["attacked"].mean() for s in sequences])
    mean_acc = 100 * m["accuracy_mean"]
    return f"""# Lab domain

Source: {src}.

{models_section(p, m)}

## Range rescaling

Apparent size s = f L / z (pixels). The lab image ({K_zed.width}x{K_zed.height}, fx = {K_zed.fx:g}) resized to
{K_syn.width}x{K_syn.height} has fx_lab_eff = {K_zed.fx:g} x {K_syn.width}/{K_zed.width} = {f_eff:.2f} px; the
mock-up is L/{lab['scale']:g}; the synthetic camera has fx = {K_syn.fx:g} px. Equal size gives
z_syn = z_lab x {lab['scale']:g} x {K_syn.fx:g} / {f_eff:.2f} = **{m['factor']:.3f} x z_lab**
(`rpod lab rescale --z 3.122` -> {3.122 * m['factor']:.2f} m). Lateral label coordinates keep the target's
pixel position. The match is on the horizontal size; K_blender has fy/fx = {K_syn.fy / K_syn.fx:.4g}
(camera.fy), so the target is {K_syn.fy / K_syn.fx:.3f}x as tall in the synthetic image as in the resized lab image.

{paper_ranges(K_syn, K_zed, float(lab['scale']), m['factor'])}

{markdown_table(m['ranges'], decimals=2)}
{loader}
## Pose error

Lab frames: {lab['frames']} per sequence at {lab['fps']} fps, mocap at {lab['mocap_hz']} Hz, rendered with the
ZED geometry (fx scaled by 1 + {ds['calib_error']:g}: a calibration error), sun direction {ds['sun_direction']}
at strength {ds['sun_strength']}, blur sigma {ds['blur_sigma']} px, noise std {ds['noise_std']}, then
segmented (masks/) and resized to {p['render']['width']}x{p['render']['height']}. Errors are in the equivalent
synthetic frame (metres x {m['factor']:.2f} of lab metres).

Synthetic test split ({which}): {synth}.

{markdown_table(clean_table, decimals=3)}
## FGSM on the lab sequences

Mean error over all lab frames (attack.eps, loss `{p['attack']['loss']}`, 8-bit images).

{markdown_table(fgsm_table, decimals=3)}
## Integrated detection, {m['attack_length']}-frame attacks

Start probability {p['evaluate']['p_start']:g} per frame, {100 * att_frac:.1f}% of the frames attacked;
accuracy = correctly classified frames / all frames (%).

{markdown_table(accuracy_table(rows, summary, names, PAPER_ACCURACY), decimals=2)}
Mean over eps: **{mean_acc:.2f}%** (paper: {PAPER_AVERAGE}% average).

{markdown_table(detail_table(summary), decimals=2)}
"""

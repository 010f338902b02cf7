"""`rpod train`: train the Darknet-19 pose CNN on the labelled renders (SPEC 4).

Reads params `seed`, `render.width/height` (the input size) and `train`; writes models/pose.pt (the
best epoch by test SPEED score), dvclive/train/ (per-epoch curves for `dvc plots show`),
reports/pose.md and reports/metrics/train.json.

Scale-out: `torchrun --nproc_per_node N .venv/bin/rpod train` runs DistributedDataParallel (gloo on
CPU, nccl on CUDA, one GPU per process); only rank 0 writes files. CUDA is used when present.
"""
from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Annotated, Any

import typer

from stages.checkpoint import POSE
from stages.io import StageError, atomic_outputs, atomic_write_text, write_metrics

REPORT = Path("reports/pose.md")
METRICS = Path("reports/metrics/train.json")
LIVE_DIR = "dvclive/train"
SEED_OFFSET = 300
SURROGATE = Path("models/surrogate.pt")
PAPER = {"pos_mean_m": 0.49, "att_mean_deg": 0.68}
TARGET_TZ_PCT, TARGET_LATERAL_M = 2.0, 0.5  # guidance needs (issue 3)


def main(
    surrogate: Annotated[bool, typer.Option("--surrogate", help="Train the robustness stage's surrogate instead: "
                                            "seed robustness.surrogate_seed, robustness.surrogate_epochs epochs, "
                                            "writes models/surrogate.pt and no reports.")] = False,
) -> None:
    """Train the pose CNN; keep the best checkpoint by test error; report errors next to the paper's."""
    import torch

    from pipeline.loss import PoseLoss
    from pipeline.model import PoseNet
    from pipeline.training import DivergenceError, fit
    from stages import checkpoint, data, params as params_mod

    params = params_mod.load()
    p, r = params["train"], params["robustness"]
    seed = int(r["surrogate_seed"]) if surrogate else int(params["seed"])
    rank, world, device = _init_distributed()
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    try:
        cfg = _config(p, int(r["surrogate_epochs"] if surrogate else p["epochs"]), seed + SEED_OFFSET)
        if surrogate:  # its own initial weights too, not only its own batches and augmentations
            torch.manual_seed(cfg.seed)
        model = PoseNet(float(p["width"]), float(p["dropout"]))
    except ValueError as e:
        raise StageError(f"params.yaml: bad train section ({e})") from None

    train_split, test_split = data.load_split(params, "train"), data.load_split(params, "test")
    train_set = data.pose_dataset(train_split, p["augment"], seed=cfg.seed)
    test_set, train_eval_set = data.pose_dataset(test_split), data.pose_dataset(train_split)
    targets = train_split.targets
    model.set_output_bias(targets[:, :3].mean(0), targets[:, 3:].mean(0))
    loss = PoseLoss("mean")
    if p["compile"]:
        model = torch.compile(model)  # type: ignore[assignment]
    input_size = (int(params["render"]["height"]), int(params["render"]["width"]))

    best: dict[str, Any] = {}  # the learned loss weights and facts of the best epoch so far
    if rank == 0:
        print(f"train: {len(train_split)} train / {len(test_split)} test images at {input_size[1]}x{input_size[0]}, "
              f"width {p['width']}, {cfg.epochs} epochs, batch {cfg.batch_size} x {world} process(es), "
              f"{torch.get_num_threads()} threads, device {device}", flush=True)

    def on_epoch(stats: Any, is_best: bool, net: Any) -> None:
        if rank != 0:
            return
        from tqdm import tqdm

        if is_best:
            best.update(loss=copy.deepcopy(loss), meta={"epoch": stats.epoch, "test_score": stats.test_score,
                                                        "test_pos_m": stats.test_pos_m,
                                                        "test_att_deg": stats.test_att_deg})
        tqdm.write(f"epoch {stats.epoch:3d}  loss {stats.loss:7.3f}  train {stats.train_pos_m:6.2f} m "
                   f"{stats.train_att_deg:5.2f} deg  test {stats.test_pos_m:6.2f} m {stats.test_att_deg:5.2f} deg  "
                   f"{stats.images_per_s:5.0f} img/s  {stats.seconds:5.1f} s{'  *best' if is_best else ''}")

    try:
        result = fit(model, loss, train_set, test_set, cfg, device, on_epoch=on_epoch)
    except DivergenceError as e:
        raise StageError(f"{e}; lower train.lr_base / train.lr_max in params.yaml "
                         f"({SURROGATE if surrogate else POSE} and the reports were left as they were)") from None
    if rank == 0:
        net = _plain(model)
        net.load_state_dict(result.best_state)
    if rank == 0 and surrogate:  # the surrogate only: no metrics, reports or curves
        checkpoint.save_pose(SURROGATE, net, best["loss"], input_size, best["meta"])
        print(f"train --surrogate: seed {seed}, best epoch {result.best_epoch} of {len(result.history)}: test "
              f"{best['meta']['test_pos_m']:.3f} m -> {SURROGATE}")
    elif rank == 0:
        _write_results(params, net, best, input_size, result, cfg, device, world, (train_split, train_eval_set),
                       (test_split, test_set))
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


def _config(p: dict[str, Any], epochs: int, seed: int) -> Any:
    """The TrainConfig of a `train` params section (ValueError on a bad value)."""
    from pipeline.training import TrainConfig

    return TrainConfig(epochs=epochs, batch_size=int(p["batch_size"]), lr_base=float(p["lr_base"]),
                       lr_max=float(p["lr_max"]), cycle_epochs=float(p["cycle_epochs"]),
                       weight_decay=float(p["weight_decay"]),
                       max_minutes=None if p["max_minutes"] is None else float(p["max_minutes"]),
                       channels_last=bool(p["channels_last"]), workers=int(p["workers"]), seed=seed)


def _write_results(params: dict[str, Any], net: Any, best: dict[str, Any], input_size: tuple[int, int], result: Any,
                   cfg: Any, device: Any, world: int, train: tuple[Any, Any], test: tuple[Any, Any]) -> None:
    """Errors of the best checkpoint on both splits (and the always-the-mean-label floor), then
    models/pose.pt (`net` with the best epoch's loss weights and facts, `best`), reports/metrics/train.json,
    reports/pose.md and dvclive/train/ moved into place together. `train`, `test`: (split, its
    un-augmented dataset)."""
    import numpy as np

    from pipeline.training import predict, summarize_errors
    from stages import checkpoint

    (train_split, train_eval_set), (test_split, test_set) = train, test
    bins = params["train"]["range_bins"]
    summary = {name: summarize_errors(predict(net, ds, 2 * cfg.batch_size, device, cfg.channels_last),
                                      split.targets, split.labels["range"].to_numpy(), bins)
               for name, ds, split in (("train", train_eval_set, train_split), ("test", test_set, test_split))}
    # the floor any useful model must beat: always answer the mean training label
    mean_pred = np.broadcast_to(train_split.targets.mean(0), test_split.targets.shape)
    summary["test_mean_baseline"] = summarize_errors(mean_pred, test_split.targets,
                                                     test_split.labels["range"].to_numpy(), bins)
    metrics = {**summary, "best_epoch": result.best_epoch, "epochs_run": len(result.history),
               "stopped_early": result.stopped_early, "train_minutes": result.seconds / 60,
               "train_images_per_s": result.train_images_per_s, "test_score": result.best_score,
               "processes": world, "device": str(device)}
    # model, metrics, report and curves move into place together, only now: a crashed, killed or
    # diverged run leaves the previous run's files as they were
    with atomic_outputs(POSE, METRICS, REPORT, dirs=(LIVE_DIR,)) as (pose, metrics_path, report, live):
        checkpoint.save_pose(pose, net, best["loss"], input_size, best["meta"])
        write_metrics(metrics_path, metrics, params)
        atomic_write_text(report, _report(metrics, params, len(train_split), len(test_split)))
        _log_curves(live, result.history)
    print(f"train: best epoch {result.best_epoch}: test {summary['test']['pos_mean_m']:.3f} m, "
          f"{summary['test']['att_mean_deg']:.2f} deg -> {POSE}, {REPORT}, {METRICS}")


def _log_curves(folder: Any, history: list[Any]) -> None:
    """Per-epoch curves of a finished run into a DVCLive folder (for `dvc plots show`)."""
    from dvclive import Live

    live = Live(dir=str(folder), dvcyaml=False, save_dvc_exp=False, report=None)
    for stats in history:
        for key in ("loss", "lr", "s_p", "s_r", "train_pos_m", "train_att_deg", "test_pos_m", "test_att_deg",
                    "test_score", "images_per_s"):
            live.log_metric(key, getattr(stats, key))
        live.next_step()
    live.end()


def _plain(model: Any) -> Any:
    """The PoseNet under a torch.compile wrapper, if any."""
    return getattr(model, "_orig_mod", model)


def _init_distributed() -> tuple[int, int, Any]:
    """(rank, world size, device) from torchrun's environment (WORLD_SIZE, RANK, LOCAL_RANK)."""
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    cuda = torch.cuda.is_available()
    if world == 1:
        return 0, 1, torch.device("cuda" if cuda else "cpu")
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if cuda:
        torch.cuda.set_device(local)
    dist.init_process_group("nccl" if cuda else "gloo")
    return dist.get_rank(), world, torch.device(f"cuda:{local}" if cuda else "cpu")


def _report(m: dict[str, Any], params: dict[str, Any], n_train: int, n_test: int) -> str:
    from pipeline.report import markdown_table

    p, r = params["train"], params["render"]
    rows = [{"split": s, "images": m[s]["n"], "position mean (m)": m[s]["pos_mean_m"],
             "position median (m)": m[s]["pos_median_m"], "attitude mean (deg)": m[s]["att_mean_deg"],
             "attitude median (deg)": m[s]["att_median_deg"]} for s in ("train", "test")]
    b = m["test_mean_baseline"]
    rows.append({"split": "test, always the mean training label (baseline)", "images": b["n"],
                 "position mean (m)": b["pos_mean_m"], "position median (m)": b["pos_median_m"],
                 "attitude mean (deg)": b["att_mean_deg"], "attitude median (deg)": b["att_median_deg"]})
    rows.append({"split": "paper, test (480x270, full width, 50 epochs)", "images": "6,500 of 32,500",
                 "position mean (m)": PAPER["pos_mean_m"], "position median (m)": "-",
                 "attitude mean (deg)": PAPER["att_mean_deg"], "attitude median (deg)": "-"})
    bins = [{"split": s, "range (m)": b["range_m"], "images": b["n"], "position mean (m)": b.get("pos_mean_m"),
             "attitude mean (deg)": b.get("att_mean_deg"), "|tz| error (% of range)": b.get("tz_pct_range"),
             "lateral error (m)": b.get("lateral_m")} for s in ("train", "test") for b in m[s]["bins"]]
    t = m["test"]
    ok = {k: "yes" if t[k] < v else "no" for k, v in
          (("tz_pct_range", TARGET_TZ_PCT), ("tz_pct_10_30", TARGET_TZ_PCT), ("lateral_10_30_m", TARGET_LATERAL_M))}
    return f"""# Pose estimator (`rpod train`)

Modified Darknet-19 (7x7 stem, stride-2 3x3 convolutions for the max-pools, Darknet-53 residual
blocks, BatchNorm + LeakyReLU, 1000-feature GAP layer, dropout {p['dropout']}, linear heads 3 + 6-D),
width {p['width']}, input {r['width']}x{r['height']}, profile `{params.get('profile_name')}`.
{n_train} training and {n_test} test images; {m['epochs_run']} epochs run
({'stopped by train.max_minutes' if m['stopped_early'] else 'all requested'}), best epoch {m['best_epoch']} by test
SPEED score ({m['test_score']:.4f}); {m['train_minutes']:.1f} minutes at {m['train_images_per_s']:.0f} training
images/s on {m['processes']} process(es), device `{m['device']}`.

Errors: position ||t_pred - t_gt|| (m), attitude 2 acos(|<q_pred, q_gt>|) (deg), both splits evaluated
with the best checkpoint in eval mode (no augmentation).

{markdown_table(rows, decimals=3)}
The split is per frame (label.test_fraction), so test frames lie between training frames of the same
approach sequences: the test error measures interpolation along the trajectories, not new geometry.
The paper trained on 8x as many images at 9x the pixels with the full-width network; the default
profile trades that accuracy for a CPU budget of about 13 minutes.

## Guidance requirements (test set)

| quantity | value | target | met |
|---|---|---|---|
| mean abs tz error, % of range, all ranges | {t['tz_pct_range']:.2f} | < {TARGET_TZ_PCT:g} | {ok['tz_pct_range']} |
| mean abs tz error, % of range, at 10-30 m | {t['tz_pct_10_30']:.2f} | < {TARGET_TZ_PCT:g} | {ok['tz_pct_10_30']} |
| mean lateral error sqrt(dx^2 + dy^2) at 10-30 m (m) | {t['lateral_10_30_m']:.3f} | < {TARGET_LATERAL_M:g} | {ok['lateral_10_30_m']} |

## Errors per range bin

Range = ||t|| (m); the lateral start offsets put the first frames beyond the top edge.

{markdown_table(bins, decimals=3)}
Training curves: `dvc plots show` (DVCLive, {LIVE_DIR}/).
"""

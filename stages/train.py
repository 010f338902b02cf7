"""`rpod train`: train the Darknet-19 pose CNN on the labelled renders.

Reads params `seed`, `render.width/height` (the input size) and `train` (but `train.adversarial`); writes
models/pose.pt (the best epoch by validation SPEED score; with `train.ema` the weights' moving average),
dvclive/train/ (per-epoch curves for `dvc plots show`), reports/pose.md and reports/metrics/train.json.

`rpod train --robust` (dvc stage `robust`): the robust model, models/pose_robust.pt: the same network with
the black-level clamp (train.adversarial.black_level) in front, fine-tuned from models/pose.pt (or trained
from the seed) with PGD-k adversarial training (pipeline/pose/adversarial.py) and chosen on clean +
attacked validation error; then both models are evaluated on test, clean and under FGSM / PGD
(pipeline/pose/robustness.py), into reports/pose_robust.md, reports/metrics/robust.json and dvclive/robust/.
Its validation split is the standard model's (same seed), so neither model was fitted on it.

Honest selection: the validation split is `train.val_fraction` of the training frames (whole frames,
seeded), the network is never fitted on it, and the test split is read only after training, for the
final evaluation of the kept checkpoint. Torch is seeded (and switched to deterministic algorithms)
before the network is built, so two runs on one machine give the same weights.

Device: the `device` param (auto = CUDA when present), with bf16 autocast there when `amp` is set;
CPU threads: `threads` (stages.config.device.distributed). Scale-out: `torchrun --nproc_per_node N
.venv/bin/rpod train` runs DistributedDataParallel (gloo on the CPU, NCCL on CUDA, one GPU per process); only rank 0 writes files.
"""

from __future__ import annotations

import copy
from typing import Annotated, Any

import typer

from pipeline.formats.renders import META
from pipeline.io.atomic import atomic_outputs, atomic_write_text, check_writable, file_hash, read_json
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import (
    CAPACITY,
    LABELS,
    POSE,
    POSE_ROBUST,
    RENDER,
    ROBUST_LIVE,
    ROBUST_METRICS,
    ROBUST_REPORT,
    SURROGATE,
    TRAIN_LIVE,
)
from stages.artifacts.paths import POSE_REPORT as REPORT
from stages.artifacts.paths import TRAIN_METRICS as METRICS
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.pose import pose_page, robust_page


def main(
    params: Params,
    surrogate: Annotated[
        bool,
        typer.Option(
            "--surrogate",
            help="Train the robustness stage's surrogate instead: "
            "seed robustness.surrogate_seed, robustness.surrogate_epochs epochs, "
            "writes models/surrogate.pt and no reports.",
        ),
    ] = False,
    robust: Annotated[
        bool,
        typer.Option(
            "--robust",
            help="Train the robust model instead (train.adversarial): "
            "writes models/pose_robust.pt and reports/pose_robust.md.",
        ),
    ] = False,
) -> None:
    """Train the pose CNN; keep the best checkpoint by validation error; report test errors next to the paper's."""
    from stages.config.device import distributed

    _check_inputs(surrogate)
    if robust:
        return _robust(params, surrogate)
    seed = params.robustness.surrogate_seed if surrogate else params.seed
    rank, world, device = distributed(params)
    model, cfg, loss, (train_split, train_set, train_eval_set), (val_split, val_set) = _build(
        params, params.robustness.surrogate_epochs if surrogate else params.train.epochs, seed, device
    )
    input_size = (params.render.height, params.render.width)
    best: dict[str, Any] = {}  # the learned loss weights and facts of the best epoch so far
    if rank == 0:
        _announce(params, (len(train_split), len(val_split)), cfg, world, device, model)
    result = _fit(model, loss, (train_set, val_set), cfg, device, _epoch_logger(rank, loss, best), surrogate)
    if rank == 0:
        net = _plain(model)
        net.load_state_dict(result.best_state)
        if surrogate:  # the surrogate only: no metrics, reports or curves
            _write_surrogate(net, best, input_size, seed, result)
        else:
            _write_results(
                params,
                net,
                best,
                input_size,
                result,
                cfg,
                device,
                world,
                (train_split, train_eval_set),
                (val_split, val_set),
            )
    _finish(world)


def _announce(params: Params, sizes: tuple[int, int], cfg: Any, world: int, device: Any, model: Any) -> None:
    """Print one line on the run about to start: the (train, validation) image counts of `sizes`, input size,
    network width, epochs, batch, processes, torch threads and device."""
    import torch

    print(
        f"train: {sizes[0]} train / {sizes[1]} validation images at {params.render.width}x{params.render.height}, "
        f"width {params.train.width}, {cfg.epochs} epochs, batch {cfg.batch_size} x {world} process(es), "
        f"{torch.get_num_threads()} threads, device {device}{' (bf16 autocast)' if _plain(model).amp else ''}",
        flush=True,
    )


def _check_inputs(surrogate: bool) -> None:
    """Refuse, before any training, outputs that cannot be written and (but for the surrogate) an empty test split."""
    from stages.artifacts import data

    check_writable(POSE.parent, REPORT.parent, METRICS.parent, TRAIN_LIVE.parent)  # found now, not after training
    if not surrogate and not data.load_labels()["split"].eq("test").any():  # found now, not after training
        raise StageError(
            f"{LABELS}: the 'test' split is empty (the test split is read after training); check "
            f"label.test_fraction and the number of rendered frames"
        )


def _build(
    params: Params, epochs: int, seed: int, device: Any
) -> tuple[Any, Any, Any, tuple[Any, Any, Any], tuple[Any, Any]]:
    """(the network on `device`, its output bias at the mean training label, compiled with train.compile; its
    TrainConfig; the PoseLoss; (train split, its training and un-augmented datasets); (validation split, its
    dataset)). Torch is seeded from `seed` before the network is built."""
    import torch

    from pipeline.pose.loss import PoseLoss
    from stages.artifacts import data

    model, cfg = _model(params, epochs, seed_for(seed, "train"))
    (train_split, train_set, train_eval_set), (val_split, val_set) = data.training_sets(params, cfg.seed)
    targets = train_split.targets
    model.set_output_bias(targets[:, :3].mean(0), targets[:, 3:].mean(0))
    model.place(device, params.amp)
    loss = PoseLoss("mean")
    if params.train.compile:
        model = torch.compile(model)  # type: ignore[assignment]
    return model, cfg, loss, (train_split, train_set, train_eval_set), (val_split, val_set)


def _fit(model: Any, loss: Any, sets: tuple[Any, Any], cfg: Any, device: Any, on_epoch: Any, surrogate: bool) -> Any:
    """fit's result of training `model` on `sets` (train, validation datasets); a diverged run is a StageError
    naming the learning rates."""
    from pipeline.pose.train import DivergenceError, fit

    train_set, val_set = sets
    try:
        return fit(model, loss, train_set, val_set, cfg, device, on_epoch=on_epoch)
    except DivergenceError as e:
        raise StageError(
            f"{e}; lower train.lr_base / train.lr_max in params.yaml "
            f"({SURROGATE if surrogate else POSE} and the reports were left as they were)"
        ) from None


def _write_surrogate(net: Any, best: dict[str, Any], input_size: tuple[int, int], seed: int, result: Any) -> None:
    """Write models/surrogate.pt (`net` with the best epoch's loss weights and facts) and print its validation
    error (m)."""
    from pipeline.formats.models import save_pose

    save_pose(SURROGATE, net, best["loss"], input_size, best["meta"], **_made_from())
    print(
        f"train --surrogate: seed {seed}, best epoch {result.best_epoch} of {len(result.history)}: "
        f"validation {best['meta']['val_pos_m']:.3f} m -> {SURROGATE}"
    )


def _finish(world: int) -> None:
    """Under torchrun, wait for every rank, then end the process group."""
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


def _epoch_logger(rank: int, loss: Any, best: dict[str, Any]) -> Any:
    """fit's per-epoch callback: on rank 0, keep the best epoch's loss weights and facts in `best`
    (validation error, m and deg) and print one line per epoch."""

    def on_epoch(stats: Any, is_best: bool, net: Any) -> None:
        if rank != 0:
            return
        from tqdm import tqdm

        attacked = "" if stats.val_adv_pos_m != stats.val_adv_pos_m else f"  PGD {stats.val_adv_pos_m:6.2f} m"
        if is_best:
            best.update(
                loss=copy.deepcopy(loss),
                meta={
                    "epoch": stats.epoch,
                    "val_score": stats.val_score,
                    "val_pos_m": stats.val_pos_m,
                    "val_att_deg": stats.val_att_deg,
                    "score": stats.score,
                },
            )
        tqdm.write(
            f"epoch {stats.epoch:3d}  loss {stats.loss:7.3f}  train {stats.train_pos_m:6.2f} m "
            f"{stats.train_att_deg:5.2f} deg  val {stats.val_pos_m:6.2f} m {stats.val_att_deg:5.2f} deg"
            f"{attacked}  {stats.images_per_s:5.0f} img/s  {stats.seconds:5.1f} s{'  *best' if is_best else ''}"
        )

    return on_epoch


def _model(params: Params, epochs: int, seed: int) -> tuple[Any, Any]:
    """(PoseNet, TrainConfig) of the `train` params section; torch is seeded (deterministic) before the
    network is built, so its initial weights come from the seed. A bad value stops the stage."""
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import make_deterministic
    from stages.config.build import train_config

    try:
        cfg = train_config(params.train, epochs, seed)
        make_deterministic(cfg.seed)
        return PoseNet(float(params.train.width), float(params.train.dropout)), cfg
    except ValueError as e:
        raise StageError(f"params.yaml: bad train section ({e})") from None


def _robust(params: Params, surrogate: bool) -> None:
    """`rpod train --robust`: adversarial training of the clamped network (with train.adversarial.ablation, also
    the clamp alone and the attacks alone), then the models on test."""
    from stages.artifacts import data
    from stages.config.device import distributed

    if surrogate:
        raise StageError("rpod train: --robust and --surrogate train different models; give one")
    adv = params.train.adversarial
    rank, world, device = distributed(params)
    # the standard model's split: its validation frames were never fitted by either model
    sets = data.training_sets(params, seed_for(params.seed, "train"))
    model, result, best = _fine_tune(params, float(adv.black_level), True, sets, (rank, world, device))
    variants = {}
    if adv.ablation:  # the ablation's variants: the same recipe without the attacks, or without the clamp
        for name, level, attacked in ABLATION:
            if rank == 0:
                print(f"train --robust: the ablation's '{name}' variant", flush=True)
            level = float(adv.black_level) if level is None else level
            variants[name] = _fine_tune(params, level, attacked, sets, (rank, world, device))[:2]
    if rank == 0:
        (train_split, _, _), (val_split, val_set) = sets
        _write_robust(params, model, best, result, (train_split, val_split, val_set), device, variants)
    _finish(world)


# the ablation's variants (name, black level (None: train.adversarial.black_level), attacked): the same recipe
ABLATION = (("clamp only", None, False), ("adversarial training only", 0.0, True))


def _fine_tune(
    params: Params, level: float, attacked: bool, sets: tuple[Any, Any], where: tuple[int, int, Any]
) -> tuple[Any, Any, dict[str, Any]]:
    """The robust recipe (train.adversarial) on `sets` (data.training_sets) with the input clamp at `level` and
    the attacks on or off: (the network at its best epoch, fit's result, the best epoch's loss and facts).
    `where`: (rank, world, device)."""
    from pipeline.pose.adversarial import Adversary
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import DivergenceError, fit, make_deterministic
    from stages.artifacts.models import load_pose
    from stages.config.build import adversarial_config, robust_train_config

    adv, (rank, world, device) = params.train.adversarial, where
    try:
        cfg = robust_train_config(params.train, seed_for(params.seed, "robust"))
    except ValueError as e:
        raise StageError(f"params.yaml: bad train.adversarial section ({e})") from None
    make_deterministic(cfg.seed)
    model, loss = PoseNet(float(params.train.width), float(params.train.dropout), level), PoseLoss("mean")
    (train_split, train_set, _), (_, val_set) = sets
    if adv.init == "standard":
        standard = load_pose(params)
        model.load_state_dict(standard.model.state_dict())
        loss.load_state_dict(standard.loss.state_dict())
    else:
        model.set_output_bias(train_split.targets[:, :3].mean(0), train_split.targets[:, 3:].mean(0))
    model.place(device, params.amp)
    steps = len(train_set) // (cfg.batch_size * world)
    adversary = Adversary(adversarial_config(adv), loss, steps, cfg.seed) if attacked else None
    best: dict[str, Any] = {}
    try:
        result = fit(
            model, loss, train_set, val_set, cfg, device, on_epoch=_epoch_logger(rank, loss, best), adversary=adversary
        )
    except DivergenceError as e:
        raise StageError(f"{e}; lower train.adversarial.lr_max ({POSE_ROBUST} was left as it was)") from None
    model.load_state_dict(result.best_state)
    return model, result, best


def _write_robust(
    params: Params,
    net: Any,
    best: dict[str, Any],
    result: Any,
    splits: tuple[Any, Any, Any],
    device: Any,
    variants: dict[str, tuple[Any, Any]],
) -> None:
    """Both models on validation and test (clean), and under the strongest-attack suite (`suite` params) on a
    seeded sample of test frames, the ablation's `variants` (name -> (network, fit's result)) too; each model's
    attacker capacity on the validation frames; the clamp threshold against the data (training frames); then
    models/pose_robust.pt, datasets/capacity/, reports/metrics/robust.json, reports/pose_robust.md and
    dvclive/robust/ together. `splits`: (fit split, validation split, its dataset). The test split is read here,
    after training."""
    from pipeline.pose.robustness import black_level_stats
    from stages.artifacts import data
    from stages.artifacts.models import load_pose

    adv, seed = params.train.adversarial, seed_for(params.seed, "robust")
    train_split, val_split, val_set = splits
    test_split = data.load_split(params, "test")
    standard = load_pose(params)
    out = {
        name: _clean(params, model, ((val_set, val_split), (data.pose_dataset(test_split), test_split)), device)
        for name, model in (("standard", standard.model), ("robust", net))
    }
    capacity, seconds = _attacked(params, out, (standard.model, net), (test_split, val_split), device)
    _training_cost(params, out, result, len(train_split))
    ablation = _ablation(params, variants, test_split, device, seconds)
    shift = params.lab.domain_shift
    metrics = {
        **out,
        "best_epoch": result.best_epoch,
        "epochs_run": len(result.history),
        "stopped_early": result.stopped_early,
        "score": result.best_score,
        "black_level": black_level_stats(
            train_split.images,
            float(adv.black_level),
            float(shift.noise_std),
            float(shift.blur_sigma),
            seed,
            backgrounds=data.backgrounds(train_split.labels),
        ),
        "train_images_per_s": result.train_images_per_s,
        "device": str(device),
        "suite_seconds": seconds,
        **({"ablation": ablation} if variants else {}),
    }
    _save_robust(params, net, best, metrics, capacity, result.history)
    print(
        f"train --robust: best epoch {result.best_epoch}: test {out['robust']['test']['pos_mean_m']:.3f} m, "
        f"{out['robust']['test']['att_mean_deg']:.2f} deg -> {POSE_ROBUST}, {ROBUST_REPORT}, {ROBUST_METRICS}"
    )


def _clean(params: Params, model: Any, sets: tuple[tuple[Any, Any], tuple[Any, Any]], device: Any) -> dict[str, Any]:
    """A model's clean errors on validation and test (`sets`: (dataset, split) each): `summarize_errors` per split
    and the test errors per background kind (`test_by_background`: means with 95% intervals)."""
    from pipeline.pose.metrics import errors_by_background, summarize_errors
    from pipeline.pose.train import predict
    from stages.artifacts import data

    out: dict[str, Any] = {}
    for split, (ds, s) in zip(("val", "test"), sets):
        pred = predict(model, ds, 64, device)
        out[split] = summarize_errors(pred, s.targets, s.labels["range"].to_numpy(), params.train.range_bins)
    out["test_by_background"] = errors_by_background(pred, s.targets, data.backgrounds(s.labels))
    return out


def _attacked(
    params: Params, out: dict[str, Any], nets: tuple[Any, Any], splits: tuple[Any, Any], device: Any
) -> tuple[Any, dict[str, float]]:
    """Both models (`nets`: standard, robust) under the attack suite on the test split (`splits`: test,
    validation) into out[model]["suite"], then their attacker capacities on the validation split: (the
    capacities, the seconds of each step)."""
    import time

    from stages.engine.suite import attacked_tables, capacities

    standard, net = nets
    test_split, val_split = splits
    t0 = time.perf_counter()
    models = {"standard": standard, "robust": net}
    for name, table in attacked_tables(params, models, test_split, device).items():
        out[name]["suite"] = table
    t1 = time.perf_counter()
    capacity = capacities(params, models, val_split, device)
    return capacity, {"suite": t1 - t0, "capacity": time.perf_counter() - t1}


def _ablation(
    params: Params, variants: dict[str, tuple[Any, Any]], test_split: Any, device: Any, seconds: dict[str, float]
) -> dict[str, Any]:
    """Each ablation variant (name -> (network, fit's result)) under the suite on the two models' test sample
    (its table without the checks: stages.engine.suite.attacked_tables), its best epoch and training minutes;
    the seconds go to `seconds["ablation"]`."""
    import time

    from stages.engine.suite import attacked_tables

    t0 = time.perf_counter()
    tables = attacked_tables(params, {k: net for k, (net, _) in variants.items()}, test_split, device, checks=False)
    seconds["ablation"] = time.perf_counter() - t0
    return {
        name: {"suite": tables[name], "best_epoch": fitted.best_epoch, "train_minutes": fitted.seconds / 60}
        for name, (_, fitted) in variants.items()
    }


def _training_cost(params: Params, out: dict[str, Any], result: Any, n_train: int) -> None:
    """Add each model's training cost to out[model]: train_minutes (this machine) and gradients (weight-gradient
    + input-gradient image passes; with trades the attacked rows' clean images are fitted too)."""
    from stages.config.build import adversarial_config

    standard_run, a = read_json(METRICS), adversarial_config(params.train.adversarial)
    per_epoch = n_train // params.train.batch_size * params.train.batch_size
    out["standard"].update(
        train_minutes=standard_run.get("train_minutes"), gradients=standard_run.get("epochs_run", 0) * per_epoch
    )
    out["robust"].update(
        train_minutes=result.seconds / 60,
        gradients=round(len(result.history) * per_epoch * (1 + (a.steps + (a.trades > 0)) * a.fraction)),
    )


def _save_robust(
    params: Params, net: Any, best: dict[str, Any], metrics: dict[str, Any], capacity: Any, history: list[Any]
) -> None:
    """models/pose_robust.pt, datasets/capacity/ (its summary added to `metrics`), reports/metrics/robust.json,
    reports/pose_robust.md and dvclive/robust/, moved into place together."""
    from pipeline.formats.models import save_pose
    from stages.engine.suite import write_capacities

    with atomic_outputs(POSE_ROBUST, ROBUST_METRICS, ROBUST_REPORT, dirs=(str(ROBUST_LIVE), str(CAPACITY))) as (
        pose,
        path,
        report,
        live,
        capacity_dir,
    ):
        save_pose(pose, net, best["loss"], (params.render.height, params.render.width), best["meta"], **_made_from())
        metrics["capacity"] = write_capacities(
            capacity_dir, capacity, params, {"standard": file_hash(POSE), "robust": file_hash(pose)}
        )
        write_metrics(path, metrics, params.profile_name)
        atomic_write_text(report, robust_page(metrics, params))
        _log_curves(live, history, params)


def _write_results(
    params: Params,
    net: Any,
    best: dict[str, Any],
    input_size: tuple[int, int],
    result: Any,
    cfg: Any,
    device: Any,
    world: int,
    train: tuple[Any, Any],
    val: tuple[Any, Any],
) -> None:
    """Errors of the best checkpoint on the train, validation and test splits (and the always-the-mean-label
    floor), then models/pose.pt (`net` with the best epoch's loss weights and facts, `best`),
    reports/metrics/train.json, reports/pose.md and dvclive/train/ moved into place together. `train`, `val`:
    (split, its un-augmented dataset). The test split is read here, after training, for the first time:
    the final evaluation."""
    from pipeline.formats.models import save_pose
    from stages.artifacts import data

    train_split, val_split = train[0], val[0]
    test_split = data.load_split(params, "test")
    summary = _summary(params, net, cfg, device, (train, val, test_split))
    metrics = {
        **summary,
        "best_epoch": result.best_epoch,
        "epochs_run": len(result.history),
        "stopped_early": result.stopped_early,
        "train_minutes": result.seconds / 60,
        "train_images_per_s": result.train_images_per_s,
        "val_score": result.best_score,
        "processes": world,
        "device": str(device),
    }
    # model, metrics, report and curves move into place together, only now: a crashed, killed or
    # diverged run leaves the previous run's files as they were
    with atomic_outputs(POSE, METRICS, REPORT, dirs=(str(TRAIN_LIVE),)) as (pose, metrics_path, report, live):
        save_pose(pose, net, best["loss"], input_size, best["meta"], **_made_from())
        write_metrics(metrics_path, metrics, params.profile_name)
        atomic_write_text(
            report, pose_page(metrics, params, len(train_split), len(val_split), len(test_split), str(TRAIN_LIVE))
        )
        _log_curves(live, result.history, params)
    print(
        f"train: best epoch {result.best_epoch}: test {summary['test']['pos_mean_m']:.3f} m, "
        f"{summary['test']['att_mean_deg']:.2f} deg -> {POSE}, {REPORT}, {METRICS}"
    )


def _summary(
    params: Params, net: Any, cfg: Any, device: Any, splits: tuple[tuple[Any, Any], tuple[Any, Any], Any]
) -> dict[str, Any]:
    """Errors (pipeline.pose.metrics.summarize_errors: m, deg) of `net` on the train, validation and test splits, and
    of always answering the mean training label on test; `splits`: (train, val: (split, its un-augmented dataset),
    the test split)."""
    import numpy as np

    from pipeline.pose.metrics import summarize_errors
    from pipeline.pose.train import predict
    from stages.artifacts import data

    (train_split, train_eval_set), (val_split, val_set), test_split = splits
    test_set = data.pose_dataset(test_split)
    bins = params.train.range_bins
    summary = {
        name: summarize_errors(
            predict(net, ds, 2 * cfg.batch_size, device, cfg.channels_last),
            split.targets,
            split.labels["range"].to_numpy(),
            bins,
        )
        for name, ds, split in (
            ("train", train_eval_set, train_split),
            ("val", val_set, val_split),
            ("test", test_set, test_split),
        )
    }
    # the floor any useful model must beat: always answer the mean training label
    mean_pred = np.broadcast_to(train_split.targets.mean(0), test_split.targets.shape)
    summary["test_mean_baseline"] = summarize_errors(
        mean_pred, test_split.targets, test_split.labels["range"].to_numpy(), bins
    )
    return summary


def _made_from() -> dict[str, Any]:
    """What a pose checkpoint records of its inputs (pipeline.formats.models.save_pose): the training images'
    camera matrix K (pixels) and the label table's hash (readers refuse a model of other labels)."""
    return {"K": read_json(RENDER / META)["K"], "labels_hash": file_hash(LABELS)}


def _log_curves(folder: Any, history: list[Any], params: Params) -> None:
    """Per-epoch curves of a finished run and the params it trained with (seed, input size, `train`) into a
    DVCLive folder (for `dvc plots show`)."""
    import dataclasses
    import json

    from dvclive import Live

    live = Live(dir=str(folder), dvcyaml=False, save_dvc_exp=False, report=None)
    live.log_params(
        json.loads(
            json.dumps(
                {
                    "seed": params.seed,
                    "render": {"width": params.render.width, "height": params.render.height},
                    "train": dataclasses.asdict(params.train),
                }
            )
        )
    )
    for stats in history:
        adversarial = (
            ("val_adv_pos_m", "val_adv_att_deg", "score") if stats.val_adv_pos_m == stats.val_adv_pos_m else ()
        )
        for key in (
            "loss",
            "lr",
            "s_p",
            "s_r",
            "train_pos_m",
            "train_att_deg",
            "val_pos_m",
            "val_att_deg",
            "val_score",
            "images_per_s",
            *adversarial,
        ):
            live.log_metric(key, getattr(stats, key))
        live.next_step()
    live.end()


def _plain(model: Any) -> Any:
    """The PoseNet under a torch.compile wrapper, if any."""
    return getattr(model, "_orig_mod", model)

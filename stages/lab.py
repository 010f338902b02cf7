"""`rpod lab`: the lab domain; `rpod lab rescale --z Z`: lab range -> synthetic range.

`rpod lab` renders lab-like sequences (the ZED camera's geometry, the mock-up at 9x scale, a domain
shift: other sun, sensor blur and noise, a small calibration error), writes each one as a real lab
recording would be stored, reads it back through the real-data loader, and evaluates the pose
model and the safety chain on it: reports/lab.md, reports/metrics/lab.json. With `lab.real_data`
set to a folder, the same evaluation runs on that recording instead.

Models (the paper's reproduction rows: pose error, FGSM errors, integrated detection): with `lab.retrain: auto`
and the main target as the mock-up, the main standard models models/pose.pt and models/detector.pt (allowed:
the lab mock-up is the same target); with `lab.retrain: always`, or another mock-up in `lab.mesh`, the pose
model and detector that `rpod lab_models` trained on a synthetic-lab set in datasets/lab_models/. The report
and metrics (`reused_models`, `models`) say which were used. Beside them, the chain that ships (the robust model
models/pose_robust.pt behind its black-level clamp, its detector models/detector_robust.pt at the threshold
`rpod calibrate` chose, models/defense.json) on the same clean lab frames: its false alarms and pose error
(metrics `shipped`).

The lab recording layout (images/, masks/, camera.csv, mocap.csv) is described in pipeline/formats/recordings.py.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import typer

from pipeline.io.atomic import atomic_dir, atomic_write_text, read_json
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import CHAINS, LAB_MODELS, LAB_MODELS_SUMMARY, PAPER, SHIPPED, TRAIN_METRICS
from stages.artifacts.paths import LAB as OUT
from stages.artifacts.paths import LAB_METRICS as METRICS
from stages.artifacts.paths import LAB_REPORT as REPORT
from stages.artifacts.recordings import read_recordings
from stages.config.build import retrain_reason
from stages.config.device import torch_setup
from stages.config.params import given, with_params
from stages.config.schema import Params
from stages.engine.lab_sets import cameras, render_lab
from stages.errors import StageError
from stages.pages.lab import lab_page
from stages.pages.paper import LAB, LAB_ATTACK_LENGTH, P_START

if TYPE_CHECKING:
    from pipeline.evaluation.sequences import Sequence

app = typer.Typer(
    help="The lab domain: lab-like sequences through the real-data loader, pose "
    "error, FGSM errors and integrated detection; `rpod lab rescale` converts ranges.",
    pretty_exceptions_enable=False,
    add_completion=False,
)


def rescale(
    params: Params, z: list[float] = typer.Option(..., "--z", help="Lab range(s) in metres (repeatable).")
) -> None:
    """Print the equivalent synthetic range of lab ranges (same apparent size in pixels; pinhole model)."""
    from pipeline.evaluation.lab import lab_to_synthetic_factor

    K_syn, K_zed = cameras(params)
    scale = float(params.lab.scale)
    k = lab_to_synthetic_factor(K_syn, K_zed, scale)
    f_eff = K_zed.fx * K_syn.width / K_zed.width
    typer.echo(
        f"factor = scale * fx_syn / fx_lab_eff = {scale:g} * {K_syn.fx:g} / ({K_zed.fx:g} * "
        f"{K_syn.width}/{K_zed.width} = {f_eff:.2f}) = {k:.4f}"
    )
    for zi in z:
        if zi <= 0:
            raise StageError(f"--z must be a positive range in metres, got {zi}")
        typer.echo(f"lab z = {zi:g} m -> synthetic z = {zi * k:.2f} m")


# ----------------------------------------------------------------------------- the stage
def main(params: Params, ctx: typer.Context) -> None:
    """Evaluate the pose model and the safety chain in the lab domain.

    Params: `lab` (sequences, frames, fps, mocap_hz, match, max_gap_s, attack_length, domain_shift,
    real_data, ...), `evaluate.p_start` / `evaluate.eps` for the integrated evaluation, `attack.eps`
    for the FGSM error table.
    """
    if ctx.invoked_subcommand is not None:
        return
    from pipeline.attacks.gradient import attack_loss
    from pipeline.evaluation.lab import lab_to_synthetic_factor

    lab = params.lab
    torch_setup(params)
    K_syn, K_zed = cameras(params)
    factor = lab_to_synthetic_factor(K_syn, K_zed, float(lab.scale))
    reason = retrain_reason(params)
    synthetic_lab = _lab_models(reason)
    paper = load_chain(params, PAPER, "." if synthetic_lab is None else LAB_MODELS, defended=False)
    chain, loss_fn, model_hash = paper.onboard, attack_loss(params.attack.loss, paper.loss), paper.pose_hash
    t0 = time.perf_counter()
    real = given(lab.real_data)
    source, truth = _lab_source(params, real)
    render_s = time.perf_counter() - t0
    sequences, ranges, loader_err = _sequences(params, source, truth, K_syn, K_zed)
    clean_rows, fgsm_rows, res, summary = _evaluate(params, chain, loss_fn, sequences)
    seconds = time.perf_counter() - t0
    train_metrics = _train_metrics(synthetic_lab)
    models = _models(synthetic_lab)
    metrics = {
        "model_hash": model_hash,
        "source": str(source),
        "synthetic": not real,
        "factor": factor,
        "retrain": lab.retrain,
        "reused_models": synthetic_lab is None,
        "retrain_reason": reason,
        "models": models,
        "synthetic_lab": synthetic_lab,
        "ranges": ranges,
        "loader_error": loader_err,
        "clean": clean_rows,
        "fgsm": fgsm_rows,
        "attack_length": lab.attack_length,
        "threshold": chain.threshold,
        "per_eps": {f"{x['eps']:g}": x for x in summary},
        "rows": res.rows,
        "clean_detection": res.clean,
        "accuracy_mean": float(np.mean([x["accuracy"] for x in summary])),
        "seconds": seconds,
        "render_seconds": render_s,
        "shipped": shipped_alarms(params, sequences),
        "rates": _rates(res.rows),
    }
    _write_outputs(params, metrics, res.rows, summary, sequences, train_metrics, K_syn, K_zed)
    typer.echo(
        f"lab: {'reused' if synthetic_lab is None else 'retrained'} models {models['pose']}, "
        f"{models['detector']}; {len(sequences)} sequences from {source}; mean detection accuracy "
        f"{100 * metrics['accuracy_mean']:.2f}% (paper {LAB}%) in {seconds:.0f} s -> {REPORT}"
    )


def _evaluate(
    p: Params, chain: Any, loss_fn: Any, sequences: list[Sequence]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], Any, list[dict[str, Any]]]:
    """(pose error rows clean, FGSM error rows at `attack.eps`: every lab frame; the integrated evaluation at
    `evaluate.eps`; its per-eps summary rows) of the paper's chain on the lab sequences."""
    from pipeline.evaluation.sequences import evaluate_sequences, fgsm_error_table, per_eps_summary

    e, length = p.evaluate, p.lab.attack_length
    clean_rows, fgsm_rows = fgsm_error_table(chain, loss_fn, sequences, [float(x) for x in p.attack.eps], e.batch_size)
    res = evaluate_sequences(chain, loss_fn, sequences, [float(x) for x in e.eps], length, e.batch_size, "lab evaluate")
    return clean_rows, fgsm_rows, res, per_eps_summary(res.rows)


def _train_metrics(synthetic_lab: dict[str, Any] | None) -> dict[str, Any] | None:
    """The training metrics of the paper's rows' pose model (main or synthetic-lab), or None when absent."""
    train_path = TRAIN_METRICS if synthetic_lab is None else LAB_MODELS / TRAIN_METRICS
    return read_json(train_path) if train_path.exists() else None


def _write_outputs(
    p: Params,
    metrics: dict[str, Any],
    rows: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    sequences: list[Sequence],
    train_metrics: dict[str, Any] | None,
    K_syn: Any,
    K_zed: Any,
) -> None:
    """Write reports/metrics/lab.json (NaN as null) and reports/lab.md."""
    from pipeline.evaluation.sequences import nan_to_none

    write_metrics(METRICS, nan_to_none(metrics), p.profile_name)
    atomic_write_text(
        REPORT,
        lab_page(p, metrics, rows, summary, [s.name for s in sequences], train_metrics, K_syn, K_zed, sequences),
    )


def _lab_source(p: Params, real: str | None) -> tuple[Path, list[dict[str, Any]]]:
    """(the folder of the lab recordings: `real` when given, else datasets/lab/ freshly rendered, the exact lab
    labels of the rendered sequences: empty for a real recording)."""
    truth: list[dict[str, Any]] = []
    source = Path(real) if real else OUT
    if not real:
        with atomic_dir(OUT) as tmp:
            truth = render_lab(p, tmp)
    return source, truth


def _models(synthetic_lab: dict[str, Any] | None) -> dict[str, Any]:
    """metrics `models`: the pose model and detector files the paper's rows used (reused main ones, or retrained)."""
    return (
        {"pose": str(CHAINS[PAPER].pose), "detector": str(CHAINS[PAPER].detector)}
        if synthetic_lab is None
        else {"pose": synthetic_lab["pose"], "detector": synthetic_lab["detector"]}
    )


def _rates(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """metrics `rates`: per eps the sequence rates with the attacked fraction of the paper's lab schedule."""
    from pipeline.attacks.schedule import attacked_fraction
    from pipeline.evaluation.rates import sequence_rates

    return {f"{x:g}": r.as_json(attacked_fraction(P_START, LAB_ATTACK_LENGTH)) for x, r in sequence_rates(rows).items()}


def shipped_alarms(p: Params, sequences: list[Sequence]) -> dict[str, Any]:
    """The chain that ships (robust model, its detector, the detector threshold of models/defense.json) on every
    clean lab frame: its false alarms (Wilson interval over frames: optimistic, frames of a sequence are
    correlated; and per sequence), the median and largest detector probability (the margin to the threshold),
    mean pose errors (m, deg; synthetic-frame metres), and the share of the frames' non-zero channel values that
    its black-level clamp erases (the lab's noise and blur lift them off zero)."""
    from pipeline.defense.chain import run_sequence
    from pipeline.pose.metrics import pose_errors
    from pipeline.stats import rate

    shipped = load_chain(p, SHIPPED)
    chain, model_hash, threshold = shipped.onboard, shipped.pose_hash, shipped.defended.settings.threshold
    level = float(getattr(chain.model, "black_level", 0.0))
    runs = [
        run_sequence(chain, s.images, s.targets, np.zeros(len(s.images), bool), None, p.evaluate.batch_size)
        for s in sequences
    ]
    flags = [res.prob >= threshold for res in runs]
    pos, att = (np.concatenate(e) for e in zip(*(pose_errors(res.pose, s.targets) for res, s in zip(runs, sequences))))
    values = np.concatenate([s.images[s.images > 0] for s in sequences]).astype(np.float64) / 255
    r = rate(np.concatenate(flags))
    probs = np.concatenate([res.prob for res in runs]).astype(np.float64)
    return {
        "model": SHIPPED.value,
        "model_hash": model_hash,
        "threshold": threshold,
        "frames": int(r.n),
        "probability_median": float(np.median(probs)),
        "probability_max": float(probs.max()),
        "false_alarms": int(np.concatenate(flags).sum()),
        "rate": r.value,
        "rate_ci95": r.ci(),
        "per_sequence": {s.name: int(f.sum()) for s, f in zip(sequences, flags)},
        "position_m": float(pos.mean()),
        "attitude_deg": float(att.mean()),
        "black_level": level,
        "clamp_erased": float((values < level).mean()) if values.size else None,
    }


def _lab_models(reason: str | None) -> dict[str, Any] | None:
    """The synthetic-lab summary of `rpod lab_models` when the lab must use retrained models (`reason`), else
    None; refuses a datasets/lab_models/ made for other params."""
    summary = read_json(LAB_MODELS_SUMMARY)
    if summary.get("reason") != reason:
        raise StageError(
            f"{LAB_MODELS} was made for other lab params (retrain reason {summary.get('reason')!r}, "
            f"now {reason!r}); run `rpod lab_models` (dvc repro lab_models)"
        )
    return summary if summary["retrained"] else None


def _sequences(
    p: Params, source: Path, truth: list[dict[str, Any]], K_syn: Any, K_zed: Any
) -> tuple[list[Sequence], list[dict[str, Any]], dict[str, dict[str, float]]]:
    """The recordings in `source` read through the real-data loader, as chain sequences (synthetic-frame
    targets in metres, seeded attack schedules), their range table rows, and the loader's label error
    against the exact render poses (`truth`, synthetic lab only)."""
    from pipeline.evaluation.lab import chain_sequences, loader_errors

    lab = p.lab
    recs = read_recordings(p, source)
    sequences, ranges = chain_sequences(
        recs, K_syn, K_zed, float(lab.scale), float(p.evaluate.p_start), lab.attack_length, lab.seed
    )
    return sequences, ranges, loader_errors(recs, truth)


app.command("rescale")(with_params(rescale))
app.callback(invoke_without_command=True)(with_params(main))

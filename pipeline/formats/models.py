"""Model checkpoints: the pose model and the LSTM detector, as plain dicts loadable with
`torch.load(weights_only=True)` (pipeline.io.checkpoints), read back safely.

Pose (`POSE_FORMAT`, written by `rpod train`):
    format: "rpodguard-pose/1", arch: {width, dropout}, input_size: [height, width] (pixels),
    K: the 3x3 camera matrix of the training images at the input size (pixels), labels_hash: the
    `file_hash` of the label table it was trained on (both absent in checkpoints written before they were
    recorded), model: the PoseNet state dict, loss: {s_p, s_r, reduction} (the
    learned loss, for attacks), meta: small JSON-like facts (epoch, errors, ...).
Detector (`DETECTOR_FORMAT`, written by `rpod detect`): pipeline.detectors.lstm.to_checkpoint's dict
plus format, threshold, pose_model_hash (the pose file's `file_hash`), background_mean (D,) and
shap_method.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pipeline.io.checkpoints import load_torch, save_torch
from pipeline.io.errors import DataError

POSE_FORMAT = "rpodguard-pose/1"
DETECTOR_FORMAT = "rpodguard-detector/1"
POSE_REDO = "re-run `rpod train`"  # how a bad pose checkpoint is remade, in messages
DETECTOR_REDO = "re-run `rpod detect`"


def save_pose(
    path: Path | str,
    model: Any,
    loss: Any,
    input_size: tuple[int, int],
    meta: dict[str, Any],
    K: Any = None,
    labels_hash: str | None = None,
) -> None:
    """Write a pose checkpoint atomically (temporary file + rename); `input_size` = (height, width) pixels,
    `K` the camera matrix (3x3, pixels at that size) of the training images and `labels_hash` the label
    table's file hash, when known."""
    state = {
        "format": POSE_FORMAT,
        "arch": model.arch(),
        "input_size": [int(input_size[0]), int(input_size[1])],
        **({} if K is None else {"K": [[float(v) for v in row] for row in K]}),
        **({} if labels_hash is None else {"labels_hash": labels_hash}),
        "model": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
        "loss": {"s_p": loss.s_p.item(), "s_r": loss.s_r.item(), "reduction": loss.reduction},
        "meta": meta,
    }
    save_torch(path, state)


POSE_KEYS = {"format", "arch", "input_size", "model", "loss", "meta"}  # required; K and labels_hash optional
ARCH_KEYS = {"width", "dropout", "black_level"}  # PoseNet's arguments (black_level: robust)
LOG_VARIANCE_LIMIT = 10.0  # |s_p|, |s_r| above this (weights exp(-2 s) beyond 5e8 or 2e-9) are no learned loss


def read_pose(path: Path | str) -> dict[str, Any]:
    """A pose checkpoint dict, loaded with weights_only=True (a DataError when missing, damaged, foreign or
    non-finite), its keys, their types and the weights' shapes checked (`pose_problem`)."""
    ckpt = load_torch(path, POSE_FORMAT, POSE_REDO)
    problem = pose_problem(ckpt)
    if problem:
        raise DataError(f"pose checkpoint {path}: {problem}; {POSE_REDO}")
    return ckpt


def pose_problem(ckpt: dict[str, Any]) -> str | None:
    """What is wrong with the keys of a pose checkpoint dict (missing, unknown, of the wrong type, learned loss
    weights out of range, weights that do not fit its arch), or None."""
    import torch

    from pipeline.pose.model import PoseNet

    keys = set(ckpt)
    if not POSE_KEYS <= keys or keys - POSE_KEYS - {"K", "labels_hash"}:
        return f"keys missing {sorted(POSE_KEYS - keys) or 'none'}, unknown {sorted(keys - POSE_KEYS - {'K', 'labels_hash'}) or 'none'}"
    arch, size, loss = ckpt["arch"], ckpt["input_size"], ckpt["loss"]
    if (
        not isinstance(arch, dict)
        or not {"width", "dropout"} <= set(arch) <= ARCH_KEYS
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in arch.values())
    ):
        return f"arch must hold numbers width, dropout and optionally black_level, got {arch!r}"
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(type(v) is int and v > 0 for v in size)):
        return f"input_size must be [height, width] in pixels, got {size!r}"
    if not isinstance(ckpt["model"], dict) or not all(isinstance(v, torch.Tensor) for v in ckpt["model"].values()):
        return "model must be a state dict of tensors"

    class Shapes(PoseNet):
        def _init_weights(self) -> None:  # random init of meta tensors is slow and needless: shapes only
            pass

    try:
        with torch.device("meta"):  # nothing allocated, whatever width the arch claims
            want = {k: tuple(v.shape) for k, v in Shapes(**arch).state_dict().items()}
    except ValueError as e:
        return f"arch {arch}: {e}"
    have = {k: tuple(v.shape) for k, v in ckpt["model"].items()}
    if want != have:
        odd = sorted(k for k in want.keys() | have.keys() if want.get(k) != have.get(k))
        return (
            f"its weights do not fit arch {arch} ({len(odd)} tensors missing, unknown or misshapen, first "
            f"{odd[0]}: {have.get(odd[0], 'missing')} for {want.get(odd[0], 'none')})"
        )
    if not (
        isinstance(loss, dict) and set(loss) == {"s_p", "s_r", "reduction"} and loss["reduction"] in ("mean", "sum")
    ):
        return f"loss must hold s_p, s_r and reduction 'mean' or 'sum', got {loss!r}"
    bad = [k for k in ("s_p", "s_r") if not isinstance(loss[k], (int, float)) or abs(loss[k]) > LOG_VARIANCE_LIMIT]
    if bad:
        return (
            f"loss {bad[0]} = {loss[bad[0]]!r} is no learned log-variance (|s| <= {LOG_VARIANCE_LIMIT:g}; the "
            f"loss weighs its term by exp(-2 s))"
        )
    if not isinstance(ckpt["meta"], dict):
        return "meta must be a dict"
    return None


def check_role(ckpt: dict[str, Any], robust: bool, path: Path | str) -> None:
    """Refuse (DataError) a pose checkpoint of the other role: the robust model (the chain that ships, `rpod train
    --robust`) has a black-level clamp in its arch (`black_level`), the standard one (`rpod train`) none."""
    clamped = "black_level" in ckpt["arch"]
    if clamped != robust:
        have, want = ("robust", "standard") if clamped else ("standard", "robust")
        raise DataError(
            f"{path} holds the {have} pose model (arch {ckpt['arch']}) where the {want} one belongs; "
            f"{'re-run `rpod train --robust`' if robust else POSE_REDO} or restore the file"
        )


def model_from_checkpoint(ckpt: dict[str, Any], device: Any = "cpu", amp: bool = False) -> Any:
    """The PoseNet of a checkpoint dict, in eval mode on `device` (`amp`: bf16 autocast there, CUDA only)."""
    from pipeline.pose.model import PoseNet

    model = PoseNet(**ckpt["arch"])
    model.load_state_dict(ckpt["model"])
    return model.place(device, amp).eval()


def loss_from_checkpoint(ckpt: dict[str, Any]) -> Any:
    """The PoseLoss with the learned weights s_p, s_r of a checkpoint dict (what attacks ascend)."""
    import torch

    from pipeline.pose.loss import PoseLoss

    loss = PoseLoss(ckpt["loss"]["reduction"])
    with torch.no_grad():
        loss.s_p.fill_(ckpt["loss"]["s_p"])
        loss.s_r.fill_(ckpt["loss"]["s_r"])
    return loss


@dataclass(frozen=True)
class Pose:
    """A pose checkpoint loaded: the PoseNet (eval mode), its learned training loss (what attacks ascend), the
    file's hash and the checkpoint's facts without the weights (`checkpoint`: arch, input_size, K, labels_hash,
    meta: best epoch, test errors in m and deg)."""

    model: Any
    loss: Any
    hash: str
    checkpoint: dict[str, Any]

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self.checkpoint.get("meta", {}))


def load_pose(
    path: Path | str,
    device: Any = "cpu",
    amp: bool = False,
    check: Callable[[Path, dict[str, Any]], None] | None = None,
) -> Pose:
    """The pose checkpoint at `path` read once (`read_pose`; `check(path, checkpoint)` may refuse it before the
    network is built), its network placed on `device` (with `amp`: bf16 autocast on CUDA)."""
    from pipeline.io.atomic import file_hash

    path = Path(path)
    ckpt = read_pose(path)
    if check is not None:
        check(path, ckpt)
    facts = {k: v for k, v in ckpt.items() if k not in ("model", "loss")}
    return Pose(model_from_checkpoint(ckpt, device, amp), loss_from_checkpoint(ckpt), file_hash(path), facts)


def read_detector(path: Path | str, model_hash: str | None = None) -> tuple[Any, dict[str, Any]]:
    """The LSTM detector (eval mode) and its checkpoint dict (threshold, pose_model_hash,
    background_mean (D,) tensor, shap_method, ...). With `model_hash`, refuse a detector trained
    on another pose checkpoint's SHAP values."""
    from pipeline.detectors.lstm import from_checkpoint

    path = Path(path)
    ckpt = load_torch(path, DETECTOR_FORMAT, DETECTOR_REDO)
    threshold, mean = ckpt.get("threshold"), ckpt.get("background_mean")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 < threshold < 1:
        raise DataError(
            f"detector checkpoint {path}: threshold {threshold!r} is no probability in (0, 1); {DETECTOR_REDO}"
        )
    try:
        detector = from_checkpoint(ckpt)
        width = detector.config.n_features
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        first = str(e).split("\n\t")[1:2] or [str(e)]
        raise DataError(
            f"detector checkpoint {path} does not hold an LSTM detector ({type(e).__name__}: "
            f"{first[0].strip()}); {DETECTOR_REDO}"
        ) from None
    if not hasattr(mean, "shape") or tuple(mean.shape) != (width,):
        raise DataError(
            f"detector checkpoint {path}: background_mean must hold the {width} features' SHAP "
            f"background mean, got shape {tuple(getattr(mean, 'shape', ())) or type(mean).__name__}; "
            f"{DETECTOR_REDO}"
        )
    if model_hash is not None and ckpt.get("pose_model_hash") != model_hash:
        raise DataError(
            f"{path} was trained for pose checkpoint {ckpt.get('pose_model_hash')!r}, not {model_hash!r}; "
            f"re-run `rpod shap` and `rpod detect`"
        )
    return detector, ckpt

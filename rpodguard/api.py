"""The trained safety chain as one object: `load_chain(folder)` -> `Chain`; `Chain.predict(images)` -> `Prediction`.

Files read: the chain that ships, the robust pose model and its LSTM detector (with its threshold and the SHAP
background mean): by default the weights bundle shipped in git (rpodguard/weights/default/pose.pt and detector.pt,
written by scripts/bundle_weights.py; its manifest's hashes are checked); a run's models/ folder (or the project
root holding it) as `rpod train --robust` and `rpod detect --model robust` wrote them, models/pose_robust.pt and
models/detector_robust.pt; or any folder holding pose.pt and detector.pt (another chain, e.g. the standard one).
Images are resized to the model's input as the lab loader resizes them (pipeline.images.resize:
area averaging when shrinking), without keeping their aspect. Given the camera the images were taken with,
`predict` warns when it is not the one the model was trained for (rpodguard/camera.py).
A frame with too few lit pixels has no target in view: it gets no pose (NaN) and no attack flag.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence, Union

import numpy as np

from pipeline.io.errors import DataError

ASPECT_TOLERANCE = 0.01   # relative difference of width/height above which `predict` warns
BATCH = 64                # images per forward pass
# No target in view: under MIN_LIT_FRACTION of the pixels (at the model input) have a channel >= LIT_LEVEL
# (pipeline/visibility.py, where the producers of data sets apply the same rule).
from pipeline.visibility import LIT_LEVEL, MIN_LIT_FRACTION  # noqa: E402

Image = Union[str, Path, np.ndarray]
BUNDLE = Path(__file__).resolve().parent / "weights" / "default"   # the default profile's trained chain (git)


@dataclass(frozen=True)
class Prediction:
    """The chain's output for N images; row k belongs to image k (`sources[k]`: its path or `array[k]`).

    position (N, 3): target origin in the camera frame (m; OpenCV axes x right, y down, z forward);
    quaternion (N, 4): (qw, qx, qy, qz), qw >= 0, rotating target-frame vectors into the camera frame;
    rotation_6d (N, 6): the network's 6-D rotation (first two columns of R, column-wise, before
    Gram-Schmidt); attack_probability (N,): the detector's P(attacked); attack_flag (N,) bool:
    probability >= the detector's threshold (chosen on validation data by `rpod detect`);
    lit_fraction (N,): the fraction of lit pixels (LIT_LEVEL); in_view (N,) bool: lit_fraction >=
    MIN_LIT_FRACTION. A frame with no target in view has NaN pose and probability and no flag.
    """

    sources: tuple[str, ...]
    position: np.ndarray
    quaternion: np.ndarray
    rotation_6d: np.ndarray
    attack_probability: np.ndarray
    attack_flag: np.ndarray
    lit_fraction: np.ndarray
    in_view: np.ndarray

    def __len__(self) -> int:
        return len(self.sources)

    def records(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per image (position in m, quaternion qw first, 6-D, probability, flag; null
        for each of these when no target is in view)."""
        def values(a: np.ndarray) -> Any:
            return None if np.isnan(a).any() else a.tolist()

        return [{"image": name, "in_view": bool(self.in_view[k]), "lit_fraction": float(self.lit_fraction[k]),
                 "position_m": values(self.position[k]), "quaternion": values(self.quaternion[k]),
                 "rotation_6d": values(self.rotation_6d[k]), "attack_probability": values(self.attack_probability[k]),
                 "attack_flag": bool(self.attack_flag[k])} for k, name in enumerate(self.sources)]


class Chain:
    """The per-image safety chain of a trained run: pose CNN -> exact SHAP signature -> LSTM detector.

    `predict` judges each image on its own. The motion-filter defense (pipeline/defense/fusion.py), which
    checks estimates against the chaser's motion, needs sequences: `track`. Positions assume
    the camera the model was trained with (params.yaml `camera`): an image from a camera with another
    field of view gives ranges off by the ratio of the focal lengths (pixels per image width).
    """

    def __init__(self, safety: Any, input_size: tuple[int, int], manifest: dict[str, Any] | None = None,
                 camera: Any = None):
        self.safety = safety                      # pipeline.defense.chain.SafetyChain
        self.height, self.width = input_size      # model input, pixels
        self.files = safety.files                 # (pose.pt, detector.pt, defense.json)
        self.manifest = manifest                  # a weights bundle's manifest (profile, commit, params), else None
        self.camera = camera                      # the model's camera at its input size (Intrinsics), None: unknown

    @property
    def threshold(self) -> float:
        """The detector's flag threshold on the attack probability."""
        return self.safety.threshold

    def predict(self, images: Image | Sequence[Image], batch_size: int = BATCH, camera: Any = None) -> Prediction:
        """Pose and attack flag per image. `images`: a path, an array (H, W, 3) or (N, H, W, 3) (RGB,
        uint8 or float in [0, 1]), or a list of paths and arrays; any size (resized to the model
        input, with a UserWarning when the aspect differs from the model's). `camera`: the images' camera,
        a 3x3 K (pixels, at the images' size) or a SPEED+ camera.json dict; a UserWarning when it is not the
        model's camera (rpodguard.camera). A frame with no target in view (`MIN_LIT_FRACTION`) gets NaN
        pose and probability and no flag."""
        import torch

        from pipeline.geometry.rotations import sixd_to_quat
        from rpodguard.camera import camera_warnings

        names, fitted, said = [], [], []
        for name, image in _items(images):
            names.append(name)
            fitted.append(self._fit(image, name))
            if camera is not None:
                said += camera_warnings(self.camera, camera, image.shape[1], image.shape[0], name)
        for text in dict.fromkeys(said):   # each once
            warnings.warn(text, UserWarning, stacklevel=2)
        if not names:
            raise ValueError("no images given (pass one or more image files or arrays)")
        x = torch.from_numpy(np.stack(fitted)).permute(0, 3, 1, 2)
        pose, prob, flag = [], [], []
        for lo in range(0, len(x), batch_size):
            out = self.safety.onboard(x[lo:lo + batch_size])
            pose.append(out.pose.numpy().astype(np.float64))
            prob.append(out.prob.numpy().astype(np.float64))
            flag.append(out.flag.numpy())
        lit = (x.numpy().max(axis=1) >= LIT_LEVEL).mean(axis=(1, 2))
        seen = lit >= MIN_LIT_FRACTION
        p = np.where(seen[:, None], np.concatenate(pose), np.nan)
        quaternion = np.full((len(p), 4), np.nan)
        quaternion[seen] = sixd_to_quat(p[seen, 3:9]).reshape(-1, 4)
        return Prediction(tuple(names), p[:, :3], quaternion, p[:, 3:9], np.where(seen, np.concatenate(prob), np.nan),
                          np.concatenate(flag).astype(bool) & seen, lit, seen)

    def track(self, images: Image | Sequence[Image], commands: np.ndarray, attitudes: np.ndarray,
              batch_size: int = BATCH, camera: Any = None) -> Any:
        """The defended chain over a sequence (rpodguard/sequence.py): `images` in time order, the chaser's
        commanded displacement of the target's relative position per frame `commands` (N, 3; world axes,
        m; row 0 unused) and camera `attitudes` (N, 3, 3; camera -> world) -> a `Track`: per frame the
        trusted estimate (world, m), its protection level (m) and availability; `camera` the images' K, as in
        `predict`. Needs FOLDER/defense.json (`rpod calibrate`)."""
        from rpodguard.sequence import track

        return track(self, images, commands, attitudes, batch_size, camera)

    def _fit(self, image: np.ndarray, name: str) -> np.ndarray:
        """One RGB image -> float32 (height, width, 3) in [0, 1] at the model input size."""
        from pipeline.images import resize

        if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) == 0:
            raise ValueError(f"{name}: an image must be (H, W, 3) RGB, got shape {tuple(image.shape)}")
        if image.dtype != np.uint8:
            if not np.issubdtype(image.dtype, np.floating):
                raise ValueError(f"{name}: pixels must be uint8 or float in [0, 1], got {image.dtype}")
            image = image.astype(np.float32)
            if not np.isfinite(image).all() or image.min() < 0 or image.max() > 1:
                raise ValueError(f"{name}: float pixels must be finite and in [0, 1]")
        h, w = image.shape[:2]
        want = self.width / self.height
        if abs(w / h - want) > ASPECT_TOLERANCE * want:
            warnings.warn(f"{name} is {w}x{h} (aspect {w / h:.3f}), the model's input {self.width}x{self.height} "
                          f"(aspect {want:.3f}): stretched to fit, so the pose may be off", UserWarning, stacklevel=3)
        out = resize(np.ascontiguousarray(image), self.width, self.height)
        return out.astype(np.float32) / 255.0 if out.dtype == np.uint8 else out.astype(np.float32)


def _items(images: Image | Sequence[Image]) -> Iterator[tuple[str, np.ndarray]]:
    """(name, RGB array) of each input image, read from disk one at a time."""
    if isinstance(images, (str, Path)):
        images = [images]
    elif isinstance(images, np.ndarray):
        if images.ndim not in (3, 4):
            raise ValueError(f"images must be (H, W, 3) or (N, H, W, 3), got shape {images.shape}")
        images = [images] if images.ndim == 3 else list(images)
    for k, item in enumerate(images):
        if isinstance(item, (str, Path)):
            yield str(item), read_image(Path(item))
        else:
            yield f"array[{k}]", np.asarray(item)


def check_files(paths: Sequence[str | Path]) -> None:
    """Refuse (DataError naming it) a path that is missing or not a file: cheap, before any model loads."""
    for path in map(Path, paths):
        if not path.exists():
            raise DataError(f"{path} not found")
        if not path.is_file():
            raise DataError(f"{path} is not a file (give image files, e.g. PNG or JPG)")


def read_image(path: Path) -> np.ndarray:
    """An image file (PNG, JPG, TIFF, ... as Pillow reads them) -> uint8 (H, W, 3) RGB as a viewer shows it:
    EXIF orientation applied, 16-bit scaled to 8 bits, float pixels in [0, 1] scaled, transparency
    composited on black (space) with a UserWarning. A missing, unreadable or truncated file, an animation
    and 32-bit integer or out-of-range float pixels are a DataError naming the file."""
    from PIL import Image as PILImage
    from PIL import ImageOps

    check_files([path])
    try:
        with PILImage.open(path) as im:
            if getattr(im, "n_frames", 1) > 1:
                raise DataError(f"{path} holds {im.n_frames} frames (an animation or a multi-page file); give "
                                f"one image per file")
            im.load()
            return _rgb(ImageOps.exif_transpose(im), path)
    except DataError:
        raise
    except (OSError, ValueError, SyntaxError, PILImage.DecompressionBombError) as e:
        raise DataError(f"{path} cannot be read as an image ({type(e).__name__}: {e})") from None


def _rgb(im: Any, path: Path) -> np.ndarray:
    """uint8 (H, W, 3) RGB of a decoded Pillow image (see `read_image`)."""
    if im.mode.startswith("I;16") or im.mode in ("F", "I"):
        if im.mode == "I":
            raise DataError(f"{path} has 32-bit integer pixels (no defined white level); save it as an 8- or "
                            f"16-bit image")
        grey = np.asarray(im)
        if im.mode == "F":
            if not np.isfinite(grey).all() or grey.min() < 0 or grey.max() > 1:
                raise DataError(f"{path} has float pixels outside [0, 1] (min {grey.min():g}, max "
                                f"{grey.max():g}); save it scaled to [0, 1] or as an 8-bit image")
            grey = np.round(grey * 255)
        else:
            grey = grey.astype(np.uint16) >> 8
        return np.repeat(grey.astype(np.uint8)[..., None], 3, axis=2)
    if "A" in im.getbands() or "transparency" in im.info:
        rgba = np.asarray(im.convert("RGBA")).astype(np.float32)
        if (rgba[..., 3] < 255).any():
            warnings.warn(f"{path} has transparent pixels: composited on black (space)", stacklevel=2)
        return np.round(rgba[..., :3] * rgba[..., 3:] / 255).astype(np.uint8)
    return np.asarray(im.convert("RGB"))


def load_chain(folder: str | Path | None = None) -> Chain:
    """The chain as the pipeline ships it (the robust pose model and its detector, and its defense when calibrated):
    with no FOLDER, the bundled weights (`BUNDLE`: the default profile's trained chain, see its manifest.json); a
    run's models/ folder (or a project root holding it): models/pose_robust.pt, detector_robust.pt and defense.json;
    else FOLDER/pose.pt, FOLDER/detector.pt and FOLDER/defense.json (read by pipeline.formats.chain.load_chain, the
    one door to a chain, which checks a bundle's sha256, that the detector and the defense were made for this pose
    model and that the defense file is sound). A missing, changed or bad file is a DataError."""
    from pipeline.formats.chain import load_chain as open_chain
    from rpodguard.camera import model_camera

    safety = open_chain(BUNDLE if folder is None else folder, defended=None, bundle=folder is None)
    ckpt = safety.checkpoint
    height, width = (int(v) for v in ckpt["input_size"])
    manifest = ckpt.get("manifest")
    return Chain(safety, (height, width), manifest, model_camera(ckpt, manifest, safety.files[0]))

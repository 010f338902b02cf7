"""The trained safety chain as one object: `load_chain(folder)` -> `Chain`; `Chain.predict(images)` -> `Prediction`.

Files read: the chain that ships, the robust pose model and its LSTM detector (with its threshold and the SHAP
background mean): by default the weights bundle shipped in git (rpodguard/weights/default/pose.pt and detector.pt,
written by scripts/bundle_weights.py; its manifest's hashes are checked); a run's models/ folder (or the project
root holding it) as `rpod train --robust` and `rpod detect --model robust` wrote them, models/pose_robust.pt and
models/detector_robust.pt; or any folder holding pose.pt and detector.pt (another chain, e.g. the standard one).
Images are resized to the model's input as the lab loader resizes them (pipeline.images.resize:
area averaging when shrinking), without keeping their aspect. Given the camera the images were taken with,
`predict` warns when it is not the one the model was trained for (rpodguard/camera.py).

Each image's verdict is the shipped chain's: "attack" from the calibrated threshold of the chain's defense file,
"doubt" from its doubt level (a frame the defended chain would not let update its motion filter), else "clean"
(`VerdictRule`; a folder without defense.json falls back on the detector checkpoint's own threshold, no doubt level,
and says so). An image that is not a camera frame with the target in view gets no pose (NaN) and no verdict on an
attack: too few lit pixels ("no target") or neighbouring pixels that do not correlate, as in noise ("not a frame";
pipeline/visibility.py says what the two rules can and cannot tell).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence, Union

import numpy as np

from pipeline.io.errors import DataError

ASPECT_TOLERANCE = 0.01  # relative difference of width/height above which `predict` warns
BATCH = 64  # images per forward pass
# No target in view: under MIN_LIT_FRACTION of the pixels (at the model input) have a channel >= LIT_LEVEL
# (pipeline/visibility.py, where the producers of data sets apply the same rule); not a camera frame: the
# correlation of neighbouring pixels under MIN_STRUCTURE (noise).
from pipeline.visibility import LIT_LEVEL, MIN_LIT_FRACTION, MIN_STRUCTURE  # noqa: E402

NO_TARGET, NOT_A_FRAME = "no target", "not a frame"  # the verdicts of an image that gets no pose

Image = Union[str, Path, np.ndarray]
BUNDLE = Path(__file__).resolve().parent / "weights" / "default"  # the default profile's trained chain (git)


@dataclass(frozen=True)
class VerdictRule:
    """How `predict` judges an image by its attack probability, as the defended chain does: `settings` (the chain's
    pipeline.defense.settings.DefenseSettings: "attack" at or above its threshold, "doubt" at or above its doubt level
    `update_below`, else "clean": `DefenseSettings.word`), `calibrated`: whether they are the defense file's
    (`path`), else the detector checkpoint's own threshold (`path`: the detector) with no doubt level."""

    settings: Any
    calibrated: bool
    path: Path

    @property
    def threshold(self) -> float:
        """The attack threshold on the probability."""
        return float(self.settings.threshold)

    @property
    def doubt(self) -> float | None:
        """The doubt level on the probability (None: none)."""
        return None if self.settings.update_below is None else float(self.settings.update_below)

    def verdict(self, prob: float) -> str:
        """ "attack", "doubt" or "clean" for an attack probability."""
        return str(self.settings.word(float(prob)))

    def describe(self) -> str:
        """One line: the levels in full and where they come from."""
        levels = f"attack at P(attack) >= {self.threshold!r}" + (
            f", doubt at >= {self.doubt!r}" if self.doubt is not None else ""
        )
        if self.calibrated:
            fusion = self.settings.fusion
            note = (
                ""
                if fusion != "motion"
                else (f"; its fusion {fusion!r} flies on the motion checks alone, so the chain would act on neither")
            )
            return f"verdict: {levels} (the chain's calibrated defense, {self.path}{note})"
        return (
            f"verdict: {levels} (the detector's own threshold, no doubt level: {self.path.parent} has no "
            f"defense.json, which `rpod calibrate` writes)"
        )

    def records(self) -> dict[str, Any]:
        """The rule as JSON-ready fields of a record."""
        return {
            "threshold": self.threshold,
            "doubt_level": self.doubt,
            "rule": "calibrated defense" if self.calibrated else "detector threshold (no defense file)",
            "rule_file": str(self.path),
        }


@dataclass(frozen=True)
class Prediction:
    """The chain's output for N images; row k belongs to image k (`sources[k]`: its path or `array[k]`).

    position (N, 3): target origin in the camera frame (m; OpenCV axes x right, y down, z forward);
    quaternion (N, 4): (qw, qx, qy, qz), qw >= 0, rotating target-frame vectors into the camera frame;
    rotation_6d (N, 6): the network's 6-D rotation (first two columns of R, column-wise, before
    Gram-Schmidt); attack_probability (N,): the detector's P(attacked); verdict (N,) str: "attack", "doubt"
    or "clean" by `rule` (the chain's calibrated levels, `VerdictRule`), or NO_TARGET / NOT_A_FRAME for an image
    that gets no pose; attack_flag (N,) bool: verdict "attack"; lit_fraction (N,): the fraction of lit pixels
    (LIT_LEVEL); structure (N,): the correlation of neighbouring pixels (pipeline.visibility.structure);
    in_view (N,) bool: a camera frame with the target in view (lit_fraction >= MIN_LIT_FRACTION and structure
    >= MIN_STRUCTURE). An image not in view has NaN pose and probability and no flag.
    """

    sources: tuple[str, ...]
    position: np.ndarray
    quaternion: np.ndarray
    rotation_6d: np.ndarray
    attack_probability: np.ndarray
    verdict: tuple[str, ...]
    lit_fraction: np.ndarray
    structure: np.ndarray
    rule: VerdictRule

    @property
    def in_view(self) -> np.ndarray:
        """(N,) bool: a camera frame with the target in view (a pose was estimated)."""
        return np.array([v not in (NO_TARGET, NOT_A_FRAME) for v in self.verdict], dtype=bool)

    @property
    def attack_flag(self) -> np.ndarray:
        """(N,) bool: the verdict is "attack"."""
        return np.array([v == "attack" for v in self.verdict], dtype=bool)

    def __len__(self) -> int:
        return len(self.sources)

    def why_no_pose(self, k: int) -> str:
        """Why image k got no pose, in words (for an image not in view)."""
        if self.verdict[k] == NO_TARGET:
            return f"no target in view ({100 * self.lit_fraction[k]:.2f}% lit pixels, under {MIN_LIT_FRACTION:.2%})"
        return (
            f"not a camera frame: neighbouring pixels correlate {self.structure[k]:.2f}, under {MIN_STRUCTURE} (noise?)"
        )

    def records(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per image (position in m, quaternion qw first, 6-D, probability, verdict and the
        rule it was judged by; null for the pose and probability when the image got no pose)."""

        def values(a: np.ndarray) -> Any:
            return None if np.isnan(a).any() else a.tolist()

        rule = self.rule.records()
        return [
            {
                "image": name,
                "in_view": bool(self.in_view[k]),
                "lit_fraction": float(self.lit_fraction[k]),
                "structure": float(self.structure[k]),
                "position_m": values(self.position[k]),
                "quaternion": values(self.quaternion[k]),
                "rotation_6d": values(self.rotation_6d[k]),
                "attack_probability": values(self.attack_probability[k]),
                "verdict": self.verdict[k],
                "attack_flag": bool(self.attack_flag[k]),
                **rule,
            }
            for k, name in enumerate(self.sources)
        ]


class Chain:
    """The per-image safety chain of a trained run: pose CNN -> exact SHAP signature -> LSTM detector.

    `predict` judges each image on its own. The motion-filter defense (pipeline/defense/fusion.py), which
    checks estimates against the chaser's motion, needs sequences: `track`. Positions assume
    the camera the model was trained with (params.yaml `camera`): an image from a camera with another
    field of view gives ranges off by the ratio of the focal lengths (pixels per image width).
    """

    def __init__(
        self, safety: Any, input_size: tuple[int, int], manifest: dict[str, Any] | None = None, camera: Any = None
    ):
        self.safety = safety  # pipeline.defense.chain.SafetyChain
        self.height, self.width = input_size  # model input, pixels
        self.files = safety.files  # (pose.pt, detector.pt, defense.json)
        self.manifest = manifest  # a weights bundle's manifest (profile, commit, params), else None
        self.camera = camera  # the model's camera at its input size (Intrinsics), None: unknown

    @property
    def rule(self) -> VerdictRule:
        """How `predict` judges an image (`VerdictRule`): the defended chain's calibrated threshold and doubt level
        from its defense file, else the detector checkpoint's own threshold."""
        from pipeline.defense.settings import DefenseSettings

        _, detector, defense = self.files
        if self.safety.defended is not None:
            return VerdictRule(self.safety.defended.settings, True, Path(defense))
        return VerdictRule(DefenseSettings(threshold=self.safety.threshold), False, Path(detector))

    @property
    def threshold(self) -> float:
        """The attack threshold on the probability that `predict` flags at (`rule`)."""
        return self.rule.threshold

    def predict(self, images: Image | Sequence[Image], batch_size: int = BATCH, camera: Any = None) -> Prediction:
        """Pose and verdict per image. `images`: a path, an array (H, W, 3) or (N, H, W, 3) (RGB,
        uint8 or float in [0, 1]), or a list of paths and arrays; any size (resized to the model
        input, with a UserWarning when the aspect differs from the model's). `camera`: the images' camera,
        a 3x3 K (pixels, at the images' size) or a SPEED+ camera.json dict; a UserWarning when it is not the
        model's camera (rpodguard.camera). The verdict is the chain's (`rule`); an image that is not a camera
        frame with the target in view (`MIN_LIT_FRACTION`, `MIN_STRUCTURE`) gets NaN pose and probability."""
        import torch

        from pipeline.geometry.rotations import sixd_to_quat
        from pipeline.visibility import structure
        from rpodguard.camera import camera_warnings

        names, fitted, said = [], [], []
        for name, image in _items(images):
            names.append(name)
            fitted.append(self._fit(image, name))
            if camera is not None:
                said += camera_warnings(self.camera, camera, image.shape[1], image.shape[0], name)
        for text in dict.fromkeys(said):  # each once
            warnings.warn(text, UserWarning, stacklevel=2)
        if not names:
            raise ValueError("no images given (pass one or more image files or arrays)")
        x = torch.from_numpy(np.stack(fitted)).permute(0, 3, 1, 2)
        pose, prob = [], []
        for lo in range(0, len(x), batch_size):
            out = self.safety.onboard(x[lo : lo + batch_size])
            pose.append(out.pose.numpy().astype(np.float64))
            prob.append(out.prob.numpy().astype(np.float64))
        pixels = np.stack(fitted)
        lit = (pixels.max(axis=3) >= LIT_LEVEL).mean(axis=(1, 2))
        smooth = structure(pixels)
        rule = self.rule
        verdict = tuple(
            NO_TARGET if lit[k] < MIN_LIT_FRACTION else NOT_A_FRAME if smooth[k] < MIN_STRUCTURE else rule.verdict(p)
            for k, p in enumerate(np.concatenate(prob))
        )
        seen = np.array([v not in (NO_TARGET, NOT_A_FRAME) for v in verdict], dtype=bool)
        p = np.where(seen[:, None], np.concatenate(pose), np.nan)
        quaternion = np.full((len(p), 4), np.nan)
        quaternion[seen] = sixd_to_quat(p[seen, 3:9]).reshape(-1, 4)
        return Prediction(
            tuple(names),
            p[:, :3],
            quaternion,
            p[:, 3:9],
            np.where(seen, np.concatenate(prob), np.nan),
            verdict,
            lit,
            smooth,
            rule,
        )

    def track(
        self,
        images: Image | Sequence[Image],
        commands: np.ndarray,
        attitudes: np.ndarray,
        batch_size: int = BATCH,
        camera: Any = None,
    ) -> Any:
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
            warnings.warn(
                f"{name} is {w}x{h} (aspect {w / h:.3f}), the model's input {self.width}x{self.height} "
                f"(aspect {want:.3f}): stretched to fit, so the pose may be off",
                UserWarning,
                stacklevel=3,
            )
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
                raise DataError(
                    f"{path} holds {im.n_frames} frames (an animation or a multi-page file); give one image per file"
                )
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
            raise DataError(
                f"{path} has 32-bit integer pixels (no defined white level); save it as an 8- or 16-bit image"
            )
        grey = np.asarray(im)
        if im.mode == "F":
            if not np.isfinite(grey).all() or grey.min() < 0 or grey.max() > 1:
                raise DataError(
                    f"{path} has float pixels outside [0, 1] (min {grey.min():g}, max "
                    f"{grey.max():g}); save it scaled to [0, 1] or as an 8-bit image"
                )
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

"""`rpod predict IMAGES...`: the trained chain on your own images (not a DVC stage; reads no params.yaml).

Prints per image the position (m, camera frame), the quaternion (qw, qx, qy, qz), the detector's attack
probability and the chain's verdict (attack / doubt / clean at the calibrated levels of its defense file, printed
in full above the table; rpodguard.api.VerdictRule) as a table, or with --json everything including the 6-D
rotation and the rule. With
--motion CSV (the chaser's commanded displacement and camera attitude per image: rpodguard.sequence)
the images are a sequence in time order through the defended chain, and it prints per frame the trusted
estimate (world frame, m), its protection level (m), whether the guidance may fly on it, and the flag. The image
paths are checked before the model loads; an image that is not a camera frame with the target in view (too few
lit pixels, or noise: pipeline/visibility.py) gets no pose and says why. Without --models it uses the weights bundle
shipped in git (rpodguard/weights/default/), so it works right after `make setup`. With --camera (a
camera.json as SPEED+ and `rpod export speed` write it) it warns when the images' camera is not the one the
model was trained for (its K is stored in pose.pt; rpodguard/camera.py).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

# The command's arguments and options (Typer reads the Annotated metadata)
Images = Annotated[
    Optional[list[Path]],
    typer.Argument(help="Image files (PNG, JPG, any size; resized to the model input).", show_default=False),
]
AsJson = Annotated[bool, typer.Option("--json", help="Print a JSON list (one object per image) instead of a table.")]
Models = Annotated[
    Optional[Path],
    typer.Option(
        "--models",
        show_default=False,
        help="A run's models/ folder (or the project root holding it: the chain that ships, "
        "pose_robust.pt and detector_robust.pt), or a folder with pose.pt and detector.pt. "
        "Default: the bundled weights (rpodguard/weights/default, the default profile's "
        "shipped chain).",
    ),
]
Camera = Annotated[
    Optional[Path],
    typer.Option(
        "--camera",
        show_default=False,
        help="camera.json of the images' camera (SPEED+ layout: Nu, Nv and cameraMatrix, or "
        "fx, fy, ppx, ppy); warns when it is not the camera the model was trained for.",
    ),
]
Motion = Annotated[
    Optional[Path],
    typer.Option(
        "--motion",
        show_default=False,
        help="CSV with the chaser's motion per image (columns u_x,u_y,u_z: commanded displacement "
        "of the target's relative position since the previous image, world axes, m; "
        "c0..c8: camera -> world rotation, row-major): the images are then a sequence "
        "through the defended chain (needs defense.json beside the models).",
    ),
]


def main(
    images: Images = None, as_json: AsJson = False, models: Models = None, camera: Camera = None, motion: Motion = None
) -> None:
    """Pose (position m, quaternion, 6-D) and the shipped chain's verdict (attack / doubt / clean) of each image.

    Each image is judged alone (pose CNN -> SHAP signature -> LSTM detector) at the calibrated threshold and doubt
    level of the chain's defense.json (printed in full); the motion filter needs a sequence (--motion).

    Positions assume the camera the model was trained with; another aspect is stretched to fit, with a warning.
    """
    from rpodguard import load_chain
    from rpodguard.api import check_files
    from rpodguard.camera import read_camera
    from stages.errors import StageError

    if not images:
        raise StageError("rpod predict: no images given (pass one or more PNG or JPG files)")
    check_files(images)  # a typo stops here, before the ~10 s of loading torch and the models
    cam = read_camera(camera) if camera is not None else None
    if motion is not None:
        from rpodguard.sequence import read_motion

        commands, attitudes = read_motion(motion, len(images))
    chain = load_chain(models)
    if models is None:
        bundle = chain.manifest or {}
        typer.secho(
            f"note: the bundled weights ({bundle.get('profile')} profile, commit "
            f"{str(bundle.get('commit'))[:12]}); --models models for this project's own run",
            err=True,
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = (
            chain.predict(images, camera=cam)
            if motion is None
            else chain.track(images, commands, attitudes, camera=cam)
        )
    for w in caught:
        typer.secho(f"warning: {' '.join(str(w.message).split())}", fg=typer.colors.YELLOW, err=True)
    (_print_predictions if motion is None else _print_track)(out, as_json)


def _print_predictions(out: Any, as_json: bool) -> None:
    """A rpodguard.api.Prediction as a JSON list (one object per image) or the verdict rule and a table."""
    if as_json:
        typer.echo("[\n" + ",\n".join(json.dumps(r) for r in out.records()) + "\n]")  # one image per line
        return
    from tabulate import tabulate

    rows = [
        [name, *out.position[k], *out.quaternion[k], out.attack_probability[k], out.verdict[k]]
        if out.in_view[k]
        else [name, *[None] * 8, out.why_no_pose(k)]
        for k, name in enumerate(out.sources)
    ]
    typer.echo(out.rule.describe())
    typer.echo(
        tabulate(
            rows,
            ["image", "x (m)", "y (m)", "z (m)", "qw", "qx", "qy", "qz", "P(attack)", "verdict"],
            floatfmt=".3f",
            missingval="-",
        )
    )


def _print_track(out: Any, as_json: bool) -> None:
    """A rpodguard.sequence.Track as a JSON list (one object per frame) or a table."""
    if as_json:
        typer.echo("[\n" + ",\n".join(json.dumps(r) for r in out.records()) + "\n]")
        return
    from tabulate import tabulate

    rows = [
        [
            name,
            *out.trusted[k],
            out.pl[k],
            "yes" if out.available[k] else "no",
            "FLAG" if out.flag[k] else "-",
            out.mode[k],
        ]
        for k, name in enumerate(out.prediction.sources)
    ]
    typer.echo(
        tabulate(
            rows, ["image", "trusted x (m)", "y (m)", "z (m)", "PL (m)", "available", "flag", "mode"], floatfmt=".3f"
        )
    )

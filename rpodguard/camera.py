"""The camera a pose model was trained for, and the check `Chain.predict` makes of the camera of the images.

A pose CNN learns range from apparent size, so it assumes the camera it was trained with: an image from a
camera with focal length f (pixels, at the model's input size) instead of the model's f_m gives ranges
about f_m / f times the true ones. pose.pt stores the training images' K (`rpod train`); for an older
checkpoint of a weights bundle the manifest's params give it (the synthetic camera, `camera` scaled to
`render.width` x `render.height`); otherwise it is unknown and nothing can be checked.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.geometry.camera import Intrinsics, camera_difference
from pipeline.io.errors import DataError

CAMERA_TOLERANCE = 0.01  # relative difference (pipeline.geometry.camera.camera_difference) above which it warns


def model_camera(ckpt: dict[str, Any], manifest: dict[str, Any] | None, path: Path) -> Intrinsics | None:
    """The camera of pose checkpoint `ckpt` (read from `path`) at its input size: its K, else a weights bundle
    manifest's synthetic camera; None when neither records it. A K that is no pinhole matrix is a DataError."""
    height, width = (int(v) for v in ckpt["input_size"])
    if "K" in ckpt:
        try:
            return Intrinsics.from_K(ckpt["K"], width, height)
        except ValueError as e:
            raise DataError(f"{path}: K {e}; re-run `rpod train`") from None
    params = (manifest or {}).get("params") or {}
    cam, render = params.get("camera"), params.get("render") or {}
    source = str(render.get("source") or "inputs/none")
    if not cam or not source.endswith("inputs/none"):  # an imported data set's camera is not in params
        return None
    return Intrinsics(cam["ref_width"], cam["ref_height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"]).scaled(
        width, height
    )


def read_camera(path: Path | str) -> dict[str, Any]:
    """A camera file in the SPEED+ camera.json layout (`Nu`, `Nv` and `cameraMatrix`, or `fx`, `fy`, `ppx`,
    `ppy`), checked; a DataError naming the file when it is missing or not such a camera."""
    from pipeline.formats.speed import camera_from_json
    from pipeline.io.atomic import read_json

    cam = read_json(path)
    try:
        camera_from_json(cam)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    return cam


def camera_warnings(model: Intrinsics | None, camera: Any, width: int, height: int, name: str) -> list[str]:
    """What is wrong with `camera` for an image `name` of width x height pixels, against the model's camera
    `model` (None: unknown): `camera` is a 3x3 K at the image's size or a camera.json dict (K at its Nu x Nv,
    pipeline.formats.speed.camera_from_json). Empty when they agree within CAMERA_TOLERANCE."""
    from pipeline.formats.speed import camera_from_json

    if isinstance(camera, dict):
        given = camera_from_json(camera)
    else:
        given = Intrinsics.from_K(camera, width, height)
    out = []
    if (given.width, given.height) != (width, height):
        out.append(
            f"{name} is {width}x{height} but its camera is given at {given.width}x{given.height}: K is "
            f"scaled to the image (a cropped image needs its own K)"
        )
        given = given.scaled(width, height)
    if model is None:
        return out + [
            "the pose model records no camera matrix (a checkpoint from before it was stored): the "
            "camera given is not checked"
        ]
    if camera_difference(model, given) > CAMERA_TOLERANCE:
        m = model.scaled(width, height)
        out.append(
            f"{name}: its camera (fx {given.fx:.1f}, fy {given.fy:.1f}, cx {given.cx:.1f}, cy {given.cy:.1f} "
            f"px at {width}x{height}) is not the one the model was trained for (fx {m.fx:.1f}, fy {m.fy:.1f}, "
            f"cx {m.cx:.1f}, cy {m.cy:.1f}): ranges come out about {m.fx / given.fx:.2f} times the true ones"
        )
    return out

"""SPEED+ as it ships: the export's camera.json has the physical fx, fy, ppx, ppy beside cameraMatrix,
the held-out split is synthetic/validation.json, images may be grayscale JPEGs; the import undistorts
with camera.json's distCoeffs and copies grayscale into the model's 3 channels (one warning per import).
Each is checked by a round trip through the official layout."""

import json

import cv2
import numpy as np
import pandas as pd
import pytest
import zarr
from PIL import Image
from test_speed import project, render_and_label, write_folder  # noqa: F401  (project: a fixture)

from pipeline.formats.speed import camera_from_json, camera_to_json, to_speed
from pipeline.formats.speed_folder import MARKER
from pipeline.geometry.camera import Intrinsics
from pipeline.io.errors import DataError
from stages.config import params as params_mod

K_BIG = Intrinsics(160, 100, 100.0, 100.0, 79.5, 49.5)  # wide enough that k1 moves the corners by pixels
DIST = np.array([-0.224, 0.05, 0.0, 0.0, 0.0])  # k1 as SPEED+'s camera has it


def exported(project, image_format):
    """(source truth, labels of the first import, export folder, labels imported back from the export)."""
    from stages.export import speed as export_speed

    root, use = project
    truth = write_folder(root / "src")
    use(root / "src")
    labels = render_and_label()
    export_speed(root / "out", image_format)
    use(root / "out")
    return truth, labels, root / "out", render_and_label()


def same_labels(a: pd.DataFrame, b: pd.DataFrame) -> None:
    assert list(a.split) == list(b.split)
    cols = ["tx", "ty", "tz", "qw", "qx", "qy", "qz"]
    assert np.abs(a[cols].to_numpy() - b[cols].to_numpy()).max() < 1e-6


def test_export_is_the_official_layout_and_imports_back(project):
    _, labels, out, again = exported(project, "png")
    cam = json.loads((out / "camera.json").read_text())
    K = camera_from_json(cam)
    assert cam["fx"] / cam["ppx"] == pytest.approx(K.fx) and cam["fy"] / cam["ppy"] == pytest.approx(K.fy)
    fov = np.rad2deg(2 * np.arctan(cam["Nu"] * cam["ppx"] / (2 * cam["fx"])))  # as SPEED+ loaders compute it
    assert fov == pytest.approx(K.fov_deg[0])
    physical = {k: v for k, v in cam.items() if k != "cameraMatrix"}  # the physical fields alone
    assert camera_from_json(physical) == K
    assert (out / "synthetic/validation.json").is_file() and not (out / "synthetic/test.json").exists()
    assert len(json.loads((out / "synthetic/validation.json").read_text())) == (labels.split == "test").sum()
    assert "synthetic/validation.json" in json.loads((out / MARKER).read_text())["files"]
    assert json.loads(open("datasets/render/meta.json").read())["source"]["test"] == "synthetic/validation.json"
    same_labels(labels, again)


def test_grayscale_jpeg_export_imports_with_one_warning(project, capsys):
    truth, labels, out, again = exported(project, "jpeg-gray")
    files = sorted((out / "synthetic/images").iterdir())
    assert files and all(f.suffix == ".jpg" and Image.open(f).mode == "L" for f in files)
    warned = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning:")]
    assert warned == [
        f"warning: render.source: {len(labels)} of {len(labels)} images are grayscale; each is "
        f"copied into the pose model's 3 channels (R = G = B)"
    ]
    same_labels(labels, again)
    stored = zarr.open_group("datasets/render/images.zarr", mode="r")["images"]
    for row in again.itertuples():
        img = np.asarray(stored[row.index])
        assert (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all()
        gray = cv2.cvtColor(truth[labels.image.iloc[row.index].split("/")[-1]][0], cv2.COLOR_RGB2GRAY)
        assert np.abs(img[..., 0].astype(int) - gray).mean() < 8  # JPEG quality 95 on random noise


def blob(size, centre, sigma=2.0):
    """uint8 RGB image of a Gaussian spot at the subpixel `centre` (u, v)."""
    v, u = np.mgrid[: size[1], : size[0]]
    spot = 255 * np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma**2))
    return np.repeat(spot.round().astype(np.uint8)[..., None], 3, axis=2)


def centroid(img):
    w = img[..., 0].astype(float)
    v, u = np.mgrid[: w.shape[0], : w.shape[1]]
    return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()


@pytest.mark.parametrize("ext, size", [("png", (160, 100)), ("jpg", (80, 50))])  # jpg: decoded at half size
def test_a_distorted_camera_round_trips_through_undistortion(project, ext, size):
    """Spots drawn where the distorted lens images a point are found, after import at `size`, where the
    pinhole K (scaled to `size`) projects it: within 0.3 px (the raw images are off by up to 4.5 px)."""
    from stages.artifacts import speed as speed_io

    root, use = project
    src = root / "dist"
    (src / "synthetic/images").mkdir(parents=True)
    points = np.array([[0.55, 0.32, 1.0], [-0.5, -0.3, 1.0], [0.1, 0.05, 1.0], [-0.45, 0.3, 1.0]]) * 20
    raw = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K_BIG.K, DIST)[0][:, 0]
    names = [f"img{i:06d}.{ext}" for i in range(len(points))]
    for name, at in zip(names, raw):
        cv2.imwrite(str(src / "synthetic/images" / name), blob((160, 100), at))
    q = np.tile([1.0, 0, 0, 0], (len(points), 1))
    (src / "synthetic/train.json").write_text(json.dumps(to_speed(names[:3], points[:3], q[:3])))
    (src / "synthetic/validation.json").write_text(json.dumps(to_speed(names[3:], points[3:], q[3:])))
    (src / "camera.json").write_text(json.dumps({**camera_to_json(K_BIG), "distCoeffs": DIST.tolist()}))
    params_mod.write_params(
        params_mod.compose(
            "smoke", [f"render.source={src}", f"render.width={size[0]}", f"render.height={size[1]}", "render.chunk=4"]
        )
    )
    speed_io.import_source(params_mod.load(), root / "store")
    stored = zarr.open_group(str(root / "store/images.zarr"), mode="r")["images"]
    pinhole = (K_BIG.scaled(*size).K @ (points / points[:, 2:]).T).T[:, :2]
    found = np.array([centroid(np.asarray(stored[i])) for i in range(len(points))])
    assert np.abs(found - pinhole).max() < 0.3, found - pinhole
    assert np.abs(raw - (K_BIG.K @ (points / points[:, 2:]).T).T[:, :2]).max() > 4  # no undistortion is caught
    assert json.loads((root / "store/meta.json").read_text())["camera"]["dist_coeffs_removed"] == DIST.tolist()
    poses = pd.read_parquet(root / "store/poses.parquet")
    assert np.allclose(poses[["tx", "ty", "tz"]].to_numpy(), points) and list(poses.split) == ["train"] * 3 + ["test"]


def test_unusable_distortion_is_refused_in_one_line(project):
    from stages.artifacts import speed as speed_io

    root, use = project
    write_folder(root / "src")
    cam = json.loads((root / "src/camera.json").read_text())
    (root / "src/camera.json").write_text(json.dumps({**cam, "distCoeffs": [-0.2, 0.1, "x"]}))
    use(root / "src")
    with pytest.raises(DataError, match="camera.json: distCoeffs must be 4, 5, 8, 12, 14 finite numbers") as err:
        speed_io.import_source(params_mod.load(), root / "store")
    assert "\n" not in str(err.value) and not (root / "store").exists()


def test_an_unknown_export_format_is_refused_before_reading(tmp_path):
    from stages.errors import StageError
    from stages.export import speed as export_speed

    with pytest.raises(StageError, match="^--format tiff: not one of png, jpeg-gray$"):
        export_speed(tmp_path / "out", "tiff")
    assert not (tmp_path / "out").exists()

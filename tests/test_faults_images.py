"""`rpod predict` (rpodguard.api.read_image) decodes an image file as a viewer shows it: EXIF orientation
applied, transparency composited on black with a warning, 16-bit and [0, 1] float pixels scaled; 32-bit
integer pixels, out-of-range floats and animations refused with one line naming the file."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from PIL import Image

from pipeline.io.errors import DataError
from rpodguard.api import read_image


def test_exif_orientation_is_applied(tmp_path):
    img = np.zeros((10, 20, 3), np.uint8)
    img[:, :10] = 255  # left half white
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: rotate 90 degrees clockwise to view
    Image.fromarray(img).save(tmp_path / "a.jpg", exif=exif, quality=95)
    out = read_image(tmp_path / "a.jpg")
    assert out.shape == (20, 10, 3)
    assert out[:8].mean() > 200 and out[12:].mean() < 50  # the white half is on top once rotated


def test_transparency_is_composited_on_black_with_a_warning(tmp_path):
    rgba = np.full((8, 8, 4), 255, np.uint8)
    rgba[:, :4, 3] = 0  # left half fully transparent white
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    with pytest.warns(UserWarning, match=r"a.png has transparent pixels: composited on black"):
        out = read_image(tmp_path / "a.png")
    assert (out[:, :4] == 0).all() and (out[:, 4:] == 255).all()
    Image.fromarray(np.full((8, 8, 4), 255, np.uint8), "RGBA").save(tmp_path / "opaque.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # fully opaque: no warning
        assert (read_image(tmp_path / "opaque.png") == 255).all()


def test_float_and_16_bit_pixels_are_scaled(tmp_path):
    Image.fromarray(np.full((4, 6), 0.5, np.float32)).save(tmp_path / "f.tif")
    assert (read_image(tmp_path / "f.tif") == 128).all()
    Image.fromarray(np.full((4, 6), 40000, np.uint16)).save(tmp_path / "g.tif")
    assert (read_image(tmp_path / "g.tif") == 40000 >> 8).all()


@pytest.mark.parametrize(
    "make, message",
    [
        (
            lambda p: Image.fromarray(np.full((4, 6), 2.0, np.float32)).save(p / "x.tif"),
            r"float pixels outside \[0, 1\]",
        ),
        (lambda p: Image.fromarray(np.full((4, 6), np.nan, np.float32)).save(p / "x.tif"), r"float pixels outside"),
        (lambda p: Image.fromarray(np.full((4, 6), 70000, np.int32)).save(p / "x.tif"), "32-bit integer pixels"),
        (
            lambda p: Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(
                p / "x.gif", save_all=True, append_images=[Image.fromarray(np.full((4, 6, 3), 255, np.uint8))]
            ),
            "holds 2 frames",
        ),
    ],
)
def test_ambiguous_images_are_refused(tmp_path, make, message):
    make(tmp_path)
    path = next(tmp_path.iterdir())
    with pytest.raises(DataError, match=message) as refused:
        read_image(path)
    assert str(refused.value).startswith(str(path)) and "\n" not in str(refused.value)

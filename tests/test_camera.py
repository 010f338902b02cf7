import numpy as np
import pytest

from pipeline.geometry.camera import Intrinsics, project, reference_intrinsics, transform


def test_reference_K_and_fov():
    K = reference_intrinsics()
    assert np.allclose(K.K, [[640, 0, 240], [0, 360, 135], [0, 0, 1]])
    fh, fv = K.fov_deg
    assert np.isclose(fh, np.rad2deg(2 * np.arctan(240 / 640))) and np.isclose(fv, np.rad2deg(2 * np.arctan(135 / 360)))


@pytest.mark.parametrize("w,h", [(160, 90), (240, 135), (64, 36), (960, 540)])
def test_scaling_keeps_the_image_geometry(w, h):
    """A point seen at pixel (u, v) of the reference image lands at the same place of the resampled image:
    with pixel centres at integers, u' = (u + 0.5) * s - 0.5."""
    K = reference_intrinsics()
    Ks = K.scaled(w, h)
    pts = np.random.default_rng(0).uniform([-3, -3, 8], [3, 3, 70], size=(50, 3))
    uv, uvs = project(pts, K), project(pts, Ks)
    s = np.array([w / 480, h / 270])
    assert np.abs(uvs - ((uv + 0.5) * s - 0.5)).max() < 1e-9
    assert np.allclose(Ks.fov_deg, K.fov_deg)  # scaling does not change the field of view
    assert np.allclose(Ks.scaled(480, 270).K, K.K)


def test_transform_and_project():
    K = reference_intrinsics()
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    p = transform(np.array([1.0, 0, 0]), R, np.array([0, 0, 10.0]))
    assert np.allclose(p, [0, 1, 10])
    assert np.allclose(project(p, K), [240, 135 + 36])


def test_bad_inputs():
    with pytest.raises(ValueError, match="positive"):
        Intrinsics(0, 90, 100, 100, 50, 45)
    with pytest.raises(ValueError, match="positive"):
        reference_intrinsics().scaled(160, 0)
    with pytest.raises(ValueError, match="behind"):
        project(np.array([0, 0, -1.0]), reference_intrinsics())


def test_a_camera_matrix_becomes_intrinsics_only_when_it_is_a_pinhole_with_positive_focal_lengths() -> None:
    """Intrinsics.from_K is the one K -> Intrinsics (the SPEED+ reader and `rpod export` use it)."""
    import numpy as np
    import pytest

    from pipeline.geometry.camera import Intrinsics

    K = np.array([[100.0, 0.0, 80.0], [0.0, 90.0, 45.0], [0.0, 0.0, 1.0]])
    cam = Intrinsics.from_K(K, 160, 90)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (100.0, 90.0, 80.0, 45.0) and np.array_equal(cam.K, K)
    with pytest.raises(ValueError, match="not transposed"):
        Intrinsics.from_K(K.T, 160, 90)
    negative = K.copy()
    negative[1, 1] = -90.0
    with pytest.raises(ValueError, match="fx, fy > 0"):
        Intrinsics.from_K(negative, 160, 90)

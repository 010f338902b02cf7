"""Blender scene tests: the rendered image agrees with K and the label pose to well under 1 px."""

import base64
import json

import numpy as np
import pytest

pytest.importorskip("bpy")

from pipeline.geometry.camera import Intrinsics, project, reference_intrinsics, transform  # noqa: E402
from pipeline.geometry.rotations import euler_to_matrix  # noqa: E402
from pipeline.render.scene import Renderer, SceneSettings  # noqa: E402

pytestmark = pytest.mark.slow
FAST = dict(samples=16, denoiser="NONE")
K160 = reference_intrinsics().scaled(160, 90)


def sphere(centre, radius, n=24):
    """Vertices and quad faces (0-based) of a UV sphere."""
    th, ph = np.linspace(0, np.pi, n // 2 + 1), np.linspace(0, 2 * np.pi, n, endpoint=False)
    v = [
        np.asarray(centre) + radius * np.array([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)])
        for a in th
        for b in ph
    ]
    f = [
        (i * n + j, i * n + (j + 1) % n, (i + 1) * n + (j + 1) % n, (i + 1) * n + j)
        for i in range(n // 2)
        for j in range(n)
    ]
    return np.array(v), f


def box(lo, hi):
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, quads


def write_obj(path, v, faces):
    with open(path, "w") as f:
        f.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in v)
        f.writelines("f " + " ".join(str(i + 1) for i in face) + "\n" for face in faces)
    return str(path)


def write_gltf(path, v, quads):
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.uint32)
    pos = v.astype(np.float32).tobytes()
    idx = tris.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [
            {
                "byteLength": len(pos) + len(idx),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(pos + idx).decode(),
            }
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": len(v),
                "type": "VEC3",
                "min": v.min(0).tolist(),
                "max": v.max(0).tolist(),
            },
            {"bufferView": 1, "componentType": 5125, "count": tris.size, "type": "SCALAR"},
        ],
    }
    path.write_text(json.dumps(doc))
    return str(path)


def centroid(alpha):
    ys, xs = np.mgrid[: alpha.shape[0], : alpha.shape[1]]
    return np.array([(alpha * xs).sum(), (alpha * ys).sum()]) / alpha.sum()


@pytest.mark.parametrize("t", [np.array([1.5, -0.8, 10.0]), np.array([8.0, 5.0, 60.0])], ids=["10m", "60m"])
@pytest.mark.parametrize("point", [np.zeros(3), np.array([1.0, 0.5, -0.7])], ids=["origin", "body_point"])
def test_marker_projects_where_K_and_the_label_pose_say(tmp_path, t, point):
    """A small sphere on the target origin or on an off-origin body point, rendered at the label pose
    (R, t), appears (mask centroid) within 1 px of its projection with K; a tilted pose and a
    principal point off the image centre make sign or half-pixel mistakes visible."""
    R = euler_to_matrix(np.array([20.0, -30.0, 15.0]))
    mesh = write_obj(tmp_path / "marker.obj", *sphere(point, 0.02 * t[2]))
    with Renderer(K160, SceneSettings(mesh=mesh, **FAST)) as r:
        _, alpha = r.render_with_alpha(R, t)
    expected = project(transform(point, R, t), K160)
    err = np.linalg.norm(centroid(alpha) - expected)
    assert alpha.sum() > 5 and err < 1.0, f"marker {err:.3f} px from its projection"
    assert err < 0.25  # measured ~0.03 px; a half-pixel convention error would show here


def test_principal_point_off_centre(tmp_path):
    """An unusual K (fy != fx, principal point far from the centre) is honoured too."""
    K = Intrinsics(96, 54, 110.0, 80.0, 30.0, 35.0)
    t = np.array([0.4, -0.3, 12.0])
    mesh = write_obj(tmp_path / "m.obj", *sphere(np.zeros(3), 0.3))
    with Renderer(K, SceneSettings(mesh=mesh, **FAST)) as r:
        _, alpha = r.render_with_alpha(np.eye(3), t)
    assert np.linalg.norm(centroid(alpha) - project(t, K)) < 0.25


def test_gltf_and_obj_agree_and_mesh_scale(tmp_path):
    """glTF (y-up on disk) is imported with its file coordinates as the target frame, like OBJ; and
    mesh_scale scales about the target origin."""
    v, quads = box([0.5, 0.2, -0.3], [1.5, 0.8, 0.1])
    R, t = euler_to_matrix(np.array([10.0, 25.0, -5.0])), np.array([0.3, 0.2, 8.0])
    alphas = {}
    for name, path, scale in [
        ("obj", write_obj(tmp_path / "b.obj", v, quads), 1.0),
        ("gltf", write_gltf(tmp_path / "b.gltf", v, quads), 1.0),
        ("half", write_obj(tmp_path / "h.obj", 2 * v, quads), 0.5),
    ]:
        with Renderer(K160, SceneSettings(mesh=path, mesh_scale=scale, **FAST)) as r:
            alphas[name] = r.render_with_alpha(R, t)[1] > 0.5
    a = alphas["obj"]
    assert a.sum() > 100
    for other in ("gltf", "half"):
        iou = (a & alphas[other]).sum() / (a | alphas[other]).sum()
        assert iou > 0.97, f"{other}: IoU {iou:.3f} with the OBJ render"


def test_procedural_satellite_is_visible_and_sunlit():
    """At 60 m the satellite spans tens of pixels at 160x90; at 10 m it fills much of the frame; the
    background is black; the sun behind the camera lights the visible faces."""
    with Renderer(K160, SceneSettings(samples=4, denoiser="NONE")) as r:
        far, a_far = r.render_with_alpha(np.eye(3), np.array([0, 0, 60.0]))
        near, a_near = r.render_with_alpha(np.eye(3), np.array([0, 0, 10.0]))
        r.set_sun((0, 0, 1.0), 6.0)  # light travels from the camera to the target
        lit = r.render(np.eye(3), np.array([0, 0, 20.0]))
        r.set_sun((0, 0, -1.0), 6.0)  # light from behind the target
        back = r.render(np.eye(3), np.array([0, 0, 20.0]))
        with pytest.raises(ValueError, match="non-zero"):
            r.set_sun((0, 0, 0), 1.0)
        with pytest.raises(ValueError, match="in front"):
            r.render(np.eye(3), np.array([0, 0, -5.0]))
    cols = np.flatnonzero((a_far > 0.5).any(0))
    assert cols.max() - cols.min() > 30
    assert (a_near > 0.5).mean() > 0.12  # about 18% at identity attitude
    assert far.shape == (90, 160, 3) and far.dtype == np.uint8
    assert far[:5, :5].max() == 0 and near[:3].max() == 0  # black space
    assert lit.mean() > 2 * back.mean()


def test_bad_meshes(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        Renderer(K160, SceneSettings(mesh=str(tmp_path / "missing.obj")))
    fbx = tmp_path / "sat.fbx"
    fbx.write_text("not a mesh")
    with pytest.raises(ValueError, match="unsupported format"):
        Renderer(K160, SceneSettings(mesh=str(fbx)))
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(ValueError, match="no mesh geometry"):
        Renderer(K160, SceneSettings(mesh=str(empty)))
    with pytest.raises(ValueError, match="positive"):
        Renderer(Intrinsics(0, 90, 100, 100, 50, 45), SceneSettings())
    with pytest.raises(ValueError, match="denoiser"):
        Renderer(K160, SceneSettings(denoiser="OPTIX"))

"""Blender (bpy) scene of the target satellite, rendered headless with Cycles on the CPU, or on a CUDA / OptiX GPU
when asked (`SceneSettings.device`: cpu, gpu or auto; `resolve_device`).

The scene is built once per `Renderer`; each frame only moves the target and the sun. The Blender
camera stays at the world origin with identity orientation (looking down Blender's -z, y up), and
the target is placed at F @ [R | t] with F = diag(1, -1, -1): this turns a pose in the OpenCV camera
frame (x right, y down, z forward) into Blender's camera convention. Check:
T_cv = diag(1, -1, -1, 1) @ inv(camera.matrix_world) @ target.matrix_world == [R | t].

Pinhole intrinsics K map onto Blender's camera as: sensor fit HORIZONTAL, lens/sensor = fx / W,
pixel aspect for fy != fx, and a lens shift that puts the principal point at (cx, cy) with pixel
centres at integer coordinates (OpenCV convention).

Importing this module imports bpy; stages import it only inside their commands.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import bpy
import cv2
import numpy as np
from mathutils import Matrix

from pipeline import interrupt
from pipeline.geometry.camera import Intrinsics
from pipeline.render.backgrounds import FrameBackground, composite
from pipeline.render.settings import BackgroundSettings

MESH_FORMATS = (".obj", ".glb", ".gltf", ".stl", ".ply")
_FLIP = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> Blender camera axes


@dataclass(frozen=True)
class SceneSettings:
    """Scene and render settings. Lengths in metres; directions are vectors in the target frame."""

    mesh: str | None = None  # None = procedural Jason-1-like satellite; else OBJ/GLB/GLTF/STL/PLY
    mesh_scale: float = 1.0  # metres per mesh unit
    sun_direction: tuple[float, float, float] = (-0.5, -0.3, 1.0)  # direction sunlight travels, target frame
    sun_strength: float = 6.0  # W/m^2 (Blender sun strength)
    samples: int = 8  # Cycles samples per pixel
    denoiser: str = "NONE"  # or OPENIMAGEDENOISE
    denoise_quality: str = "FAST"  # OIDN: FAST, BALANCED, HIGH
    threads: int = 2
    device: str = "cpu"  # Cycles: cpu | gpu (OptiX or CUDA, refused without one) | auto (`resolve_device`)
    ambient: float = 0.08  # world light strength (Earth-shine fill); the background stays black
    max_bounces: int = 2
    background: BackgroundSettings = BackgroundSettings()  # behind the frames given a FrameBackground


def _material(name: str, color: tuple[float, float, float], metallic: float, roughness: float) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    return mat


def _add(obj: bpy.types.Object, parent: bpy.types.Object, mat: bpy.types.Material) -> bpy.types.Object:
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    obj.parent = parent
    return obj


def _box(
    name: str,
    size: tuple[float, float, float],
    loc: tuple[float, float, float],
    parent: bpy.types.Object,
    mat: bpy.types.Material,
) -> bpy.types.Object:
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=loc)
    obj = bpy.context.active_object
    obj.name = name
    obj.scale = size
    return _add(obj, parent, mat)


def _build_satellite(parent: bpy.types.Object) -> None:
    """Procedural Jason-1-like satellite, target frame in metres.

    Bus 1.0 (x) x 1.2 (y) x 1.0 (z) m of gold foil centred on the origin; two solar wings along
    +-x, each 4 dark-blue panels (1.5 m along y x 1.25 m along x, 5 m per wing) on a short yoke,
    panel normals along -z (towards a chaser on the nominal approach); a 1.2 m nadir dish on the +y
    face (image-down side for an identity attitude); a radiometer cylinder on the -y face.
    """
    gold = _material("gold_foil", (1.0, 0.62, 0.18), metallic=0.85, roughness=0.35)
    cell = _material("solar_cell", (0.02, 0.05, 0.22), metallic=0.3, roughness=0.25)
    frame = _material("frame", (0.6, 0.6, 0.62), metallic=0.6, roughness=0.4)
    white = _material("white_paint", (0.85, 0.85, 0.85), metallic=0.0, roughness=0.6)

    _box("bus", (1.0, 1.2, 1.0), (0, 0, 0), parent, gold)
    for side in (-1, 1):
        _box(f"yoke_{side}", (0.5, 0.06, 0.06), (side * 0.75, 0, 0), parent, frame)
        for k in range(4):
            x = side * (1.0 + 1.25 * k + 0.625)
            _box(f"panel_{side}_{k}", (1.2, 1.5, 0.03), (x, 0, 0), parent, cell)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, segments=32, ring_count=16, location=(0, 0.75, 0))
    dish = bpy.context.active_object
    dish.name = "dish"
    dish.scale = (1.0, 0.25, 1.0)  # a shallow 1.2 m dish on the +y (nadir) face
    _add(dish, parent, white)
    bpy.ops.mesh.primitive_cylinder_add(radius=0.25, depth=0.6, vertices=24, location=(0.2, -0.9, 0.2))
    radiometer = bpy.context.active_object
    radiometer.name = "radiometer"
    radiometer.rotation_euler = (np.pi / 2, 0, 0)
    _add(radiometer, parent, white)


def _import_mesh(path: str, parent: bpy.types.Object) -> None:
    """Import a user mesh; its file coordinates become the target frame (axes kept as stored)."""
    p = Path(path)
    ext = p.suffix.lower()
    before = set(bpy.data.objects)
    try:
        if ext == ".obj":
            bpy.ops.wm.obj_import(filepath=str(p), forward_axis="Y", up_axis="Z")
        elif ext == ".stl":
            bpy.ops.wm.stl_import(filepath=str(p), forward_axis="Y", up_axis="Z")
        elif ext == ".ply":
            bpy.ops.wm.ply_import(filepath=str(p), forward_axis="Y", up_axis="Z")
        else:
            bpy.ops.import_scene.gltf(filepath=str(p))
    except RuntimeError as e:
        raise ValueError(f"mesh file {path!r} could not be read: {e}") from None
    new = [o for o in bpy.data.objects if o not in before]
    if sum(len(o.data.vertices) for o in new if o.type == "MESH") == 0:
        raise ValueError(f"mesh file {path!r} contains no mesh geometry")
    # glTF is y-up and Blender's importer turns it z-up; undo that so file coordinates = target frame.
    fix = Matrix(((1, 0, 0, 0), (0, 0, 1, 0), (0, -1, 0, 0), (0, 0, 0, 1))) if ext in (".glb", ".gltf") else Matrix()
    for o in new:
        if o.parent is None:
            o.matrix_basis = fix @ o.matrix_basis
            o.parent = parent


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence Blender's per-frame log lines (written to file descriptor 1) so progress bars stay readable."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


DEVICES = ("cpu", "gpu", "auto")
GPU_BACKENDS = ("OPTIX", "CUDA")  # Cycles' GPU backends, in the order tried


@dataclass(frozen=True)
class CyclesDevice:
    """Where Cycles renders: `device` "CPU" or "GPU", the GPU `backend` (OPTIX or CUDA; None on the CPU) and a `note`
    when `auto` fell back to the CPU."""

    device: str
    backend: str | None = None
    note: str | None = None

    def record(self, requested: str) -> dict[str, Any]:
        """For a render's metadata: the device asked for and the one used."""
        return {"requested": requested, "used": self.device.lower(), "backend": self.backend, "note": self.note}


def gpu_backend() -> str | None:
    """The first Cycles GPU backend (`GPU_BACKENDS`) for which bpy lists a device, its devices enabled for rendering;
    None when bpy sees no GPU. Blender's preferences of this process are changed (compute device type)."""
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for backend in GPU_BACKENDS:
        try:
            prefs.compute_device_type = backend
        except TypeError:  # a Blender build without this backend
            continue
        with _quiet_stdout():  # Cycles prints a warning per backend library it cannot open
            prefs.refresh_devices()
        found = [d for d in prefs.devices if d.type == backend]
        if found:
            for d in prefs.devices:
                d.use = d.type == backend
            return backend
    return None


def resolve_device(requested: str, probe: Callable[[], str | None] = gpu_backend) -> CyclesDevice:
    """The Cycles device for `render.device` `requested`: "cpu" the CPU (the probe is not run); "gpu" the GPU backend
    `probe` finds, a ValueError when it finds none; "auto" the GPU when found, else the CPU with a note."""
    if requested not in DEVICES:
        raise ValueError(f"render device must be one of {', '.join(DEVICES)}, got {requested!r}")
    if requested == "cpu":
        return CyclesDevice("CPU")
    backend = probe()
    if backend is not None:
        return CyclesDevice("GPU", backend)
    if requested == "gpu":
        raise ValueError("render device gpu: bpy sees no OptiX or CUDA device; use cpu or auto")
    return CyclesDevice(
        "CPU", note="render device auto: bpy sees no OptiX or CUDA device, so Cycles renders on the CPU"
    )


def check_settings(K: Intrinsics, settings: SceneSettings) -> None:
    """ValueError naming the first bad setting (resolution, scale, samples, denoiser, mesh file), so a
    caller can refuse them before starting any worker."""
    if K.width <= 0 or K.height <= 0:
        raise ValueError(f"render resolution must be positive, got {K.width}x{K.height}")
    if settings.mesh_scale <= 0:
        raise ValueError(f"mesh_scale must be positive, got {settings.mesh_scale}")
    if settings.samples < 1:
        raise ValueError(f"samples must be at least 1, got {settings.samples}")
    if settings.device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, got {settings.device!r}")
    if settings.denoiser.upper() not in ("NONE", "OPENIMAGEDENOISE"):
        raise ValueError(f"denoiser must be NONE or OPENIMAGEDENOISE, got {settings.denoiser!r}")
    if settings.denoise_quality.upper() not in ("FAST", "BALANCED", "HIGH"):
        raise ValueError(f"denoise_quality must be FAST, BALANCED or HIGH, got {settings.denoise_quality!r}")
    if settings.mesh is not None:
        p = Path(settings.mesh)
        if not p.is_file():
            raise ValueError(f"mesh file {settings.mesh!r} not found")
        if p.suffix.lower() not in MESH_FORMATS:
            raise ValueError(
                f"mesh file {settings.mesh!r}: unsupported format {p.suffix.lower() or '(none)'!r}; "
                f"use one of {', '.join(MESH_FORMATS)}"
            )


class Renderer:
    """A headless Cycles scene of the target; `render(R, t)` returns an RGB image for one pose.

    Pose: R (3, 3) rotates target-frame vectors into the OpenCV camera frame, t (3,) is the target
    origin in that frame (metres). The image is (H, W, 3) uint8 RGB with a black background, or with a
    frame's draw of settings.background behind the target (pipeline/render/backgrounds.py).
    """

    def __init__(self, K: Intrinsics, settings: SceneSettings = SceneSettings()) -> None:
        check_settings(K, settings)
        self.K = K
        self.settings = settings
        # Blender runs Python of its own whenever it is called (its factory settings, Cycles' render engine) and
        # swallows what that raises: inside a Blender call a signal only sets the stop flag (pipeline/interrupt.py),
        # which stops the scene here, once built, or between two frames
        with interrupt.deferred():
            self._build()

    def _build(self) -> None:
        """The empty scene, the camera, the target (procedural or `settings.mesh`) and the sun."""
        settings = self.settings
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self._setup_render()
        self._setup_camera()
        self.target = bpy.data.objects.new("target", None)
        self.scene.collection.objects.link(self.target)
        mesh_root = bpy.data.objects.new("mesh_root", None)
        self.scene.collection.objects.link(mesh_root)
        mesh_root.parent = self.target
        mesh_root.scale = (settings.mesh_scale,) * 3
        if settings.mesh is None:
            _build_satellite(mesh_root)
        else:
            _import_mesh(settings.mesh, mesh_root)
        sun_data = bpy.data.lights.new("sun", "SUN")
        sun_data.angle = np.deg2rad(0.53)
        self.sun = bpy.data.objects.new("sun", sun_data)
        self.scene.collection.objects.link(self.sun)
        self._sun_dir = np.asarray(settings.sun_direction, dtype=np.float64)
        self.set_sun(settings.sun_direction, settings.sun_strength)
        fd, self._png = tempfile.mkstemp(
            prefix=f"rpod_{os.getpid()}_{uuid.uuid4().hex[:8]}_",
            suffix=".png",
            dir="/dev/shm" if os.path.isdir("/dev/shm") else None,
        )
        os.close(fd)
        os.unlink(self._png)  # only the unique name is kept: Blender writes the file per frame
        self.scene.render.filepath = self._png

    def _setup_render(self) -> None:
        s, r = self.settings, self.scene.render
        r.engine = "CYCLES"
        r.resolution_x, r.resolution_y, r.resolution_percentage = self.K.width, self.K.height, 100
        r.film_transparent = True
        r.use_persistent_data = False  # measured: persistent data is slower for these tiny scenes
        r.threads_mode, r.threads = "FIXED", max(1, s.threads)
        r.image_settings.file_format = "PNG"
        r.image_settings.color_mode = "RGBA"
        r.image_settings.color_depth = "8"
        r.image_settings.compression = 0
        self.scene.view_settings.view_transform = "Standard"
        c = self.scene.cycles
        self.cycles = resolve_device(s.device)  # after read_factory_settings, which resets the preferences
        c.device = self.cycles.device
        c.samples = s.samples
        c.use_adaptive_sampling = False
        c.max_bounces = s.max_bounces
        c.diffuse_bounces = c.glossy_bounces = min(s.max_bounces, 2)
        c.transmission_bounces = c.volume_bounces = c.transparent_max_bounces = 0
        c.caustics_reflective = c.caustics_refractive = False
        c.seed = 0
        if s.denoiser.upper() == "NONE":
            c.use_denoising = False
        else:
            c.use_denoising = True
            c.denoiser = s.denoiser.upper()
            c.denoising_quality = s.denoise_quality.upper()
            c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
            c.denoising_prefilter = "FAST"  # ACCURATE prefiltering triples the time per frame
        world = bpy.data.worlds.new("world")
        world.use_nodes = True
        bg = world.node_tree.nodes["Background"]
        bg.inputs["Color"].default_value = (0.35, 0.45, 0.6, 1.0)
        bg.inputs["Strength"].default_value = s.ambient
        self.scene.world = world

    def _setup_camera(self) -> None:
        K = self.K
        cam_data = bpy.data.cameras.new("camera")
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.sensor_width = 36.0
        cam_data.lens = K.fx * cam_data.sensor_width / K.width
        cam_data.clip_start, cam_data.clip_end = 0.05, 10000.0
        r = self.scene.render
        # fy / fx = pixel_aspect_x / pixel_aspect_y (Blender wants both >= 1).
        ratio = K.fy / K.fx
        r.pixel_aspect_x, r.pixel_aspect_y = (ratio, 1.0) if ratio >= 1 else (1.0, 1.0 / ratio)
        ycor = r.pixel_aspect_y / r.pixel_aspect_x  # height of one pixel in units of its width
        # Lens shift, in units of the image width (sensor fit HORIZONTAL), moves the view window: a
        # positive shift_x moves the content left, so the principal point moves by -shift_x * W
        # pixels; a positive shift_y (Blender y up) moves the content down the image. The image
        # centre has pixel-centre coordinates ((W - 1) / 2, (H - 1) / 2). Verified to 0.05 px by
        # tests/test_render.py.
        cam_data.shift_x = -(K.cx - (K.width - 1) / 2) / K.width
        cam_data.shift_y = (K.cy - (K.height - 1) / 2) * ycor / K.width
        self.camera = bpy.data.objects.new("camera", cam_data)
        self.scene.collection.objects.link(self.camera)
        self.scene.camera = self.camera

    def set_sun(self, direction: tuple[float, float, float] | np.ndarray, strength: float) -> None:
        """Sunlight travelling along `direction` (target frame) with Blender strength `strength`."""
        d = np.asarray(direction, dtype=np.float64)
        if d.shape != (3,) or not np.linalg.norm(d) > 0:
            raise ValueError(f"sun direction must be a non-zero 3-vector, got {direction!r}")
        self._sun_dir = d / np.linalg.norm(d)
        self.sun.data.energy = float(strength)

    def _place(self, R: np.ndarray, t: np.ndarray) -> None:
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = _FLIP @ R, _FLIP @ t
        self.target.matrix_world = Matrix(M.tolist())
        # The sun is fixed to the target frame: its light travels along F R d; a Blender sun shines
        # along its local -z, so build a rotation whose -z is that direction.
        d = _FLIP @ R @ self._sun_dir
        z = -d
        a = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
        x = np.cross(a, z)
        x /= np.linalg.norm(x)
        S = np.eye(4)
        S[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        self.sun.matrix_world = Matrix(S.tolist())

    def render_with_alpha(
        self, R: np.ndarray, t: np.ndarray, background: FrameBackground | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render one pose -> (RGB (H, W, 3) uint8, the target's alpha (H, W) float in [0, 1]): on black, or
        composited over `background` (this frame's draw of settings.background: backgrounds.composite)."""
        if np.asarray(t, dtype=np.float64).reshape(3)[2] <= 0:
            raise ValueError(f"target must be in front of the camera (tz > 0), got t={t}")
        with _quiet_stdout(), interrupt.deferred():  # a signal stops the render after the frame (`__init__`)
            self._place(R, t)
            bpy.ops.render.render(write_still=True)
        bgra = cv2.imread(self._png, cv2.IMREAD_UNCHANGED)
        Path(self._png).unlink(missing_ok=True)  # a worker killed between frames leaves no file behind
        if bgra is None or bgra.shape[:2] != (self.K.height, self.K.width):
            raise RuntimeError(
                f"Blender did not write the expected {self.K.width}x{self.K.height} image to {self._png}"
            )
        alpha = bgra[..., 3].astype(np.float32) / 255.0
        straight = bgra[..., 2::-1].astype(np.float32)
        if background is not None:
            sun = np.asarray(R, dtype=np.float64).reshape(3, 3) @ self._sun_dir  # camera frame
            return composite(
                straight, alpha, self.K, self.settings.background, background, sun, self.sun.data.energy
            ), alpha
        rgb = straight * alpha[..., None]  # straight alpha -> black space
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), alpha

    def render(self, R: np.ndarray, t: np.ndarray, background: FrameBackground | None = None) -> np.ndarray:
        """Render one pose -> RGB (H, W, 3) uint8: on black, or over `background` (`render_with_alpha`)."""
        return self.render_with_alpha(R, t, background)[0]

    def close(self) -> None:
        """Remove the temporary image file and empty the Blender scene."""
        Path(self._png).unlink(missing_ok=True)
        with interrupt.deferred():
            bpy.ops.wm.read_factory_settings(use_empty=True)

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

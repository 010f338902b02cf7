"""Space backgrounds behind the rendered target: the Earth below it, stars, and the sensor's black offset and
read noise, drawn in numpy and composited under the target with the render's alpha (pipeline/render/scene.py
renders the target on a transparent film; issue 37: the robust model's black-level clamp assumes a black sky).

Frames. Camera frame = OpenCV (x right, y down, z boresight); world frame = pipeline/geometry/trajectories.py
(centred on the target, the nominal approach along world +z, image-down = world +y for an unrolled camera);
`R_cam` rotates camera-frame vectors into world axes. The nadir (the direction from the target to the Earth's
centre) is a world-frame setting; in the camera frame it is R_cam^T @ nadir. The camera-to-target distance
(<= 100 m) is neglected against the Earth's (thousands of km): the Earth's centre is at (R_E + altitude) * nadir
from the camera. Sunlight travels along the scene's sun direction, which scene.py fixes to the target frame, so
in the camera frame it is R @ sun_direction (R: target -> camera, the label rotation): the Earth is lit by the
same sun as the target (light travelling downwards, +y, shows the Earth below in daylight; the default
sun_direction's light travels 15 deg upwards: the Earth below is at dawn, lit towards the bottom of the image).
Eclipses (the target in the Earth's shadow) are not modelled.

Kinds. The frames of the share show stars, the sensor's offset and noise, and the Earth where the geometry puts
it in view: a frame's `kind` is "earth" when the Earth's day side covers a pixel centre, else "space"; the other
frames are "black".

Radiometry. Blender's sun of strength E (W/m^2) gives a Lambertian surface of albedo a a linear pixel value
a * E * cos(incidence) / pi, shown through the Standard view transform (the sRGB curve, clipped at 1): measured
on a flat grey plate in this scene to 1% (the Earth below is exposed like the target). Stars, the black offset
and the read noise are in display pixel units ([0, 1], as the network sees them).

Compositing. Blender writes straight (unassociated) colour C and alpha a; a frame is
rint(C * a + B * (1 - a) + offset + noise), all in display units before the one rounding: where a = 1 the
target's pixel is C whatever the backdrop B (no seams: the same a weighs both terms), where a = 0 it is B. On
black (no background drawn) scene.py keeps its own rint(C * a), byte for byte. The black offset and read noise
are the sensor's: they lift every pixel, the target's too. Earth-shine on the target is not modelled beyond the
scene's ambient fill.

Determinism. A frame's draw comes from a generator seeded by (the stream tag, the set's seed, the frame's key):
its index in its render set, or for a frame rendered on demand (the guidance loop) a hash of its pose, so the
pixels do not depend on which worker renders which chunk. The draw for a frame is the same for every share
(only the comparison with `share` changes), so raising the share only turns more black frames into space ones.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pipeline.geometry.camera import Intrinsics
from pipeline.render.settings import BackgroundSettings

EARTH_RADIUS_KM = 6371.0
KINDS = ("black", "space", "earth")  # a poses/labels table's `background` column (absent: black): `kind`
_STREAM = 0x6267  # keeps a set's background draws apart from its other draws of the same seed
_SUPERSAMPLE = 4  # rays per pixel side for the Earth's coverage (an antialiased limb)
_LATTICE = 32  # period of the texture's noise lattice, lattice cells
_OCEAN = np.array([0.03, 0.06, 0.14])  # linear albedos
_LAND = np.array([[0.09, 0.11, 0.05], [0.30, 0.25, 0.16]])  # vegetation, desert
_CLOUD = np.array([0.72, 0.72, 0.72])
_HAZE = np.array([0.20, 0.32, 0.65])  # the atmosphere's albedo seen at grazing incidence
_HAZE_DEPTH = 0.05  # the atmosphere's optical depth seen straight down
_GLOW_KM = 25.0  # scale height of the limb's glow above the surface, km
_STAR_SIGMA = 0.6  # star image (Gaussian PSF) standard deviation, pixels
_STAR_RANGE = 10.0  # faintest drawn star = star_peak / this (2.5 magnitudes)
_STAR_SLOPE = 1.25  # star counts N(> flux) ~ flux^-slope (about x3 per magnitude)


@dataclass(frozen=True)
class FrameBackground:
    """One frame's draw of the space background."""

    nadir: tuple[float, float, float]  # unit vector from the camera to the Earth's centre, camera frame
    seed: int  # of the frame's Earth texture, stars and read noise


def background_kinds(backgrounds: Sequence[str] | None, n: int) -> np.ndarray:
    """(n,) each frame's background kind (KINDS) from `backgrounds` (None: every frame black); a ValueError naming
    the shape and kinds given otherwise."""
    kinds = np.full(n, KINDS[0]) if backgrounds is None else np.asarray(backgrounds, str)
    if kinds.shape != (n,) or not set(kinds.ravel()) <= set(KINDS):
        raise ValueError(
            f"backgrounds must be ({n},) kinds of {', '.join(KINDS)}, got {kinds.shape} {sorted(set(kinds.ravel()))}"
        )
    return kinds


def pose_key(R: np.ndarray, t: np.ndarray) -> int:
    """The key of a frame rendered on demand: a 63-bit hash of its pose (R target -> camera, t in metres),
    rounded to 1e-9 as the guidance loop's image cache keys it."""
    raw = np.round(np.concatenate([np.ravel(R), np.ravel(t)]), 9).tobytes()
    return int.from_bytes(hashlib.blake2b(raw, digest_size=8).digest(), "little") >> 1


def draw(s: BackgroundSettings, R_cam: np.ndarray, seed: int, key: int) -> FrameBackground | None:
    """Frame `key`'s background in the set seeded `seed`: None (black) with probability 1 - share, else the
    Earth at the jittered nadir (R_cam (3, 3): camera -> world) and the seed of its texture, stars and noise."""
    rng = np.random.default_rng([_STREAM, seed, key])
    u, seed_out = rng.random(), int(rng.integers(2**63))
    n = np.asarray(s.nadir, dtype=np.float64)
    n = n / np.linalg.norm(n)
    # uniform over the cone: cos(tilt) uniform in [cos(jitter), 1], azimuth uniform
    cos_tilt = 1 - rng.random() * (1 - np.cos(np.deg2rad(s.nadir_jitter_deg)))
    azimuth = rng.random() * 2 * np.pi
    a, b = _basis(n)
    sin_tilt = np.sqrt(max(0.0, 1 - cos_tilt**2))
    n_world = cos_tilt * n + sin_tilt * (np.cos(azimuth) * a + np.sin(azimuth) * b)
    if u >= s.share:
        return None
    return FrameBackground(tuple(float(v) for v in np.asarray(R_cam, dtype=np.float64).T @ n_world), seed_out)


def kind(K: Intrinsics, s: BackgroundSettings, frame: FrameBackground | None, sun: np.ndarray) -> str:
    """The `background` column's value of a frame drawn by `draw`: "black" (none drawn), "earth" (the Earth's
    day side, lit by sunlight travelling along `sun` (camera frame), covers a pixel centre of the image K) or
    "space" (drawn, but no sunlit Earth in view: stars, offset and noise only)."""
    if frame is None:
        return KINDS[0]
    c = _centre(s, frame)
    d = _pixel_rays(K)
    hit, tc, b2 = _sphere(d, c)
    normal = _normals(d[hit], tc[hit], b2[hit], c)
    return KINDS[2] if (normal @ np.asarray(sun, dtype=np.float64) < 0).any() else KINDS[1]


def _centre(s: BackgroundSettings, frame: FrameBackground) -> np.ndarray:
    """The Earth's centre seen from the camera (3,), km, camera frame."""
    return (EARTH_RADIUS_KM + s.altitude_km) * np.asarray(frame.nadir, dtype=np.float64)


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to the unit vector n and to each other."""
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)


def _rays(K: Intrinsics, u: np.ndarray, v: np.ndarray, sub: int) -> np.ndarray:
    """Unit ray directions (M, sub * sub, 3), camera frame, through a sub x sub grid in each of the pixels
    (u, v) (M,) (pixel centres at integer coordinates)."""
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    du, dv = (g.ravel() for g in np.meshgrid(offsets, offsets))
    x = (u[:, None] + du - K.cx) / K.fx
    y = (v[:, None] + dv - K.cy) / K.fy
    d = np.stack([x, y, np.ones_like(x)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@functools.lru_cache(maxsize=4)
def _pixel_rays(K: Intrinsics) -> np.ndarray:
    """Unit ray directions (H, W, 3), camera frame, through the pixel centres of the image K."""
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    return _rays(K, u.ravel().astype(np.float64), v.ravel().astype(np.float64), 1)[:, 0].reshape(K.height, K.width, 3)


def _sphere(d: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit rays d (..., 3) from the camera against the Earth centred at c (km, camera frame) -> (whether each
    hits it, the distance along it to its closest approach to the centre (km), that approach's squared distance
    from the centre (km^2))."""
    tc = d @ c
    b2 = np.maximum(c @ c - tc**2, 0.0)
    return (tc > 0) & (b2 < EARTH_RADIUS_KM**2), tc, b2


def _normals(d: np.ndarray, tc: np.ndarray, b2: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Outward unit normals (M, 3) where the rays d (M, 3) (`_sphere`'s tc, b2) first meet the Earth centred at c,
    or for a ray that passes it, at the tangent point below its closest approach (the limb)."""
    p = (tc - np.sqrt(np.maximum(EARTH_RADIUS_KM**2 - b2, 0.0)))[:, None] * d - c
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _coverage(K: Intrinsics, hit: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The share (H, W) of each pixel's area that sees the sphere of radius R_E centred at c (km, camera
    frame), from the pixel-centre hits `hit` (H, W): pixels whose 3 x 3 neighbourhood is all in or all out
    keep 1 or 0, the others (the limb) are supersampled."""
    pad = np.pad(hit, 1, mode="edge")
    edge = np.zeros_like(hit)
    for dy, dx in itertools.product((0, 1, 2), repeat=2):
        edge |= pad[dy : dy + K.height, dx : dx + K.width] != hit
    coverage = hit.astype(np.float64)
    v, u = np.nonzero(edge)
    coverage[v, u] = _sphere(_rays(K, u, v, _SUPERSAMPLE), c)[0].mean(-1)
    return coverage


def _value_noise(p: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p (M, 3): the random values `table` (G, G, G) on the integer
    lattice (periodic in G), blended with a smoothstep."""
    g = len(table)
    i = np.floor(p)
    f = (p - i).astype(np.float32)
    w = f * f * (3 - 2 * f)
    lo = i.astype(np.int64) & (g - 1)  # g is a power of two
    hi = (lo + 1) & (g - 1)
    flat = table.ravel()

    def at(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        return flat[(x * g + y) * g + z]

    def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        return a + (b - a) * t

    x0, y0, z0 = lo.T
    x1, y1, z1 = hi.T
    wx, wy, wz = w.T
    near = lerp(lerp(at(x0, y0, z0), at(x1, y0, z0), wx), lerp(at(x0, y1, z0), at(x1, y1, z0), wx), wy)
    far = lerp(lerp(at(x0, y0, z1), at(x1, y0, z1), wx), lerp(at(x0, y1, z1), at(x1, y1, z1), wx), wy)
    return lerp(near, far, wz)


def _fbm(p: np.ndarray, rng: np.random.Generator, octaves: int = 5) -> np.ndarray:
    """Fractal value noise (octaves halving in amplitude, doubling in frequency) in [0, 1] at p (M, 3)."""
    table = rng.random((_LATTICE,) * 3, dtype=np.float32)
    p = p.astype(np.float32)
    total, norm = np.zeros(len(p), dtype=np.float32), 0.0
    for k in range(octaves):
        total += 0.5**k * _value_noise(p * 2**k + 7.3 * k, table)
        norm += 0.5**k
    return total / norm


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _albedo(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear RGB albedo (M, 3) of the Earth at unit vectors x (M, 3) of a texture frame: oceans, vegetation and
    desert, clouds."""
    land = _smoothstep(0.50, 0.54, _fbm(1.6 * x, rng))
    dry = _smoothstep(0.40, 0.60, _fbm(3.0 * x, rng, octaves=2))
    cloud = _smoothstep(0.48, 0.66, _fbm(5.0 * x, rng))
    ground = (1 - land)[:, None] * _OCEAN + land[:, None] * ((1 - dry)[:, None] * _LAND[0] + dry[:, None] * _LAND[1])
    return (1 - cloud)[:, None] * ground + cloud[:, None] * _CLOUD


def _srgb(linear: np.ndarray) -> np.ndarray:
    """Blender's Standard view transform: the sRGB curve, clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def earth(
    K: Intrinsics,
    s: BackgroundSettings,
    frame: FrameBackground,
    sun: np.ndarray,
    sun_strength: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """The Earth as the camera sees it -> (display colour (H, W, 3) in [0, 1], coverage (H, W) in [0, 1]).

    A sphere of radius R_E at distance R_E + altitude along frame.nadir (camera frame), Lambertian, lit by
    sunlight travelling along `sun` (camera frame) with Blender strength `sun_strength` (W/m^2); a procedural
    texture (a random orientation per frame); an atmosphere that hazes the surface towards the limb and glows
    above it (the bright limb). Coverage: the share of each pixel's rays that hit the sphere.
    """
    c = _centre(s, frame)
    sun = np.asarray(sun, dtype=np.float64) / np.linalg.norm(sun)
    d = _pixel_rays(K)
    hit, tc, b2 = _sphere(d, c)
    coverage = _coverage(K, hit, c)
    height = np.sqrt(b2) - EARTH_RADIUS_KM  # of each ray's closest approach above the surface, km
    near = (tc > 0) & ((coverage > 0) | (height < 8 * _GLOW_KM))
    out = np.zeros((K.height, K.width, 3))
    if not near.any():
        return out, coverage
    dn = d[near]
    normal = _normals(dn, tc[near], b2[near], c)
    lit = np.clip(-(normal @ sun), 0.0, None) * sun_strength / np.pi
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))  # the texture's orientation this frame
    cos_view = np.clip(-np.sum(normal * dn, axis=1), 1e-3, 1.0)
    haze = 1 - np.exp(-_HAZE_DEPTH / cos_view)
    surface = ((1 - haze)[:, None] * _albedo(normal @ q, rng) + haze[:, None] * _HAZE) * lit[:, None]
    glow = _HAZE * (lit * np.exp(-np.maximum(height[near], 0.0) / _GLOW_KM))[:, None]
    cov = coverage[near][:, None]
    out[near] = _srgb(cov * surface + (1 - cov) * glow)
    return out, coverage


def stars(K: Intrinsics, s: BackgroundSettings, rng: np.random.Generator) -> np.ndarray:
    """A star field (H, W) in display units: a Poisson number of stars (s.stars per square degree, uniform on
    the sky), Gaussian images of peak value in [star_peak / 10, star_peak] with counts ~ flux^-1.25."""
    out = np.zeros((K.height, K.width))
    if s.stars == 0:
        return out
    # thinning: pixel positions uniform on the image, kept with probability cos^3 (the pixel's solid angle
    # relative to the centre's 1 / (fx fy) sr), is a Poisson process uniform on the sky
    sq_deg = K.width * K.height / (K.fx * K.fy) * np.rad2deg(1.0) ** 2
    n = rng.poisson(s.stars * sq_deg)
    u, v = rng.uniform(-0.5, K.width - 0.5, n), rng.uniform(-0.5, K.height - 0.5, n)
    cos3 = (1 + ((u - K.cx) / K.fx) ** 2 + ((v - K.cy) / K.fy) ** 2) ** -1.5
    keep = rng.random(n) < cos3
    low = 1 / _STAR_RANGE**_STAR_SLOPE
    peak = s.star_peak / _STAR_RANGE * (1 - rng.random(n) * (1 - low)) ** (-1 / _STAR_SLOPE)
    r = int(np.ceil(3 * _STAR_SIGMA))
    for x, y, a in zip(u[keep], v[keep], peak[keep]):
        x0, y0 = int(round(x)), int(round(y))
        ys, xs = np.mgrid[max(0, y0 - r) : min(K.height, y0 + r + 1), max(0, x0 - r) : min(K.width, x0 + r + 1)]
        out[ys, xs] += a * np.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * _STAR_SIGMA**2))
    return out


def backdrop(
    K: Intrinsics,
    s: BackgroundSettings,
    frame: FrameBackground,
    sun: np.ndarray,
    sun_strength: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """What lies behind the target (H, W, 3), display units in [0, 1]: the Earth, and stars where it is not."""
    colour, coverage = earth(K, s, frame, sun, sun_strength, rng)
    return np.minimum(colour + (stars(K, s, rng) * (1 - coverage))[..., None], 1.0)


def composite(
    straight: np.ndarray,
    alpha: np.ndarray,
    K: Intrinsics,
    s: BackgroundSettings,
    frame: FrameBackground,
    sun: np.ndarray,
    sun_strength: float,
) -> np.ndarray:
    """The frame (H, W, 3) uint8: the target's straight colour `straight` (H, W, 3; 0..255) with `alpha`
    (H, W; [0, 1]) over the backdrop of `frame`, then the sensor's black offset and read noise, rounded once.
    `sun`: the direction sunlight travels, camera frame; `sun_strength`: W/m^2."""
    rng = np.random.default_rng(frame.seed)
    b = (255.0 * backdrop(K, s, frame, sun, sun_strength, rng)).astype(np.float32)
    a = alpha.astype(np.float32)[..., None]
    # float32 as scene.py's black path: over a black backdrop, with no offset or noise, the same bytes
    x = straight.astype(np.float32) * a + b * (1 - a) + np.float32(255.0 * s.black_offset)
    if s.noise_std > 0:
        x = x + rng.normal(0.0, 255.0 * s.noise_std, x.shape).astype(np.float32)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)

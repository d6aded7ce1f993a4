"""Shared helpers of the rasteriser tests: fixed buffer sizes (so that the tests compile the
rasteriser only a few times), scene builders and a compilation counter."""

from __future__ import annotations

import contextlib

import jax
import numpy as np

from spectral_fit import geometry as raster
from spectral_fit.geometry import _raster_setup, perspective_camera, project
from spectral_fit.io import concat_meshes, translate, uv_sphere

SMALL = (32, 64)  # (H, W) of the frames compared with the brute-force reference
MID = (72, 96)
T_PAD = 4096  # triangle lists are padded to this many (degenerate triangles are never drawn)
V_PAD = 4096
T_COVER = V_COVER = 2560  # sizes of the dense coverage counts (T × H × W)


def fixed_config(shape) -> raster.RasterConfig:
    """Generous fixed capacities for ≤ T_PAD triangles on a small frame: no overflow, no plan,
    one compilation per (shape, cull)."""
    h, w = shape
    caps = []
    for s in raster.TILE_SIZES:
        per_tri = -(-max(h, w) // s)  # windows of a 1-px-wide sliver along the longer side
        caps.append(min(T_PAD * per_tri, 4 * (-(-h // s) + 1) * (-(-w // s) + 1) * 8 + T_PAD))
    blocks = (-(-h // 8)) * (-(-w // 8))
    return raster.RasterConfig(raster.TILE_SIZES, tuple(caps), blocks)


def pad(clip, tris):
    """(clip (V_PAD, 4), tris (T_PAD, 3)): extra vertices at w = 1, extra triangles (0, 0, 0)."""
    clip = np.asarray(clip, np.float32)
    tris = np.asarray(tris, np.int32)
    assert len(clip) <= V_PAD and len(tris) <= T_PAD
    cp = np.zeros((V_PAD, 4), np.float32)
    cp[:, 3] = 1.0
    cp[: len(clip)] = clip
    tp = np.zeros((T_PAD, 3), np.int32)
    tp[: len(tris)] = tris
    return cp, tp


def rasterize_padded(clip, tris, shape, *, cull="none"):
    """rasterize() on the padded inputs with the fixed config; checks for overflow."""
    cp, tp = pad(clip, tris)
    r = raster.rasterize(cp, tp, shape, cull=cull, config=fixed_config(shape), check=False)
    assert not bool(r.overflow), np.asarray(r.needed)
    return r


def camera(shape, *, fov_y_deg=60.0, near=0.01, far=100.0):
    h, w = shape
    return perspective_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y_deg=fov_y_deg,
                              aspect=w / h, near=near, far=far)


def clip_of(cam, vertices, model=None):
    return np.asarray(project(cam, vertices, model))


def soup(seed, n_tri=48, *, behind=True):
    """Random triangles of all sizes in eye space (some crossing the near plane, the eye plane
    and the far plane), projected with the test camera: (clip (3n, 4), tris (n, 3))."""
    rng = np.random.default_rng(seed)
    cam = camera(SMALL, near=0.5, far=6.0)
    centre = np.stack([rng.uniform(-2, 2, n_tri), rng.uniform(-1.5, 1.5, n_tri),
                       rng.uniform(-7, -0.3 if behind else -1.0, n_tri)], -1)
    size = np.exp(rng.uniform(np.log(0.02), np.log(4.0), n_tri))[:, None, None]
    pts = centre[:, None, :] + size * rng.normal(size=(n_tri, 3, 3))
    verts = pts.reshape(-1, 3)
    tris = np.arange(3 * n_tri).reshape(n_tri, 3)
    return clip_of(cam, verts), tris


def two_spheres(z):
    """Two UV spheres (radius 0.3, 12 × 16) side by side at depth ``z`` (and ``z`` − 0.2), one
    mesh."""
    s = uv_sphere(0.3, 12, 16)
    return concat_meshes([s.transformed(translate((-0.35, 0.0, z))),
                          s.transformed(translate((0.35, 0.1, z - 0.2)))])[0]


def pixel_rays(cam, shape):
    """World-space ray directions (H, W, 3) through the pixel centres (camera at the origin
    looking down −Z, float64)."""
    h, w = shape
    proj = np.asarray(cam.projection, np.float64)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    xn = 2 * xs / w - 1
    yn = 1 - 2 * ys / h
    d = np.stack([xn / proj[0, 0], yn / proj[1, 1], -np.ones_like(xn)], -1)
    view = np.asarray(cam.view, np.float64)
    return d @ view[:3, :3]  # rotation part transposed = inverse


_COUNT_EVENT = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def count_compilations():
    """Context manager yielding a list that receives one entry per XLA compilation."""
    seen: list[float] = []

    def listener(name, duration, **_):
        if name == _COUNT_EVENT:
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


@jax.jit
def _coverage_counts_jit(clip, tris, valid_mask, h_iota, w_iota):
    data = _raster_setup._triangle_setup(clip, tris, (h_iota.shape[0], w_iota.shape[0]), "none")
    px = w_iota[None, :] + 0.5
    py = h_iota[:, None] + 0.5
    inside, _ = _raster_setup._cover(data, px, py)  # (T, H, W)
    inside &= (data[:, 15] > 0)[:, None, None] & valid_mask[:, None, None]
    return inside


def coverage_sets(clip, tris, shape):
    """(T, H, W) bool: which pixel centres each triangle covers by the rasteriser's OWN edge
    functions (to count double coverage, which the visibility buffers cannot show)."""
    h, w = shape
    cp, tp = pad(clip, tris)
    cp, tp = cp[:V_COVER], tp[:T_COVER]
    assert len(tris) <= T_COVER and len(clip) <= V_COVER
    valid = np.zeros(T_COVER, bool)
    valid[: len(tris)] = True
    out = _coverage_counts_jit(cp, tp, valid, np.arange(h, dtype=np.float32),
                               np.arange(w, dtype=np.float32))
    return np.asarray(out)[: len(tris)]


def facing(clip, tris):
    """+1 for front faces (counter-clockwise in NDC), −1 for back faces, from float64
    clip-space triple products."""
    c = np.asarray(clip, np.float64)[np.asarray(tris)]  # (T, 3, 4)
    return np.sign(np.linalg.det(c[:, :, [0, 1, 3]]))

"""Benchmarks of eq. (5) shading under a spectral environment.

``shade_100k_bands`` / ``shade_100k_k8``: 100k random surface points (unit normals N, view
directions V on N's visible hemisphere), one material (Gaussian D, V-cavity G), the realistic
synthetic environment of :func:`synthetic_environment` (128 × 256 texels); 81 bands, or K = 8
PCA coefficients (environment and reflectance projected; the diffuse product through the
K×K×K tensor). Gloss quality "render" (the frame renderer's).

``shade_frame_render`` / ``shade_frame_exact``: the covered pixels of the benchmark frame
(docs/benchmark.md "paper": two spheres of radius 37.5 mm at z = −0.275 m, 720 × 480, 90° vertical
FOV; 6,944 pixels, normals and view directions from exact ray–sphere intersections), under the
benchmark environment (``measurements/benchmark/anchor_environment.exr``, 31 bands, rotated
180° about +Y), materials of the benchmark (α = β = 1, χ = 0, μ = 0.1, n = 1.5, ColorChecker
N Ohta yellow / red), one :func:`shade_points` call per sphere; gloss quality "render" or
"exact". ``shade_frame_exact_wide``: the same with μ = 0.4 (a wide lobe: "exact" then sums the
bilinear map at the centres of a 2× finer grid directly), quality "exact".
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..._runtime.paths import REPO_ROOT
from .._harness import BenchOptions, measure

_ANCHOR_ENV = REPO_ROOT / "measurements" / "benchmark" / \
    "anchor_environment.exr"


def _inputs(n_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(n_points, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(n_points, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where((np.sum(n * v, axis=1) < 0)[:, None], -v, v)
    return n.astype(np.float32), v.astype(np.float32)


def frame_points(width: int = 720, height: int = 480, fov_y_deg: float = 90.0,
                 radius: float = 0.0375,
                 centres: tuple[tuple[float, float, float], ...] = ((-0.045, 0.0, -0.275),
                                                                    (0.045, 0.0, -0.275)),
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (P, 3), view directions (P, 3) and object ids (P,) of the pixels (centres at
    integer + 0.5) covered by spheres seen from a camera at the origin looking down −Z (exact
    ray–sphere intersection, nearest hit). The benchmark frame gives P = 6,944."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d = np.stack([(2.0 * j / width - 1.0) * (width / height) / f, (1.0 - 2.0 * i / height) / f,
                  -np.ones_like(j)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    best = np.full(d.shape[:2], np.inf)
    normal = np.zeros_like(d)
    obj = -np.ones(d.shape[:2], np.int32)
    for k, c in enumerate(centres):
        c = np.asarray(c, np.float64)
        b = d @ c
        disc = b * b - (c @ c - radius * radius)
        t = b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc > 0.0) & (t > 0.0) & (t < best)
        best = np.where(hit, t, best)
        obj = np.where(hit, k, obj)
        normal = np.where(hit[..., None], (d * t[..., None] - c) / radius, normal)
    m = obj >= 0
    return normal[m].astype(np.float32), (-d[m]).astype(np.float32), obj[m]


def _case(opts: BenchOptions, k: int | None) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from ...color import default_wavelengths, pca_basis, reflectances_5nm
    from ...lighting import EnvironmentMap, make_material, shade_points, synthetic_environment

    wl = default_wavelengths()
    h, w = (32, 64) if opts.quick else (128, 256)
    n_points = 2_000 if opts.quick else 100_000
    img = synthetic_environment(h, w, wl)
    w5, refl = reflectances_5nm()
    s = np.interp(wl, w5, refl[15])
    if k is None:
        env = EnvironmentMap.from_array(img)
        refl_c = s
    else:
        basis = pca_basis(k, wl)
        env = EnvironmentMap.from_array(basis.project(img), product_tensor=basis.product_tensor)
        refl_c = basis.project(s)
    mat = make_material(alpha=0.8, beta=1.0, chi=0.5, mu=0.15, n=1.5, reflectance=refl_c)
    normals, views = _inputs(n_points)
    fn = jax.jit(lambda m, e, a, b: shade_points(m, e, a, b, quality="render"))
    out = measure(fn, mat, env, jnp.asarray(normals), jnp.asarray(views), repeats=opts.repeats)
    q = env.quadrature
    out.update(points=n_points, channels=int(env.channels), map_shape=[h, w], quality="render",
               gloss_nodes=q.render_radial * q.render_azimuthal,
               sources=int(env.source_flux.shape[0]), gloss_channels=int(env.atlas.shape[1]))
    return out


def _frame_case(opts: BenchOptions, quality: str, mu: float = 0.1) -> dict[str, Any]:
    import colour
    import jax
    import jax.numpy as jnp

    from ...io import read_spectral_exr
    from ...lighting import EnvironmentMap, make_material, shade_points

    wl, img = read_spectral_exr(_ANCHOR_ENV)
    env = EnvironmentMap.from_array(np.asarray(img, np.float64), rotation_y_deg=180.0)
    normals, views, obj = frame_points()
    if opts.quick:
        keep = np.arange(0, normals.shape[0], 16)
        normals, views, obj = normals[keep], views[keep], obj[keep]
    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    mats = [make_material(alpha=1.0, beta=1.0, chi=0.0, mu=mu, n=1.5,
                          reflectance=np.interp(wl, cc[name].wavelengths, cc[name].values))
            for name in ("yellow", "red")]
    parts = [(jnp.asarray(normals[obj == i]), jnp.asarray(views[obj == i])) for i in (0, 1)]

    @jax.jit
    def fn(mats, env, parts):
        return [shade_points(m, env, nn, vv, quality=quality)
                for m, (nn, vv) in zip(mats, parts, strict=True)]

    out = measure(fn, mats, env, parts, repeats=opts.repeats)
    q = env.quadrature
    if quality == "render" or q.nodes != "grid":
        nodes = (q.render_radial * q.render_azimuthal if quality == "render"
                 else q.radial * q.azimuthal)
    else:  # the exact lobe grid cut to its disc (environment._grid_nodes)
        gx = (np.arange(q.grid_along) + 0.5) * (2.0 / q.grid_along) - 1.0
        gy = (np.arange(q.grid_across) + 0.5) * (2.0 / q.grid_across) - 1.0
        nodes = int(np.sum(gx[:, None] ** 2 + gy[None, :] ** 2 <= 1.0))
    out.update(points=int(normals.shape[0]), channels=int(env.channels), quality=quality, mu=mu,
               gloss_nodes=nodes, gloss_channels=int(env.atlas.shape[1]))
    return out


def shade_100k_bands(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, None)


def shade_100k_k8(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, 8)


def shade_frame_render(opts: BenchOptions) -> dict[str, Any]:
    return _frame_case(opts, "render")


def shade_frame_exact(opts: BenchOptions) -> dict[str, Any]:
    return _frame_case(opts, "exact")


def shade_frame_exact_wide(opts: BenchOptions) -> dict[str, Any]:
    return _frame_case(opts, "exact", mu=0.4)


CASES = {"shade_100k_bands": shade_100k_bands, "shade_100k_k8": shade_100k_k8,
         "shade_frame_render": shade_frame_render, "shade_frame_exact": shade_frame_exact,
         "shade_frame_exact_wide": shade_frame_exact_wide}

"""Benchmarks of eq. (5) shading: 100k surface points under a spectral environment.

Random unit normals N and view directions V on N's visible hemisphere, one material (Gaussian D,
V-cavity G), the realistic synthetic environment of :func:`synthetic_environment` (128 × 256
texels). ``shade_100k_bands``: 81 bands; ``shade_100k_k8``: K = 8 PCA coefficients (environment
and reflectance projected; the diffuse product through the K×K×K tensor). Points are shaded by
:func:`shade_points` (batches of 4096 through ``jax.lax.map``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bench import BenchOptions, measure


def _inputs(n_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(n_points, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(n_points, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where((np.sum(n * v, axis=1) < 0)[:, None], -v, v)
    return n.astype(np.float32), v.astype(np.float32)


def _case(opts: BenchOptions, k: int | None) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from ..basis import _reflectances_5nm, pca_basis
    from ..environment import EnvironmentMap, shade_points, synthetic_environment
    from ..reflectance import make_material
    from ..spectra import default_wavelengths

    wl = default_wavelengths()
    h, w = (32, 64) if opts.quick else (128, 256)
    n_points = 2_000 if opts.quick else 100_000
    img = synthetic_environment(h, w, wl)
    w5, refl = _reflectances_5nm()
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
    fn = jax.jit(shade_points)
    out = measure(fn, mat, env, jnp.asarray(normals), jnp.asarray(views), repeats=opts.repeats)
    out.update(points=n_points, channels=int(env.channels), map_shape=[h, w],
               gloss_nodes=env.quadrature.radial * env.quadrature.azimuthal,
               sources=int(env.source_flux.shape[0]),
               gloss_channels=int(env.atlas.shape[1]))
    return out


def shade_100k_bands(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, None)


def shade_100k_k8(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, 8)


CASES = {"shade_100k_bands": shade_100k_bands, "shade_100k_k8": shade_100k_k8}

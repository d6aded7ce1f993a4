"""The environment map sampled on the host along world directions for the radiance caches:
the prefiltered residual map at a given std (in the map's principal spectra), the unfiltered
bilinear map, and the table of its texels (directions, solid angles, radiance).

Shapes: N directions (N, 3) in world space; r principal-spectra channels, C map channels.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def _level_blend(env: Any, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Adjacent prefilter levels (lo, hi) and hi's weight whose blended variance is σ²."""
    sig = np.asarray(env.level_sigma, np.float64)
    s = np.clip(sigma, 0.0, sig[-1])
    hi = np.clip(np.searchsorted(sig, s, side="right"), 1, sig.size - 1)
    lo = hi - 1
    w = (s ** 2 - sig[lo] ** 2) / (sig[hi] ** 2 - sig[lo] ** 2)
    return lo.astype(np.int32), hi.astype(np.int32), np.clip(w, 0.0, 1.0)


@eqx.filter_jit
def _lookup_levels(env: Any, dirs: jax.Array, lo: jax.Array, hi: jax.Array, w: jax.Array
                   ) -> jax.Array:
    from ..lighting import lookup_level

    def one(d: jax.Array, a: jax.Array, b: jax.Array, ww: jax.Array) -> jax.Array:
        dm = d @ env.rotation  # world → map frame
        return (1.0 - ww) * lookup_level(env, a, dm) + ww * lookup_level(env, b, dm)

    return jax.vmap(one)(dirs, lo, hi, w)


def _pad(x: np.ndarray, size: int) -> np.ndarray:
    """``x`` padded to ``size`` rows by repeating its last row (one compiled size)."""
    return np.concatenate([x, np.repeat(x[-1:], size - x.shape[0], 0)])


def _prefiltered(env: Any, dirs: np.ndarray, sigma: np.ndarray, chunk: int = 32768
                 ) -> np.ndarray:
    """Residual-map radiance (N, r) along world directions (N, 3) prefiltered to std σ (N,)."""
    lo, hi, w = _level_blend(env, sigma)
    out = np.zeros((dirs.shape[0], env.atlas.shape[1]), np.float32)
    dt = env.atlas.dtype
    for a in range(0, dirs.shape[0], chunk):
        sl = slice(a, a + chunk)
        n = dirs[sl].shape[0]
        got = _lookup_levels(env, jnp.asarray(_pad(dirs[sl], chunk), dt),
                             jnp.asarray(_pad(lo[sl], chunk)), jnp.asarray(_pad(hi[sl], chunk)),
                             jnp.asarray(_pad(w[sl], chunk), dt))
        out[sl] = np.asarray(got)[:n]
    return out


def _texel_table(env: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World directions (T, 3), solid angles (T,) and radiance (T, C) of the unfiltered map."""
    from ..lighting import texel_directions, texel_solid_angles

    h, w, c = env.texels.shape
    R = np.asarray(env.rotation, np.float64)
    dirs = texel_directions(h, w).reshape(-1, 3) @ R.T
    return dirs, texel_solid_angles(h, w).reshape(-1), np.asarray(env.texels,
                                                                   np.float64).reshape(-1, c)


def _env_lookup(env: Any, dirs: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Unfiltered bilinear radiance (N, C) along world directions (N, 3)."""
    out = np.zeros((dirs.shape[0], env.texels.shape[-1]))
    for a in range(0, dirs.shape[0], chunk):
        d = dirs[a:a + chunk]
        n = d.shape[0]
        d = np.concatenate([d, np.repeat(d[-1:], chunk - n, 0)])
        out[a:a + n] = np.asarray(_lookup_jit(env, jnp.asarray(d, env.texels.dtype)))[:n]
    return out


@eqx.filter_jit
def _lookup_jit(env: Any, dirs: jax.Array) -> jax.Array:
    from ..lighting import lookup

    return jax.vmap(lambda d: lookup(env, d))(dirs)

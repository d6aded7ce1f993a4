"""Geometry of equirectangular maps, and their bilinear lookup in flat tables.

Map convention (docs/conventions.md, 'Conventions'): texel (row k, column j) of an (H, W, C) map
has its centre at v = (k + 0.5)/H, u = (j + 0.5)/W, with polar angle θ = πv from +Y and azimuth
φ = 2πu, direction

    d = (sinφ sinθ, cosθ, −cosφ sinθ)        (row 0 at the top, i.e. around +Y).

Texel directions and exact texel solid angles are NumPy (float64, at construction); direction →
(u, v) is JAX (:func:`direction_to_uv`, and :func:`fast_direction_to_uv` with a polynomial
atan2).

The lookup is bilinear, wraps in u (seam), and near the poles blends towards the mean of the first
/ last row placed at the pole itself, so it is continuous everywhere on the sphere. A level of
(H_k, W_k) texels is stored row-major in a flat (T, C) table from offset ``off``, followed by its
north and south pole means; :func:`bilinear_taps` gives the four table rows and weights of a
lookup and :func:`taps_sum` sums them (:func:`padded_table` / :func:`padded_bilinear`: the same
lookup from a padded layout).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._fastmath import atan2_poly

__all__ = [
    "rotation_y",
    "texel_directions",
    "texel_solid_angles",
    "direction_to_uv",
    "uv_to_direction",
    "fast_direction_to_uv",
    "uv_of",
    "bilinear_taps",
    "taps_sum",
    "padded_bilinear",
    "padded_table",
]


def rotation_y(degrees: float) -> np.ndarray:
    """Rotation matrix (3, 3) by ``degrees`` about +Y (right-handed: +Z turns towards +X)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def uv_to_direction(u: Any, v: Any) -> np.ndarray:
    """Direction (..., 3) of map coordinates u = φ/2π, v = θ/π (NumPy, float64)."""
    phi, theta = np.broadcast_arrays(2.0 * np.pi * np.asarray(u, np.float64),
                                     np.pi * np.asarray(v, np.float64))
    st = np.sin(theta)
    return np.stack([np.sin(phi) * st, np.cos(theta), -np.cos(phi) * st], axis=-1)


def texel_directions(height: int, width: int) -> np.ndarray:
    """Directions (H, W, 3) of texel centres (float64)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    return uv_to_direction(u[None, :], v[:, None])


def texel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angles (H, W) of the texels, Δφ (cosθ_top − cosθ_bottom); they sum to 4π."""
    edges = np.cos(np.pi * np.arange(height + 1) / height)
    rows = (2.0 * np.pi / width) * (edges[:-1] - edges[1:])
    return np.broadcast_to(rows[:, None], (height, width)).copy()


def direction_to_uv(d: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(u, v) in [0, 1) × [0, 1] of unit directions (..., 3) in the map frame (JAX).

    Gradient-safe at the poles (the azimuth is then arbitrary, and has zero gradient).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    rho2 = x * x + z * z
    small = rho2 < 1e-20
    rho = jnp.sqrt(jnp.where(small, 1.0, rho2))
    rho = jnp.where(small, 0.0, rho)
    theta = jnp.arctan2(rho, y)
    phi = jnp.arctan2(jnp.where(small, 0.0, x), jnp.where(small, 1.0, -z))
    u = jnp.mod(phi / (2.0 * math.pi), 1.0)
    return u, theta / math.pi


def fast_direction_to_uv(d: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`direction_to_uv` (same conventions, gradient-safe at the poles) with the
    vectorisable :func:`atan2_poly`; differs from it by < 1e-7 in u and v."""
    return uv_of(d[..., 0], d[..., 1], d[..., 2])


def uv_of(x: jax.Array, y: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`fast_direction_to_uv` of the direction with components (x, y, z)."""
    rho2 = x * x + z * z
    small = rho2 < 1e-20
    rho = jnp.sqrt(jnp.where(small, 1.0, rho2))
    rho = jnp.where(small, 0.0, rho)
    theta = atan2_poly(rho, y)
    phi = atan2_poly(jnp.where(small, 0.0, x), jnp.where(small, 1.0, -z))
    u = phi * (0.5 / math.pi)
    u = jnp.where(u < 0.0, u + 1.0, u)
    return u, theta * (1.0 / math.pi)


def _wrap(i: jax.Array, w: jax.Array) -> jax.Array:
    """``i mod w`` for ``i`` in [−w, 2w) (a texel column one beyond either edge), by selects:
    ``jnp.mod`` with a per-lookup ``w`` (the level's width) is an integer division per element
    on the CPU. Clipped to [0, w − 1] outside that range (e.g. a NaN coordinate), so a
    gather with it stays in bounds."""
    i = jnp.where(i < 0, i + w, i)
    return jnp.clip(jnp.where(i >= w, i - w, i), 0, w - 1)


def _tap_coords(u: jax.Array, v: jax.Array, hk: jax.Array, wk: jax.Array
                ) -> tuple[jax.Array, ...]:
    """The texel coordinates of a bilinear lookup at map coordinates (u, v) in a level of
    (hk, wk) texels (int32, scalars or per lookup): the column x0 (wrapped into [0, wk)), its
    weight fx towards x0 + 1, the row y0 (−1 above the first row centre, hk − 1 below the
    last), the flags north (y0 < 0) and south (y0 ≥ hk − 1), and the weight wy1 of row
    y0 + 1, blended linearly towards the pole mean past the first and last row centres."""
    dtype = u.dtype
    tx = u * wk.astype(dtype) - 0.5
    ty = v * hk.astype(dtype) - 0.5
    x0f = jnp.floor(tx)
    fx = tx - x0f
    x0 = _wrap(x0f.astype(jnp.int32), wk)
    y0f = jnp.floor(ty)
    fy = ty - y0f
    y0 = y0f.astype(jnp.int32)
    north = y0 < 0
    south = y0 >= hk - 1
    wy1 = jnp.clip(jnp.where(north, 2.0 * fy - 1.0, jnp.where(south, 2.0 * fy, fy)), 0.0, 1.0)
    return x0, fx, y0, north, south, wy1


def bilinear_taps(u: jax.Array, v: jax.Array, off: jax.Array, hk: jax.Array, wk: jax.Array,
                   *, lead: bool = False) -> tuple[jax.Array, jax.Array]:
    """Atlas rows (..., 4) and weights (..., 4) of the bilinear lookup of :func:`_bilinear`
    (wrapped in u; between the first (last) row centre and the pole blended linearly towards
    the pole mean stored after the level), elementwise in (u, v) and the level's (off, hk, wk).
    ``lead``: as (4, ...) instead, for :func:`taps_sum` with ``lead`` (a stack on the last
    axis is a concatenate XLA:CPU writes element by element, which is slower)."""
    x0, fx, y0, north, south, wy1 = _tap_coords(u, v, hk, wk)
    x1 = jnp.where(x0 + 1 >= wk, 0, x0 + 1)
    r0 = off + jnp.clip(y0, 0, hk - 1) * wk
    r1 = off + jnp.clip(y0 + 1, 0, hk - 1) * wk
    pole_n = off + hk * wk
    ax = 0 if lead else -1
    idx = jnp.stack([jnp.where(north, pole_n, r0 + x0), jnp.where(north, pole_n, r0 + x1),
                     jnp.where(south, pole_n + 1, r1 + x0),
                     jnp.where(south, pole_n + 1, r1 + x1)], axis=ax)
    w = jnp.stack([(1 - wy1) * (1 - fx), (1 - wy1) * fx, wy1 * (1 - fx), wy1 * fx], axis=ax)
    return idx, w


def taps_sum(flat: jax.Array, idx: jax.Array, w: jax.Array, *, lead: bool = False
              ) -> jax.Array:
    """Σ_k w[..., k] flat[idx[..., k]]: (..., K) taps → (..., C), unrolled over k (XLA:CPU
    runs a reduction over a short middle axis, or a batched dot of tiny matrices, as a slow
    loop, much slower than this sum of products), one gather per tap: a gather of all K taps
    at once has the (..., K) indices written to memory first, whereas a tap's own gather
    computes its index in place. ``lead``: the taps on the leading axis,
    ``idx``, ``w`` (K, ...)."""
    if lead:
        out = flat.at[idx[0]].get(mode="promise_in_bounds") * w[0][..., None]
        for k in range(1, idx.shape[0]):
            out = out + flat.at[idx[k]].get(mode="promise_in_bounds") * w[k][..., None]
        return out
    out = flat.at[idx[..., 0]].get(mode="promise_in_bounds") * w[..., 0, None]
    for k in range(1, idx.shape[-1]):
        out = out + flat.at[idx[..., k]].get(mode="promise_in_bounds") * w[..., k, None]
    return out


def padded_table(flat: jax.Array, hm: int, wm: int) -> jax.Array:
    """A map's table laid out for :func:`padded_bilinear`: ``flat`` ((Hm·Wm + 2, C), the
    texels then the north and south pole means, as :func:`bilinear_taps` reads it) as
    (Hm + 2) rows of (Wm + 1) texels: a row of the north pole mean, the map's rows, a row of
    the south pole mean, each row followed by a copy of its first texel (the wrap in u).
    Returns ((Hm + 2)·(Wm + 1), C)."""
    c = flat.shape[-1]
    tex = flat[:hm * wm].reshape(hm, wm, c)
    rows = jnp.concatenate([jnp.broadcast_to(flat[hm * wm], (1, wm, c)), tex,
                            jnp.broadcast_to(flat[hm * wm + 1], (1, wm, c))])
    return jnp.concatenate([rows, rows[:, :1]], axis=1).reshape(-1, c)


def padded_bilinear(table: jax.Array, u: jax.Array, v: jax.Array, hm: int, wm: int
                    ) -> jax.Array:
    """The bilinear lookup of :func:`bilinear_taps` + :func:`taps_sum` (one level of size
    (Hm, Wm); wrapped in u, blended towards the pole means past the first and last row
    centres) at map coordinates u, v (N,), from :func:`padded_table`'s layout: the four taps
    are the texels at b, b + 1, b + Wm + 1 and b + Wm + 2 of one base index b, so the index
    arithmetic (done again for every channel of the result) is a third of the general one's.
    The same texels, weights and summation order: bit-identical to the general lookup, and
    cheaper for the frame's background. Returns (N, C)."""
    wp = wm + 1
    x0, fx, y0, _, _, wy1 = _tap_coords(u, v, jnp.int32(hm), jnp.int32(wm))
    base = (jnp.clip(y0, -1, hm - 1) + 1) * wp + x0
    out = table.at[base].get(mode="promise_in_bounds") * ((1 - wy1) * (1 - fx))[..., None]
    out = out + table.at[base + 1].get(mode="promise_in_bounds") * ((1 - wy1) * fx)[..., None]
    out = out + table.at[base + wp].get(mode="promise_in_bounds") * (wy1 * (1 - fx))[..., None]
    return out + table.at[base + wp + 1].get(mode="promise_in_bounds") * (wy1 * fx)[..., None]

"""Elementwise arithmetic that XLA:CPU vectorises, for the per-point, per-node code of the gloss
quadratures and of the frame's lookups (JAX, elementwise and broadcasting).

XLA:CPU calls libm's scalar sinf/cosf/atan2f per element, and runs short reductions and small
dots as loops: :func:`sincos_poly` and :func:`atan2_poly` replace the former by polynomials
(|error| < 1e-7 and < 3e-7 rad), :func:`dot3` and :func:`select_static` the latter by sums of
products and selects. :func:`smootherstep` is the quintic (C²) step that blends prefilter levels
and quadrature methods.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

__all__ = [
    "atan2_poly",
    "dot3",
    "select_static",
    "sincos_poly",
    "smootherstep",
]


def select_static(table: Any, index: jax.Array) -> jax.Array:
    """``table[index]`` for a short static table and an index in range, as masked constants
    (elementwise, so it fuses into the surrounding arithmetic instead of becoming a
    gather)."""
    out = jnp.full(index.shape, table[0])
    for k in range(1, len(table)):
        out = jnp.where(index == k, table[k], out)
    return out


def smootherstep(x: jax.Array) -> jax.Array:
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def sincos_poly(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(sin x, cos x) by elementwise arithmetic: Cody–Waite reduction by π/2 (three-part π/2)
    and the Cephes sinf/cosf polynomials on [−π/4, π/4] (|error| < 1e-7 for |x| < 100).
    XLA:CPU calls libm's scalar sinf/cosf per element (several times slower); the gloss
    quadratures evaluate them per point and per node."""
    k = jnp.round(x * (2.0 / math.pi))
    r = ((x - k * 1.5703125) - k * 4.837512969970703125e-4) - k * 7.54978995489188216e-8
    r2 = r * r
    s = r + r * r2 * (-1.6666654611e-1 + r2 * (8.3321608736e-3 + r2 * -1.9515295891e-4))
    c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166664568298827e-2 + r2 * (
        -1.388731625493765e-3 + r2 * 2.443315711809948e-5))
    q = k.astype(jnp.int32) & 3
    odd = (q & 1) == 1
    sn = jnp.where(odd, c, s)
    cs = jnp.where(odd, s, c)
    return jnp.where(q >= 2, -sn, sn), jnp.where((q == 1) | (q == 2), -cs, cs)


def atan2_poly(y: jax.Array, x: jax.Array) -> jax.Array:
    """atan2(y, x) by elementwise arithmetic: reduction to [0, tan π/8] and the Cephes atanf
    polynomial (|error| < 3e-7 rad). XLA:CPU vectorises it; its own atan2 (and arccos) is a
    scalar library call, far slower per element than exp or a division."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi = jnp.maximum(ax, ay)
    a = jnp.minimum(ax, ay) / jnp.where(hi > 0.0, hi, 1.0)
    big = a > 0.41421356237
    z = jnp.where(big, (a - 1.0) / (a + 1.0), a)
    z2 = z * z
    p = ((((8.05374449538e-2 * z2 - 1.38776856032e-1) * z2 + 1.99777106478e-1) * z2
          - 3.33329491539e-1) * z2) * z + z
    r = jnp.where(big, 0.25 * math.pi + p, p)
    r = jnp.where(ay > ax, 0.5 * math.pi - r, r)
    r = jnp.where(x < 0.0, math.pi - r, r)
    return jnp.where(y < 0.0, -r, r)


def dot3(a: jax.Array, b: jax.Array) -> jax.Array:
    """a·b over the last axis (3) by components (vectorises; see :func:`taps_sum`)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]

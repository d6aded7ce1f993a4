"""The gather's mip atlas: per pair, the g × g sender samples' premultiplied values (radiance
× coverage, normal × coverage) and all their mip levels down to 1 × 1, each level padded by
a one-texel zero border, in one flat (P·T, C) array (:func:`_build_mips`), and the trilinear
taps (atlas rows and weights, C¹ within and across levels) of a lookup at level-0 texel
coordinates and a fractional level (:func:`_mip_taps`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.backend import materialise, on_accelerator
from ...lighting import select_static, smootherstep

__all__: list[str] = []


def _mip_levels(g: int) -> list[int]:
    sizes = [g]
    while sizes[-1] > 1:
        sizes.append(sizes[-1] // 2)
    return sizes


def _mip_layout(g: int) -> tuple[list[int], list[int], int]:
    """Sizes, offsets and total texels per pair of the padded mip atlas of a g × g grid."""
    sizes = _mip_levels(g)
    offs = [int(o) for o in np.cumsum([0] + [(s + 2) ** 2 for s in sizes])]
    return sizes, offs[:-1], offs[-1]


def _build_mips(values: jax.Array, g: int) -> jax.Array:
    """(P, g², C) premultiplied texels → (P·T, C) atlas of all mip levels of every pair (T
    texels per pair), each level padded by a one-texel zero border (so bilinear lookups fade
    to 0 outside j)."""
    p, _, c = values.shape
    # computed once into memory: otherwise XLA:CPU fuses the texels' whole expression (a
    # bounce's lum: the samples' gather and its interpolation) into every level's reduction
    # and evaluates it again there, g² times for the 1 × 1 level
    lev = materialise(values, cut=True).reshape(p, g, g, c)
    flat = []
    for s in _mip_levels(g):
        if lev.shape[1] != s:
            lev = lev.reshape(p, s, 2, s, 2, c).mean(axis=(2, 4))
            if on_accelerator():
                # each level from the stored previous one: fused into the atlas's one
                # kernel, the 1 × 1 level's thread summed all g² texels alone
                lev = jax.lax.optimization_barrier(lev)
        flat.append(jnp.pad(lev, ((0, 0), (1, 1), (1, 1), (0, 0))).reshape(p, -1, c))
    return jnp.concatenate(flat, axis=1).reshape(-1, c)


def _mip_taps(pair: jax.Array, tx: jax.Array, ty: jax.Array, level: jax.Array, g: int
              ) -> tuple[jax.Array, jax.Array]:
    """Atlas rows (..., 8) and weights (..., 8) of the trilinear lookup of pair ``pair``'s mip
    atlas (:func:`_build_mips`) at level-0 texel coordinates (tx, ty) (texel centres at
    integer + 0.5) and fractional ``level`` (clamped); C¹ smoothstep weights within and across
    levels (gradients). Elementwise in all arguments."""
    sizes, offs, per_pair = _mip_layout(g)
    nl = len(sizes)
    level = jnp.clip(level, 0.0, nl - 1.0)
    lo = jnp.minimum(jnp.floor(level).astype(jnp.int32), nl - 1)
    hi = jnp.minimum(lo + 1, nl - 1)
    wh = smootherstep(level - lo.astype(level.dtype))
    idx, wts = [], []
    for lev, wl in ((lo, 1.0 - wh), (hi, wh)):
        si = select_static([np.int32(s) for s in sizes], lev)
        scale = select_static([np.float32(s / g) for s in sizes], lev).astype(tx.dtype)
        base = pair * per_pair + select_static([np.int32(o) for o in offs], lev)
        x = tx * scale + 0.5  # −0.5 (texel centres) + 1 (border)
        y = ty * scale + 0.5
        x0f, y0f = jnp.floor(x), jnp.floor(y)
        fx, fy = smootherstep(x - x0f), smootherstep(y - y0f)
        x0 = jnp.clip(x0f.astype(jnp.int32), 0, si + 1)
        y0 = jnp.clip(y0f.astype(jnp.int32), 0, si + 1)
        x1 = jnp.minimum(x0 + 1, si + 1)
        y1 = jnp.minimum(y0 + 1, si + 1)
        row = si + 2
        idx += [base + y0 * row + x0, base + y0 * row + x1, base + y1 * row + x0,
                base + y1 * row + x1]
        wts += [wl * (1 - fy) * (1 - fx), wl * (1 - fy) * fx, wl * fy * (1 - fx), wl * fy * fx]
    return jnp.stack(idx, -1), jnp.stack(wts, -1)

"""The "paper" mode's shading pass: eq. (6) of Mochizuki & Tanaka, literally.

Pass 1 shading (:func:`_paper_textures`): each sender j's covered pass-1 texels, seen from the
receiver's centre, into two spectral textures (P, T², C): T_d, the diffuse-only radiance
α_j S_j E_irr/π, and T_s, the specular-only β_j I_gloss + χ_j I_mirror. Pass 2
(:func:`_paper_mode`): each receiving fragment x projected through the same camera adds
α_paper T_d + γ T_s looked up bilinearly (clamp to edge, texels outside j are 0) where the
projection is valid (in front of the eye, inside the view, the fragment facing j);
α_paper = α/π. Radiance in the environment's unit (bands or basis coefficients), (N, C).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ...geometry import GBuffer
from ...lighting import (
    EnvironmentMap,
    Material,
    gloss_integral,
    gloss_split_sum,
    irradiance,
    lobe_moment_table,
    mirror_radiance,
)
from ._pass1 import IRGeometry, _normalize
from ._shading import _stack_materials, _times_reflectance

__all__: list[str] = []


def _paper_textures(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                    split: tuple[Any, Any] | None = None) -> tuple[jax.Array, jax.Array]:
    """Pass 1 shading: T_d, T_s (P, T², C) of each sender seen from the receiver's centre.
    The gloss uses the environment module's "render" quadrature (8 × 16 nodes: the textures
    are a 64² approximation of the sender anyway, and "exact" costs far more per texel), or
    with ``split`` = (:class:`~spectral_fit.lighting.SplitSumMap`, its
    :class:`~spectral_fit.lighting.SplitSum` settings) the frame's split-sum gloss
    (:func:`~spectral_fit.lighting.gloss_split_sum`, quality "fast": many times cheaper
    than the quadrature over the textures' texels, its texels' gloss within the split sum's
    accuracy of the quadrature; it is 0 below the texel's horizon, as the quadrature)."""
    t2 = geom.texture_size ** 2
    c = env.channels
    tds, tss = [], []
    for p, (_, j) in enumerate(geom.pairs):
        m = materials[j]
        nrm = geom.p_nrm[p]
        view = _normalize(geom.centre_i[p] - geom.p_pos[p])

        def texel(nn: jax.Array, vv: jax.Array, m: Material = m) -> tuple[jax.Array, jax.Array]:
            e = irradiance(env, nn)
            td = (m.alpha / math.pi) * _times_reflectance(env, m.reflectance, e)
            ts = m.chi * mirror_radiance(env, nn, vv, m.n)
            if split is None:
                ts = ts + m.beta * gloss_integral(
                    env, nn, vv, m.mu, m.n, distribution=m.distribution,
                    geometry=m.geometry, quality="render")
            front = jnp.dot(nn, vv) > 0.0
            return td, jnp.where(front, ts, 0.0)

        td, ts = jax.vmap(texel)(nrm, view)
        if split is not None:
            split_map, settings = split
            table = lobe_moment_table(m.mu, m.n, distribution=m.distribution,
                                      geometry=m.geometry, settings=settings)
            ts = ts + m.beta * gloss_split_sum(env, split_map, table, nrm, view, m.mu, m.n,
                                               distribution=m.distribution,
                                               geometry=m.geometry, settings=settings)
        valid = geom.p_valid[p][:, None]
        idx = jnp.where(geom.p_valid[p], geom.p_index[p], t2)
        tds.append(jnp.zeros((t2, c), td.dtype).at[idx].set(jnp.where(valid, td, 0.0),
                                                            mode="drop"))
        tss.append(jnp.zeros((t2, c), ts.dtype).at[idx].set(jnp.where(valid, ts, 0.0),
                                                            mode="drop"))
    return jnp.stack(tds), jnp.stack(tss)


def _bilinear_clamped(tex: jax.Array, pair: jax.Array, t: int, px: jax.Array, py: jax.Array
                      ) -> jax.Array:
    """GL_LINEAR + CLAMP_TO_EDGE lookup (C,) of texture ``tex[pair]`` (T², C) at pixel
    coordinates (px, py) (texel centres at integer + 0.5)."""
    x = px - 0.5
    y = py - 0.5
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = jnp.clip(x0f.astype(jnp.int32), 0, t - 1)
    x1 = jnp.clip(x0f.astype(jnp.int32) + 1, 0, t - 1)
    y0 = jnp.clip(y0f.astype(jnp.int32), 0, t - 1)
    y1 = jnp.clip(y0f.astype(jnp.int32) + 1, 0, t - 1)
    idx = jnp.stack([y0 * t + x0, y0 * t + x1, y1 * t + x0, y1 * t + x1])
    w = jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx])
    return w @ tex[pair, idx]


def _paper_mode(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                receivers: GBuffer, split: tuple[Any, Any] | None = None) -> jax.Array:
    td, ts = _paper_textures(geom, materials, env, split)
    t = geom.texture_size
    k_per = geom.n_objects - 1
    obj = receivers.object
    ok = obj >= 0
    o = jnp.maximum(obj, 0)
    mats = _stack_materials(materials)
    a_paper = mats["alpha"][o] / math.pi
    gamma = mats["gamma"][o]
    pos, nrm = receivers.position, receivers.normal
    out = jnp.zeros((pos.shape[0], env.channels), td.dtype)
    for k in range(k_per):
        pair = o * k_per + k
        vp = geom.p_view_proj[pair]  # (N, 4, 4)
        clip = jnp.einsum("nij,nj->ni", vp[:, :, :3], pos) + vp[:, :, 3]
        w = clip[:, 3]
        wsafe = jnp.where(w > 0, w, 1.0)
        nx, ny = clip[:, 0] / wsafe, clip[:, 1] / wsafe
        facing = jnp.sum(nrm * (geom.centre_j[pair] - pos), -1) > 0.0
        valid = ok & (w > 0) & (jnp.abs(nx) <= 1.0) & (jnp.abs(ny) <= 1.0) & facing
        px = (nx + 1.0) * 0.5 * t
        py = (1.0 - ny) * 0.5 * t
        look = jax.vmap(lambda p_, a, b, tex: _bilinear_clamped(tex, p_, t, a, b),
                        in_axes=(0, 0, 0, None))
        add = a_paper[:, None] * look(pair, px, py, td) + gamma[:, None] * look(pair, px, py,
                                                                                 ts)
        out = out + jnp.where(valid[:, None], add, 0.0)
    return out

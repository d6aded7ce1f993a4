"""Shading under an environment map, eq. (5): the mirror term F(n, θr) L(R), R = reflect(−V, N),
by a bilinear lookup of the unfiltered map (:func:`mirror_radiance`), and diffuse + β gloss +
χ mirror at one point (:func:`shade`) or many (:func:`shade_points`), for world unit normals and
views. Radiance in the map's channels: bands, or K basis coefficients (the diffuse S·E product
through ``env.product_tensor``).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from ._environment import EnvironmentMap, lookup
from ._gloss import gloss_integral
from ._irradiance import irradiance
from ._reflectance import Material, fresnel_dielectric

__all__ = [
    "mirror_radiance",
    "shade",
    "shade_points",
]


def mirror_radiance(env: EnvironmentMap, normal: Any, view: Any, n: Any) -> jax.Array:
    """Mirror radiance per unit χ (C,): F(n, θr) · L(R), R = reflect(−V, N) = 2(N·V)N − V."""
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    nv = jnp.dot(N, V)
    R = 2.0 * nv * N - V
    out = fresnel_dielectric(nv, n) * lookup(env, R)
    return jnp.where(nv > 0.0, out, 0.0)


def shade(material: Material, env: EnvironmentMap, normal: Any, view: Any, *,
          quality: str = "exact") -> jax.Array:
    """Radiance (C,) leaving a surface point towards V under the environment, eq. (5) in
    our physical reading:

        α S(λ) E_irr(λ, N)/π + β ∫ L F D G /(4 cosθr) dω + χ F(n, θr) L(λ, R).

    (The paper's E(λ) factor of the gloss and mirror terms is the environment's own radiance
    here.) Bands: ``material.reflectance`` and the map are (L,) / (H, W, L). Coefficients: both
    are K basis coefficients and the result is the K coefficients of the radiance (the S·E
    product through ``env.product_tensor``). Unbatched: ``jax.vmap`` over points and/or
    materials. Zero if N·V <= 0.

    Args:
        normal, view: world unit vectors (3,), away from the surface.
        quality: gloss quadrature, "exact" (fitting, validation) or "render" (frames); see
            :func:`gloss_integral`.
    """
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    E = irradiance(env, N)
    if env.product_tensor is None:
        se = material.reflectance * E
    else:
        se = jnp.einsum("i,j,ijk->k", material.reflectance, E, env.product_tensor)
    diffuse = (material.alpha / math.pi) * se
    gloss = gloss_integral(env, N, V, material.mu, material.n,
                           distribution=material.distribution, geometry=material.geometry,
                           quality=quality)
    mirror = mirror_radiance(env, N, V, material.n)
    out = diffuse + material.beta * gloss + material.chi * mirror
    return jnp.where(jnp.dot(N, V) > 0.0, out, 0.0)


def shade_points(material: Material, env: EnvironmentMap, normals: Any, views: Any, *,
                 batch_size: int = 32, quality: str = "exact") -> jax.Array:
    """:func:`shade` over many points, (P, 3) normals and views → (P, C), evaluated in batches
    of ``batch_size`` points (``jax.lax.map``): small batches keep each batch's gloss nodes and
    map taps (points × nodes × 8 × channels) in cache, which on a CPU is several times faster
    than one large batch (such as 4096 points).
    jit/grad-able; the same numbers as ``jax.vmap(shade)``. ``quality``: see :func:`shade`."""
    normals = jnp.asarray(normals)
    views = jnp.asarray(views)
    return jax.lax.map(lambda nv: shade(material, env, nv[0], nv[1], quality=quality),
                       jnp.stack([normals, views], axis=1), batch_size=batch_size)

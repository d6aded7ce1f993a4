"""Diffuse irradiance under an environment map: E(N) = ∫ L(ω) max(0, N·ω) dω (C,) on a surface
of world unit normal N (3,), by order-2 spherical harmonics (R&H 2001 eq. 13,
:func:`irradiance_sh`) or exactly by a texel sum with exact texel solid angles
(:func:`irradiance_exact`); and :func:`white_reference`, the radiance of a white Lambertian
facing +Y under an (H, W, L) map (NumPy).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._environment import EnvironmentMap, _to_map
from ._equirect import texel_directions, texel_solid_angles
from ._sh import SH_C1, SH_C2, SH_C3, SH_C4, SH_C5

__all__ = [
    "irradiance_sh",
    "irradiance_exact",
    "irradiance",
    "white_reference",
]


def irradiance_sh(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) on a surface of world unit normal (3,), R&H 2001 eq. 13."""
    n = _to_map(env, jnp.asarray(normal))
    x, y, z = n[0], n[1], n[2]
    L = env.sh
    return (SH_C1 * L[8] * (x * x - y * y) + SH_C3 * L[6] * z * z + SH_C4 * L[0]
            - SH_C5 * L[6]
            + 2.0 * SH_C1 * (L[4] * x * y + L[7] * x * z + L[5] * y * z)
            + 2.0 * SH_C2 * (L[3] * x + L[1] * y + L[2] * z))


def irradiance_exact(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) by the texel sum Σ L max(0, N·ω) Δω over the unfiltered map."""
    h, w, c = env.texels.shape
    dirs = jnp.asarray(texel_directions(h, w).reshape(-1, 3), env.texels.dtype)
    sa = jnp.asarray(texel_solid_angles(h, w).reshape(-1), env.texels.dtype)
    n = _to_map(env, jnp.asarray(normal))
    wgt = jnp.maximum(dirs @ n, 0.0) * sa
    return wgt @ env.texels.reshape(-1, c)


def irradiance(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) by the environment's ``diffuse`` mode ("sh" or "exact")."""
    if env.diffuse == "exact":
        return irradiance_exact(env, normal)
    return irradiance_sh(env, normal)


def white_reference(environment: np.ndarray) -> np.ndarray:
    """(L,) radiance of a white Lambertian facing world +Y (the table) under an
    equirectangular map (Hm, Wm, L) (our mapping: row k at polar angle π(k + ½)/Hm):
    E(+Y)/π = (1/π) ∑ L cosθ sinθ Δθ Δφ over the upper hemisphere. Rotations about +Y do not
    change it."""
    env = np.asarray(environment, np.float64)
    hm, wm = env.shape[:2]
    theta = (np.arange(hm) + 0.5) * np.pi / hm
    wgt = np.cos(theta) * np.sin(theta) * (np.pi / hm) * (2 * np.pi / wm)
    wgt = np.where(theta < np.pi / 2, wgt, 0.0)
    e = np.einsum("h,hwl->l", wgt, env)
    return e / np.pi

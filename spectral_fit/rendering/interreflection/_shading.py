"""The shading context of the interreflection's shading pass: the objects' materials stacked
per object, the receivers' gloss-lobe albedo tables, and the environment lookups that the
gather's senders and receivers share (prefiltered radiance along directions, the bright
sources, a sender's view-dependent radiance :func:`_specular`).

Shapes: per point (K,) or (N,) with unit vectors (..., 3); radiance (..., C) in the
environment's channels (bands, or basis coefficients through ``env.product_tensor``), or
(..., r) in the map's r principal channels (``env.spectral_basis``) for what comes from the
environment alone, until it has been summed. Object indices −1 (empty slots) read object 0's
material (their results are masked by the caller).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.backend import materialise_each
from ...lighting import (
    EnvironmentMap,
    Material,
    bilinear_taps,
    dot3,
    fast_direction_to_uv,
    fast_lookup,
    fresnel_dielectric,
    levels_for,
    lobe_albedo,
    microfacet_fdg,
    select_static,
    smootherstep,
    taps_sum,
    to_map_fast,
)

__all__: list[str] = []

#: lobe-albedo quadrature of the receiver's gloss (radial × azimuthal nodes, scalar only),
#: tabulated at this many cosines per object
_ALBEDO_NODES = (16, 8)
_ALBEDO_TABLE = 33


def _stack_materials(materials: Sequence[Material]) -> dict[str, jax.Array]:
    return {k: jnp.stack([jnp.asarray(getattr(m, k)) for m in materials])
            for k in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance")}


def _times_reflectance(env: EnvironmentMap, s: jax.Array, x: jax.Array) -> jax.Array:
    """S ⊙ X per row (bands), or the basis product (coefficients)."""
    if env.product_tensor is None:
        return s * x
    return jnp.einsum("...i,...j,ijk->...k", s, x, env.product_tensor)


def _albedo_tables(materials: Sequence[Material]) -> jax.Array:
    """(n, T) receiver lobe albedos A(cosθr) = ∫ D F G (V·H)/(N·V) dω_H per object, at
    ``_ALBEDO_TABLE`` cosines in [0, 1], with the object's μ, n, D and G (differentiable)."""
    nodes = np.linspace(0.0, 1.0, _ALBEDO_TABLE)
    nodes[0] = 1e-3
    rows = []
    for m in materials:
        rows.append(jax.vmap(lambda c, m=m: lobe_albedo(
            c, m.mu, m.n, m.mu, distribution=m.distribution, geometry=m.geometry,
            fresnel=True, radial=_ALBEDO_NODES[0], azimuthal=_ALBEDO_NODES[1]))(
                jnp.asarray(nodes, jnp.result_type(m.mu, jnp.float32))))
    return jnp.stack(rows)


def _albedo_at(table: jax.Array, obj: jax.Array, nv: jax.Array) -> jax.Array:
    """Lobe albedo (...) of object ``obj`` at cosθr ``nv``: :func:`_albedo_tables` interpolated
    linearly in cosθr."""
    size = table.shape[1]
    x = jnp.clip(nv, 0.0, 1.0) * (size - 1)
    i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    f = x - i0.astype(x.dtype)
    flat = table.reshape(-1)
    base = jnp.maximum(obj, 0) * size + i0
    return (1.0 - f) * flat[base] + f * flat[base + 1]


def _env_blur(env: EnvironmentMap, dirs: jax.Array, sigma: jax.Array) -> jax.Array:
    """Environment radiance (..., r) along world unit directions ``dirs`` (..., 3), prefiltered
    to angular std ``sigma`` (...) (radians; the residual map without its bright sources), in
    the r channels of ``env.spectral_basis``: two adjacent prefiltered levels blended, eight
    bilinear taps gathered at once."""
    lead = dirs.shape[:-1]
    d = to_map_fast(env, dirs.reshape(-1, 3))
    u, v = fast_direction_to_uv(d)
    u, v = materialise_each(u, v)
    lo, hi, w_hi, _ = levels_for(env, jnp.broadcast_to(sigma, lead).reshape(-1))
    shapes = env.level_shapes
    levels = []
    for lev in (lo, hi):
        levels += [select_static([np.int32(h) for h, _ in shapes], lev),
                   select_static([np.int32(w) for _, w in shapes], lev),
                   select_static([np.int32(o) for o in env.level_offsets], lev)]
    # computed once per lookup: fused into the taps, the select chains would run once per
    # tap and per index/weight array
    levels = materialise_each(*levels)
    idx, wts = [], []
    for k, wl in ((0, 1.0 - w_hi), (1, w_hi)):
        hk, wk, off = levels[3 * k:3 * k + 3]
        i, w = bilinear_taps(u, v, off, hk, wk, lead=True)
        idx.append(i)
        wts.append(w * wl)
    out = taps_sum(env.atlas, jnp.concatenate(idx, 0), jnp.concatenate(wts, 0), lead=True)
    return out.reshape(*lead, -1)


def _source_terms(env: EnvironmentMap) -> tuple[jax.Array, jax.Array] | None:
    """World directions (S·k, 3) and flux (S·k, r) (``env.spectral_basis`` channels) of the
    environment's bright-source sub-points (None without sources)."""
    if not env.source_flux.shape[0]:
        return None
    k = env.source_dirs.shape[1]
    sdir = env.source_dirs.reshape(-1, 3) @ env.rotation.T
    return sdir, jnp.repeat(env.source_flux, k, axis=0)


def _gloss_weights(nrm: jax.Array, view: jax.Array, light: jax.Array, mu: jax.Array,
                   eta: jax.Array, distribution: str, geometry: str) -> jax.Array:
    """F D G / (4 cosθr) (the gloss BRDF times cosθi) for unit vectors (..., 3) (broadcast),
    0 unless both directions are above the surface."""
    fdg, nv, nl = microfacet_fdg(nrm, view, light, mu, eta, distribution, geometry)
    ok = (nl > 0.0) & (nv > 0.0)
    return jnp.where(ok, fdg / (4.0 * jnp.where(ok, nv, 1.0)), 0.0)


class _Shading(eqx.Module):
    """Per-call shading context of the gather: the objects' materials (stacked per object and
    as given), the environment, and the receivers' lobe-albedo tables."""

    mats: dict[str, jax.Array]
    env: EnvironmentMap
    albedo: jax.Array
    materials: tuple[Material, ...]
    mirror: bool = eqx.field(static=True)
    #: (C, D) linear map into the caller's output channels (None: the C channels)
    output: jax.Array | None = None

    @property
    def basis(self) -> jax.Array:
        """(r, D) the environment's principal channels → the output channels."""
        b = self.env.spectral_basis
        return b if self.output is None else b @ self.output

    @property
    def channels(self) -> int:
        """D: the number of output channels."""
        return self.env.channels if self.output is None else self.output.shape[1]

    def to_output(self, x: jax.Array) -> jax.Array:
        """(..., C) radiance → (..., D) output channels."""
        return x if self.output is None else x @ self.output

    def diffuse_matrices(self) -> jax.Array:
        """(n, C, D) per object: net diffuse light (C) → α S(λ) ⊙ net in the output channels
        (bands: α diag(S) M; coefficients: through the basis product tensor)."""
        mats = self.mats
        out = (jnp.eye(self.env.channels, dtype=jnp.float32) if self.output is None
               else self.output)
        s = mats["reflectance"]
        if self.env.product_tensor is None:
            m = s[:, :, None] * out[None]
        else:
            m = jnp.einsum("oi,ijk,kd->ojd", s, self.env.product_tensor, out)
        return mats["alpha"][:, None, None] * m


def _shading(materials: Sequence[Material], env: EnvironmentMap) -> _Shading:
    return _Shading(mats=_stack_materials(materials), env=env,
                    albedo=_albedo_tables(materials), materials=tuple(materials),
                    mirror=any(not _is_zero(m.chi) for m in materials))


def _specular(sh: _Shading, obj: jax.Array, nrm: jax.Array, view: jax.Array
              ) -> tuple[jax.Array, jax.Array | None]:
    """View-dependent radiance of object ``obj`` (K,) at normals ``nrm`` towards ``view``
    (K, 3): the gloss β (A(cosθr) L_σ(R) + Σ_sources F D G/(4cosθr) Φ) (K, r) in the r channels
    of ``env.spectral_basis``, and the mirror χ F(θr) L(R) (K, C) (None when every χ is a
    concrete 0).

    The gloss is the split-sum reading of eq. (5)'s gloss term: the lobe's directional albedo A
    (tabulated per object) times the environment prefiltered to the lobe's width
    σ = √2 μ √cosθr around the mirror direction R (within ±20 % of the full quadrature of
    :func:`~spectral_fit.lighting.gloss_integral` at grazing angles, a few % near the
    normal; unbiased on average), so that a neighbour's gloss can be evaluated towards every
    receiver point instead of towards one."""
    mats = sh.mats
    o = jnp.maximum(obj, 0)
    beta, chi, mu, eta = mats["beta"][o], mats["chi"][o], mats["mu"][o], mats["n"][o]
    nv = dot3(nrm, view)
    nvc = jnp.clip(nv, 0.0, 1.0)
    refl = 2.0 * nv[:, None] * nrm - view
    albedo = _albedo_at(sh.albedo, obj, nv)
    sigma = math.sqrt(2.0) * mu * jnp.sqrt(jnp.maximum(nvc, 0.05))
    gloss = albedo[:, None] * _env_blur(sh.env, refl, sigma)
    src = _source_terms(sh.env)
    if src is not None:
        sdir, sflux = src
        for k, m in enumerate(sh.materials):
            w = _gloss_weights(nrm[:, None], view[:, None], sdir[None], mu[:, None],
                               eta[:, None], m.distribution, m.geometry)
            gloss = gloss + jnp.where((o == k)[:, None], w @ sflux, 0.0)
    # faded out over the last few degrees above the horizon (continuous in N and V, so the
    # neighbour's silhouette does not switch it on and off)
    fade = smootherstep(nv / _HORIZON_FADE)
    out = (beta * fade)[:, None] * gloss
    mirror = None
    if sh.mirror:
        mirror = (chi * fresnel_dielectric(nvc, eta) * fade)[:, None] * fast_lookup(sh.env,
                                                                                 refl)
    return out, mirror


def _is_zero(x: Any) -> bool:
    """True only for a concrete zero (a traced value may be anything)."""
    try:
        return bool(np.all(np.asarray(x) == 0.0))
    except (TypeError, jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return False


#: cosθr below which a neighbour's view-dependent radiance fades to 0 at its horizon
_HORIZON_FADE = 0.05

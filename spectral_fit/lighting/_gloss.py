"""Gloss under an environment map by quadrature: :func:`gloss_integral`, the gloss term of eq. 5
per unit β, ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω (C,) for world unit normal and view (3,).

It is split as A · ⟨L⟩: the lobe's directional albedo A (``_lobe``) times the lobe's mean
radiance ⟨L⟩, by a quadrature of the narrowed lobe on the prefiltered map (:func:`_lobe_mean`)
or, for wide lobes, by the direct texel sum (:func:`_texel_mean`); the bright sources taken out
of the map are summed exactly (:func:`_source_gloss`). Qualities ``"exact"`` (fitting,
validation) and ``"render"`` (frames), settings :class:`GlossQuadrature`.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from .._runtime.errors import InputError
from ._environment import QUALITIES, EnvironmentMap, _lookup_blend, _to_map, levels_for
from ._equirect import direction_to_uv, texel_directions, texel_solid_angles
from ._fastmath import smootherstep
from ._lobe import (
    _albedo_table,
    _grid_nodes,
    _interp_table,
    _narrowed_nodes,
    lobe_albedo,
    lobe_factor,
    visible_nodes,
)
from ._reflectance import beckmann_d, fresnel_dielectric, gaussian_d, smith_g, vcavity_g

__all__ = [
    "gloss_integral",
]


def gloss_integral(
    env: EnvironmentMap,
    normal: Any,
    view: Any,
    mu: Any,
    n: Any,
    *,
    distribution: str = "gaussian",
    geometry: str = "vcavity",
    fresnel: bool = True,
    quality: str = "exact",
) -> jax.Array:
    """Gloss radiance per unit β (C,): ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω (the gloss
    term of eq. 5).

    Method. With dω_L = 4 (V·H) dω_H the integral is ∫ D(H) g(H) L(l(H)) dω_H,
    g = F G (V·H)/(N·V), over the half vectors whose reflection l(H) is above the surface. It is
    split as A · ⟨L⟩:

    - A = ∫ D g dω_H, the lobe's directional albedo, by a fine scalar quadrature
      (``albedo_radial`` × ``albedo_azimuthal`` nodes; no map lookups). ``"render"``
      interpolates it from a per-material table in cosθr (:func:`_albedo_table`).
    - ⟨L⟩ = ∫ D' g L_σ / ∫ D' g, the g-weighted mean radiance over the lobe, by a quadrature on
      the visible part of the lobe (:func:`visible_nodes`) of a prefiltered copy L_σ of the
      map (exact spherical Gaussian, std σ = r·√2·μ·cosθr in reflected directions, two adjacent
      levels blended smoothly in log σ) with the lobe D' narrowed so that narrowed lobe ⊛
      prefilter has the true lobe's width; near the surface's horizon each node's σ is cut to
      ``horizon_ratio`` × its elevation.
    - ``"exact"``, wide lobes: ⟨L⟩ = Σ w_t L_t / Σ w_t, the direct sum over the unfiltered
      (bilinear) map sampled at the centres of a 2× finer grid, w_t = F D G/(4 cosθr) Δω_t
      (:func:`_texel_mean`; four integrand evaluations per texel, no lookups; 1× — each
      texel a box — was up to 3 % off for μ = 0.2 at θr = 80°, where the lobe is two texels
      across). The narrowing above is exact only for
      a Gaussian lobe in a flat tangent plane; for wide lobes g, the horizon and the sphere's
      curvature change the lobe on the scale of σ and the prefiltered quadrature is biased
      (∝ σ²: 3–9 % at μ = 0.5 with r = 0.3, up to 26 % on the room map), while the texel
      sum's error (the integrand's variation inside one texel) falls as the lobe widens.
      From μ = ``texel_sum_from`` (0.12) to ``texel_sum_full`` (0.18) the two are blended
      with a C² weight in μ; only the branches a given μ needs run (``jax.lax.cond``).
    - ``"exact"``, narrow lobes: the nodes are a Cartesian grid in the half-vector tangent
      plane (:func:`_grid_nodes`, 128 along the plane of incidence × 36 across, r = 0.1),
      dense along the plane of incidence so that at grazing views, where the prefilter must
      be as narrow as the lobe is across (∝ cosθr), the map is still sampled finely; the
      across-narrowing uses each column's own V·H. (The polar rule of
      :func:`visible_nodes`, kept for ``"render"``, aliased there: up to 6.8 % at θr = 75°.)
      The prefilter is kept small (r = 0.1): narrowing the lobe restores its variance, not
      its exact shape (the reflected lobe is not the flat Gaussian the narrowing assumes,
      and two blended levels are a mix of two Gaussians), and an edge of high contrast in
      the lobe's tail weighs that difference: on the room map at μ = 0.07, θr = 45° (the
      dim bands next to the window) a 512 × 256 grid gives 0.1 % at r = 0.05, 0.5 % at
      0.1, 1.0–1.2 % at 0.15–0.3. r = 0.1 needs the 36 columns against aliasing (24: 1.5 %).
    - Bright sources taken out of the map (:func:`_extract_sources`) are added exactly
      at sub-points: in ``"exact"`` by a product Gauss rule (8 × 8 points) over each source
      texel's footprint in the bilinear map (:func:`_tent_gauss_subpoints`), in the map's
      own channels; in ``"render"`` its ``source_subpoints`` in the compressed channels.

    The nodes move smoothly with μ, n, N, V and the texel weights are smooth functions of them,
    so the result is smooth in μ and n (no tables in μ or n; the level blend and the method
    blend are C²; the bilinear lookups make it piecewise smooth, with slope jumps of ~1/M of
    the lobe where one of the M nodes crosses a texel line). ``quality`` picks the node
    counts and r: ``"exact"`` (128 × 36 grid, r = 0.1, texel sum for wide lobes) or
    ``"render"`` (8 × 16 polar nodes, r = 0.3; see
    docs/lighting.md for the measured accuracy of each). Zero if N·V <= 0.

    Args:
        normal, view: world unit vectors (3,).
        mu: Gaussian width μ (radians) or Beckmann slope m, > 0.
        n: refractive index > 1.
        geometry: "vcavity", "smith" or "none" (G = 1, for furnace tests).
        fresnel: False sets F = 1 (furnace tests).
        quality: "exact" or "render" (static).
    """
    if quality not in QUALITIES:
        raise InputError(f"unknown quality {quality!r}; choose one of {QUALITIES}",
                         field="quality")
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    dtype = env.atlas.dtype
    N = N.astype(dtype)
    V = V.astype(dtype)
    mu = jnp.asarray(mu, dtype)
    n = jnp.asarray(n, dtype)
    quad = env.quadrature
    kw = dict(geometry=geometry, fresnel=fresnel)
    nv_raw = jnp.dot(N, V)
    nv = jnp.clip(nv_raw, 0.0, 1.0)
    # A: directional albedo of the lobe (true width)
    akw = dict(distribution=distribution, radial=quad.albedo_radial,
               azimuthal=quad.albedo_azimuthal, **kw)
    if quality == "render":
        albedo = _interp_table(_albedo_table(mu, n, quad.albedo_table, **akw), nv)
        radial, azimuthal, ratio = (quad.render_radial, quad.render_azimuthal,
                                    quad.render_prefilter_ratio)
    else:
        albedo = lobe_albedo(nv_raw, mu, n, mu, **akw)
        radial, azimuthal, ratio = quad.radial, quad.azimuthal, quad.prefilter_ratio
    mean_kw = dict(distribution=distribution, **kw)
    if quality == "render":
        rule = "visible" if quad.nodes == "grid" else quad.nodes
        mean = _lobe_mean(env, N, V, mu, n, nv, radial=radial, azimuthal=azimuthal,
                          ratio=ratio, node_rule=rule, **mean_kw)
    else:
        # wide lobes: the texel sum; narrow ones: the lobe quadrature; C² blend in between.
        # Only the branches needed for this μ run (both, if μ is batched under vmap).
        a, b = quad.texel_sum_from, quad.texel_sum_full

        def lobe() -> jax.Array:
            return _lobe_mean(env, N, V, mu, n, nv, radial=radial, azimuthal=azimuthal,
                              ratio=ratio, **mean_kw)

        def texels() -> jax.Array:
            return _texel_mean(env, N, V, mu, n, **mean_kw)

        def blend() -> jax.Array:
            t = smootherstep((mu - a) / (b - a))
            return (1.0 - t) * lobe() + t * texels()

        if isinstance(mu, jax.core.Tracer):
            mean = jax.lax.cond(mu <= a, lobe, lambda: jax.lax.cond(mu >= b, texels, blend))
        else:  # a concrete μ (eager calls): choose here, so nothing is traced per call
            mu_c = float(mu)
            mean = lobe() if mu_c <= a else texels() if mu_c >= b else blend()
    out = albedo * mean
    tent = "exact" if quality == "exact" else "render"
    full = env.source_flux_full is not None and (
        env.source_fine_dirs if tent == "exact" else env.source_render_dirs) is not None
    if env.source_flux.shape[0] and not full:
        out = out + _source_gloss(env, N, V, mu, n, distribution=distribution, **kw)
    spec = out @ env.spectral_basis
    if env.source_flux.shape[0] and full:
        # in the map's own channels: the principal-spectra compression bounds the error per
        # texel over all channels, not per band (up to 0.4 % in the dim bands of a lamp)
        spec = spec + _source_gloss(env, N, V, mu, n, distribution=distribution, tent=tent,
                                    **kw)
    return jnp.where(nv_raw > 0.0, spec, 0.0)


def _lobe_mean(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
               nv: jax.Array, *, radial: int, azimuthal: int, ratio: float, distribution: str,
               geometry: str, fresnel: bool, node_rule: str | None = None) -> jax.Array:
    """⟨L⟩ (r,): the g-weighted mean of the prefiltered residual map over the narrowed lobe
    (:func:`visible_nodes`), zero where the lobe has no weight."""
    quad = env.quadrature
    sigma = ratio * math.sqrt(2.0) * mu * jnp.maximum(nv, 0.05)
    _, _, _, var = levels_for(env, sigma)
    rule = node_rule or quad.nodes
    if rule == "grid":
        Hb, wb, chb = _grid_nodes(N, V, mu, var, nv, distribution=distribution,
                                  along=quad.grid_along, across=quad.grid_across,
                                  extent=quad.grid_extent)
    else:
        nodes = visible_nodes if rule == "visible" else _narrowed_nodes
        Hb, wb, chb = nodes(N, V, mu, var, nv, distribution=distribution,
                            radial=radial, azimuthal=azimuthal)
    gb, L = lobe_factor(N, V, Hb, chb, mu, n, geometry=geometry, fresnel=fresnel)
    f = wb * gb
    # near the surface's horizon the prefilter would blur in light from behind the surface:
    # there each node's prefilter std is cut to a fraction of its elevation above the horizon
    elev = jnp.maximum(L @ N, 0.0)
    lo, hi, w_hi, _ = levels_for(env, jnp.minimum(sigma, quad.horizon_ratio * elev))
    u, v = direction_to_uv(_to_map(env, L))
    radiance = _lookup_blend(env, u, v, lo, hi, w_hi)  # (M, r)
    total = jnp.sum(f)
    return (f @ radiance) / jnp.where(total > 0.0, total, 1.0)


def _texel_mean(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
                *, distribution: str, geometry: str, fresnel: bool) -> jax.Array:
    """⟨L⟩ (r,) by the direct texel sum over the unfiltered residual map as the bilinear
    lookup defines it, sampled at the texel centres of an s× finer grid (``fine_texels``,
    s = ``texel_sum_supersample``; s = 1: level 0 of the atlas, each texel a box):
    Σ w_t L_t / Σ w_t with w_t = F D G /(4 cosθr) Δω_t at the fine centres. Its error is the
    variation of the integrand inside one fine texel, so it is accurate for lobes a few
    texels wide (μ >~ 0.12 on a 128-row map at s = 2, up to θr = 80°); it costs s² integrand
    evaluations per texel and no lookups."""
    h, w = env.level_shapes[0]
    dtype = env.atlas.dtype
    ss = env.quadrature.texel_sum_supersample
    values = env.atlas[: h * w] if env.fine_texels is None else env.fine_texels
    if env.fine_texels is None:
        ss = 1
    dirs = jnp.asarray(texel_directions(h * ss, w * ss).reshape(-1, 3), dtype)
    sa = jnp.asarray(texel_solid_angles(h * ss, w * ss).reshape(-1), dtype)
    # work in the map frame: rotate N and V instead of every texel direction
    wgt = _integrand(dirs, _to_map(env, N), _to_map(env, V), mu, n, distribution=distribution,
                     geometry=geometry, fresnel=fresnel) * sa
    total = jnp.sum(wgt)
    return (wgt @ values) / jnp.where(total > 0.0, total, 1.0)


def _integrand(d: jax.Array, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array, *,
               distribution: str, geometry: str, fresnel: bool) -> jax.Array:
    """F D G / (4 cosθr) (M,) for light directions d (M, 3) (the gloss integrand per unit
    radiance and solid angle), zero where N·L <= 0 or N·V <= 0."""
    nv = jnp.dot(N, V)
    nl = d @ N
    Hs = d + V
    Hs = Hs / jnp.sqrt(jnp.maximum(jnp.sum(Hs * Hs, axis=-1, keepdims=True), 1e-30))
    nh = Hs @ N
    vh = Hs @ V
    if distribution == "gaussian":
        D = gaussian_d(nh, mu)
    else:
        D = beckmann_d(nh, mu)
    if geometry == "vcavity":
        G = vcavity_g(nh, nv, nl, vh)
    elif geometry == "smith":
        G = smith_g(nv, nl, vh, vh, mu)
    else:
        G = jnp.where((vh > 0.0) & (nl > 0.0), 1.0, 0.0)
    F = fresnel_dielectric(vh, n) if fresnel else 1.0
    ok = (nl > 0.0) & (nv > 0.0)
    return jnp.where(ok, F * D * G / (4.0 * jnp.where(nv > 0.0, nv, 1.0)), 0.0)


def _source_gloss(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
                  *, distribution: str, geometry: str, fresnel: bool, tent: str | None = None
                  ) -> jax.Array:
    """Σ over source sub-points of F D G / (4 cosθr) · excess flux (the exact integrand), in
    the r compressed channels (``source_subpoints`` points inside each source texel), or with
    ``tent`` in the map's C channels: the product Gauss rule over each source texel's
    footprint in the bilinear map (:func:`_tent_gauss_subpoints`, ``source_flux_full``);
    lobes narrower than a few texels (small μ, grazing views) need the footprint.
    ``tent`` = "exact": (2·tent_gauss)² points per source texel; "render": 2 × 2."""
    if tent:
        dirs, pw = ((env.source_fine_dirs, env.source_fine_weights) if tent == "exact"
                    else (env.source_render_dirs, env.source_render_weights))
        d = dirs.reshape(-1, 3) @ env.rotation.T  # world directions (S·P, 3)
        wgt = _integrand(d, N, V, mu, n, distribution=distribution, geometry=geometry,
                         fresnel=fresnel).reshape(dirs.shape[:2])
        return jnp.sum(wgt * pw, axis=1) @ env.source_flux_full
    dirs = env.source_dirs
    d = dirs.reshape(-1, 3) @ env.rotation.T  # world directions (S·k, 3)
    flux = jnp.repeat(env.source_flux, dirs.shape[1], axis=0)
    wgt = _integrand(d, N, V, mu, n, distribution=distribution, geometry=geometry,
                     fresnel=fresnel)
    return wgt @ flux

"""Split-sum gloss for frames: :func:`gloss_split_sum`, the gloss integral of
:func:`gloss_integral` approximated as the lobe's directional albedo times a few lookups of
finely spaced prefiltered levels (:class:`SplitSumMap`) along the lobe, the lobe's albedo,
off-specular shift and angular variances (radians²) per material from a table in cosθr
(:func:`lobe_moment_table`); settings :class:`SplitSum`. Batched over points (..., 3) and
written elementwise for XLA:CPU; radiance (..., C) in the map's channels.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import materialise as _materialise
from .._runtime.backend import materialise_each
from .._runtime.errors import InputError
from ._environment import EnvironmentMap
from ._equirect import bilinear_taps, taps_sum, uv_of
from ._fastmath import atan2_poly, sincos_poly, smootherstep
from ._gloss import _source_gloss
from ._lobe import _lobe_grid
from ._prefilter import _downsample2, _sphere_blur_many, level_atlas
from ._sources import _extract_sources

__all__ = [
    "SplitSum",
    "SplitSumMap",
    "lobe_moment_table",
    "gloss_split_sum",
    "split_sum_albedo",
    "split_sum_moments",
]


def _along_rule(k: int) -> tuple[np.ndarray, np.ndarray]:
    """k binomial nodes (positions in standard deviations, weights): C(k−1, j)/2^(k−1) at
    (j − (k−1)/2)·2/√(k−1), unit variance (a discrete Gaussian)."""
    j = np.arange(k)
    w = np.array([math.comb(k - 1, int(i)) for i in j], np.float64) / 2.0 ** (k - 1)
    x = (j - 0.5 * (k - 1)) * (2.0 / math.sqrt(k - 1) if k > 1 else 0.0)
    return x, w


#: parity in x = √(1 − cosθr) of the columns of :func:`lobe_moment_table` (A, δ, var_t, var_b)
_MOMENT_PARITY = (1.0, -1.0, 1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class SplitSum:
    """Settings of the split-sum gloss :func:`gloss_split_sum` (static).

    Attributes:
        table: entries of the per-material moment table in x = √(1 − cosθr) (Catmull–Rom).
        radial, azimuthal: Gauss–Legendre nodes of the scalar moment quadrature (rings ×
            half visible arc, as :func:`lobe_albedo`); no map lookups.
        along: lookups (1–8) along the lobe's long axis (the plane of incidence), binomial
            weights, for its spread beyond the isotropic prefilter of each lookup.
        min_ratio: each lookup's prefilter std is at least this fraction of the lobe's long
            axis std (at grazing views the lobe is narrow across the plane of incidence;
            a wider prefilter keeps the sum of ``along`` lookups smooth along it).
        horizon_ratio: each lookup's prefilter std is at most this fraction of its elevation
            above the surface's horizon.
        per_octave: prefiltered levels per octave of std (:class:`SplitSumMap`).
    """

    table: int = 32
    radial: int = 16
    azimuthal: int = 16
    along: int = 4
    min_ratio: float = 0.5
    horizon_ratio: float = 0.5
    per_octave: int = 4


def _lobe_moments(
    nv: jax.Array, mu: jax.Array, n: jax.Array, *, distribution: str, geometry: str,
    fresnel: bool, radial: int, azimuthal: int,
) -> jax.Array:
    """(A, δ, var_t, var_b) of the gloss lobe in reflected directions at cosθr = ``nv``.

    With weights D F G (V·H)/(N·V) dω_H over the half vectors that reflect V above the surface
    (the integrand of :func:`gloss_integral` without the radiance): A = ∫ weight (the
    directional albedo); the weighted mean reflected direction m lies in the plane of
    incidence at polar angle θr + δ (δ > 0: away from the normal, the off-specular shift);
    var_t and var_b are the weighted means of the squared components of the reflected
    direction across m within the plane of incidence and perpendicular to it (the lobe's
    angular variances, long and short axis). Same nodes as :func:`lobe_albedo`; scalars only.
    """
    g, vh, nl, _, sin_h, sin_r, phi = _lobe_grid(
        nv, mu, mu, n, distribution=distribution, geometry=geometry, fresnel=fresnel,
        radial=radial, azimuthal=azimuthal)
    nv = jnp.clip(nv, 0.0, 1.0)
    sphi, cphi = sincos_poly(phi)
    # reflected direction L = 2 (V·H) H − V in the frame (T, B, N), V = (sinθr, 0, cosθr)
    lt = 2.0 * vh * sin_h[:, None] * cphi - sin_r
    lb = 2.0 * vh * sin_h[:, None] * sphi
    a = jnp.sum(g)
    a_safe = jnp.where(a > 0.0, a, 1.0)
    mt = jnp.sum(g * lt) / a_safe
    mn = jnp.sum(g * nl) / a_safe
    theta_m = atan2_poly(-mt, mn)
    delta = theta_m - jnp.arccos(nv)
    # coordinates of L in the tangent plane at m (azimuthal equidistant: angle γ from m),
    # e1 = (cosθm, 0, sinθm) in the plane of incidence, e2 = B across it
    sm, cm = sincos_poly(theta_m)
    l1 = lt * cm + nl * sm
    lm = jnp.clip(nl * cm - lt * sm, -1.0, 1.0)  # cos γ
    sin_g = jnp.sqrt(jnp.maximum(l1 * l1 + lb * lb, 1e-30))
    # (atan2_poly: XLA:CPU's atan2 is a scalar call, a large share of the tables' cost;
    # results within 1.2e-7 of it)
    scale = atan2_poly(sin_g, lm) / sin_g  # γ / sin γ
    var_t = jnp.sum(g * (l1 * scale) ** 2) / a_safe
    var_b = jnp.sum(g * (lb * scale) ** 2) / a_safe
    return jnp.stack([a, delta, var_t, var_b])


def lobe_moment_table(mu: Any, n: Any, *, distribution: str = "gaussian",
                      geometry: str = "vcavity", fresnel: bool = True,
                      settings: SplitSum | None = None) -> jax.Array:
    """Moments (size, 4) of the gloss lobe, columns (A, δ, var_t, var_b) of
    :func:`_lobe_moments`, at cosθr = 1 − x², x = j/(size − 1) (the last at cosθr = 1e-3).

    One table per material and frame (it depends on μ and n only, not on the point: under
    ``jax.vmap`` over points it is computed once); smooth and differentiable in μ and n.
    """
    s = settings or SplitSum()
    x = np.linspace(0.0, 1.0, s.table)
    c = np.maximum(1.0 - x * x, 1e-3)
    mu = jnp.asarray(mu)
    dtype = jnp.result_type(mu, jnp.float32)
    mu = mu.astype(dtype)
    n = jnp.asarray(n, dtype)
    return jax.vmap(lambda cc: _lobe_moments(
        cc, mu, n, distribution=distribution, geometry=geometry, fresnel=fresnel,
        radial=s.radial, azimuthal=s.azimuthal))(jnp.asarray(c, dtype))


def split_sum_albedo(table: jax.Array, nv: jax.Array) -> jax.Array:
    """The gloss lobe's directional albedo A(θr) (...,) at cosθr = ``nv`` (...,) from a
    :func:`lobe_moment_table` (size, 4): the gloss per unit β under a uniform sky of radiance 1,
    as :func:`gloss_split_sum` uses it."""
    return split_sum_moments(table, nv)[..., 0]


def split_sum_moments(table: jax.Array, nv: jax.Array) -> jax.Array:
    """The gloss lobe's moments (..., 4) (A, δ, var_t, var_b) at cosθr = ``nv`` (...,) from a
    :func:`lobe_moment_table` (size, 4): albedo, off-specular shift (rad, away from the
    normal) and angular variances along and across the plane of incidence (rad²), as
    :func:`gloss_split_sum` uses them."""
    return _interp_moments(jnp.asarray(table), jnp.clip(jnp.asarray(nv), 0.0, 1.0))


def _interp_moments(table: jax.Array, nv: jax.Array) -> jax.Array:
    """Catmull–Rom interpolation (C¹) of the columns of :func:`lobe_moment_table` at
    cosθr = ``nv``, continued through x = 0 as even (A, variances) or odd (δ) functions."""
    size = table.shape[0]
    x = jnp.sqrt(jnp.clip(1.0 - nv, 0.0, 1.0)) * (size - 1)
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    t = (x - i.astype(x.dtype))[..., None]
    parity = jnp.asarray(_MOMENT_PARITY, table.dtype)
    p0 = table[jnp.abs(i - 1)] * jnp.where((i >= 1)[..., None], 1.0, parity)
    p1 = table[i]
    p2 = table[i + 1]
    p3 = table[jnp.minimum(i + 2, size - 1)]
    return p1 + 0.5 * t * (p2 - p0 + t * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
                                          + t * (3.0 * (p1 - p2) + p3 - p0)))


class SplitSumMap(eqx.Module):
    """Finely spaced prefiltered levels of an environment's residual map (bright sources
    removed, as in :class:`EnvironmentMap`) for :func:`gloss_split_sum`: level 0 the map,
    level k >= 1 an exact spherical Gaussian blur of std σ_k = (π/H)·2^((k−1)/p), p levels per
    octave, stored at the coarsest halving of the map with texels <= σ_k/2. A prefilter of any
    std between two levels is their blend (matched variance), whose shape error against one
    Gaussian falls with p (a point source's peak: +23 % at p = 1, +3 % at p = 4).

    Attributes:
        atlas: (T, r) all levels flattened, each followed by its two pole means, in the
            channels of the environment's ``spectral_basis``.
        level_table: (M, 3) int32 (offset, H_k, W_k) per level.
        level_sigma: (M,) std per level (radians), level 0 = 0.
        per_octave: static p.
    """

    atlas: jax.Array
    level_table: jax.Array
    level_sigma: jax.Array
    per_octave: int = eqx.field(static=True, default=4)

    @classmethod
    def from_environment(cls, env: EnvironmentMap, texels: Any = None, *,
                         per_octave: int = 4) -> SplitSumMap:
        """Build the levels (NumPy, at preparation) from ``texels`` (H, W, C), default
        ``env.texels`` (pass the float64 map when at hand)."""
        if not (isinstance(per_octave, int) and 1 <= per_octave <= 16):
            raise InputError(f"must be an int in 1..16, got {per_octave!r}",
                             field="per_octave")
        img = np.asarray(env.texels if texels is None else texels, np.float64)
        quad = env.quadrature
        residual, _, _ = _extract_sources(img, quad.max_sources, quad.source_threshold,
                                          quad.source_subpoints)
        basis = np.asarray(env.spectral_basis, np.float64)
        residual = residual @ basis.T  # blurring is linear: work in the r principal spectra
        h0 = residual.shape[0]
        delta = math.pi / h0
        count = int(math.ceil(per_octave * math.log2(0.5 * math.pi / delta))) + 1
        sigmas = [0.0] + [delta * 2.0 ** (k / per_octave) for k in range(count)]
        pyramid = [(residual, 0.0)]  # halvings and the variance each adds
        cur, var = residual, 0.0
        while cur.shape[0] % 2 == 0 and cur.shape[1] % 2 == 0 and cur.shape[0] >= 8:
            d_new = 2.0 * math.pi / cur.shape[0]
            cur = _downsample2(cur)
            var += d_new**2 / 16.0
            pyramid.append((cur, var))
        # each level from the coarsest halving with texels <= σ/2, blurred by the rest of the
        # variance; the levels sharing a halving share its kernel geometry and FFT
        jobs: dict[int, list[tuple[int, float]]] = {}
        for k, sigma in enumerate(sigmas[1:], start=1):
            b = 0
            for i, (cand, cvar) in enumerate(pyramid[1:], start=1):
                if math.pi / cand.shape[0] <= sigma / 2.0 + 1e-12 and cvar <= sigma**2:
                    b = i
            jobs.setdefault(b, []).append((k, math.sqrt(max(sigma**2 - pyramid[b][1], 0.0))))
        levels = {0: residual}
        for b, todo in jobs.items():
            blurred = _sphere_blur_many(pyramid[b][0], [sg for _, sg in todo])
            levels.update({k: lev for (k, _), lev in zip(todo, blurred, strict=True)})
        atlas, shapes, offsets = level_atlas([levels[k] for k in range(len(sigmas))])
        table = [(off, h, w) for off, (h, w) in zip(offsets, shapes, strict=True)]
        dtype = env.atlas.dtype
        return cls(atlas=jnp.asarray(atlas, dtype),
                   level_table=jnp.asarray(np.asarray(table, np.int32)),
                   level_sigma=jnp.asarray(sigmas, dtype), per_octave=per_octave)


def _split_levels(pre: SplitSumMap, sigma: jax.Array
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Adjacent levels (lo, hi) of ``pre`` around std ``sigma`` and the weight of hi: the
    variance-matching weight (σ² − σ_lo²)/(σ_hi² − σ_lo²) through a quintic smoothstep (C²
    in σ; below level 1, a smoothstep in σ/σ_1 from the unfiltered map)."""
    sig = pre.level_sigma
    m = sig.shape[0]
    s1 = sig[1]
    t = jnp.log2(jnp.maximum(sigma, 1e-30) / s1) * pre.per_octave
    below = t < 0.0
    k = jnp.clip(jnp.floor(t), 0, m - 3).astype(jnp.int32)
    lo = jnp.where(below, 0, k + 1)
    hi = jnp.where(below, 1, k + 2)
    slo, shi = sig[lo], sig[hi]
    frac = (sigma * sigma - slo * slo) / (shi * shi - slo * slo)
    w = jnp.where(below, smootherstep(sigma / s1), smootherstep(frac))
    return lo, hi, w


def _split_lookup(pre: SplitSumMap, u: jax.Array, v: jax.Array, lo: jax.Array,
                  hi: jax.Array, w_hi: jax.Array) -> jax.Array:
    """(1 − w_hi)·level lo + w_hi·level hi of ``pre`` at map coordinates (u, v), bilinear,
    all eight taps gathered at once; every argument (...) → (..., r)."""
    plo = pre.level_table[lo]  # (..., 3): offset, H_k, W_k
    phi = pre.level_table[hi]
    i0, w0 = bilinear_taps(u, v, plo[..., 0], plo[..., 1], plo[..., 2], lead=True)
    i1, w1 = bilinear_taps(u, v, phi[..., 0], phi[..., 1], phi[..., 2], lead=True)
    idx = jnp.concatenate([i0, i1], axis=0)
    w = jnp.concatenate([w0 * (1.0 - w_hi), w1 * w_hi], axis=0)
    return taps_sum(pre.atlas, idx, w, lead=True)


def gloss_split_sum(
    env: EnvironmentMap,
    pre: SplitSumMap,
    table: jax.Array,
    normal: Any,
    view: Any,
    mu: Any,
    n: Any,
    *,
    distribution: str = "gaussian",
    geometry: str = "vcavity",
    fresnel: bool = True,
    settings: SplitSum | None = None,
) -> jax.Array:
    """Gloss radiance per unit β (..., C), the same integral as :func:`gloss_integral`
    (the gloss term of eq. 5), by a pre-integrated ("split-sum") approximation:

        gloss ≈ A(θr) · Σ_k w_k L_σ(d_k) + Σ_sources (exact),

    A the lobe's directional albedo and the lobe's shape in reflected directions from
    ``table`` (:func:`lobe_moment_table` of the material, interpolated in cosθr): its mean
    direction (the mirror direction shifted by δ away from the normal, the off-specular peak)
    and its angular variances along (var_t) and across (var_b) the plane of incidence.
    L_σ is the prefiltered residual map ``pre`` (:class:`SplitSumMap`, two levels blended)
    with σ² = max(var_b, (min_ratio)² var_t); the ``settings.along`` lookups d_k lie on the
    great circle through the mean direction in the plane of incidence, binomial weights, spread
    so that the total variance along is var_t. Each lookup's σ is capped at
    ``horizon_ratio`` × its elevation above the surface's horizon. The bright source texels of
    ``env`` (see :class:`GlossQuadrature`) are summed exactly as in :func:`gloss_integral`.
    Zero if N·V <= 0. Smooth in μ and n (the table's nodes move smoothly with them; the level
    blend is C² in σ). Accuracy vs :func:`gloss_integral` and brute force: docs/rendering.md.

    Batched: ``normal`` and ``view`` may have any leading shape (..., 3) (also under
    ``jax.vmap``); the code is elementwise over it, with the lookups unrolled, because XLA:CPU
    runs small dots and short reductions as slow loops.

    Args:
        env: the environment (rotation, spectral basis, sources).
        pre: its :class:`SplitSumMap`.
        table: (size, 4) from :func:`lobe_moment_table` for this μ, n, D, G.
        normal, view: world unit vectors (..., 3).
        mu, n: the material's μ and n (scalars; for the exact source sum).
        settings: :class:`SplitSum` (static).
    """
    s = settings or SplitSum()
    if not (isinstance(s.along, int) and 1 <= s.along <= 8):
        raise InputError(f"must be an int in 1..8, got {s.along!r}", field="along")
    dtype = pre.atlas.dtype
    N = jnp.asarray(normal).astype(dtype)
    V = jnp.asarray(view).astype(dtype)
    table = jnp.asarray(table, dtype)
    n3 = [N[..., i] for i in range(3)]
    v3 = [V[..., i] for i in range(3)]
    nv_raw = n3[0] * v3[0] + n3[1] * v3[1] + n3[2] * v3[2]
    nv = jnp.clip(nv_raw, 0.0, 1.0)
    mom = _interp_moments(table, nv)
    albedo, delta, var_t, var_b = (mom[..., j] for j in range(4))
    # tangent T along V's projection (Duff's frame when V ∥ N)
    p = [v3[i] - nv_raw * n3[i] for i in range(3)]
    p2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    ok = p2 > 1e-12
    sign = jnp.where(n3[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n3[2])
    t0 = [1.0 + sign * n3[0] * n3[0] * a, sign * n3[0] * n3[1] * a, -sign * n3[0]]
    inv_p = jax.lax.rsqrt(jnp.where(ok, p2, 1.0))
    T = [jnp.where(ok, p[i] * inv_p, t0[i]) for i in range(3)]
    sr = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    sd, cd = sincos_poly(delta)
    # each materialised block below is computed once per point (or per lookup); without the
    # barriers XLA fuses it into, and recomputes it in, each of its consumers
    albedo, var_t, var_b, cd, sd, sr, nv, *T = materialise_each(
        albedo, var_t, var_b, cd, sd, sr, nv, *T)
    # mirror direction R = nv N − sr T; P = ∂R/∂θr = −sr N − nv T (away from the normal);
    # mean direction d = cosδ R + sinδ P; e1 = cosδ P − sinδ R
    R = [nv * n3[i] - sr * T[i] for i in range(3)]
    P = [-sr * n3[i] - nv * T[i] for i in range(3)]
    d = [cd * R[i] + sd * P[i] for i in range(3)]
    e1 = [cd * P[i] - sd * R[i] for i in range(3)]
    # prefilter of each lookup: the lobe's variance across, at least (min_ratio σ_t)²; the
    # rest of the variance along comes from the spread of the lookups
    var_t = jnp.maximum(var_t, 1e-12)
    var_n = jnp.maximum(jnp.maximum(var_b, (s.min_ratio * s.min_ratio) * var_t), 1e-12)
    spread = jnp.sqrt(jnp.maximum(var_t - var_n, 1e-12))
    # a spherical Gaussian exp(−γ²/2σ²) has the angular variance σ²(1 − σ²/3) per axis
    sigma0 = jnp.sqrt(var_n * (1.0 + var_n / 3.0))
    offs, wts = _along_rule(s.along)
    rot = env.rotation
    # materialise the per-point quantities once: XLA would otherwise fuse (and recompute)
    # them into every lookup's index arithmetic
    packed = materialise_each(*d, *e1, *n3, spread, sigma0)
    d, e1, n3 = packed[0:3], packed[3:6], packed[6:9]
    spread, sigma0 = packed[9], packed[10]
    ang = jnp.asarray(offs, dtype) * spread[..., None]  # (..., k)
    sa, ca = materialise_each(*sincos_poly(ang))
    dk = [ca * d[i][..., None] + sa * e1[i][..., None] for i in range(3)]  # (..., k) each
    elev = jnp.maximum(dk[0] * n3[0][..., None] + dk[1] * n3[1][..., None]
                       + dk[2] * n3[2][..., None], 0.0)
    sigma = jnp.minimum(sigma0[..., None], s.horizon_ratio * elev)
    *dm, sigma = materialise_each(*(dk[0] * rot[0, j] + dk[1] * rot[1, j] + dk[2] * rot[2, j]
                                    for j in range(3)), sigma)
    lo, hi, w_hi = _split_levels(pre, sigma)
    u, v = uv_of(*dm)
    shape = u.shape
    u, v, w_hi, lo, hi = materialise_each(u, v, w_hi, lo.astype(dtype), hi.astype(dtype))
    lo, hi = lo.astype(jnp.int32), hi.astype(jnp.int32)
    rad = _split_lookup(pre, u.reshape(-1), v.reshape(-1), lo.reshape(-1), hi.reshape(-1),
                        w_hi.reshape(-1)).reshape(*shape, -1)  # (..., k, r)
    mean = float(wts[0]) * rad[..., 0, :]
    for j in range(1, s.along):
        mean = mean + float(wts[j]) * rad[..., j, :]
    out = albedo[..., None] * mean
    if env.source_flux.shape[0]:
        mu_ = jnp.asarray(mu, dtype)
        n_ = jnp.asarray(n, dtype)

        def one(nn: jax.Array, vv: jax.Array) -> jax.Array:
            return _source_gloss(env, nn, vv, mu_, n_, distribution=distribution,
                                 geometry=geometry, fresnel=fresnel)

        lead = N.shape[:-1]
        src = jax.vmap(one)(N.reshape(-1, 3), V.reshape(-1, 3))
        out = out + src.reshape(*lead, -1)
    # to the map's channels: the tap sums materialised once (XLA would otherwise fuse them
    # into each of the C outputs and recompute them C/r times), then a sum of r products
    # (a matrix product here went to a library call that cost more than the sum for C <= 8)
    basis = env.spectral_basis
    out = _materialise(out)
    if basis.shape[1] > 8:
        lead = out.shape[:-1]
        spec = (out.reshape(-1, out.shape[-1]) @ basis).reshape(*lead, -1)
    else:
        spec = out[..., 0:1] * basis[0]
        for i in range(1, basis.shape[0]):
            spec = spec + out[..., i:i + 1] * basis[i]
    return jnp.where((nv_raw > 0.0)[..., None], spec, 0.0)

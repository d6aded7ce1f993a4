"""The reflection model of plastic: Lambert + Torrance–Sparrow gloss + mirror.

Pure JAX functions of a :class:`Material` (an ``equinox.Module``); they jit, vmap (over pixels and
over materials) and differentiate in every parameter. Float32 by default; float64 when the caller
runs under ``jax.enable_x64``.

Angles (docs/conventions.md, 'Reflection model'): θi = ∠(N, L), θr = ∠(N, V), θh = ∠(N, H) (the
paper's φ), θd = ∠(L, H) = ∠(V, H) (the paper's θH), with H = (L + V)/|L + V|. All direction
arguments are unit 3-vectors pointing AWAY from the surface.

Physical reading of eq. (4) of Mochizuki & Tanaka, radiance leaving towards V under a
point/directional light of irradiance E(λ) (W·m⁻²·nm⁻¹ on a surface facing the light):

    C(λ) = α S(λ) E(λ) cosθi / π  +  β F(n, θd) D(μ, θh) G / (4 cosθr) · E(λ)

(the mirror term is a delta lobe; it vanishes for point lights). α = 1 is an ideal Lambertian of
albedo S, β = 1 is the physically normalised microfacet lobe. The paper's scaling is
α_paper = α/π and β_paper = β/4 (:func:`to_paper_params`, :func:`from_paper_params`).

Spectral representation: a material's ``reflectance`` is either S(λ) on the band grid (L,) or K
coefficients in a :class:`~spectral_fit.color.SpectralBasis`; F, D, G do not depend on λ.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError

__all__ = [
    "DISTRIBUTIONS",
    "GEOMETRIES",
    "fresnel_dielectric",
    "gaussian_normalisation",
    "gaussian_d",
    "beckmann_d",
    "microfacet_d",
    "vcavity_g",
    "smith_g1_beckmann",
    "smith_g",
    "microfacet_g",
    "Material",
    "make_material",
    "check_material",
    "gloss_brdf",
    "brdf",
    "shade_point_light",
    "to_paper_params",
    "from_paper_params",
    "microfacet_fdg",
]

DISTRIBUTIONS = ("gaussian", "beckmann")
GEOMETRIES = ("vcavity", "smith")


# --------------------------------------------------------------------------------------------
# Fresnel


def fresnel_dielectric(cos_theta: Any, n: Any) -> jax.Array:
    """Exact unpolarised Fresnel reflectance of a dielectric interface, F = (Rs + Rp)/2.

    Formula (Cook & Torrance 1982): with c = cosθ, g² = n² + c² − 1,

        F = ½ (g − c)²/(g + c)² · {1 + [c(g + c) − 1]² / [c(g − c) + 1]²}.

    Args:
        cos_theta: cosine of the angle of incidence (any shape); |cosθ| is used and clipped to
            [0, 1], so grazing (c = 0 → F = 1) and normal (c = 1 → ((n−1)/(n+1))²) incidence
            are exact.
        n: relative refractive index (> 1), broadcast against ``cos_theta``; F is smooth in n.
    Returns:
        F with the broadcast shape, in [0, 1].
    """
    c = jnp.asarray(cos_theta)
    n = jnp.asarray(n)
    # promote, never demote: a float64 n keeps its precision under a float32 cosine (finite
    # differences in n); a Python float n keeps the cosine's dtype; integers become floats
    dtype = jnp.result_type(c, n, float)
    c = jnp.clip(jnp.abs(c.astype(dtype)), 0.0, 1.0)
    n = n.astype(dtype)
    g = jnp.sqrt(n * n + c * c - 1.0)  # > 0 for n > 1, so no singular sqrt gradient
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


# --------------------------------------------------------------------------------------------
# Microfacet distributions

# Gauss–Legendre nodes on [0, 1] for the normalisation integral of the Gaussian distribution.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W
#: Beyond s = θ/μ = 6.5 the Gaussian is below e^-42: the normalisation integral is cut there.
_S_CUT = 6.5


def gaussian_normalisation(mu: Any) -> jax.Array:
    """K(μ) such that D = K(μ) exp(−(θh/μ)²) has ∫ D cosθh dω = 1 over the hemisphere.

    With θ = μ s, ∫ D cosθh dω = 2π K ∫₀^{π/2} e^{−θ²/μ²} sinθ cosθ dθ
    = π K μ ∫₀^{π/(2μ)} e^{−s²} sin(2μs) ds. The last integral is evaluated by 48-point
    Gauss–Legendre on [0, min(π/(2μ), 6.5)] (smooth in μ; the cut at 6.5 changes it by < 1e-18),
    accurate to float64 round-off for every μ > 0. K(0.1) = 32.0438, K(0.5) = 1.49991
    (docs/conventions.md, 'Reference values'); K → 1/(πμ²) as μ → 0.
    """
    mu = jnp.asarray(mu)
    dtype = mu.dtype if jnp.issubdtype(mu.dtype, jnp.floating) else jnp.float32
    mu = mu.astype(dtype)
    upper = jnp.minimum(0.5 * math.pi / mu, _S_CUT)
    s = upper[..., None] * jnp.asarray(_GL_X, dtype)
    f = jnp.exp(-s * s) * jnp.sin(2.0 * mu[..., None] * s)
    integral = upper * jnp.sum(f * jnp.asarray(_GL_W, dtype), axis=-1)
    return 1.0 / (math.pi * mu * integral)


def _theta_squared(c: jax.Array) -> jax.Array:
    """θ² = arccos(c)², smooth up to c = 1 (arccos has an infinite slope there): for
    x = 1 − c < 1e-3 the series 2x + x²/3 + 8x³/45 + 4x⁴/35 (error < 1e-15) is used."""
    x = 1.0 - jnp.clip(c, -1.0, 1.0)
    near = x < 1e-3
    xs = jnp.where(near, x, 0.0)
    series = xs * (2.0 + xs * (1.0 / 3.0 + xs * (8.0 / 45.0 + xs * 4.0 / 35.0)))
    far = jnp.arccos(jnp.where(near, 0.0, 1.0 - x))
    return jnp.where(near, series, far * far)


def gaussian_d(cos_theta_h: Any, mu: Any) -> jax.Array:
    """Normalised Gaussian (Torrance–Sparrow) distribution D = K(μ) exp(−(θh/μ)²), θh in radians.

    Zero where cosθh <= 0. ``mu`` > 0 (radians), broadcast against ``cos_theta_h``.
    """
    c = jnp.asarray(cos_theta_h)
    theta2 = _theta_squared(c)
    d = gaussian_normalisation(mu) * jnp.exp(-theta2 / (mu * mu))
    return jnp.where(c > 0.0, d, 0.0)


def beckmann_d(cos_theta_h: Any, m: Any) -> jax.Array:
    """Beckmann distribution D = exp(−tan²θh / m²) / (π m² cos⁴θh), ∫ D cosθh dω = 1.

    Zero where cosθh <= 0; ``m`` > 0 is the RMS slope.
    """
    c = jnp.asarray(cos_theta_h)
    cs = jnp.where(c > 0.0, c, 1.0)
    c2 = cs * cs
    tan2 = (1.0 - c2) / c2
    d = jnp.exp(-tan2 / (m * m)) / (math.pi * m * m * c2 * c2)
    return jnp.where(c > 0.0, d, 0.0)


def microfacet_d(cos_theta_h: Any, mu: Any, distribution: str = "gaussian") -> jax.Array:
    """D for the named distribution ("gaussian": μ is the Gaussian width in radians;
    "beckmann": μ is the RMS slope m)."""
    if distribution == "gaussian":
        return gaussian_d(cos_theta_h, mu)
    if distribution == "beckmann":
        return beckmann_d(cos_theta_h, mu)
    raise InputError(f"unknown distribution {distribution!r}; choose one of {DISTRIBUTIONS}",
                     field="distribution")


# --------------------------------------------------------------------------------------------
# Geometric attenuation


def vcavity_g(n_dot_h: Any, n_dot_v: Any, n_dot_l: Any, v_dot_h: Any) -> jax.Array:
    """V-cavity masking–shadowing of Torrance & Sparrow (the paper's G; Blinn 1977 form):

        G = min(1, 2(N·H)(N·V)/(V·H), 2(N·H)(N·L)/(V·H)),

    clamped to [0, 1] (0 where either direction is below the surface or V·H <= 0).
    """
    vh = jnp.asarray(v_dot_h)
    vh_safe = jnp.where(vh > 0.0, vh, 1.0)
    a = 2.0 * n_dot_h * n_dot_v / vh_safe
    b = 2.0 * n_dot_h * n_dot_l / vh_safe
    g = jnp.clip(jnp.minimum(1.0, jnp.minimum(a, b)), 0.0, 1.0)
    return jnp.where(vh > 0.0, g, 0.0)


def smith_g1_beckmann(cos_theta: Any, m: Any) -> jax.Array:
    """Smith masking G1 for the Beckmann distribution (exact form, Walter et al. 2007 eq. 25):
    G1 = 1/(1 + Λ(a)), a = cotθ / m, Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2a√π). 0 for cosθ <= 0."""
    c = jnp.clip(jnp.asarray(cos_theta), 0.0, 1.0)
    s = jnp.sqrt(jnp.maximum(1.0 - c * c, 1e-12))
    a = jnp.maximum(c / (m * s), 1e-6)
    lam = -0.5 * jax.scipy.special.erfc(a) + jnp.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
    return jnp.where(c > 0.0, 1.0 / (1.0 + lam), 0.0)


def smith_g(n_dot_v: Any, n_dot_l: Any, v_dot_h: Any, l_dot_h: Any, m: Any) -> jax.Array:
    """Separable Smith shadowing–masking G = G1(V) G1(L) with Beckmann's G1 (see
    :func:`smith_g1_beckmann`); for the Gaussian distribution m = μ is used (the two
    distributions agree to first order in θh: exp(−tan²θh/μ²) ≈ exp(−θh²/μ²)). Zero where a
    microfacet would be seen from behind (V·H or L·H <= 0)."""
    ok = (jnp.asarray(v_dot_h) > 0.0) & (jnp.asarray(l_dot_h) > 0.0)
    return jnp.where(ok, smith_g1_beckmann(n_dot_v, m) * smith_g1_beckmann(n_dot_l, m), 0.0)


def microfacet_g(n_dot_h: Any, n_dot_v: Any, n_dot_l: Any, v_dot_h: Any, mu: Any,
                 geometry: str = "vcavity") -> jax.Array:
    """G for the named form ("vcavity" | "smith")."""
    if geometry == "vcavity":
        return vcavity_g(n_dot_h, n_dot_v, n_dot_l, v_dot_h)
    if geometry == "smith":
        return smith_g(n_dot_v, n_dot_l, v_dot_h, v_dot_h, mu)
    raise InputError(f"unknown geometry term {geometry!r}; choose one of {GEOMETRIES}",
                     field="geometry")


# --------------------------------------------------------------------------------------------
# Material


class Material(eqx.Module):
    """Parameters of the reflection model (our physical scaling).

    Attributes (scalars are 0-d arrays; a batch of materials stacks them for ``jax.vmap``):
        alpha: Lambert weight (α = 1: ideal Lambertian of albedo S).
        beta: gloss weight (β = 1: energy-normalised microfacet lobe).
        chi: mirror weight (χ = 1: perfect dielectric mirror).
        mu: roughness μ > 0 (Gaussian: lobe width in radians; Beckmann: RMS slope m).
        n: refractive index n > 1.
        gamma: weight of the specular interreflection texture (eq. 6); unused by single-object
            shading.
        reflectance: S(λ) on the band grid (L,), or its K basis coefficients (K,).
        distribution: "gaussian" (default, the paper's) or "beckmann" (static).
        geometry: "vcavity" (default, the paper's) or "smith" (static).
    """

    alpha: jax.Array
    beta: jax.Array
    chi: jax.Array
    mu: jax.Array
    n: jax.Array
    gamma: jax.Array
    reflectance: jax.Array
    distribution: str = eqx.field(static=True, default="gaussian")
    geometry: str = eqx.field(static=True, default="vcavity")


_SCALARS = ("alpha", "beta", "chi", "mu", "n", "gamma")


def check_material(material: Material, *, channels: int | None = None,
                   path: str | None = None) -> Material:
    """Validate a material outside ``jit`` (Python boundary); raise :class:`InputError`.

    Checks: every parameter finite and of the same batch shape; α, β, χ, γ >= 0; μ > 0; n > 1;
    reflectance finite with ``channels`` entries on its last axis (when given); the static
    choices known. Returns the material unchanged.
    """
    if material.distribution not in DISTRIBUTIONS:
        raise InputError(f"unknown distribution {material.distribution!r}; choose one of "
                         f"{DISTRIBUTIONS}", path=path, field="distribution")
    if material.geometry not in GEOMETRIES:
        raise InputError(f"unknown geometry term {material.geometry!r}; choose one of "
                         f"{GEOMETRIES}", path=path, field="geometry")
    shape = None
    for name in _SCALARS:
        v = np.asarray(getattr(material, name), dtype=np.float64)
        if shape is None:
            shape = v.shape
        elif v.shape != shape:
            raise InputError(f"shape {v.shape} differs from alpha's {shape}", path=path,
                             field=name)
        if not np.all(np.isfinite(v)):
            raise InputError("NaN or infinite value", path=path, field=name)
        if name == "mu" and np.any(v <= 0):
            raise InputError(f"roughness must be > 0, got {v.min():g}", path=path, field=name)
        elif name == "n" and np.any(v <= 1):
            raise InputError(f"refractive index must be > 1, got {v.min():g}", path=path,
                             field=name)
        elif name in ("alpha", "beta", "chi", "gamma") and np.any(v < 0):
            raise InputError(f"weight must be >= 0, got {v.min():g}", path=path, field=name)
    s = np.asarray(material.reflectance, dtype=np.float64)
    if s.ndim != len(shape or ()) + 1:
        raise InputError(f"expected shape {tuple(shape or ())} + (channels,), got {s.shape}",
                         path=path, field="reflectance")
    if channels is not None and s.shape[-1] != channels:
        raise InputError(f"expected {channels} channels (bands or basis coefficients), got "
                         f"{s.shape[-1]}", path=path, field="reflectance")
    if not np.all(np.isfinite(s)):
        raise InputError("NaN or infinite value", path=path, field="reflectance")
    return material


def make_material(
    *,
    alpha: float = 1.0,
    beta: float = 1.0,
    chi: float = 1.0,
    mu: float = 0.2,
    n: float = 1.5,
    gamma: float = 0.0,
    reflectance: Any,
    distribution: str = "gaussian",
    geometry: str = "vcavity",
    channels: int | None = None,
    dtype: Any = None,
) -> Material:
    """Build and validate a :class:`Material` (raises :class:`InputError` on bad input)."""
    def arr(x: Any) -> jax.Array:
        return jnp.asarray(np.asarray(x, dtype=np.float64), dtype=dtype or jnp.float32)

    try:
        values = {k: np.asarray(v, dtype=np.float64) for k, v in
                  dict(alpha=alpha, beta=beta, chi=chi, mu=mu, n=n, gamma=gamma,
                       reflectance=reflectance).items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"material parameters must be numeric ({exc})",
                         field="material") from None
    m = Material(**{k: arr(v) for k, v in values.items()}, distribution=distribution,
                 geometry=geometry)
    # validate on the float64 values so NaN/ranges are judged before any rounding
    check_material(Material(**values, distribution=distribution, geometry=geometry),
                   channels=channels)
    return m


# --------------------------------------------------------------------------------------------
# BRDF and point lights


def _dot(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.sum(a * b, axis=-1)


def _normalize(v: jax.Array) -> jax.Array:
    return v / jnp.sqrt(jnp.maximum(_dot(v, v), 1e-30))[..., None]


def microfacet_fdg(normal: Any, view: Any, light: Any, mu: Any, n: Any, distribution: str,
                   geometry: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """F(n, θd) D(μ, θh) G and the cosines N·V, N·L for unit vectors (..., 3) (broadcasting;
    ``mu`` and ``n`` broadcast with the cosines): the numerator of the gloss BRDF."""
    N, V, L = (jnp.asarray(x) for x in (normal, view, light))
    nv, nl = _dot(N, V), _dot(N, L)
    H = _normalize(L + V)
    nh, vh = _dot(N, H), _dot(V, H)
    fdg = (fresnel_dielectric(vh, n) * microfacet_d(nh, mu, distribution)
           * microfacet_g(nh, nv, nl, vh, mu, geometry))
    return fdg, nv, nl


def gloss_brdf(material: Material, normal: Any, view: Any, light: Any) -> jax.Array:
    """Scalar microfacet BRDF F(n, θd) D(μ, θh) G / (4 cosθi cosθr) (1/sr), without β.

    Zero unless both L and V are above the surface. Unbatched: unit 3-vectors.
    """
    fdg, nv, nl = microfacet_fdg(normal, view, light, material.mu, material.n,
                                 material.distribution, material.geometry)
    ok = (nv > 0.0) & (nl > 0.0)
    denom = jnp.where(ok, 4.0 * nv * nl, 1.0)
    return jnp.where(ok, fdg / denom, 0.0)


def brdf(material: Material, normal: Any, view: Any, light: Any) -> jax.Array:
    """Spectral BRDF (C,) = α S/π + β F D G/(4 cosθi cosθr) (1/sr), band representation only
    (in a basis the constant gloss term is not a coefficient vector). The mirror (δ) lobe is
    excluded. Symmetric in V and L (Helmholtz reciprocity)."""
    N, V, L = (jnp.asarray(x) for x in (normal, view, light))
    ok = (_dot(N, V) > 0.0) & (_dot(N, L) > 0.0)
    diffuse = jnp.where(ok, material.alpha / math.pi, 0.0) * material.reflectance
    return diffuse + material.beta * gloss_brdf(material, N, V, L)


def shade_point_light(
    material: Material,
    normal: Any,
    view: Any,
    light: Any,
    irradiance: Any,
    *,
    product_tensor: Any = None,
) -> jax.Array:
    """Radiance (C,) towards V from a point/directional light, eq. (4) in our physical reading:

        α S(λ) E(λ) cosθi / π + β F(n, θd) D(μ, θh) G / (4 cosθr) · E(λ).

    Args:
        light: unit direction towards the light (3,).
        irradiance: E (C,), W·m⁻²·nm⁻¹ on a surface facing the light (bands or coefficients).
        product_tensor: (K, K, K) :attr:`SpectralBasis.product_tensor` when ``reflectance`` and
            ``irradiance`` are basis coefficients; None for bands.
    The mirror term vanishes for a point source. Zero if N·V <= 0 or N·L <= 0.
    """
    N, V, L = (jnp.asarray(x) for x in (normal, view, light))
    E = jnp.asarray(irradiance)
    nl = _dot(N, L)
    ok = (_dot(N, V) > 0.0) & (nl > 0.0)
    if product_tensor is None:
        se = material.reflectance * E
    else:
        se = jnp.einsum("i,j,ijk->k", material.reflectance, E, jnp.asarray(product_tensor))
    diffuse = jnp.where(ok, material.alpha * nl / math.pi, 0.0) * se
    gloss = material.beta * gloss_brdf(material, N, V, L) * jnp.where(ok, nl, 0.0)
    return diffuse + gloss * E


# --------------------------------------------------------------------------------------------
# Paper scaling

_PAPER_SCALE = {"alpha": math.pi, "beta": 4.0}


def to_paper_params(params: dict[str, Any] | Material) -> dict[str, Any]:
    """Our parameters → the paper's scaling: α_paper = α/π, β_paper = β/4; χ, μ, n, γ equal.

    Accepts a :class:`Material` or a dict with any of alpha, beta, chi, mu, n, gamma.
    """
    d = {k: getattr(params, k) for k in _SCALARS} if isinstance(params, Material) else params
    return {k: (v / _PAPER_SCALE[k] if k in _PAPER_SCALE else v) for k, v in d.items()}


def from_paper_params(params: dict[str, Any]) -> dict[str, Any]:
    """The paper's parameters → ours: α = π α_paper, β = 4 β_paper; χ, μ, n, γ equal."""
    return {k: (v * _PAPER_SCALE[k] if k in _PAPER_SCALE else v) for k, v in params.items()}

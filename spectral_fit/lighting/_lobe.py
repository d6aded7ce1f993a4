"""The gloss lobe in half-vector space: quadrature nodes and scalar lobe integrals (JAX; no map).

With dω_L = 4 (V·H) dω_H the gloss integrand of eq. 5 is D(H) g(H) L(l(H)), g = F G (V·H)/(N·V),
over the half vectors H whose reflection l(H) is above the surface. Here: the lobe's directional
albedo A = ∫ D g dω_H (:func:`lobe_albedo`, a function of cosθr only, and per-material tables of
it), g at given half vectors (:func:`lobe_factor`), and node sets of the lobe narrowed for a
reflected-direction prefilter of variance ``var`` (radians²) per axis: half vectors (M, 3),
relative weights (M,) and cosθh (M,), by rings over the visible arc (:func:`visible_nodes`), a
Cartesian grid (:func:`_grid_nodes`) or Gauss–Laguerre rings (:func:`_narrowed_nodes`). Lobe
widths are the Gaussian μ (radians; s = θh/μ) or the Beckmann slope m (s = tanθh/m); N and V are
unit vectors (3,).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ._fastmath import sincos_poly
from ._reflectance import fresnel_dielectric, gaussian_normalisation, smith_g, vcavity_g

__all__ = [
    "lobe_albedo",
    "lobe_factor",
    "visible_nodes",
]


def _frame(n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Orthonormal tangents (T, B) of unit n (Duff et al. 2017, branchless)."""
    sign = jnp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t = jnp.stack([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    bt = jnp.stack([b, sign + n[1] * n[1] * a, -n[1]])
    return t, bt


def _view_frame(N: jax.Array, V: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tangent T along V's projection on the tangent plane, B = N × T (Duff's frame if V ∥ N)."""
    p = V - jnp.dot(N, V) * N
    p2 = jnp.dot(p, p)
    ok = p2 > 1e-12
    t0, _ = _frame(N)
    T = jnp.where(ok, p / jnp.sqrt(jnp.where(ok, p2, 1.0)), t0)
    return T, jnp.cross(N, T)


_S_MAX = 4.5  # lobe truncation in s = θh/μ (Gaussian) or tanθh/m (Beckmann): e^-20 of the peak


def _lobe_rings(nv: jax.Array, width: jax.Array, xr: np.ndarray, wr: np.ndarray, *,
                distribution: str, radial_rule: str = "uniform") -> tuple[jax.Array, ...]:
    """Radial rings of a microfacet lobe of ``width``: s = θh/width (Gaussian) or tanθh/width
    (Beckmann) at Gauss–Legendre nodes ``xr`` (weights ``wr``, both on [0, 1]) scaled to
    [0, s_max], s_max from the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5.

    ``radial_rule`` "uniform": the nodes uniform in s (weight s e^{−s²} in the integrand);
    "mass": uniform in the radial mass t = 1 − e^{−s²} (s = √(−ln(1 − t)), ds s e^{−s²} =
    dt/2), every ring at the lobe's weight — for few rings (with 2 uniform rings on [0, 4.5]
    the outer one, at s = 3.5, carries e^−12 of the weight and the lobe is one ring at s ≈ 1).

    Returns (R,) arrays: s, the ring weight s e^{−s²} ds, cosθh, sinθh and the Jacobian
    factor sinθh/θh (Gaussian) or 1/cosθh (Beckmann) of dω_H in s ds dφ."""
    dtype = nv.dtype
    theta_r = jnp.arccos(jnp.clip(nv, 1e-7, 1.0 - 1e-7))
    theta_max = jnp.minimum(0.25 * math.pi + 0.5 * theta_r, 0.5 * math.pi - 1e-4)
    if distribution == "gaussian":
        s_max = jnp.minimum(theta_max / width, _S_MAX)
    elif distribution == "beckmann":
        s_max = jnp.minimum(jnp.tan(theta_max) / width, _S_MAX)
    else:
        raise InputError(f"unknown distribution {distribution!r}", field="distribution")
    if radial_rule == "uniform":
        s = s_max * jnp.asarray(xr, dtype)  # (R,)
        ring = s_max * jnp.asarray(wr, dtype) * s * jnp.exp(-s * s)  # s e^{-s²} ds
    elif radial_rule == "mass":
        t_max = -jnp.expm1(-s_max * s_max)
        s = jnp.sqrt(-jnp.log1p(-t_max * jnp.asarray(xr, dtype)))
        ring = 0.5 * t_max * jnp.asarray(wr, dtype)
    else:
        raise InputError(f"unknown radial rule {radial_rule!r}", field="radial_rule")
    if distribution == "gaussian":
        th = width * s
        sin_h, cos_h = sincos_poly(th)
        jac = jnp.where(th > 1e-4, sin_h / jnp.where(th > 1e-4, th, 1.0), 1.0 - th * th / 6.0)
    else:
        tan_h = width * s
        cos_h = 1.0 / jnp.sqrt(1.0 + tan_h * tan_h)
        sin_h = tan_h * cos_h
        jac = 1.0 / cos_h
    return s, ring, cos_h, sin_h, jac


def _visible_arc(nv: jax.Array, cos_h: jax.Array, sin_h: jax.Array) -> jax.Array:
    """φ_max (R,) of each ring θh: the half vectors at azimuth |φ'| <= φ_max (from V's
    azimuth) reflect V above the surface, N·L > 0 ⟺ sin2θh sinθr cosφ' > −cosθr cos2θh
    (π when the whole ring is visible, 0 when none of it is)."""
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    a = 2.0 * sin_h * cos_h * sin_r
    bnum = -nv * (cos_h * cos_h - sin_h * sin_h)
    full = bnum < -jnp.abs(a) * (1.0 - 1e-6)
    empty = bnum > jnp.abs(a) * (1.0 - 1e-6)
    c = jnp.where(full | empty, 0.0, bnum / jnp.where(full | empty, 1.0, a))
    return jnp.where(full, math.pi, jnp.where(empty, 0.0, jnp.arccos(c)))


def lobe_albedo(
    nv: jax.Array, width: jax.Array, n: jax.Array, mu: jax.Array, *, distribution: str,
    geometry: str, fresnel: bool, radial: int, azimuthal: int,
) -> jax.Array:
    """A = ∫ D(width) F G (V·H)/(N·V) dω_H over the half vectors whose reflection is above the
    surface (the gloss lobe's directional albedo), a function of cosθr = ``nv`` only.

    Rings θh(s) with Gauss–Legendre in s on [0, s_max] (weight s e^{−s²} of the distribution),
    s_max from the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5; on each ring
    Gauss–Legendre in the azimuth φ' (from V's azimuth) over the visible arc 0 <= φ' <= φ_max,
    where N·L > 0 ⟺ sin2θh sinθr cosφ' > −cosθr cos2θh (the integrand is even in φ', so half
    the arc is integrated and doubled). The integrand vanishes or jumps only at the domain
    boundary, so the rule converges fast, and the nodes move smoothly with μ and θr. Only
    scalars: V·H = cosθh cosθr + sinθh sinθr cosφ', N·L = 2 (V·H) cosθh − cosθr."""
    g, *_ = _lobe_grid(nv, width, mu, n, distribution=distribution, geometry=geometry,
                       fresnel=fresnel, radial=radial, azimuthal=azimuthal)
    return jnp.sum(g)


def _lobe_grid(nv: jax.Array, width: jax.Array, mu: jax.Array, n: jax.Array, *,
               distribution: str, geometry: str, fresnel: bool, radial: int, azimuthal: int
               ) -> tuple[jax.Array, ...]:
    """The node set of :func:`lobe_albedo` and :func:`_lobe_moments` (see the former): the
    weights w F G (V·H)/(N·V) (R, A) of the distribution of roughness ``width`` with the
    geometry and Fresnel factor of ``mu`` and ``n``, and per node V·H, N·L (R, A), the ring's
    cosθh, sinθh (R,), sinθr and the azimuth φ' (R, A). Scalars only."""
    dtype = nv.dtype
    xr, wr = np.polynomial.legendre.leggauss(radial)
    xa, wa = np.polynomial.legendre.leggauss(azimuthal)
    xr, wr = 0.5 * (xr + 1.0), 0.5 * wr
    xa = 0.5 * (xa + 1.0)  # [0, 1]; the weights (sum 2) double the half arc
    nv = jnp.clip(nv, 0.0, 1.0)
    _, ws, cos_h, sin_h, jac = _lobe_rings(nv, width, xr, wr, distribution=distribution)
    if distribution == "gaussian":
        # D dω_H = K(μ) e^{−s²} sinθh dθh dφ = K μ² e^{−s²} s ds dφ · sinθh/θh
        ws = ws * gaussian_normalisation(width) * width * width * jac
    else:
        # D dω_H = e^{−s²} s ds dφ / (π cosθh)
        ws = ws * jac / math.pi
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    phi_max = _visible_arc(nv, cos_h, sin_h)  # (R,)
    phi = phi_max[:, None] * jnp.asarray(xa, dtype)[None, :]  # (R, A)
    w = (ws * phi_max)[:, None] * jnp.asarray(wa, dtype)[None, :]
    vh = cos_h[:, None] * nv + (sin_h * sin_r)[:, None] * sincos_poly(phi)[1]
    nl = 2.0 * vh * cos_h[:, None] - nv
    ch = jnp.broadcast_to(cos_h[:, None], vh.shape)
    g = w * _microfacet_factor(nv, nl, vh, ch, mu, n, geometry=geometry, fresnel=fresnel)
    return g, vh, nl, cos_h, sin_h, sin_r, phi


def _microfacet_factor(nv: jax.Array, nl: jax.Array, vh: jax.Array, nh: jax.Array,
                       mu: jax.Array, n: jax.Array, *, geometry: str, fresnel: bool
                       ) -> jax.Array:
    """F G (V·H)/(N·V) from the cosines (broadcasting)."""
    if geometry == "vcavity":
        G = vcavity_g(nh, nv, nl, vh)
    elif geometry == "smith":
        G = smith_g(nv, nl, vh, vh, mu)
    elif geometry == "none":
        G = jnp.where((vh > 0.0) & (nl > 0.0), 1.0, 0.0)
    else:
        raise InputError(f"unknown geometry term {geometry!r}", field="geometry")
    F = fresnel_dielectric(vh, n) if fresnel else 1.0
    nv_safe = jnp.where(nv > 0.0, nv, 1.0)
    return F * G * jnp.maximum(vh, 0.0) / nv_safe


def lobe_factor(
    N: jax.Array, V: jax.Array, H: jax.Array, cos_h: jax.Array, mu: jax.Array, n: jax.Array,
    *, geometry: str, fresnel: bool,
) -> tuple[jax.Array, jax.Array]:
    """F G (V·H)/(N·V) at half vectors H (M, 3) (the rest of the integrand after D dω_H and
    dω_L = 4 (V·H) dω_H), and the reflected directions L (M, 3)."""
    nv = jnp.dot(N, V)
    vh = H @ V
    L = 2.0 * vh[:, None] * H - V
    nl = L @ N
    return _microfacet_factor(nv, nl, vh, cos_h, mu, n, geometry=geometry, fresnel=fresnel), L


def _narrowed_nodes(
    N: jax.Array, V: jax.Array, width: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, radial: int, azimuthal: int,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Nodes and relative weights of the lobe narrowed for a reflected-direction prefilter of
    variance ``var`` per axis: an anisotropic Gaussian in the lobe's tangent coordinates
    (exponential map θh for the Gaussian D, tanθh for Beckmann) with squared widths
    width² − var/2 along V's azimuth (reflection doubles angles in the plane of incidence) and
    width² − var/(2cos²θr) across it (there it multiplies them by 2cosθd ≈ 2cosθr).
    Gauss–Laguerre in s² × equally spaced azimuths (rings staggered). Weights are relative
    (the caller normalises)."""
    dtype = N.dtype
    t_nodes, t_w = np.polynomial.laguerre.laggauss(radial)
    phi = 2.0 * np.pi * (np.arange(azimuthal)[None, :] + 0.5
                         + 0.5 * (np.arange(radial)[:, None] % 2)) / azimuthal
    s = np.sqrt(t_nodes)[:, None]
    cx = jnp.asarray((s * np.cos(phi)).reshape(-1), dtype)
    cy = jnp.asarray((s * np.sin(phi)).reshape(-1), dtype)
    wq = jnp.asarray(np.broadcast_to(t_w[:, None], phi.shape).reshape(-1), dtype)
    floor = 0.01 * width * width
    wt = jnp.sqrt(jnp.maximum(width * width - 0.5 * var, floor))
    wb = jnp.sqrt(jnp.maximum(width * width - 0.5 * var / jnp.maximum(nv * nv, 1e-4), floor))
    x, y = wt * cx, wb * cy
    r = jnp.sqrt(x * x + y * y)
    r_safe = jnp.where(r > 1e-12, r, 1.0)
    if distribution == "gaussian":
        theta = r
        sin_h, cos_h = sincos_poly(theta)
        jac = jnp.where(r > 1e-4, sin_h / r_safe, 1.0 - r * r / 6.0)
    else:
        cos_h = 1.0 / jnp.sqrt(1.0 + r * r)
        sin_h = r * cos_h
        jac = 1.0 / cos_h  # D dω_H ∝ e^{−s²} s ds dφ / cosθh
        sin_h = jnp.where(r > 1e-12, sin_h, 0.0)
    T, B = _view_frame(N, V)
    ux = jnp.where(r > 1e-12, x / r_safe, 1.0)
    uy = jnp.where(r > 1e-12, y / r_safe, 0.0)
    H = cos_h[:, None] * N + sin_h[:, None] * (ux[:, None] * T + uy[:, None] * B)
    return H, wq * jac, cos_h


def visible_nodes(
    N: jax.Array, V: jax.Array, mu: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, radial: int, azimuthal: int, radial_rule: str = "uniform",
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Half vectors (M, 3), relative weights (M,) and cosθh (M,) of a quadrature of the gloss
    lobe narrowed for a reflected-direction prefilter of variance ``var`` per axis, restricted to
    the half vectors whose reflection is above the surface.

    The narrowed lobe is an anisotropic Gaussian in the lobe's tangent coordinates (θh for the
    Gaussian D, tanθh for Beckmann) with squared widths w_t² = μ² − var/2 along V's azimuth
    (reflection doubles angles in the plane of incidence) and w_b² = μ² − var/(2cos²θr) across
    it. Nodes: rings at s = θh/w_t (or tanθh/w_t), Gauss–Legendre in s on [0, s_max] with the
    radial weight s e^{−s²} ds (:func:`_lobe_rings`), s_max from
    the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5; on each ring Gauss–Legendre in
    the azimuth φ' (from V's azimuth) over the whole visible arc |φ'| <= φ_max(θh) (N·L > 0 ⟺
    sin2θh sinθr cosφ' > −cosθr cos2θh). The across-axis narrowing enters the weights as
    exp(−s² sin²φ' (w_t²/w_b² − 1)). The nodes move smoothly with μ, N and V and never sample
    the map below the horizon, so the quadrature converges on the visible lobe alone.
    ``radial_rule``: see :func:`_lobe_rings` ("mass" for few rings)."""
    dtype = N.dtype
    xr, wr = np.polynomial.legendre.leggauss(radial)
    xa, wa = np.polynomial.legendre.leggauss(azimuthal)
    xr, wr = 0.5 * (xr + 1.0), 0.5 * wr
    nv = jnp.clip(nv, 0.0, 1.0)
    floor = 0.01 * mu * mu
    wt2 = jnp.maximum(mu * mu - 0.5 * var, floor)
    wb2 = jnp.maximum(mu * mu - 0.5 * var / jnp.maximum(nv * nv, 1e-4), floor)
    wt = jnp.sqrt(wt2)
    s, wring, cos_h, sin_h, jac = _lobe_rings(nv, wt, xr, wr, distribution=distribution,
                                              radial_rule=radial_rule)
    phi_max = _visible_arc(nv, cos_h, sin_h)  # (R,)
    phi = phi_max[:, None] * jnp.asarray(xa, dtype)[None, :]  # (R, A), xa in [-1, 1]
    wgt = (wring * jac * phi_max)[:, None] * jnp.asarray(wa, dtype)[None, :]
    sp, cp = sincos_poly(phi)
    wgt = wgt * jnp.exp(-(s * s)[:, None] * sp * sp * (wt2 / wb2 - 1.0))
    T, B = _view_frame(N, V)
    tang = cp[..., None] * T + sp[..., None] * B  # (R, A, 3)
    H = cos_h[:, None, None] * N + sin_h[:, None, None] * tang
    ch = jnp.broadcast_to(cos_h[:, None], phi.shape)
    return H.reshape(-1, 3), wgt.reshape(-1), ch.reshape(-1)


def _grid_nodes(
    N: jax.Array, V: jax.Array, mu: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, along: int, across: int, extent: float,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Half vectors (M, 3), relative weights (M,) and cosθh (M,) of a Cartesian quadrature of
    the gloss lobe narrowed for a reflected-direction prefilter of variance ``var`` per axis.

    Tangent coordinates (x, y) of H around N (exponential map θh for the Gaussian D, tanθh for
    Beckmann), x along V's azimuth (the plane of incidence), y across it. The narrowed lobe is
    exp(−x²/w_t² − y²/w_b²) with w_t² = μ² − var/2, w_b² = μ² − var/(2cos²θr) (reflection
    maps a step in x to 2 in reflected directions and a step in y to ≈ 2cosθr). Nodes: a
    uniform ``along`` × ``across`` midpoint grid on [−extent, extent]² in (x/w_t, y/w_b)
    (the trapezoid rule, spectrally accurate for the Gaussian). The reflected directions are
    then spaced 4·extent·w_t/along along the plane of incidence and
    4·extent·w_b·cosθr/across across it, so at grazing views, where the isotropic prefilter
    must be as narrow as the lobe across (∝ cosθr), the many nodes along keep the spacing
    at 0.88/cosθr prefilter stds (r = 0.1; 5 at θr = 80°, where the lobe itself is then
    only a few texels across; the polar rule of :func:`visible_nodes` had ~20 there and
    aliased). Half vectors that reflect V below the surface
    get zero weight from G in the caller's lobe factor (the integrand goes to zero
    continuously at the horizon). Nodes move smoothly with μ, N and V."""
    dtype = N.dtype
    nv = jnp.clip(nv, 0.0, 1.0)
    floor = 0.01 * mu * mu
    wt = jnp.sqrt(jnp.maximum(mu * mu - 0.5 * var, floor))
    gx = extent * ((np.arange(along) + 0.5) * (2.0 / along) - 1.0)
    gy = extent * ((np.arange(across) + 0.5) * (2.0 / across) - 1.0)
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    X, Y = X.reshape(-1), Y.reshape(-1)
    keep = X * X + Y * Y <= extent * extent  # outside the disc the weight is < e^-extent²
    X, Y = X[keep], Y[keep]
    wq = jnp.asarray(np.exp(-(X * X + Y * Y)), dtype)
    x = wt * jnp.asarray(X, dtype)
    # across the plane of incidence a step in y moves the reflected direction by 2 (V·H); along
    # the lobe V·H = cos(θr − θx) changes (strongly at grazing views), so the across width is
    # narrowed per column with the local factor. Nodes at y = w_b(x)·Y keep the weights
    # exp(−X² − Y²): the narrowed column's density (μ/w_b) e^{−y²/w_b²} times dy = w_b dY.
    theta_x = x if distribution == "gaussian" else jnp.arctan(x)
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 1e-12))  # gradient-safe at V = N
    sx, cx_ = sincos_poly(theta_x)
    c = nv * cx_ + sin_r * sx  # cos(θr − θx)
    wb = jnp.sqrt(jnp.maximum(mu * mu - 0.5 * var / jnp.maximum(c * c, 1e-4), floor))
    y = wb * jnp.asarray(Y, dtype)
    r = jnp.sqrt(x * x + y * y)
    r_safe = jnp.where(r > 1e-12, r, 1.0)
    if distribution == "gaussian":
        sin_h, cos_h = sincos_poly(r)
        jac = jnp.where(r > 1e-4, sin_h / r_safe, 1.0 - r * r / 6.0)
    elif distribution == "beckmann":
        cos_h = 1.0 / jnp.sqrt(1.0 + r * r)
        sin_h = r * cos_h
        jac = 1.0 / cos_h  # D dω_H ∝ e^{−(x²+y²)/m²} dx dy / cosθh
    else:
        raise InputError(f"unknown distribution {distribution!r}", field="distribution")
    T, B = _view_frame(N, V)
    ux = x / r_safe
    uy = y / r_safe
    H = cos_h[:, None] * N + (sin_h * ux)[:, None] * T + (sin_h * uy)[:, None] * B
    # past θh = π/2 a half vector is below the surface: no weight (D = 0 there)
    w = jnp.where(cos_h > 0.0, wq * jac, 0.0)
    return H, w, cos_h


def _albedo_table(mu: jax.Array, n: jax.Array, size: int, *, distribution: str, geometry: str,
                  fresnel: bool, radial: int, azimuthal: int) -> jax.Array:
    """Exact lobe albedos (size,) at cosθr = 1 − x², x = j/(size − 1) (see :func:`lobe_albedo`).
    Independent of the point, so under ``jax.vmap`` over points it is computed once."""
    x = np.linspace(0.0, 1.0, size)
    c = np.maximum(1.0 - x * x, 1e-3)
    dtype = jnp.result_type(mu, jnp.float32)
    return jax.vmap(lambda cc: lobe_albedo(cc, mu, n, mu, distribution=distribution,
                                            geometry=geometry, fresnel=fresnel, radial=radial,
                                            azimuthal=azimuthal))(jnp.asarray(c, dtype))


def _interp_table(table: jax.Array, nv: jax.Array) -> jax.Array:
    """Catmull–Rom cubic interpolation (C¹) of :func:`_albedo_table` at cosθr = ``nv``; the
    albedo is even in θr, hence smooth in x = √(1 − cosθr)."""
    size = table.shape[0]
    x = jnp.sqrt(jnp.clip(1.0 - nv, 0.0, 1.0)) * (size - 1)
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    t = x - i.astype(x.dtype)
    # mirror at x = 0 (even function), clamp at the grazing end
    p0 = table[jnp.abs(i - 1)]
    p1 = table[i]
    p2 = table[i + 1]
    p3 = table[jnp.minimum(i + 2, size - 1)]
    return p1 + 0.5 * t * (p2 - p0 + t * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
                                          + t * (3.0 * (p1 - p2) + p3 - p0)))

"""The fit's forward model and its weighted residuals, per reading b (mean over its field):

    M_b(λ) = k(λ) · B ∘ mean_p∈field(b) [ α S(λ) E(λ, N_p)/π + β ∫ L F D G/(4 cosθr) dω
                                      + χ F(n, θr) L(λ, R_p) + I_p(λ) ]

(eq. 5 in our physical reading; I_p the light of the neighbours, eq. 6 in the gather
reading, when the scene's interreflection mode is not "none" and every object is a
sphere; every term is a weighted sum of cached radiances with weights from F, D, G, so
the Jacobian is exact autodiff, interreflection included; B the instrument's band-pass,
:func:`~spectral_fit.fitting.band_matrix`). With ``geometry = "SCI"`` reflectance,
S = max(S_SCI − F(n, 8°), 0). A bin of a camera photograph is a reading whose field is the
bin's pixels and whose "band-pass" is the camera's: counts_c = Σ_λ t s_c(λ) Δλ M_b(λ).

Shapes: B readings, P samples, O objects, L bands; readings in W·sr⁻¹·m⁻²·nm⁻¹.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ._params import physical_from_y, prior_residuals
from ._problem import FitProblem

__all__ = [
    "predict",
    "residuals",
    "interreflection_term",
    "whiten_correlated",
]


_SCI_ANGLE_DEG = 8.0  # d/8° spectrophotometers: specular component reflected at 8°


def _reflectances(problem: FitProblem, values: jax.Array) -> jax.Array:
    """(O, L) Lambert S(λ) of the objects for physical parameters ``values (O, 6)``: the
    measured reflectance, minus the first-surface reflection F(n, 8°) where it is SCI."""
    from ..lighting import fresnel_dielectric

    cos8 = math.cos(math.radians(_SCI_ANGLE_DEG))
    f8 = fresnel_dielectric(jnp.full_like(values[:, 4], cos8), values[:, 4])  # (O,)
    s = problem.surfaces.reflectance
    return jnp.where(problem.surfaces.sci[:, None] > 0, jnp.maximum(s - f8[:, None], 0.0), s)


@eqx.filter_jit
def interreflection_term(problem: FitProblem, values: jax.Array) -> jax.Array:
    """(P, L) interreflection radiance (eq. 6 in the gather reading; unit environment
    scale) at the samples for physical parameters ``values (O, 6)``; zeros when off."""
    from ._cache_model import cached_radiance

    g = problem.receivers
    if not problem.interreflection:
        return jnp.zeros_like(problem.irradiance)
    obj = jnp.maximum(g.object, 0)
    S = _reflectances(problem, values)
    _, ir = cached_radiance(problem.cache, values, S, obj, problem.surfaces.models)
    return jnp.where(g.valid[:, None], ir, 0.0)


def predict(problem: FitProblem, values: jax.Array, scale: Any = 1.0) -> jax.Array:
    """Predicted mean readings (B, L), W·sr⁻¹·m⁻²·nm⁻¹, for physical parameters
    ``values (O, 6)`` (columns α, β, χ, μ, n, γ) and the global environment scale: the field
    means of eq. (5) (+ eq. 6) from the radiance cache, through the band-pass, times k(λ).
    The rows of camera photographs' bins (the last S) hold their C channels' counts instead
    (:class:`~spectral_fit.fitting.FitReadings`), zeros after them."""
    from ._cache_model import field_radiance

    obj = jnp.maximum(problem.receivers.object, 0)
    S = _reflectances(problem, values)
    mean = field_radiance(problem.cache, values, S, obj, problem.surfaces.models,
                          interreflection=problem.interreflection)
    mean = mean + problem.readings.background
    k = problem.instrument.calibration
    resp = problem.readings.response
    n_img = resp.shape[0]
    if n_img == 0:
        return k * scale * (mean @ problem.instrument.band.T)
    n_spot = mean.shape[0] - n_img
    spots = k * (mean[:n_spot] @ problem.instrument.band.T)
    counts = jnp.einsum("scl,sl->sc", resp, k * mean[n_spot:])
    counts = jnp.pad(counts, ((0, 0), (0, mean.shape[1] - resp.shape[1])))
    return scale * jnp.concatenate([spots, counts])


def whiten_correlated(z: jax.Array, readings: Any, rows: jax.Array | None = None
                      ) -> jax.Array:
    """Residuals (or their Jacobian) already divided by σ, ``z`` (B, L[, F]), whitened for
    each row's model error shared by its bands: a level ℓ_b and a tilt t_b (fractions of the
    measured row m_b; the tilt's shape x runs from −1 at the first band to 1 at the last).

    The row's covariance is C = diag(σ²) + ℓ² m mᵀ + t² (m∘x)(m∘x)ᵀ. With v = m/σ and the
    columns V = [ℓ v, t v∘x] (L, k ≤ 2), D^-½ C D^-½ = I + V Vᵀ, and
    W = I − V g(VᵀV) Vᵀ with g(λ) = 1/(√(1+λ)(1+√(1+λ))) (a function of the k×k Gram
    matrix, by its eigendecomposition) satisfies WᵀW = (I + V Vᵀ)⁻¹: |W z|² is the
    generalised least-squares cost, in which the level and the tilt count once per row
    instead of once per band. Unchanged where ``readings.level`` and ``readings.tilt`` are
    None (or 0).

    ``rows`` (B, L): the radiance m the level and tilt are fractions of (default the measured
    rows). The fit passes its current prediction, held constant (iteratively reweighted least
    squares): with the measured rows the covariance's direction carries each band's noise,
    the whitening removes part of that noise with it, and the estimates come out biased (in
    simulated sessions with 1 % noise per band and a stated 1 % level, α by −0.6 %, two of its
    standard errors)."""
    lvl, tlt = readings.level, readings.tilt
    if lvl is None and tlt is None:
        return z
    v = (readings.measured if rows is None else rows) / readings.sigma
    cols = []
    if lvl is not None:
        cols.append(lvl[:, None] * v)
    if tlt is not None:
        x = jnp.linspace(-1.0, 1.0, v.shape[1], dtype=v.dtype)
        cols.append(tlt[:, None] * v * x[None, :])
    V = jnp.stack(cols, axis=-1)  # (B, L, k)
    lam, P = jnp.linalg.eigh(jnp.einsum("blk,blj->bkj", V, V))
    r = jnp.sqrt(1.0 + jnp.maximum(lam, 0.0))
    M = jnp.einsum("bkj,bj,bij->bki", P, 1.0 / (r * (1.0 + r)), P)  # g(VᵀV) (B, k, k)
    if z.ndim == 3:
        Vz = jnp.einsum("blk,blf->bkf", V, z)
        return z - jnp.einsum("blk,bkf->blf", V, jnp.einsum("bkj,bjf->bkf", M, Vz))
    Vz = jnp.einsum("blk,bl->bk", V, z)
    return z - jnp.einsum("blk,bk->bl", V, jnp.einsum("bkj,bj->bk", M, Vz))


def reading_residuals(pred: jax.Array, problem: FitProblem, reading_weights: jax.Array
                      ) -> jax.Array:
    """(B, L) weighted residuals of predicted readings ``pred`` (B, L): (model − measured)/σ,
    whitened for the rows' level and tilt errors around the prediction held constant
    (:func:`whiten_correlated`), times √w_b."""
    rd = problem.readings
    r = whiten_correlated((pred - rd.measured) / rd.sigma, rd, jax.lax.stop_gradient(pred))
    return r * jnp.sqrt(reading_weights)[:, None]


def residuals(y: jax.Array, problem: FitProblem, reading_weights: jax.Array) -> jax.Array:
    """Weighted residuals (B·L + K,) (:func:`reading_residuals`, then the K priors'
    (p − mean)/σ) at unconstrained ``y``."""
    vals, scale = physical_from_y(problem, y)
    r = reading_residuals(predict(problem, vals, scale), problem, reading_weights).reshape(-1)
    return jnp.concatenate([r, prior_residuals(problem, y)])


@eqx.filter_jit
def _predict_jit(problem: FitProblem, values: jax.Array, scale: jax.Array) -> jax.Array:
    return predict(problem, values, scale)

"""The fit's parametrisation: unconstrained y ↔ physical parameters, and the starts.

Parametrisation (unconstrained y → physical p): α, β, μ = lo + exp(y); χ, γ = lo + y² (lo is
reachable); n = lo + exp(y); the global environment scale (calibration "global") = exp(y);
lo is the physical limit (0; 1 for n) or a lower bound stated in the session. A parameter with
an upper bound hi is lo + (hi − lo)/(1 + e^−y) instead. Priors stated in the session add rows
(p − mean)/σ to the residuals (:func:`prior_residuals`).

The unknowns y (F,) of a :class:`~spectral_fit.fitting.FitProblem` are its free (object,
parameter) pairs in order, then the scale when it is fitted; physical parameters are (O, 6),
columns ``PARAMETERS`` (α, β, χ, μ, n, γ).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..io import PARAMETERS, PHYSICAL_LOWER
from ._problem import FitProblem

__all__ = [
    "PARAMETERS",
    "PARAM_INDEX",
    "to_physical",
    "to_unconstrained",
    "physical_from_y",
    "prior_residuals",
    "unknowns",
    "y_start",
]


PARAM_INDEX = {k: i for i, k in enumerate(PARAMETERS)}


# the unconstrained parametrisation without an upper bound: p = lo + y² for these, p = lo +
# exp(y) for the others (lo: the physical lower limit, or a stated lower bound)
_SQUARED = ("chi", "gamma")
#: each unknown's physical lower limit (none has an upper one)
LOWER = {k: lo for k, (lo, _) in PHYSICAL_LOWER.items()} | {"scale": 0.0}
#: how close to a stated bound a start is moved (a fraction of the interval): the logistic
#: map's gradient vanishes at the ends
_EDGE = 1e-3


def to_physical(y: Any, name: str, lower: float | None = None, upper: float | None = None
                ) -> Any:
    """Unconstrained y → physical parameter (see the module docstring). ``lower``/``upper``:
    stated bounds (None: the physical limit / none); with an upper bound the map is
    lo + (hi − lo) / (1 + e^−y)."""
    lo = LOWER[name] if lower is None else lower
    if upper is not None and math.isfinite(upper):
        return lo + (upper - lo) * jax.nn.sigmoid(y)
    if name in _SQUARED:
        return lo + y * y
    return lo + jnp.exp(y)


def to_unconstrained(p: float, name: str, lower: float | None = None,
                     upper: float | None = None) -> float:
    """Physical parameter → unconstrained y (inverse of :func:`to_physical`; a value at or
    past a bound is moved just inside it, so the gradient does not vanish: χ, γ = 0 to 1e-4
    above, a two-sided interval's ends to 0.1 % of its width inside)."""
    lo = LOWER[name] if lower is None else lower
    if upper is not None and math.isfinite(upper):
        f = min(max((p - lo) / (upper - lo), _EDGE), 1.0 - _EDGE)
        return math.log(f / (1.0 - f))
    if name in _SQUARED:
        return math.sqrt(max(p - lo, 1e-4))
    return math.log(max(p - lo, 1e-6))


def _dp_dy(y: float, name: str, lower: float | None = None, upper: float | None = None
           ) -> float:
    """Derivative of :func:`to_physical` at y."""
    lo = LOWER[name] if lower is None else lower
    if upper is not None and math.isfinite(upper):
        sg = 1.0 / (1.0 + math.exp(-y))
        return (upper - lo) * sg * (1.0 - sg)
    if name in _SQUARED:
        return 2.0 * y
    return math.exp(y)


def unknowns(problem: FitProblem) -> list[tuple[str, float, float]]:
    """(parameter name, lower, upper) of each unknown of ``problem``, in the order of y: the
    stated bounds (``problem.bounds``) or the physical range (upper = inf: none)."""
    out = []
    for j, (_, k) in enumerate(problem.free):
        name = PARAMETERS[k]
        lo, hi = problem.bounds[j] if problem.bounds else (LOWER[name], math.inf)
        out.append((name, lo, hi))
    if problem.fit_scale:
        out.append(("scale", 0.0, math.inf))
    return out


def physical_from_y(problem: FitProblem, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(O, 6) physical parameters (fixed ones from ``problem.values``) and the global scale
    at unconstrained ``y`` (:func:`to_physical`, all free parameters in one vector op)."""
    vals = problem.values
    if problem.free:
        spec = unknowns(problem)[:len(problem.free)]
        sq = np.array([k in _SQUARED for k, _, _ in spec])
        two = np.array([math.isfinite(hi) for _, _, hi in spec])
        lo = np.array([lo for _, lo, _ in spec])
        width = np.array([hi - lo if math.isfinite(hi) else 1.0 for _, lo, hi in spec])
        yf = y[:len(spec)]
        one_sided = jnp.where(sq, yf * yf, jnp.exp(jnp.where(two, 0.0, yf)))
        p = lo.astype(vals.dtype) + jnp.where(two, width.astype(vals.dtype) * jax.nn.sigmoid(yf),
                                              one_sided)
        o_idx = np.array([o for o, _ in problem.free])
        k_idx = np.array([k for _, k in problem.free])
        vals = vals.at[o_idx, k_idx].set(p)
    scale = to_physical(y[-1], "scale") if problem.fit_scale else jnp.ones((), vals.dtype)
    return vals, scale


def prior_residuals(problem: FitProblem, y: jax.Array) -> jax.Array:
    """(K,) (p − mean)/σ of the K Gaussian priors of ``problem`` (``problem.prior``: unknown
    index, mean, σ) at unconstrained ``y``: rows appended to the weighted residuals, so the
    least-squares solution is the maximum a posteriori estimate."""
    if not problem.prior:
        return jnp.zeros((0,), y.dtype)
    vals, _ = physical_from_y(problem, y)
    idx = [j for j, _, _ in problem.prior]
    o_idx = np.array([problem.free[j][0] for j in idx])
    k_idx = np.array([problem.free[j][1] for j in idx])
    mean = np.array([m for _, m, _ in problem.prior])
    sig = np.array([s_ for _, _, s_ in problem.prior])
    return ((vals[o_idx, k_idx] - mean) / sig).astype(y.dtype)


def y_start(problem: FitProblem, values: np.ndarray, scale: float) -> np.ndarray:
    spec = unknowns(problem)
    y = [to_unconstrained(float(values[o, k]), *spec[j])
         for j, (o, k) in enumerate(problem.free)]
    if problem.fit_scale:
        y.append(to_unconstrained(scale, "scale"))
    return np.asarray(y, np.float64)


def _starts(problem: FitProblem, y0: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The start and n − 1 perturbed copies (log-normal ×/÷ e^0.5 on α, β, μ, the scale; n − 1
    ×/÷ e^0.4; χ, γ: √ value ± 0.2)."""
    rng = np.random.default_rng(seed)
    out = [y0]
    spec = unknowns(problem)
    # (a bounded unknown: ± 0.5 in its logistic y)
    sd = np.array([0.5 if math.isfinite(hi) else {"chi": 0.2, "gamma": 0.2, "n": 0.4}.get(k, 0.5)
                   for k, _, hi in spec])
    for _ in range(max(0, n - 1)):
        y = y0 + sd * rng.standard_normal(y0.shape)
        y = np.array([abs(v) if k in _SQUARED and not math.isfinite(hi) else v
                      for v, (k, _, hi) in zip(y, spec, strict=True)])
        out.append(y)
    return np.stack(out)

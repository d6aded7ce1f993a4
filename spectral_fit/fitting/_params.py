"""The fit's parametrisation: unconstrained y ↔ physical parameters, and the starts.

Parametrisation (unconstrained y → physical p): α, β, μ = exp(y); χ, γ = y² (0 is reachable);
n = 1 + exp(y); the global environment scale (calibration "global") = exp(y).

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

from ..io import PARAMETERS
from ._problem import FitProblem

__all__ = [
    "PARAMETERS",
    "PARAM_INDEX",
    "to_physical",
    "to_unconstrained",
    "physical_from_y",
    "y_start",
]


PARAM_INDEX = {k: i for i, k in enumerate(PARAMETERS)}


# the unconstrained parametrisation: p = y² for these, p = offset + exp(y) for the others
_SQUARED = ("chi", "gamma")
_EXP_OFFSET = {"alpha": 0.0, "beta": 0.0, "mu": 0.0, "scale": 0.0, "n": 1.0}


def to_physical(y: Any, name: str) -> Any:
    """Unconstrained y → physical parameter (see the module docstring)."""
    if name in _SQUARED:
        return y * y
    if name in _EXP_OFFSET:
        return _EXP_OFFSET[name] + jnp.exp(y)
    raise KeyError(name)


def to_unconstrained(p: float, name: str) -> float:
    """Physical parameter → unconstrained y (inverse of :func:`to_physical`; χ, γ >= 0 map to
    √p, and 0 is moved to a small positive start so the gradient does not vanish)."""
    if name in ("alpha", "beta", "mu", "scale"):
        return math.log(max(p, 1e-6))
    if name in _SQUARED:
        return math.sqrt(max(p, 1e-4))
    if name == "n":
        return math.log(max(p - 1.0, 1e-6))
    raise KeyError(name)


def physical_from_y(problem: FitProblem, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(O, 6) physical parameters (fixed ones from ``problem.values``) and the global scale
    at unconstrained ``y`` (:func:`to_physical`, all free parameters in one vector op)."""
    vals = problem.values
    if problem.free:
        kinds = [PARAMETERS[k] for _, k in problem.free]
        sq = np.array([k in _SQUARED for k in kinds])
        shift = np.array([0.0 if k in _SQUARED else _EXP_OFFSET[k] for k in kinds])
        yf = y[:len(kinds)]
        p = jnp.where(sq, yf * yf, shift.astype(vals.dtype) + jnp.exp(yf))
        o_idx = np.array([o for o, _ in problem.free])
        k_idx = np.array([k for _, k in problem.free])
        vals = vals.at[o_idx, k_idx].set(p)
    scale = to_physical(y[-1], "scale") if problem.fit_scale else jnp.ones((), vals.dtype)
    return vals, scale


def _dp_dy(y: float, name: str) -> float:
    """Derivative of :func:`to_physical` at y."""
    if name in ("alpha", "beta", "mu", "scale", "n"):
        return math.exp(y)
    return 2.0 * y  # chi, gamma


def y_start(problem: FitProblem, values: np.ndarray, scale: float) -> np.ndarray:
    y = [to_unconstrained(float(values[o, k]), PARAMETERS[k]) for o, k in problem.free]
    if problem.fit_scale:
        y.append(to_unconstrained(scale, "scale"))
    return np.asarray(y, np.float64)


def _starts(problem: FitProblem, y0: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The start and n − 1 perturbed copies (log-normal ×/÷ e^0.5 on α, β, μ, the scale; n − 1
    ×/÷ e^0.4; χ, γ: √ value ± 0.2)."""
    rng = np.random.default_rng(seed)
    out = [y0]
    kinds = [PARAMETERS[k] for _, k in problem.free] + (["scale"] if problem.fit_scale else [])
    sd = np.array([{"chi": 0.2, "gamma": 0.2, "n": 0.4}.get(k, 0.5) for k in kinds])
    for _ in range(max(0, n - 1)):
        y = y0 + sd * rng.standard_normal(y0.shape)
        y = np.array([abs(v) if k in _SQUARED else v
                      for v, k in zip(y, kinds, strict=True)])
        out.append(y)
    return np.stack(out)

"""Profile-likelihood intervals of the fitted parameters.

For each free parameter p_j the fit is repeated with p_j held at values around its estimate and
every other unknown optimised again (from the best fit's values, one compiled batch of solves);
the profile Δχ²(p_j) = Σr²(p_j) − Σr²(p̂) rises by s² = max(1, χ²/dof) at the ends of the
interval (the 68.3 % interval of one parameter, Wilks' theorem, with the same inflation by the
reduced χ² as the linearised standard errors). Where the model is close to linear in the
parameter over the interval, the ends are p̂ ± the linearised standard error; in a curved
valley (β against χ and n, from few readings) they are not, and the profile says so: an
interval can be lopsided, reach a physical bound, or stay open past the scanned range (the
readings do not bound the parameter there).

The scanned values are p̂ + k·σ_lin for the multiples :data:`STEPS` (σ_lin the linearised
standard error; 10 % of |p̂| or 0.05 where that is 0 or not finite), clipped to the
parameter's range (physical, or the bounds stated in the session); a second batch of held
fits then samples the bracket of each end (between the last scanned value inside the interval
and the first outside) at 5 more values
(σ_lin can be far from the interval's width: in a curved valley it is the width of the
linearisation, not of the valley). Each end is found where √(Δχ²/s²) crosses 1, linearly
interpolated between the held values around it (√Δχ² is linear in p where the profile is
quadratic).
"""

from __future__ import annotations

import math
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._params import _EDGE, LOWER, to_unconstrained
from ._problem import FitProblem
from ._solver import CompactLM, solve_frozen

__all__ = ["STEPS", "profile_intervals"]

#: multiples of the linearised standard error at which each parameter is held
STEPS = (-6.0, -3.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 3.0, 6.0)
def _floor(p: float, kind: str, lo: float, hi: float = math.inf) -> float:
    """The lowest value a parameter is held at: its lower limit ``lo``, which χ, γ = lo + y²
    reach; the exp-parametrised ones approach it without reaching it, and an interval with
    an upper bound ``hi`` (logistic) is held 0.1 % of its width inside."""
    if math.isfinite(hi):
        return lo + _EDGE * (hi - lo)
    return lo if kind in ("chi", "gamma") else lo + 1e-6 * max(abs(p), 1e-3)


def _ceiling(lo: float, hi: float) -> float:
    """The highest value a parameter is held at: 0.1 % of its interval inside a stated upper
    bound (inf: none)."""
    return hi - _EDGE * (hi - lo) if math.isfinite(hi) else math.inf


def _held_values(p: float, se: float, kind: str, lo: float = -math.inf,
                 hi: float = math.inf) -> np.ndarray:
    """The values (len(STEPS),) at which a parameter is held (inside its limits
    [``lo``, ``hi``]); NaN for repeats of a limit."""
    step = se if (math.isfinite(se) and se > 0) else (0.1 * abs(p) if p != 0 else 0.05)
    lo = LOWER[kind] if lo == -math.inf else lo
    floor, ceil = _floor(p, kind, lo, hi), _ceiling(lo, hi)
    out = np.minimum(np.maximum(p + step * np.asarray(STEPS), floor), ceil)
    # a value clipped to a limit once is enough: the later ones repeat it
    for edge, pick in ((floor, slice(None, -1)), (ceil, slice(1, None))):
        at = np.flatnonzero(out == edge)
        if at.size > 1:
            out[at[pick]] = np.nan
    return out


def _bracket(values: np.ndarray, rise: np.ndarray, p_hat: float, side: int
             ) -> tuple[float, float, str]:
    """The end of the interval on one side (+1 above p̂, −1 below) from the held values:
    (end, the held value before it (towards p̂), how it ended: "profile" where √rise crosses
    1, interpolated linearly in √rise; "open" when the scan ends inside the interval)."""
    order = np.argsort(side * (values - p_hat))
    xs = [p_hat] + [float(values[i]) for i in order if side * (values[i] - p_hat) > 0]
    zs = [0.0] + [math.sqrt(max(float(rise[i]), 0.0)) for i in order
                  if side * (values[i] - p_hat) > 0]
    for k in range(1, len(xs)):
        if zs[k] >= 1.0:
            f = (1.0 - zs[k - 1]) / max(zs[k] - zs[k - 1], 1e-30)
            return xs[k - 1] + f * (xs[k] - xs[k - 1]), xs[k - 1], "profile"
    return xs[-1], xs[-1], "open"


def profile_intervals(problem: FitProblem, y_hat: np.ndarray, p_hat: np.ndarray,
                      se: np.ndarray, cost_hat: float, use: np.ndarray, s2: float, *,
                      labels: list[str], kinds: list[str], rtol: float, atol: float,
                      max_steps: int, jacobian: np.ndarray | None = None,
                      limits: list[tuple[float, float]] | None = None) -> dict[str, Any]:
    """Profile-likelihood intervals of every unknown of ``problem`` (see the module
    docstring).

    Args:
        problem: the fit's problem; ``y_hat`` (F,) its unconstrained optimum, ``p_hat`` (F,)
            the physical values, ``se`` (F,) their linearised standard errors, ``cost_hat``
            the optimum's ½ Σ r².
        use: (B,) reading weights of the fit.
        s2: the Δχ² of the interval's ends (max(1, χ²/dof)).
        labels, kinds: per unknown, ``object.parameter`` and the parameter's name.
        limits: per unknown, (lower, upper) (the session's bounds, else the physical range;
            None: the physical range).
        rtol, atol, max_steps: the solver's settings for the held fits.
        jacobian: (B·L, F) the residuals' Jacobian w.r.t. y at the optimum: each held fit
            then starts where the Gauss–Newton model puts the other unknowns for the held
            value (δy_o = −(J_oᵀJ_o)⁻¹ J_oᵀ J_j δy_j), not at the optimum's.

    Returns:
        {"intervals": {label: {"value", "lower", "upper", "lower_end", "upper_end"
        ("profile": where the profile crosses; "bound": the parameter's physical limit lies
        inside the interval; "open": the scanned range ends inside it), "held" (the held
        values), "delta_chi2" (the Σr² rise at each, in units of s²)}}, "lower_cost": the
        lowest ½ Σ r² of a held fit when it is below the optimum's (the fit stopped short of
        the best minimum), else None}.
    """
    F = len(y_hat)
    limits = limits or [(LOWER[k], math.inf) for k in kinds]
    held = np.stack([_held_values(float(p_hat[j]), float(se[j]), kinds[j], *limits[j])
                     for j in range(F)])
    n = held.shape[1]
    dt = problem.values.dtype
    solver = CompactLM(rtol=rtol, atol=atol)
    frozen = np.repeat(np.eye(F, dtype=bool), n, axis=0)  # (F·n, F): row j·n + i holds j
    rw = jnp.asarray(np.tile(use, (F * n, 1)), dt)

    # the other unknowns' response to a held one in the Gauss–Newton model: (F, F), row j
    follow = np.zeros((F, F))
    if jacobian is not None and F > 1:
        a = jacobian.T @ jacobian
        for j in range(F):
            o = np.arange(F) != j
            follow[j, o] = -np.linalg.lstsq(a[np.ix_(o, o)], a[o, j], rcond=1e-10)[0]

    def rises(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Held fits at values (F, n) (NaN: no fit): Δχ² / s² (F, n) and ½ Σr² (F, n)."""
        y0 = np.tile(y_hat, (F * n, 1))
        for j in range(F):
            yj = np.array([to_unconstrained(float(v), kinds[j], *limits[j])
                           if np.isfinite(v) else y_hat[j] for v in values[j]])
            y0[j * n:(j + 1) * n] += (yj - y_hat[j])[:, None] * follow[j][None]
            y0[j * n:(j + 1) * n, j] = yj
        y0 = np.where(np.isfinite(y0), y0, np.tile(y_hat, (F * n, 1)))
        out = solve_frozen(problem, jnp.asarray(y0, dt), rw, jnp.asarray(frozen), solver,
                           max_steps)
        cost = np.where(np.isfinite(values), np.asarray(out["cost"], np.float64).reshape(F, n),
                        np.nan)
        return 2.0 * (cost - cost_hat) / s2, cost

    # the scan, then the same number of held fits again inside the brackets of the ends
    # (one compiled program for both: the batch keeps its shape)
    rise, cost = rises(held)
    refine = np.full_like(held, np.nan)
    half = n // 2
    for j in range(F):
        ok = np.isfinite(held[j]) & np.isfinite(rise[j])
        for k, side in enumerate((-1, 1)):
            end, inner, how = _bracket(held[j][ok], rise[j][ok], float(p_hat[j]), side)
            if how != "profile":
                continue
            outer = min((float(v) for v in held[j][ok] if side * (v - end) >= 0),
                        key=lambda v: abs(v - end))
            refine[j, k * half:(k + 1) * half] = np.linspace(inner, outer, half + 2)[1:-1]
    rise2, cost2 = rises(refine)
    held_all = np.concatenate([held, refine], 1)
    rise_all = np.concatenate([rise, rise2], 1)
    intervals: dict[str, Any] = {}
    for j in range(F):
        ok = np.isfinite(held_all[j]) & np.isfinite(rise_all[j])
        order = np.argsort(held_all[j][ok])
        xs, zs = held_all[j][ok][order], rise_all[j][ok][order]
        ends: dict[str, Any] = {}
        for side, name in ((-1, "lower"), (1, "upper")):
            v, _, how = _bracket(xs, zs, float(p_hat[j]), side)
            if how == "open" and ((side < 0 and v <= _floor(float(p_hat[j]), kinds[j],
                                                             *limits[j]))
                                  or (side > 0 and v >= _ceiling(*limits[j]))):
                how = "bound"
            ends[name], ends[f"{name}_end"] = v, how
        intervals[labels[j]] = {"value": float(p_hat[j]), **ends, "held": xs.tolist(),
                                "delta_chi2": zs.tolist()}
    lowest = float(np.nanmin(np.concatenate([cost, cost2], 1)))
    return {"intervals": intervals,
            "lower_cost": lowest if lowest < cost_hat * (1 - 1e-4) - 1e-9 else None}

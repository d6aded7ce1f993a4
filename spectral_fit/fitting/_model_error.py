"""The model's own error per reading kind, estimated from the fit's residuals.

The instrument's noise σ_inst (from repeats or the session's ``[noise]``) says how far a reading
scatters around the truth; it says nothing about how far the model is from the truth (a gap the
renderer's transfer gets wrong, a lamp it blurs, a reflectance measured with another
geometry). With only σ_inst the fit's intervals are too narrow as soon as the model's error
exceeds the noise: the estimates are then many reported standard errors from the truth.

Each reading kind k gets a relative model error f_k added in quadrature,
σ² = σ_inst² + (f_k · L_measured)², stated in the session (``[model_error]``, a fraction per
kind) or estimated (``"auto"``): f_k is the value at which the kind's normalised residuals
have their expected size, Σ_k r²/σ² = n_k (N − F)/N (n_k data of kind k, N data in all, F
unknowns: each kind carries its share of the degrees of freedom), 0 when they are within it
already. The fit is then solved again with those σ, so that the kinds weigh each other by
their own error and the standard errors and profile intervals include it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["estimate_model_error", "with_model_error"]


def estimate_model_error(residual: np.ndarray, measured: np.ndarray, sigma: np.ndarray,
                         kinds: Sequence[str], use: np.ndarray, estimate: Sequence[str], *,
                         n_free: int, data: np.ndarray | None = None) -> dict[str, float]:
    """Relative model error f_k of each kind in ``estimate`` (see the module docstring).

    Args:
        residual: (B, L) fitted − measured radiance.
        measured: (B, L) measured radiance.
        sigma: (B, L) the readings' σ so far (instrument noise and stated model errors).
        kinds: (B,) each reading's kind.
        use: (B,) reading weights of the fit (0: not fitted).
        estimate: the kinds to estimate.
        n_free: F, the fit's unknowns.
        data: (B,) data per row (default L; a camera bin holds C channels, zeros after).

    Returns:
        {kind: f_k} (a fraction of each reading; 0 where the residuals need none).
    """
    r = np.asarray(residual, np.float64)
    m = np.abs(np.asarray(measured, np.float64))
    s2 = np.asarray(sigma, np.float64) ** 2
    kinds = np.asarray(kinds)
    used = np.asarray(use) > 0
    per = np.full(r.shape[0], r.shape[1]) if data is None else np.asarray(data)
    n_all = int(per[used].sum())
    share = max(n_all - n_free, 1) / max(n_all, 1)
    out: dict[str, float] = {}
    for k in estimate:
        rows = used & (kinds == k)
        if not rows.any():
            continue
        e2, var, mm = r[rows] ** 2, s2[rows], m[rows] ** 2
        target = per[rows].sum() * share

        def chi2(f: float, e2: np.ndarray = e2, var: np.ndarray = var,
                 mm: np.ndarray = mm) -> float:
            return float(np.sum(e2 / (var + f * f * mm)))

        if chi2(0.0) <= target:
            out[k] = 0.0
            continue
        lo, hi = -14.0, math.log(10.0)  # bisection on log f: χ²(f) falls as f grows
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if chi2(math.exp(mid)) > target else (lo, mid)
        out[k] = math.exp(0.5 * (lo + hi))
    return out


def with_model_error(sigma: np.ndarray, measured: np.ndarray, kinds: Sequence[str],
                     fractions: dict[str, float]) -> np.ndarray:
    """(B, L) σ with each kind's relative model error added in quadrature."""
    f = np.array([fractions.get(k, 0.0) for k in kinds], np.float64)[:, None]
    return np.sqrt(np.asarray(sigma, np.float64) ** 2
                   + (f * np.asarray(measured, np.float64)) ** 2)

"""The noise of one spectroradiometer reading: σ(λ)² = absolute² + (relative · L(λ))² in
radiance units (W·sr⁻¹·m⁻²·nm⁻¹), and its estimate from the sample variances of repeated
readings.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["NoiseModel", "estimate_noise"]


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """σ of ONE reading: σ(λ)² = absolute² + (relative · L(λ))² (radiance units)."""

    absolute: float
    relative: float
    source: str  # "manifest", "repeats" or "default"

    def sigma(self, radiance: np.ndarray) -> np.ndarray:
        r = np.asarray(radiance, np.float64)
        return np.sqrt(self.absolute ** 2 + (self.relative * r) ** 2)


def estimate_noise(groups: list[np.ndarray], *, floor_abs: float = 1e-9) -> NoiseModel | None:
    """Fit σ² = a² + (b L)² to the sample variances of repeated readings.

    Args:
        groups: arrays (M_i, L) of repeats of the same spot (groups with M_i < 2 are ignored).

    Returns:
        the noise of ONE reading, or None when no spot was repeated. Linear least squares of
        s²(λ) on [1, mean(λ)²] over all bands of all repeated spots, with both coefficients
        constrained >= 0 (non-negative least squares on two unknowns).
    """
    rows, rhs, dof = [], [], []
    for g in groups:
        g = np.asarray(g, np.float64)
        if g.ndim != 2 or g.shape[0] < 2:
            continue
        m = g.mean(axis=0)
        s2 = g.var(axis=0, ddof=1)
        rows.append(np.stack([np.ones_like(m), m * m], -1))
        rhs.append(s2)
        dof.append(np.full(m.shape, g.shape[0] - 1.0))
    if not rows:
        return None
    A = np.concatenate(rows)
    y = np.concatenate(rhs)
    w = np.concatenate(dof)
    # weight by dof / expected variance (iterate once: variance of s² ∝ σ⁴ / dof)
    coef = np.array([np.mean(y), 0.0])
    for _ in range(3):
        pred = np.maximum(A @ coef, 1e-30)
        sw = np.sqrt(w) / pred
        coef = _nnls2(A * sw[:, None], y * sw)
    a2, b2 = coef
    return NoiseModel(absolute=float(math.sqrt(max(a2, floor_abs ** 2))),
                      relative=float(math.sqrt(max(b2, 0.0))), source="repeats")


def _nnls2(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    best, best_r = np.zeros(2), float(np.sum(y * y))
    cands = []
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    cands.append(sol)
    for j in range(2):
        c = np.zeros(2)
        d = float(A[:, j] @ A[:, j])
        if d > 0:
            c[j] = float(A[:, j] @ y) / d
        cands.append(c)
    for c in cands:
        if np.all(c >= 0):
            r = float(np.sum((A @ c - y) ** 2))
            if r < best_r:
                best, best_r = c, r
    return best

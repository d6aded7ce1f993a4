"""A camera's spectral sensitivities estimated from a shot of a colour chart whose patches'
spectral radiance is known (the chart's reflectances under a measured light).

Counts of channel c at patch i (black subtracted): v_ic = t Σ_λ s_c(λ) L_i(λ) Δλ. With N ≈ 24
patches and L ≈ 41 bands the system is under-determined (a chart's reflectances span about
eight dimensions), so each channel is the non-negative least-squares solution with a
second-difference smoothness penalty (Tikhonov regularisation, as in the camera
characterisation literature, e.g. Finlayson, Hordley & Hubel 1998), the penalty's weight
chosen by generalised cross-validation over a grid. What the estimate is good for is the
camera's response to smooth spectra like the chart's (an object's, a room's light); it is
not the true curve band by band.

Plain NumPy/SciPy (the data layer).
"""

from __future__ import annotations

import numpy as np

from .._runtime.errors import InputError

__all__ = ["estimate_camera_sensitivities", "chart_radiance"]


def chart_radiance(white_radiance: np.ndarray, wavelengths: np.ndarray, *,
                   chart: str = "ColorChecker N Ohta",
                   white_reflectance: float | np.ndarray = 1.0) -> np.ndarray:
    """(24, L) radiance of a ColorChecker's patches (colour-science's reflectances of
    ``chart``) under the light whose reflected radiance off a white of
    ``white_reflectance`` is ``white_radiance`` (L,) (a spectroradiometer reading of a white
    standard at the chart)."""
    import colour

    from ._spectra import colour_sd

    sds = colour.SDS_COLOURCHECKERS[chart]
    refl = np.stack([colour_sd(sd, np.asarray(wavelengths, np.float64))
                     for sd in sds.values()])
    return refl * (np.asarray(white_radiance, np.float64)
                   / np.asarray(white_reflectance, np.float64))[None, :]


def _second_difference(n: int) -> np.ndarray:
    d = np.zeros((max(n - 2, 0), n))
    for i in range(n - 2):
        d[i, i:i + 3] = (1.0, -2.0, 1.0)
    return d


def estimate_camera_sensitivities(counts: np.ndarray, radiance: np.ndarray,
                                  wavelengths: np.ndarray, exposure_s: float, *,
                                  smoothness: float | None = None) -> np.ndarray:
    """(C, L) sensitivities s_c(λ), counts · s⁻¹ per (W·sr⁻¹·m⁻²·nm⁻¹ · nm), from a chart.

    Args:
        counts: (N, C) mean counts of each patch per channel, black level subtracted.
        radiance: (N, L) the patches' spectral radiance on ``wavelengths``
            (:func:`chart_radiance`).
        exposure_s: the shot's exposure t.
        smoothness: the penalty's weight relative to the data term's scale; None chooses it
            by generalised cross-validation (GCV) per channel.

    Raises:
        InputError: shapes that do not match, or non-finite / negative inputs.
    """
    from scipy.optimize import nnls

    from ._colorimetry import integration_weights

    v = np.asarray(counts, np.float64)
    Lr = np.asarray(radiance, np.float64)
    wl = np.asarray(wavelengths, np.float64)
    if v.ndim != 2 or Lr.ndim != 2 or Lr.shape != (v.shape[0], wl.size):
        raise InputError(f"counts (N, C) and radiance (N, {wl.size}) expected, got "
                         f"{v.shape} and {Lr.shape}", field="chart")
    if v.shape[0] < 6:
        raise InputError(f"need at least 6 patches, got {v.shape[0]}", field="chart")
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(Lr)) and np.all(Lr >= 0)):
        raise InputError("counts and radiance must be finite (radiance non-negative)",
                         field="chart")
    dl = integration_weights(wl)
    A = exposure_s * Lr * dl[None, :]  # (N, L)
    scale = np.linalg.norm(A, 2)
    An = A / scale
    D = _second_difference(wl.size)
    grid = [smoothness] if smoothness is not None else list(10.0 ** np.arange(-6.0, 0.5, 0.5))
    out = np.zeros((v.shape[1], wl.size))
    for c in range(v.shape[1]):
        best = None
        for lam in grid:
            M = np.vstack([An, np.sqrt(lam) * D])
            x, _ = nnls(M, np.concatenate([v[:, c], np.zeros(D.shape[0])]), maxiter=50 * wl.size)
            r = An @ x - v[:, c]
            # GCV with the unconstrained smoother's effective degrees of freedom
            H = An @ np.linalg.solve(An.T @ An + lam * D.T @ D + 1e-12 * np.eye(wl.size),
                                     An.T)
            dof = v.shape[0] - np.trace(H)
            g = v.shape[0] * float(r @ r) / max(dof, 1e-6) ** 2
            if best is None or g < best[0]:
                best = (g, x)
        out[c] = best[1] / scale
    return out

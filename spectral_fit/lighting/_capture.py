"""Camera-aware lifting of RGB environment captures to spectra (the seed's ref. [2] route).

An HDR panorama shot with a camera of known spectral sensitivities c_k(λ) (k = R, G, B) records
per texel ``rgb_k = Σ_λ L(λ) c_k(λ) Δλ`` (a linear map A (3, L)). Three numbers do not fix a
spectrum; a prior does. :class:`CameraLifter` estimates each texel's spectrum as

    s = t · Bᵀ ĉ,   ĉ = argmin ‖A Bᵀ c − rgb/t‖²/σ² + (c − c̄)ᵀ Σ⁻¹ (c − c̄),   t = Σ_k rgb_k,

with B (K, L) an uncentred PCA basis of brightness-normalised training radiances (products
of emitters — CIE daylights 4000–24000 K, Planckian radiators 1800–6500 K, colour-science's CIE
illuminants and measured light sources — with the CIE 2017 CES and rawtoaces reflectances, plus
the emitters themselves at 30 % of the rows: what an environment shows), and c̄, Σ the mean and
covariance of their coefficients (a Gaussian prior, i.e. Wiener estimation in the PCA subspace).
Because t is linear in rgb, the estimate is one fixed (L, 3) matrix: linear, so it commutes with
filtering and exposure. Negative values (rare, for saturated colours outside the prior) are
removed by alternating projections onto {s >= 0} and {A s = rgb}, which keeps the camera
response exact whenever a non-negative spectrum with that response exists.

The generic alternative, :func:`lift_generic_mallett`, ignores the camera: camera RGB → XYZ by a
3 × 3 colour-correction matrix fitted on training reflectances under D65 (the usual camera
characterisation), XYZ → linear sRGB, and Mallett & Yuksel's (2019) sRGB basis spectra
(colour.recovery) times D65.

Everything here is NumPy (data layer).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ..color import default_wavelengths, validate_wavelengths

__all__ = [
    "DEFAULT_CAMERA",
    "camera_sensitivities",
    "simulate_capture",
    "CameraLifter",
    "camera_lifter",
    "lift_generic_mallett",
    "compare_lifting",
]

DEFAULT_CAMERA = "Nikon 5100 (NPL)"


def camera_sensitivities(name: str = DEFAULT_CAMERA, wavelengths: Any = None) -> np.ndarray:
    """Measured camera RGB spectral sensitivities (L, 3) from colour-science
    (``colour.MSDS_CAMERA_SENSITIVITIES``, e.g. 'Nikon 5100 (NPL)'), zero outside their range,
    clipped at 0 (the tables hold round-off negatives) and scaled so green peaks at 1."""
    import colour

    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    if name not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise InputError(f"unknown camera {name!r}; colour-science has "
                         f"{sorted(colour.MSDS_CAMERA_SENSITIVITIES)}", field="camera")
    msds = colour.MSDS_CAMERA_SENSITIVITIES[name]
    inside = (wl >= msds.wavelengths[0]) & (wl <= msds.wavelengths[-1])
    sens = np.where(inside[:, None], np.maximum(np.asarray(msds[wl], np.float64), 0.0), 0.0)
    return sens / sens[:, 1].max()


def _response_matrix(sensitivities: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    from ..color import integration_weights

    return (sensitivities * integration_weights(wavelengths)[:, None]).T  # (3, L)


def simulate_capture(
    spectral_map: Any,
    sensitivities: Any,
    wavelengths: Any = None,
    *,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Camera RGB (..., 3) of a spectral map (..., L): ``rgb = Σ L(λ) c(λ) Δλ``, plus optional
    Gaussian noise of relative std ``noise`` (photon-noise-like: proportional to the signal)."""
    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    A = _response_matrix(np.asarray(sensitivities, np.float64), wl)
    rgb = np.asarray(spectral_map, np.float64) @ A.T
    if noise > 0:
        rng = np.random.default_rng(seed)
        rgb = rgb * (1.0 + noise * rng.standard_normal(rgb.shape))
    return rgb


def _natural_emitters(wl: np.ndarray) -> np.ndarray:
    """Unit-norm CIE daylights (D series, CCT 4000–24000 K, CIE 015:2018) and Planckian
    radiators (1800–6500 K), from colour-science, (25, L)."""
    import colour

    rows = []
    for cct in np.linspace(4000.0, 24000.0, 15):
        xy = colour.temperature.CCT_to_xy_CIE_D(cct * 1.4388 / 1.4380)
        rows.append(np.asarray(colour.sd_CIE_illuminant_D_series(xy)[wl], np.float64))
    for cct in np.linspace(1800.0, 6500.0, 10):
        rows.append(np.asarray(colour.sd_blackbody(cct)[wl], np.float64))
    out = np.stack(rows)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


@functools.lru_cache(maxsize=4)
def _product_training(wl_key: tuple[float, ...], emitter_share: float = 0.3) -> np.ndarray:
    """Training radiances (M, L): emitters × reflectances, and the emitters alone (replicated
    so that they make up ``emitter_share`` of the rows: an environment shows its light sources
    directly as well as lit surfaces)."""
    from ..color import training_spectra

    wl = np.asarray(wl_key)
    refl = training_spectra("reflectances", wl)
    emit = np.concatenate([_natural_emitters(wl), training_spectra("illuminants", wl)])
    prod = (emit[:, None, :] * refl[None, :, :]).reshape(-1, wl.size)
    reps = max(1, int(round(emitter_share / (1.0 - emitter_share) * len(prod) / len(emit))))
    return np.concatenate([prod, np.repeat(emit, reps, axis=0)])


@dataclasses.dataclass(frozen=True, eq=False)
class CameraLifter:
    """Linear camera-aware RGB → spectrum estimator (see the module docstring).

    Attributes:
        wavelengths: (L,) nm.
        response: A (3, L), camera RGB = spectra @ A.T.
        basis: B (K, L) orthonormal rows.
        matrix: P (L, 3), the linear estimate s = rgb @ P.T.
    """

    wavelengths: np.ndarray
    response: np.ndarray
    basis: np.ndarray
    matrix: np.ndarray

    def lift(self, rgb: Any, *, nonnegative: bool = True, iterations: int = 50
             ) -> tuple[np.ndarray, float]:
        """Spectra (..., L) of camera RGB (..., 3); returns (spectra, fraction of texels whose
        linear estimate had negative values and were projected)."""
        x = np.asarray(rgb, np.float64)
        if x.shape[-1] != 3 or not np.all(np.isfinite(x)):
            raise InputError(f"need finite (..., 3) camera RGB, got shape {x.shape}",
                             field="rgb")
        s = x @ self.matrix.T
        if not nonnegative:
            return s, 0.0
        flat = s.reshape(-1, s.shape[-1])
        bad = np.any(flat < 0, axis=1)
        if bad.any():
            A = self.response
            pinv = A.T @ np.linalg.inv(A @ A.T)  # (L, 3): projection onto {A s = y}
            y = x.reshape(-1, 3)[bad]
            z = flat[bad]
            for _ in range(iterations):
                z = np.maximum(z, 0.0)
                z = z + (y - z @ A.T) @ pinv.T
            flat = flat.copy()
            flat[bad] = np.maximum(z, 0.0)
        return flat.reshape(s.shape), float(bad.mean())


def camera_lifter(
    sensitivities: Any,
    wavelengths: Any = None,
    *,
    k: int = 8,
    noise_variance: float = 1e-5,
) -> CameraLifter:
    """Build the camera-aware estimator for ``sensitivities`` (L, 3) on ``wavelengths``.

    ``k``: PCA basis size of the prior; ``noise_variance``: σ² of the normalised RGB (relative
    to t²), the weight of the data term against the prior (small: the camera response is then
    reproduced to ~1e-3)."""
    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    sens = np.asarray(sensitivities, np.float64)
    if sens.shape != (wl.size, 3) or not np.all(np.isfinite(sens)):
        raise InputError(f"expected finite ({wl.size}, 3) sensitivities, got {sens.shape}",
                         field="sensitivities")
    if not isinstance(k, int | np.integer) or not 3 <= k <= wl.size:
        raise InputError(f"k must be an integer in 3..{wl.size}", field="k")
    A = _response_matrix(sens, wl)
    X = _product_training(tuple(float(v) for v in wl))
    t = (X @ A.T).sum(axis=1)
    X = X[t > 0] / t[t > 0, None]  # camera-brightness normalised: Σ rgb = 1
    _, _, vt = np.linalg.svd(X, full_matrices=False)
    B = vt[:k]
    C = X @ B.T
    cbar = C.mean(axis=0)
    cov = np.cov(C, rowvar=False) + 1e-12 * np.eye(k)
    M = A @ B.T  # (3, K)
    gain = cov @ M.T @ np.linalg.inv(M @ cov @ M.T + noise_variance * np.eye(3))  # (K, 3)
    # s = Bᵀ[t c̄ + G (rgb − t M c̄)], t = 1ᵀ rgb
    ones = np.ones((1, 3))
    coef = gain + np.outer(cbar - gain @ M @ cbar, ones[0])  # (K, 3)
    return CameraLifter(wavelengths=wl, response=A, basis=B, matrix=B.T @ coef)


def _ccm_to_xyz(A: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """3 × 3 matrix camera RGB → absolute XYZ, least squares over the training reflectances
    under CIE D65 (a standard camera characterisation)."""
    from ..color import illuminant, training_spectra, xyz_weights

    refl = training_spectra("reflectances", wl)
    spectra = refl * illuminant("D65", wl)
    rgb = spectra @ A.T
    xyz = spectra @ xyz_weights(wl)
    m, *_ = np.linalg.lstsq(rgb, xyz, rcond=None)
    return m.T


def lift_generic_mallett(rgb: Any, sensitivities: Any, wavelengths: Any = None) -> np.ndarray:
    """Generic upsampling: camera RGB → XYZ (colour-correction matrix) → linear sRGB →
    Mallett–Yuksel 2019 basis (colour.recovery) × D65, scaled so that sRGB white has the XYZ it
    came from. Linear in RGB. Returns spectra (..., L)."""
    import colour

    from ..color import illuminant, xyz_weights

    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    A = _response_matrix(np.asarray(sensitivities, np.float64), wl)
    xyz = np.asarray(rgb, np.float64) @ _ccm_to_xyz(A, wl).T
    d65 = illuminant("D65", wl)
    W = xyz_weights(wl)
    scale = 1.0 / (d65 @ W[:, 1])  # D65 · scale has Y = 1 (sRGB white)
    cs = colour.RGB_COLOURSPACES["sRGB"]
    srgb = xyz @ np.asarray(cs.matrix_XYZ_to_RGB).T
    basis = np.asarray(colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019[wl])  # (L, 3)
    return (srgb @ basis.T) * d65 * scale


def compare_lifting(
    spectral_map: Any,
    wavelengths: Any = None,
    *,
    camera: str = DEFAULT_CAMERA,
    k: int = 8,
    noise: float = 0.0,
) -> dict[str, Any]:
    """Simulate a capture of ``spectral_map`` (H, W, L) with ``camera`` and compare the
    camera-aware lifting with generic Mallett–Yuksel upsampling.

    Figures per method: ΔE00 (mean, p95, max) against the true spectra, with CIELAB taken
    relative to the map's own white (the XYZ of its solid-angle-weighted mean radiance), and
    the relative spectral RMS error ‖ŝ − s‖/‖s‖ (mean, p95) over texels, over the whole grid and
    over 420–680 nm (where the camera's data constrain the spectrum); plus the camera
    response error of the camera-aware result and its projected fraction."""
    from ..color import delta_e00, xyz_to_lab, xyz_weights
    from ._equirect import texel_solid_angles

    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    img = np.asarray(spectral_map, np.float64)
    if img.ndim != 3 or img.shape[-1] != wl.size:
        raise InputError(f"expected an (H, W, {wl.size}) map, got {img.shape}",
                         field="spectral_map")
    sens = camera_sensitivities(camera, wl)
    rgb = simulate_capture(img, sens, wl, noise=noise)
    lifter = camera_lifter(sens, wl, k=k)
    aware, projected = lifter.lift(rgb)
    generic = lift_generic_mallett(rgb, sens, wl)
    W = xyz_weights(wl)
    sa = texel_solid_angles(*img.shape[:2])
    white = ((img * sa[..., None]).sum(axis=(0, 1)) / sa.sum()) @ W
    lab_true = xyz_to_lab(img @ W, white)
    out: dict[str, Any] = {"camera": camera, "k": k, "noise": noise,
                           "projected_fraction": projected}
    norm = np.linalg.norm(img, axis=-1)
    ok = norm > 1e-12 * norm.max()
    vis = (wl >= 420.0) & (wl <= 680.0)  # where the camera sees: its data constrain this range
    norm_vis = np.linalg.norm(img[..., vis], axis=-1)
    for name, est in (("camera_aware", aware), ("generic_mallett", generic)):
        de = delta_e00(lab_true, xyz_to_lab(est @ W, white))[ok]
        rms = (np.linalg.norm(est - img, axis=-1) / np.where(ok, norm, 1.0))[ok]
        rms_vis = (np.linalg.norm((est - img)[..., vis], axis=-1)
                   / np.where(norm_vis > 0, norm_vis, 1.0))[ok]
        out[name] = {
            "dE00_mean": float(de.mean()), "dE00_p95": float(np.percentile(de, 95)),
            "dE00_max": float(de.max()), "spectral_rms_mean": float(rms.mean()),
            "spectral_rms_p95": float(np.percentile(rms, 95)),
            "spectral_rms_420_680_mean": float(rms_vis.mean()),
        }
    resp = simulate_capture(aware, sens, wl)
    out["camera_aware"]["rgb_rel_error_max"] = float(
        np.max(np.abs(resp - rgb).sum(-1)[ok] / np.abs(rgb).sum(-1)[ok]))
    return out

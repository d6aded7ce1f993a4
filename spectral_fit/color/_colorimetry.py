"""Colorimetry: CIE colour-matching functions, illuminants, spectra → XYZ, xy, u′v′, CIELAB, ΔE00.

All colour-science data and formulas are taken from colour-science (CIE 015:2018 CMFs and
illuminants, CIE 1976 L*a*b*, CIE 1976 UCS u′v′, CIEDE2000 as in Sharma, Wu & Dalal 2005).

Spectra → XYZ is a linear map, so it is provided as a weight matrix ``W (L, 3)`` with
``XYZ = spectra @ W``; the same matrix serves NumPy and JAX arrays (inside ``jax.jit``).

Units: absolute XYZ uses K_m = 683 lm/W, so spectral radiance in W·sr⁻¹·m⁻²·nm⁻¹ gives Y in cd/m².
"""

from __future__ import annotations

import functools

import numpy as np

from .._runtime.errors import InputError
from ._spectra import default_wavelengths, validate_wavelengths

__all__ = [
    "K_M",
    "DEFAULT_OBSERVER",
    "cmfs",
    "illuminant",
    "light_source",
    "integration_weights",
    "xyz_weights",
    "radiance_to_xyz",
    "reflectance_to_xyz",
    "xyz_to_xy",
    "xyz_to_uv_prime",
    "xyz_to_lab",
    "delta_e00",
    "delta_uv_prime",
    "daylight_coefficients",
]

#: Maximum luminous efficacy for photopic vision, lm/W (CIE 015:2018).
K_M = 683.0
DEFAULT_OBSERVER = "CIE 1931 2 Degree Standard Observer"


def _wl(wavelengths: object | None) -> np.ndarray:
    return default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)


@functools.lru_cache(maxsize=32)
def _cmfs_cached(wl: tuple[float, ...], observer: str) -> np.ndarray:
    import colour

    try:
        msds = colour.MSDS_CMFS[observer]
    except KeyError:
        raise InputError(f"unknown observer {observer!r}; colour-science knows "
                         f"{sorted(colour.MSDS_CMFS)}", field="observer") from None
    out = np.asarray(msds[np.asarray(wl)], dtype=np.float64)
    out.setflags(write=False)
    return out


def cmfs(wavelengths: object | None = None, observer: str = DEFAULT_OBSERVER) -> np.ndarray:
    """Colour-matching functions x̄ȳz̄ on ``wavelengths`` (default grid), shape (L, 3).

    Outside the tabulated 360–830 nm range the CMFs are taken as zero.
    """
    wl = _wl(wavelengths)
    return _cmfs_cached(tuple(float(x) for x in wl), observer)


def illuminant(name: str, wavelengths: object | None = None) -> np.ndarray:
    """Relative spectral power of a CIE illuminant from colour-science (e.g. "D65", "A"), (L,)."""
    import colour

    if name not in colour.SDS_ILLUMINANTS:
        raise InputError(f"unknown illuminant {name!r}", field="illuminant")
    return np.asarray(colour.SDS_ILLUMINANTS[name][_wl(wavelengths)], dtype=np.float64)


def light_source(name: str, wavelengths: object | None = None) -> np.ndarray:
    """Relative spectral power of a measured light source in colour-science's
    ``SDS_LIGHT_SOURCES`` (lamps, LEDs, fluorescents), (L,). Zero outside the measured range."""
    import colour

    if name not in colour.SDS_LIGHT_SOURCES:
        raise InputError(f"unknown light source {name!r}", field="light_source")
    sd = colour.SDS_LIGHT_SOURCES[name]
    wl = _wl(wavelengths)
    values = np.asarray(sd[wl], dtype=np.float64)
    inside = (wl >= sd.wavelengths[0]) & (wl <= sd.wavelengths[-1])
    return np.where(inside, values, 0.0)


def integration_weights(wavelengths: object) -> np.ndarray:
    """Quadrature weights Δλ (nm) for sums over ``wavelengths``, shape (L,).

    Uniform grids get the constant step (a Riemann sum, as colour-science's "Integration" method
    of ``sd_to_XYZ``); non-uniform grids get trapezoid weights.
    """
    wl = validate_wavelengths(wavelengths)
    d = np.diff(wl)
    if np.allclose(d, d[0], rtol=1e-6, atol=1e-9):
        return np.full(wl.shape, d[0])
    w = np.empty_like(wl)
    w[0], w[-1] = d[0] / 2, d[-1] / 2
    w[1:-1] = (d[:-1] + d[1:]) / 2
    return w


def xyz_weights(
    wavelengths: object | None = None,
    *,
    observer: str = DEFAULT_OBSERVER,
    scale: float = K_M,
) -> np.ndarray:
    """Matrix ``W (L, 3)`` with ``XYZ = spectra (..., L) @ W``.

    ``W = scale · cmf(λ) · Δλ``; the default ``scale = 683 lm/W`` gives absolute XYZ (cd/m²) from
    spectral radiance in W·sr⁻¹·m⁻²·nm⁻¹.
    """
    wl = _wl(wavelengths)
    return scale * cmfs(wl, observer) * integration_weights(wl)[:, None]


def radiance_to_xyz(
    radiance: object, wavelengths: object | None = None, *, observer: str = DEFAULT_OBSERVER
) -> np.ndarray:
    """Absolute CIE XYZ (Y in cd/m²) of spectral radiance (..., L) in W·sr⁻¹·m⁻²·nm⁻¹."""
    return np.asarray(radiance, dtype=np.float64) @ xyz_weights(wavelengths, observer=observer)


def reflectance_to_xyz(
    reflectance: object,
    illuminant_spd: object,
    wavelengths: object | None = None,
    *,
    observer: str = DEFAULT_OBSERVER,
) -> np.ndarray:
    """Relative XYZ (the perfect reflecting diffuser has Y = 100) of reflectances (..., L) under
    an illuminant (L,), as CIE 015:2018 §7 (Riemann sum on the given grid)."""
    W = xyz_weights(wavelengths, observer=observer, scale=1.0)
    e = np.asarray(illuminant_spd, dtype=np.float64)
    k = 100.0 / (e @ W[:, 1])
    return k * (np.asarray(reflectance, dtype=np.float64) * e) @ W


def xyz_to_xy(xyz: object) -> np.ndarray:
    """CIE 1931 xy chromaticity (..., 2) of XYZ (..., 3) (colour.XYZ_to_xy)."""
    import colour

    return np.asarray(colour.XYZ_to_xy(np.asarray(xyz, dtype=np.float64)))


def xyz_to_uv_prime(xyz: object) -> np.ndarray:
    """CIE 1976 UCS u′v′ chromaticity (..., 2) of XYZ (..., 3) (colour.xy_to_Luv_uv)."""
    import colour

    return np.asarray(colour.xy_to_Luv_uv(xyz_to_xy(xyz)))


def delta_uv_prime(xyz_a: object, xyz_b: object) -> np.ndarray:
    """Euclidean distance Δu′v′ between two colours, (...,)."""
    return np.linalg.norm(xyz_to_uv_prime(xyz_a) - xyz_to_uv_prime(xyz_b), axis=-1)


def xyz_to_lab(xyz: object, white_xyz: object) -> np.ndarray:
    """CIE 1976 L*a*b* (..., 3) of XYZ (..., 3) against the reference white ``white_xyz`` (3,).

    Both in the same (absolute or relative) units: the colour is divided by the white's Y, and
    the white's chromaticity is the Lab reference (colour.XYZ_to_Lab).
    """
    import colour

    w = np.asarray(white_xyz, dtype=np.float64)
    if w.shape != (3,) or not np.all(np.isfinite(w)) or w[1] <= 0:
        raise InputError(f"reference white must be a finite XYZ with Y > 0, got {w}",
                         field="white_xyz")
    x = np.asarray(xyz, dtype=np.float64) / w[1]
    return np.asarray(colour.XYZ_to_Lab(x, colour.XYZ_to_xy(w)))


def delta_e00(lab_a: object, lab_b: object) -> np.ndarray:
    """CIEDE2000 colour difference (CIE 142-2001; Sharma et al. 2005) via colour.delta_E."""
    import colour

    return np.asarray(colour.delta_E(np.asarray(lab_a, np.float64), np.asarray(lab_b, np.float64),
                                     method="CIE 2000"))


def daylight_coefficients(spd: object, wavelengths: object | None = None) -> tuple[float, float]:
    """Least-squares CIE daylight coefficients (M1, M2) of a spectrum (L,).

    Fits ``spd ≈ k (S0 + M1 S1 + M2 S2)`` with the CIE daylight basis functions S0, S1, S2
    (CIE 015:2018 Table 6, from colour-science) over the grid, and returns (M1, M2). This
    parametrises daylight-like environment spectra by two numbers.
    """
    import colour

    wl = _wl(wavelengths)
    basis = colour.colorimetry.SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES
    inside = (wl >= 300.0) & (wl <= 830.0)
    S = np.stack([np.asarray(basis[n][wl[inside]], np.float64) for n in ("S0", "S1", "S2")], -1)
    s = np.asarray(spd, dtype=np.float64)[inside]
    coef, *_ = np.linalg.lstsq(S, s, rcond=None)
    return float(coef[1] / coef[0]), float(coef[2] / coef[0])

"""Lifting RGB to spectra (spectral upsampling) with colour-science.

Methods:

* ``"mallett2019"`` (default): Mallett & Yuksel, "Spectral Primary Decomposition for Rendering
  with sRGB Reflectance", EGSR 2019, via ``colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019``.
  A spectrum is ``rgb @ B`` with three non-negative basis spectra ``B (3, L)`` that sum to 1 at
  every wavelength, so the lift is LINEAR in RGB: it commutes with filtering, downsampling and
  prefiltering of an environment map, and is computed for a whole image by one matrix product.
  Under CIE D65 the basis reproduces sRGB exactly up to colour's tabulation (round-trip error
  ~1e-3). It covers the sRGB gamut with reflectances in [0, 1].
* ``"jakob2019"``: Jakob & Hanika, "A Low-Dimensional Function Space for Efficient Spectral
  Upsampling", CGF 2019 (colour's ``find_coefficients_Jakob2019`` and ``sd_Jakob2019``): smooth
  sigmoid spectra, more saturated and always within [0, 1] as reflectances, but NOT linear in
  RGB, so a lifted map must not be filtered/downsampled spectrally as if it were (filter the
  RGB first, then lift). colour's optimiser runs once per distinct colour (slow), so it suits
  material colours and small images, not whole environment maps.

Reflectance vs emission: ``emission=False`` returns reflectance-like spectra whose colour under
CIE D65 (the sRGB white) is the input. ``emission=True`` returns spectral radiance
(W·sr⁻¹·m⁻²·nm⁻¹): the reflectance spectrum times the D65 spectrum, scaled so that an RGB value
of (1, 1, 1) has luminance ``luminance_scale`` cd/m² (683 lm/W), i.e. absolute XYZ of the result
is ``luminance_scale · M_sRGB→XYZ · rgb``.

Values above 1 and out-of-gamut colours (HDR policy): Mallett–Yuksel is linear, so an HDR value
``rgb = s · rgb'`` lifts to ``s ·`` (lift of ``rgb'``) exactly: values > 1 need no treatment.
Negative components (colours outside the sRGB gamut, e.g. from a wider-gamut ``colourspace``)
have no non-negative spectrum in this basis; with ``negative="clip"`` (default) they are clipped
to 0 before lifting (spectra stay >= 0; the colour is desaturated towards the gamut boundary, and
linearity holds only among in-gamut colours); ``negative="keep"`` keeps exact linearity and may
produce negative spectral values; ``negative="error"`` raises. For Jakob–Hanika, an RGB with
maximum ``m`` is lifted as ``s · sigmoid(rgb / s)`` with ``s = max(1, m)`` for reflectance and
``s = 2m`` for emission (so the fitted colour has maximum 0.5, where the sigmoid model is
accurate, as pbrt-v4 does for illuminants).
"""

from __future__ import annotations

import functools
import os

import numpy as np

from .._runtime.errors import InputError
from ..color import default_wavelengths, validate_wavelengths

__all__ = [
    "METHODS",
    "mallett2019_basis",
    "rgb_to_spectra",
    "read_rgb_environment",
]

METHODS = ("mallett2019", "jakob2019")


def _wl(wavelengths: object | None) -> np.ndarray:
    return default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)


@functools.lru_cache(maxsize=16)
def _mallett_cached(wl: tuple[float, ...]) -> np.ndarray:
    import colour

    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    # colour's interpolation inside 380-780 nm (its tabulated range), constant outside
    out = np.asarray(basis[np.asarray(wl)], dtype=np.float64).T.copy()
    out.setflags(write=False)
    return out


def mallett2019_basis(wavelengths: object | None = None) -> np.ndarray:
    """The Mallett–Yuksel (2019) sRGB basis sampled on ``wavelengths``: (3, L), rows R, G, B.

    A reflectance for linear sRGB ``rgb (..., 3)`` is ``rgb @ basis``.
    """
    return _mallett_cached(tuple(float(x) for x in _wl(wavelengths)))


@functools.lru_cache(maxsize=16)
def _d65_cached(wl: tuple[float, ...]) -> tuple[np.ndarray, float]:
    """D65 on the grid and the factor c such that c · D65 has luminance 1 cd/m² (683 lm/W)."""
    from ..color import illuminant, xyz_weights

    w = np.asarray(wl)
    e = illuminant("D65", w)
    y = float(e @ xyz_weights(w)[:, 1])
    e.setflags(write=False)
    return e, 1.0 / y


def _to_srgb(rgb: np.ndarray, colourspace: str) -> np.ndarray:
    if colourspace == "sRGB":
        return rgb
    import colour

    if colourspace not in colour.RGB_COLOURSPACES:
        raise InputError(f"unknown RGB colourspace {colourspace!r}", field="colourspace")
    return np.asarray(colour.RGB_to_RGB(rgb, colourspace, "sRGB",
                                        chromatic_adaptation_transform="CAT02"))


def _jakob(rgb: np.ndarray, wl: np.ndarray, emission: bool) -> np.ndarray:
    import colour
    from colour.recovery import find_coefficients_Jakob2019, sd_Jakob2019

    flat = rgb.reshape(-1, 3)
    uniq, inverse = np.unique(flat, axis=0, return_inverse=True)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(cmfs.shape)
    shape = colour.SpectralShape(360.0, 830.0, 1.0)
    out = np.empty((uniq.shape[0], wl.size))
    for i, c in enumerate(uniq):
        m = float(c.max())
        if m <= 0:
            out[i] = 0.0
            continue
        s = 2.0 * m if emission else max(1.0, m)
        xyz = colour.RGB_to_XYZ(c / s, "sRGB", chromatic_adaptation_transform=None)
        coef, _ = find_coefficients_Jakob2019(xyz, cmfs, d65)
        sd = sd_Jakob2019(coef, shape)
        out[i] = s * np.interp(wl, sd.wavelengths, sd.values)
    return out[inverse.reshape(-1)].reshape(*rgb.shape[:-1], wl.size)


def rgb_to_spectra(
    rgb: object,
    wavelengths: object | None = None,
    *,
    method: str = "mallett2019",
    colourspace: str = "sRGB",
    emission: bool = False,
    luminance_scale: float = 1.0,
    negative: str = "clip",
) -> np.ndarray:
    """Lift linear RGB (..., 3) to spectra (..., L) on ``wavelengths`` (default grid).

    Args:
        rgb: linear (not gamma-encoded) RGB in ``colourspace``, any leading shape.
        method: ``"mallett2019"`` (linear; default) or ``"jakob2019"`` (see module doc).
        colourspace: a colour-science RGB colourspace name; converted to linear sRGB first
            (CAT02 adaptation when the whites differ).
        emission: False → reflectance-like spectra (unitless; D65 reproduces the colour);
            True → spectral radiance W·sr⁻¹·m⁻²·nm⁻¹ with RGB (1, 1, 1) at ``luminance_scale``
            cd/m².
        negative: ``"clip"``, ``"keep"`` or ``"error"``: out-of-gamut policy (module doc).

    Returns:
        float64 (..., L).
    """
    wl = _wl(wavelengths)
    try:
        x = np.asarray(rgb, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"not numeric ({exc})", field="rgb") from None
    if x.ndim == 0 or x.shape[-1] != 3:
        raise InputError(f"last axis must be 3 (R, G, B), got shape {x.shape}", field="rgb")
    if not np.all(np.isfinite(x)):
        raise InputError("contains NaN or infinite values", field="rgb")
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; use one of {METHODS}", field="method")
    if negative not in ("clip", "keep", "error"):
        raise InputError(f"must be 'clip', 'keep' or 'error', got {negative!r}",
                         field="negative")
    if not (np.isfinite(luminance_scale) and luminance_scale > 0):
        raise InputError(f"must be finite and > 0, got {luminance_scale}",
                         field="luminance_scale")
    x = _to_srgb(x, colourspace)
    if (x < 0).any():
        if negative == "error":
            raise InputError(f"{int((x < 0).any(-1).sum())} colour(s) outside the sRGB gamut "
                             "(negative components)", field="rgb")
        if negative == "clip" or method == "jakob2019":
            x = np.maximum(x, 0.0)
    if method == "mallett2019":
        spectra = x @ mallett2019_basis(wl)
    else:
        spectra = _jakob(x, wl, emission)
    if emission:
        e, c = _d65_cached(tuple(float(v) for v in wl))
        spectra = spectra * (luminance_scale * c * e)
    return spectra


def read_rgb_environment(
    path: str | os.PathLike[str],
    wavelengths: object | None = None,
    *,
    method: str = "mallett2019",
    colourspace: str = "sRGB",
    luminance_scale: float = 1.0,
    negative: str = "clip",
) -> tuple[np.ndarray, np.ndarray]:
    """Read an RGB OpenEXR environment map and lift it to spectral radiance.

    RGB value 1 is taken as ``luminance_scale`` cd/m² (RGB EXRs carry relative radiance; pass
    the absolute scale when it is known). Returns ``(wavelengths (L,), image (H, W, L) float32)``
    in W·sr⁻¹·m⁻²·nm⁻¹.
    """
    from ..io import read_rgb_exr

    wl = _wl(wavelengths)
    rgb = read_rgb_exr(path)
    try:
        spectra = rgb_to_spectra(rgb, wl, method=method, colourspace=colourspace, emission=True,
                                 luminance_scale=luminance_scale, negative=negative)
    except InputError as exc:
        raise InputError(exc.reason, path=path, field=exc.field) from None
    return wl, spectra.astype(np.float32)

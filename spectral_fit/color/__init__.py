"""Colour: wavelength grids and spectra, CIE colorimetry, display characterisation, spectral bases,
pictures (chromaticity diagrams, PNG).

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "DEFAULT_END_NM": "_spectra",
    "DEFAULT_OBSERVER": "_colorimetry",
    "DEFAULT_START_NM": "_spectra",
    "DEFAULT_STEP_NM": "_spectra",
    "Display": "_display",
    "DisplayImage": "_display",
    "EXTRAPOLATION_MARGIN_NM": "_spectra",
    "K_M": "_colorimetry",
    "SpectralBasis": "_basis",
    "chart_radiance": "_camera_sensitivities",
    "chromaticity_diagram": "_plots",
    "cmfs": "_colorimetry",
    "colour_sd": "_spectra",
    "daylight_coefficients": "_colorimetry",
    "decode": "_display",
    "default_wavelengths": "_spectra",
    "delta_e00": "_colorimetry",
    "delta_uv_prime": "_colorimetry",
    "display_linear": "_display",
    "encode": "_display",
    "estimate_camera_sensitivities": "_camera_sensitivities",
    "fit_display_csv": "_display",
    "gamut_fractions": "_display",
    "illuminant": "_colorimetry",
    "integration_weights": "_colorimetry",
    "light_source": "_colorimetry",
    "parse_spectrum_text": "_spectra",
    "pca_basis": "_basis",
    "radiance_to_xyz": "_colorimetry",
    "read_spectrum_csv": "_spectra",
    "reflectance_to_xyz": "_colorimetry",
    "reflectances_5nm": "_basis",
    "resample": "_spectra",
    "save_png": "_plots",
    "to_display": "_display",
    "training_spectra": "_basis",
    "validate_spectrum": "_spectra",
    "validate_wavelengths": "_spectra",
    "visual_weights": "_basis",
    "wavelength_grid": "_spectra",
    "xyz_to_lab": "_colorimetry",
    "xyz_to_uv_prime": "_colorimetry",
    "xyz_to_xy": "_colorimetry",
    "xyz_weights": "_colorimetry",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

"""RGB → spectra (Mallett & Yuksel 2019 default, Jakob & Hanika 2019 option), checked with
colour-science's own spectral integration and RGB conversions."""

from __future__ import annotations

import colour
import numpy as np
import OpenEXR
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.lighting import mallett2019_basis, read_rgb_environment, rgb_to_spectra

WL = np.arange(380.0, 781.0, 5.0)
SHAPE = colour.SpectralShape(380, 780, 5)
D65 = colour.SDS_ILLUMINANTS["D65"].copy().align(SHAPE)
CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(SHAPE)


def _reflectance_to_srgb(spectra):
    """colour's own pipeline: reflectance under D65 (ASTM-free 'Integration'), XYZ → sRGB."""
    xyz = np.array([colour.sd_to_XYZ(colour.SpectralDistribution(s, WL), CMFS, illuminant=D65,
                                     method="Integration") / 100.0 for s in spectra])
    return np.asarray(colour.XYZ_to_RGB(xyz, "sRGB", chromatic_adaptation_transform=None))


def _radiance_to_xyz(spectra):
    return np.array([colour.sd_to_XYZ(colour.SpectralDistribution(s, WL), CMFS, k=683.0,
                                      method="Integration") for s in spectra])


RGB = np.random.default_rng(0).uniform(0.02, 0.98, (12, 3))


def test_mallett_basis_matches_colour():
    """Our (3, L) matrix equals colour's RGB_to_sd_Mallett2019 applied colour by colour."""
    B = mallett2019_basis(WL)
    for rgb in RGB[:4]:
        sd = colour.recovery.RGB_to_sd_Mallett2019(rgb)
        assert np.allclose(rgb @ B, sd[WL], atol=1e-12)
    assert np.allclose(B.sum(0), 1.0, atol=1e-6)  # partition of unity: white → flat 1


def test_mallett_round_trip_reflectance():
    out = _reflectance_to_srgb(rgb_to_spectra(RGB, WL))
    assert np.abs(out - RGB).max() < 1e-3


def test_mallett_round_trip_emission_absolute():
    """Emission: absolute XYZ (683 lm/W) = luminance_scale · M_sRGB→XYZ · rgb, also for HDR."""
    rgb = RGB * np.array([[1.0], [30.0], [0.01], [1e3]] * 3)
    scale = 250.0
    L = rgb_to_spectra(rgb, WL, emission=True, luminance_scale=scale)
    xyz = _radiance_to_xyz(L)
    expected = scale * np.asarray(colour.RGB_to_XYZ(rgb, "sRGB",
                                                    chromatic_adaptation_transform=None))
    assert np.allclose(xyz, expected, rtol=2e-3, atol=1e-6 * scale)
    white = rgb_to_spectra([1.0, 1.0, 1.0], WL, emission=True, luminance_scale=scale)
    assert _radiance_to_xyz(white[None])[0, 1] == pytest.approx(scale, rel=1e-4)


def test_mallett_linearity_and_filtering():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.2, 3.0, (2, 5, 3))
    a, b = 0.7, -2.5
    for emission in (False, True):
        def up(v, emission=emission):
            return rgb_to_spectra(v, WL, emission=emission, negative="keep")
        assert np.allclose(up(a * x + b * y), a * up(x) + b * up(y), atol=1e-10)
    # a 2x2 box filter commutes with the lift (environment-map prefiltering)
    img = rng.uniform(0.0, 50.0, (4, 6, 3))
    lifted = rgb_to_spectra(img, WL, emission=True)
    pooled = lifted.reshape(2, 2, 3, 2, -1).mean((1, 3))
    assert np.allclose(pooled, rgb_to_spectra(img.reshape(2, 2, 3, 2, 3).mean((1, 3)), WL,
                                              emission=True), rtol=1e-12)


def test_negative_policies():
    rgb = np.array([[0.5, -0.1, 0.2]])
    clipped = rgb_to_spectra(rgb, WL)
    assert np.all(clipped >= 0)
    assert np.allclose(clipped, rgb_to_spectra([[0.5, 0.0, 0.2]], WL))
    assert np.any(rgb_to_spectra(rgb, WL, negative="keep") < clipped)
    with pytest.raises(InputError, match="gamut"):
        rgb_to_spectra(rgb, WL, negative="error")


def test_other_colourspace():
    """A Display-P3 colour inside the sRGB gamut lifts to the same XYZ as colour computes."""
    p3 = np.asarray(colour.RGB_to_RGB([0.4, 0.5, 0.3], "sRGB", "Display P3"))
    L = rgb_to_spectra(p3, WL, colourspace="Display P3", emission=True)
    xyz = _radiance_to_xyz(L[None])[0]
    ref = colour.RGB_to_XYZ(p3, "Display P3", chromatic_adaptation_transform=None)
    assert np.allclose(xyz, ref, rtol=3e-3)


def test_bad_input():
    with pytest.raises(InputError):
        rgb_to_spectra([[1.0, 2.0]], WL)
    with pytest.raises(InputError):
        rgb_to_spectra([[np.nan, 0, 0]], WL)
    with pytest.raises(InputError):
        rgb_to_spectra([[0.1, 0.2, 0.3]], WL, method="smits")
    with pytest.raises(InputError):
        rgb_to_spectra([[0.1, 0.2, 0.3]], WL, colourspace="nope")


def test_jakob_round_trip_and_range():
    rgb = np.array([[0.8, 0.1, 0.1], [0.1, 0.6, 0.2], [0.2, 0.3, 0.9], [0.8, 0.1, 0.1]])
    R = rgb_to_spectra(rgb, WL, method="jakob2019")
    assert np.all((R >= 0) & (R <= 1))
    assert np.array_equal(R[0], R[3])  # one solve per distinct colour
    assert np.abs(_reflectance_to_srgb(R) - rgb).max() < 5e-3
    # more saturated than Mallett-Yuksel for a saturated red: lower minimum
    assert R[0].min() < rgb_to_spectra(rgb[0], WL).min()
    L = rgb_to_spectra(rgb[:2] * 40.0, WL, method="jakob2019", emission=True)
    xyz = _radiance_to_xyz(L)
    ref = np.asarray(colour.RGB_to_XYZ(rgb[:2] * 40.0, "sRGB",
                                       chromatic_adaptation_transform=None))
    assert np.allclose(xyz, ref, rtol=1e-2)


def test_read_rgb_environment(tmp_path):
    rgb = np.random.default_rng(2).uniform(0.0, 4.0, (3, 6, 3)).astype(np.float32)
    p = tmp_path / "env.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                 {c: np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("RGB")}
                 ).write(str(p))
    wl, img = read_rgb_environment(p, luminance_scale=100.0)
    assert img.shape == (3, 6, wl.size) and img.dtype == np.float32
    xyz = _radiance_to_xyz(img.reshape(-1, wl.size).astype(np.float64))
    ref = 100.0 * np.asarray(colour.RGB_to_XYZ(rgb.reshape(-1, 3).astype(np.float64), "sRGB",
                                               chromatic_adaptation_transform=None))
    assert np.allclose(xyz, ref, rtol=2e-3, atol=1e-3)

"""Camera-aware lifting of RGB environment captures vs generic Mallett–Yuksel upsampling."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import illuminant, xyz_weights
from spectral_fit.lighting import (
    camera_lifter,
    camera_sensitivities,
    compare_lifting,
    lift_generic_mallett,
    simulate_capture,
    synthetic_environment,
)

WL = np.arange(380.0, 781.0, 5.0)


@pytest.fixture(scope="module")
def sens():
    return camera_sensitivities("Nikon 5100 (NPL)", WL)


@pytest.fixture(scope="module")
def lifter(sens):
    return camera_lifter(sens, WL, k=8)


def checker_environment(h=32, w=64):
    """The synthetic room plus a band of the 24 BabelColor ColorChecker patches (not in the
    prior's training set) at the horizon, half under D65, half under illuminant A."""
    img = synthetic_environment(h, w, WL)
    cc = colour.SDS_COLOURCHECKERS["BabelColor Average"]
    patches = np.stack([np.asarray(sd[WL]) for sd in cc.values()])
    d65 = illuminant("D65", WL) / 100 * 0.02
    a = illuminant("A", WL)
    a = a / np.interp(560, WL, a) * 0.02
    r0 = h // 2 - h // 8
    for j in range(w):
        img[r0:r0 + h // 8, j] = patches[(j * 24) // w] * (d65 if j < w // 2 else a) * 0.8
    return img


def test_camera_sensitivities(sens):
    assert sens.shape == (81, 3) and np.all(sens >= 0)
    assert sens[:, 1].max() == pytest.approx(1.0)
    raw = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    ratio = sens[WL == 550.0][0] / np.asarray(raw[550.0])
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)  # one common scale
    with pytest.raises(InputError):
        camera_sensitivities("Nokia 3310")


def test_simulate_capture_is_the_response_integral(sens):
    rng = np.random.default_rng(0)
    s = rng.uniform(0, 1, size=(4, 81))
    rgb = simulate_capture(s, sens, WL)
    np.testing.assert_allclose(rgb, np.einsum("nl,lk->nk", s, sens) * 5.0, rtol=1e-12)


def test_lifter_reproduces_camera_rgb_and_is_linear(sens, lifter):
    img = checker_environment(16, 32)
    rgb = simulate_capture(img, sens, WL)
    est, frac = lifter.lift(rgb)
    assert np.all(est >= 0)
    back = simulate_capture(est, sens, WL)
    rel = np.abs(back - rgb).sum(-1) / np.abs(rgb).sum(-1)
    assert rel.max() < 2e-3, rel.max()
    assert frac < 0.2
    lin, _ = lifter.lift(rgb, nonnegative=False)
    a, _ = lifter.lift(rgb[:2, :2], nonnegative=False)
    b, _ = lifter.lift(rgb[2:4, 2:4], nonnegative=False)
    c, _ = lifter.lift(2.0 * rgb[:2, :2] + 0.5 * rgb[2:4, 2:4], nonnegative=False)
    np.testing.assert_allclose(c, 2.0 * a + 0.5 * b, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(lin @ lifter.response.T, rgb, rtol=2e-3, atol=1e-12)


def test_generic_mallett_matches_colour_recovery(sens):
    """Our linear Mallett route equals colour's RGB_to_sd_Mallett2019 on the sRGB it computes,
    and reproduces the colour-corrected XYZ."""
    d65 = illuminant("D65", WL)
    s = d65 * 0.01 * (0.4 + 0.3 * np.exp(-(((WL - 520.0) / 60.0) ** 2)))
    rgb = simulate_capture(s, sens, WL)
    est = lift_generic_mallett(rgb, sens, WL)
    W = xyz_weights(WL)
    xyz = est @ W
    scale = 1.0 / (d65 @ W[:, 1])
    srgb = colour.XYZ_to_RGB(xyz, "sRGB")  # linear (no transfer function applied)
    ref = np.asarray(colour.recovery.RGB_to_sd_Mallett2019(srgb)[WL]) * d65 * scale
    np.testing.assert_allclose(est, ref, rtol=2e-4, atol=1e-12)
    # close to the true colour (the camera's CCM is not exact): ΔXYZ small
    np.testing.assert_allclose(xyz, s @ W, rtol=0.03)


def test_camera_aware_beats_generic_on_realistic_capture():
    res = compare_lifting(checker_environment(), WL, k=8)
    aw, gen = res["camera_aware"], res["generic_mallett"]
    print(f"camera-aware: dE00 mean {aw['dE00_mean']:.2f} p95 {aw['dE00_p95']:.2f} max "
          f"{aw['dE00_max']:.2f}, spectral RMS {aw['spectral_rms_mean']:.3f} "
          f"(420-680 nm {aw['spectral_rms_420_680_mean']:.3f}); generic Mallett: dE00 mean "
          f"{gen['dE00_mean']:.2f} p95 {gen['dE00_p95']:.2f} max {gen['dE00_max']:.2f}, "
          f"spectral RMS {gen['spectral_rms_mean']:.3f} "
          f"(420-680 nm {gen['spectral_rms_420_680_mean']:.3f}); projected "
          f"{res['projected_fraction']:.3f}")
    assert aw["rgb_rel_error_max"] < 2e-3
    assert aw["dE00_mean"] < gen["dE00_mean"]
    assert aw["dE00_max"] < gen["dE00_max"]


def test_bad_inputs(sens, lifter):
    with pytest.raises(InputError):
        camera_lifter(sens[:10], WL)
    with pytest.raises(InputError):
        camera_lifter(sens, WL, k=2)
    with pytest.raises(InputError):
        lifter.lift(np.array([[1.0, np.nan, 0.0]]))
    with pytest.raises(InputError):
        compare_lifting(np.ones((4, 8, 3)), WL)

"""Colour-matched compositing: camera models from sensitivities / a ColorChecker shot, and the
linear-light composite, against colour-science's own colorimetry."""

from __future__ import annotations

import colour
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("cv2")

from spectral_fit.color import illuminant, xyz_weights
from spectral_fit.live import (
    camera_model_from_colorchecker,
    camera_model_from_sensitivities,
    colorchecker_reflectances,
    composite,
    composite_pixels,
    sample_chart,
)

WL = np.arange(400.0, 701.0, 10.0)
D65_XY = colour.RGB_COLOURSPACES["sRGB"].whitepoint


def _reference_lab(radiance, white):
    """CIELAB (D65) of radiances as a colorimetric camera would show them: XYZ relative to
    the white, CAT02-adapted from the white to D65 (colour-science throughout)."""
    w = xyz_weights(WL)
    xyz, wxyz = radiance @ w, white @ w
    d65 = colour.xy_to_XYZ(D65_XY)
    xa = colour.chromatic_adaptation(xyz / wxyz[1], wxyz / wxyz[1], d65, method="Von Kries",
                                     transform="CAT02")
    return colour.XYZ_to_Lab(xa, D65_XY)


def _lab_of_linear_srgb(lin):
    return colour.XYZ_to_Lab(colour.RGB_to_XYZ(np.asarray(lin, np.float64), "sRGB"), D65_XY)


@pytest.mark.parametrize(("light", "camera", "mean_max"), [
    ("D65", "Nikon 5100 (NPL)", (1.5, 3.5)),
    ("A", "Nikon 5100 (NPL)", (1.5, 3.5)),
    ("D65", "Sigma SDMerill (NPL)", (2.5, 6.0)),
])
def test_sensitivity_model_matches_colorimetry(light, camera, mean_max):
    white = illuminant(light, WL) / 100.0 * 0.05  # radiance of a white reflector, W/(sr m² nm)
    m = camera_model_from_sensitivities(camera, WL, white, white_level=1.0)
    # the white reference is neutral at the exposure level
    np.testing.assert_allclose(np.asarray(m.linear_from_spectra(jnp.asarray(white))), 1.0,
                               atol=2e-6)
    # a grey patch stays neutral at its reflectance (linear camera)
    np.testing.assert_allclose(np.asarray(m.linear_from_spectra(jnp.asarray(0.2 * white))),
                               0.2, atol=1e-6)
    patches = colorchecker_reflectances(WL) * white
    de = colour.delta_E(_reference_lab(patches, white),
                        _lab_of_linear_srgb(m.linear_from_spectra(jnp.asarray(patches))),
                        method="CIE 2000")
    assert de.mean() < mean_max[0] and de.max() < mean_max[1]
    # the XYZ route (3x3 fitted on the same patches) is close to the spectral one
    lin_xyz = m.linear_from_xyz(jnp.asarray(patches @ xyz_weights(WL), jnp.float32))
    de2 = colour.delta_E(_lab_of_linear_srgb(lin_xyz),
                         _lab_of_linear_srgb(m.linear_from_spectra(jnp.asarray(patches))),
                         method="CIE 2000")
    assert de2.mean() < 2.0


def test_luther_camera_is_colorimetric():
    """Sensitivities that are a linear mix of the CMFs: both routes are exact (ΔE00 ≈ 0)."""
    from spectral_fit.color import cmfs

    mix = np.array([[0.9, 0.3, -0.1], [-0.2, 1.1, 0.1], [0.0, 0.05, 0.95]])
    sens = cmfs(WL) @ mix.T
    white = illuminant("A", WL) / 100.0 * 0.05
    m = camera_model_from_sensitivities(sens, WL, white, white_level=0.8)
    patches = colorchecker_reflectances(WL) * white
    lin = np.asarray(m.linear_from_spectra(jnp.asarray(patches)))
    ref = _reference_lab(patches, white)
    de = colour.delta_E(ref, _lab_of_linear_srgb(lin / 0.8), method="CIE 2000")
    assert de.max() < 0.05
    lin_x = np.asarray(m.linear_from_xyz(jnp.asarray(patches @ xyz_weights(WL))))
    np.testing.assert_allclose(lin_x, lin, atol=2e-4)


def test_colorchecker_shot_recovers_the_camera_matrix():
    """A synthetic camera (known 3x3 from XYZ + sRGB curve) photographs a chart in
    perspective; sampling the chart and fitting recovers the matrix."""
    import cv2

    rng = np.random.default_rng(3)
    white = illuminant("D65", WL) / 100.0 * 0.05
    xyz = (colorchecker_reflectances(WL) * white) @ xyz_weights(WL)
    m_true = np.array([[3.0, -1.4, -0.5], [-0.9, 1.9, 0.05], [0.05, -0.2, 1.05]]) * 0.9 / (
        white @ xyz_weights(WL))[1]
    lin = np.clip(xyz @ m_true.T, 0, 1)
    enc = colour.cctf_encoding(lin, function="sRGB")
    chart = np.repeat(np.repeat((enc * 255).reshape(4, 6, 3), 60, 0), 60, 1).astype(np.float32)
    dst = np.array([[150, 90], [600, 120], [580, 420], [130, 380]], np.float32)
    src = np.array([[0, 0], [360, 0], [360, 240], [0, 240]], np.float32)
    h = cv2.getPerspectiveTransform(src, dst)
    img = cv2.warpPerspective(chart, h, (720, 480), flags=cv2.INTER_LINEAR)
    img = np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8)
    vals = sample_chart(img, dst) / 255.0
    np.testing.assert_allclose(vals, enc, atol=0.01)
    m = camera_model_from_colorchecker(xyz, vals)
    ok = np.all((enc > 0.02) & (enc < 0.98), axis=1)
    got = np.asarray(m.linear_from_xyz(jnp.asarray(xyz[ok])))
    np.testing.assert_allclose(got, lin[ok], atol=6e-3)
    np.testing.assert_allclose(np.asarray(m.xyz_matrix), m_true, rtol=0.03,
                               atol=0.03 * np.abs(m_true).max())


def test_composite_in_linear_light():
    white = illuminant("D65", WL) / 100.0
    m = camera_model_from_sensitivities("Nikon 5100 (NPL)", WL, white)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    cg = rng.uniform(0.0, 1.0, (6, 5, 3)).astype(np.float32)
    cov = np.zeros((6, 5), np.float32)
    cov[1, :] = 1.0
    cov[2, :] = 0.5
    out = np.asarray(composite(jnp.asarray(frame), jnp.asarray(cg), jnp.asarray(cov), m))
    assert out.dtype == np.uint8
    untouched = cov == 0
    np.testing.assert_array_equal(out[untouched], frame[untouched])
    want1 = colour.cctf_encoding(cg[1].astype(np.float64), function="sRGB") * 255
    np.testing.assert_allclose(out[1], want1, atol=0.51)
    bg_lin = colour.cctf_decoding(frame[2] / 255.0, function="sRGB")
    want2 = colour.cctf_encoding(0.5 * cg[2] + 0.5 * bg_lin, function="sRGB") * 255
    np.testing.assert_allclose(out[2], want2, atol=0.51)


def test_composite_bool_mask_matches_full_coverage():
    """The renderer's bool mask takes the no-decode path: covered pixels are encode(cg) as with
    coverage 1.0, the rest the frame's own bytes."""
    white = illuminant("D65", WL) / 100.0
    m = camera_model_from_sensitivities("Nikon 5100 (NPL)", WL, white)
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    cg = rng.uniform(-0.1, 1.2, (7, 9, 3)).astype(np.float32)
    mask = rng.random((7, 9)) < 0.4
    out = np.asarray(composite(jnp.asarray(frame), jnp.asarray(cg), jnp.asarray(mask), m))
    ref = np.asarray(composite(jnp.asarray(frame), jnp.asarray(cg),
                               jnp.asarray(mask.astype(np.float32)), m))
    np.testing.assert_array_equal(out, ref)
    np.testing.assert_array_equal(out[~mask], frame[~mask])
    want = colour.cctf_encoding(np.clip(cg[mask], 0, 1).astype(np.float64), function="sRGB")
    np.testing.assert_allclose(out[mask], want * 255, atol=0.51)


def test_composite_pixels_matches_the_full_image_composite():
    """Writing a list of covered pixels (the renderer's PixelFrame: values, flat index, valid)
    into the frame gives the same bytes as compositing the full CG image with the bool mask;
    invalid slots write nothing."""
    white = illuminant("D65", WL) / 100.0
    m = camera_model_from_sensitivities("Nikon 5100 (NPL)", WL, white)
    rng = np.random.default_rng(2)
    h, w = 7, 9
    frame = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    cg = rng.uniform(-0.1, 1.2, (h, w, 3)).astype(np.float32)
    mask = rng.random((h, w)) < 0.4
    idx = np.flatnonzero(mask)
    n = idx.size
    # slots: the covered pixels, then empty slots (index 0, garbage values, valid False)
    index = np.concatenate([idx, np.zeros(5, np.int64)]).astype(np.int32)
    values = np.concatenate([cg.reshape(-1, 3)[idx], np.full((5, 3), 0.7, np.float32)])
    valid = np.arange(n + 5) < n
    out = np.asarray(composite_pixels(jnp.asarray(frame), jnp.asarray(values),
                                      jnp.asarray(index), jnp.asarray(valid), m))
    ref = np.asarray(composite(jnp.asarray(frame), jnp.asarray(cg), jnp.asarray(mask), m))
    np.testing.assert_array_equal(out, ref)
    np.testing.assert_array_equal(out[~mask], frame[~mask])


def test_white_reference_closed_forms():
    """E(+Y)/π of a white Lambertian facing up: a uniform map of radiance L gives L; a map
    bright only in the lower hemisphere gives 0; L ∝ cosθ (upper) gives (2/3)·L₀."""
    from spectral_fit.lighting import white_reference

    hm, wm = 64, 128
    theta = (np.arange(hm) + 0.5) * np.pi / hm
    uniform = np.full((hm, wm, 2), [0.3, 1.7])
    np.testing.assert_allclose(white_reference(uniform), [0.3, 1.7], rtol=1e-3)
    lower = np.where((theta > np.pi / 2)[:, None, None], 1.0, 0.0) * np.ones((hm, wm, 1))
    np.testing.assert_allclose(white_reference(lower), [0.0], atol=1e-12)
    cosine = np.clip(np.cos(theta), 0, None)[:, None, None] * np.ones((hm, wm, 1))
    np.testing.assert_allclose(white_reference(cosine), [2 / 3], rtol=1e-3)


def _disc_slots(h, w, cy, cx, r):
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    mask = (ii + 0.5 - cy) ** 2 + (jj + 0.5 - cx) ** 2 < r * r
    idx = np.flatnonzero(mask).astype(np.int32)
    return mask, idx


@pytest.mark.parametrize("h, w, cy, cx, radius, sigma", [
    (48, 64, 20.0, 30.0, 9.0, 1.3),
    (100, 150, 12.0, 140.0, 8.0, 0.6),  # the disc cut by two frame edges
    (160, 240, 100.0, 90.0, 34.0, 2.0),
])
def test_composite_pixels_gives_the_cg_the_camera_blur(h, w, cy, cx, radius, sigma):
    """With ``blur_px`` the CG and its coverage are blurred in linear light before the
    composite: against SciPy's Gaussian filter (same ±3σ support, zeros outside) and
    colour-science's sRGB curves; pixels the blurred CG does not reach keep their bytes."""
    import dataclasses

    from scipy.ndimage import gaussian_filter

    white = illuminant("D65", WL) / 100.0
    sharp = camera_model_from_sensitivities("Nikon 5100 (NPL)", WL, white)
    m = dataclasses.replace(sharp, blur_px=sigma)
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mask, idx = _disc_slots(h, w, cy, cx, radius)
    cg = np.clip(rng.normal(0.5, 0.2, (idx.size, 3)), 0, 1).astype(np.float32)
    valid = np.ones(idx.size, bool)
    out = np.asarray(composite_pixels(jnp.asarray(frame), jnp.asarray(cg), jnp.asarray(idx),
                                      jnp.asarray(valid), m)).astype(int)
    layer = np.zeros((h * w, 4))
    layer[idx, :3] = cg
    layer[idx, 3] = 1.0
    r = int(np.ceil(3 * sigma))
    blurred = np.stack([gaussian_filter(layer.reshape(h, w, 4)[..., c], sigma, mode="constant",
                                        truncate=r / sigma) for c in range(4)], -1)
    a = blurred[..., 3:]
    bg = colour.cctf_decoding(frame / 255.0, function="sRGB")
    want = colour.cctf_encoding(np.clip(bg * (1 - a) + blurred[..., :3], 0, 1),
                                function="sRGB") * 255
    reached = a[..., 0] > 1 / 512
    assert np.abs(out[reached] - want[reached]).max() <= 1
    np.testing.assert_array_equal(out[~reached], frame[~reached])
    # the blur reaches past the silhouette, and softens it: the rim is a mix of CG and video
    assert np.all(reached[mask]) and reached.sum() > mask.sum() + 2 * np.pi * radius
    rim = reached & ~mask
    assert np.abs(out[rim] - frame[rim]).max() > 20
    # the full-image composite gives the same bytes for the same CG and mask
    image = np.zeros((h * w, 3), np.float32)
    image[idx] = cg
    full = composite(jnp.asarray(frame), jnp.asarray(image.reshape(h, w, 3)),
                     jnp.asarray(mask), m)
    np.testing.assert_array_equal(np.asarray(full), out)


@pytest.mark.parametrize("h, w, cy, cx, radius", [
    (64, 80, 32.0, 40.0, 20.0),
    (128, 160, 40.0, 50.0, 22.0),
])
def test_composite_pixels_gives_the_cg_the_camera_noise(h, w, cy, cx, radius):
    """With ``noise`` the CG gets Gaussian noise of that σ (8-bit levels) where it covers the
    pixel; the same frame gets the same noise, another frame other noise."""
    import dataclasses

    white = illuminant("D65", WL) / 100.0
    sharp = camera_model_from_sensitivities("Nikon 5100 (NPL)", WL, white)
    noisy = dataclasses.replace(sharp, noise=3.0)
    rng = np.random.default_rng(6)
    frame = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mask, idx = _disc_slots(h, w, cy, cx, radius)
    cg = np.full((idx.size, 3), 0.4, np.float32)
    args = (jnp.asarray(cg), jnp.asarray(idx), jnp.asarray(np.ones(idx.size, bool)))
    base = np.asarray(composite_pixels(jnp.asarray(frame), *args, sharp)).astype(float)
    out = np.asarray(composite_pixels(jnp.asarray(frame), *args, noisy)).astype(float)
    level = colour.cctf_encoding(0.4, function="sRGB") * 255  # the CG's unrounded level
    assert np.all(np.abs(base[mask] - level) <= 0.5)
    d = out[mask] - level
    assert d.size > 3000
    assert abs(d.mean()) < 0.15 and 2.8 < d.std() < 3.2  # rounding adds 1/12 of a level²
    np.testing.assert_array_equal(out[~mask], frame[~mask])
    again = np.asarray(composite_pixels(jnp.asarray(frame), *args, noisy))
    np.testing.assert_array_equal(again, out)
    other = frame.copy()
    other[0, 0] ^= 1
    moved = np.asarray(composite_pixels(jnp.asarray(other), *args, noisy)).astype(float)
    assert np.mean(moved[mask] != out[mask]) > 0.5

"""Display output against colour-science and closed forms."""

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import Display, decode, encode, fit_display_csv, to_display


def test_srgb_curve_matches_iec_61966_2_1_in_colour():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(encode(x), colour.models.eotf_inverse_sRGB(x), atol=1e-12)
    np.testing.assert_allclose(decode(x), colour.models.eotf_sRGB(x), atol=1e-12)
    g = Display.srgb().__class__.from_colourspace("sRGB", tone="gamma", gamma=2.2)
    np.testing.assert_allclose(decode(encode(x, g), g), x, atol=1e-12)


def test_srgb_encoding_of_jax_arrays_matches_iec_61966_2_1_and_its_derivative():
    """The JAX path's x^(1/2.4) (float bits + a degree-7 polynomial, not exp/log) against
    colour's IEC 61966-2-1 encoding on a dense grid, every power of two of its range and the
    segment join; its gradient against the closed form d/dx 1.055 x^(1/2.4); float64 arrays
    (x64 mode) exact."""
    pow2 = np.float32(2.0) ** -np.arange(10.0, dtype=np.float32)
    below = np.nextafter(pow2, np.float32(0.0))  # the largest mantissa of the binade below
    x = np.concatenate([np.linspace(0.0, 1.0, 200_001), np.geomspace(1e-5, 1.0, 20_001),
                        pow2, below, [0.0031308, 0.0031309]]).astype(np.float32)
    want = colour.models.eotf_inverse_sRGB(x.astype(np.float64))
    got = np.asarray(jax.jit(encode)(jnp.asarray(x)), np.float64)
    assert np.abs(got - want).max() < 2e-7
    assert got.min() >= 0.0 and got.max() <= 1.0  # drive values stay in range
    assert float(jax.jit(encode)(jnp.float32(1.5))) <= 1.0
    xs = np.array([0.001, 0.0031309, 0.01, 0.2, 0.5, 0.9], np.float32)
    g = np.asarray(jax.grad(lambda a: encode(a).sum())(jnp.asarray(xs)))
    d = xs.astype(np.float64)
    want_g = np.where(d <= 0.0031308, 12.92, 1.055 / 2.4 * d ** (1.0 / 2.4 - 1.0))
    np.testing.assert_allclose(g, want_g, rtol=2e-6)
    with jax.enable_x64(True):  # float64 arrays keep the exact power
        x64 = np.linspace(0.0, 1.0, 10_001)
        got64 = np.asarray(jax.jit(encode)(jnp.asarray(x64, jnp.float64)))
        assert got64.dtype == np.float64
        np.testing.assert_allclose(got64, colour.models.eotf_inverse_sRGB(x64), atol=1e-12)


def test_white_and_primaries_map_to_display_corners():
    d = Display.srgb()
    white = colour.xy_to_XYZ(d.white_xy) * 250.0  # a 250 cd/m² white shown at exposure 250
    out = to_display(white, exposure_luminance=250.0)
    np.testing.assert_allclose(out.rgb, [1.0, 1.0, 1.0], atol=1e-6)
    prims = d.rgb_to_xyz.T * 0.5  # XYZ of each primary at half drive (linear)
    out = to_display(prims, exposure_luminance=1.0)
    np.testing.assert_allclose(out.linear, 0.5 * np.eye(3), atol=1e-9)
    assert float(out.out_of_gamut_fraction) == 0.0


def test_matches_colour_xyz_to_srgb():
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0.05, 0.6, (50, 3))
    ref = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False, chromatic_adaptation_transform=None)
    out = to_display(xyz, exposure_luminance=1.0)
    # colour uses IEC 61966-2-1's matrix rounded to 4 decimals; ours is derived from the
    # primaries (the normalised primary matrix), so they agree to the rounding
    np.testing.assert_allclose(out.linear, ref, atol=5e-4)


def test_clipping_policy_reports_fractions():
    # monochromatic 520 nm light lies outside the sRGB gamut (negative red)
    cmf = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"][520.0]
    xyz = np.stack([cmf * 0.3, colour.xy_to_XYZ([0.3127, 0.329]) * 3.0,
                    colour.xy_to_XYZ([0.3127, 0.329]) * 0.5, colour.xy_to_XYZ([0.3127, 0.329])])
    out = to_display(xyz, exposure_luminance=1.0)
    assert out.linear[0, 0] < 0
    assert float(out.below_zero_fraction) == pytest.approx(0.25)
    assert float(out.overexposed_fraction) == pytest.approx(0.25)
    assert float(out.out_of_gamut_fraction) == pytest.approx(0.5)
    assert np.all((out.rgb >= 0) & (out.rgb <= 1))
    masked = to_display(xyz, exposure_luminance=1.0, mask=np.array([1, 0, 0, 0], bool))
    assert float(masked.out_of_gamut_fraction) == 1.0


def test_black_level():
    d = Display.from_colourspace("sRGB", black_level=0.01)
    white = colour.xy_to_XYZ(d.white_xy)
    out = to_display(np.stack([white * 0.01, white]), exposure_luminance=1.0, display=d)
    np.testing.assert_allclose(out.linear, [[0, 0, 0], [1, 1, 1]], atol=1e-9)


def test_cat02_adaptation_maps_scene_white_to_display_white():
    a_xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["A"]
    out = to_display(colour.xy_to_XYZ(a_xy), exposure_luminance=1.0, scene_white_xy=a_xy)
    np.testing.assert_allclose(out.linear, [1.0, 1.0, 1.0], atol=1e-6)


def test_jit_matches_numpy_and_has_finite_gradient():
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0.0, 1.2, (64, 3))
    ref = to_display(xyz, exposure_luminance=1.0).rgb
    f = jax.jit(lambda x: to_display(x, exposure_luminance=1.0).rgb)
    np.testing.assert_allclose(f(jnp.asarray(xyz, jnp.float32)), ref, atol=2e-6)
    g = jax.grad(lambda x: to_display(x, exposure_luminance=1.0).rgb.sum())(
        jnp.zeros((2, 3)) + 1e-9)
    assert np.all(np.isfinite(g))


def _write_patches(path, disp, white_lum, gamma, black, noise=0.0, seed=3):
    rng = np.random.default_rng(seed)
    ramps = [np.array(v) for v in ([0, 0, 0], [1, 1, 1])]
    for c in range(3):
        for t in (0.25, 0.5, 0.75, 1.0):
            v = np.zeros(3)
            v[c] = t
            ramps.append(v)
    ramps += [rng.uniform(0, 1, 3) for _ in range(10)]
    M = disp.rgb_to_xyz * white_lum * (1 - black)
    bxyz = colour.xy_to_XYZ(disp.white_xy) * white_lum * black
    lines = ["R,G,B,X,Y,Z"]
    for v in ramps:
        xyz = M @ v**gamma + bxyz
        xyz = xyz * (1 + noise * rng.standard_normal(3))
        lines.append(",".join(f"{x:.9g}" for x in (*v, *xyz)))
    path.write_text("\n".join(lines) + "\n")


def test_fit_display_recovers_known_characterisation(tmp_path):
    true = Display.from_colourspace("Display P3")
    p = tmp_path / "patches.csv"
    _write_patches(p, true, white_lum=150.0, gamma=2.3, black=0.002)
    fit = fit_display_csv(p)
    np.testing.assert_allclose(fit.primaries_xy, true.primaries_xy, atol=1e-5)
    np.testing.assert_allclose(fit.white_xy, true.white_xy, atol=1e-5)
    assert fit.gamma == pytest.approx(2.3, abs=1e-4)
    assert fit.black_level == pytest.approx(0.002, abs=1e-5)
    assert fit.white_luminance == pytest.approx(150.0, rel=1e-5)
    _write_patches(p, true, white_lum=150.0, gamma=2.3, black=0.002, noise=0.003)
    noisy = fit_display_csv(p)
    np.testing.assert_allclose(noisy.primaries_xy, true.primaries_xy, atol=0.01)
    assert noisy.gamma == pytest.approx(2.3, abs=0.05)


@pytest.mark.parametrize(
    "text, match",
    [
        ("R,G,B,X,Y\n", "missing"),
        ("R,G,B,X,Y,Z\n0,0,0,1,1\n", "line 2: expected 6 cells"),
        ("R,G,B,X,Y,Z\n0,0,x,1,1,1\n", "line 2: B: not a number"),
        ("R,G,B,X,Y,Z\n0,0,2,1,1,1\n", "line 2: B: drive value 2.0 outside"),
        ("R,G,B,X,Y,Z\n0,0,1,1,-1,1\n", "line 2: Y: negative"),
        ("R,G,B,X,Y,Z\n0,0,1,1,nan,1\n", "line 2: Y: not finite"),
        ("R,G,B,X,Y,Z\n0,0,1,1,1,1\n", "at least 8 patches"),
    ],
)
def test_fit_display_errors(tmp_path, text, match):
    p = tmp_path / "d.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        fit_display_csv(p)


def test_display_validation():
    with pytest.raises(InputError, match="tone"):
        Display.from_colourspace("sRGB", tone="log")
    with pytest.raises(InputError, match="black"):
        Display.from_colourspace("sRGB", black_level=1.0)
    with pytest.raises(InputError, match="collinear"):
        Display(primaries_xy=[[0.1, 0.1], [0.2, 0.2], [0.3, 0.3]], white_xy=[0.3, 0.3])

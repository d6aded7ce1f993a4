"""The synthetic spectral environment map, the bundled file, and ``spectral-fit view``."""

from __future__ import annotations

import json

import colour
import numpy as np
import pytest
from helpers import STUDIO_ROOM
from PIL import Image

from spectral_fit.cli import main
from spectral_fit.io import read_spectral_exr, read_spectral_exr_ex
from spectral_fit.lighting import _synthetic as se

SHAPE = colour.SpectralShape(380, 780, 5)
CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(SHAPE)
WL = np.arange(380.0, 781.0, 5.0)


def luminance(spectrum) -> float:
    """Luminance (cd/m²) by colour-science: 683 lm/W, CIE 1931 2°, 'Integration' method."""
    sd = colour.SpectralDistribution(np.asarray(spectrum, np.float64), WL)
    return float(colour.sd_to_XYZ(sd, CMFS, k=683.0, method="Integration")[1])


def direction(row, col, w, h):
    """Our equirectangular mapping, written out independently: u = φ/2π, v = θ/π, texel centres
    at k + 0.5."""
    phi = 2 * np.pi * (col + 0.5) / w
    theta = np.pi * (row + 0.5) / h
    return np.array([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)])


@pytest.fixture(scope="module")
def env():
    return se.make_environment(256, 128)


def test_deterministic_finite_nonnegative(env):
    wl, img = env
    assert np.array_equal(wl, WL)
    assert img.shape == (128, 256, 81) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and img.min() >= 0.0
    _, again = se.make_environment(256, 128)
    assert np.array_equal(img, again)


def test_absolute_scale_emitters(env):
    _, img = env
    # panel: direction straight at its centre (x=0, z=0.8, y=1.6)
    target = np.array([0.0, 1.6, 0.8])
    d = target / np.linalg.norm(target)
    theta, phi = np.arccos(d[1]), np.arctan2(d[0], -d[2]) % (2 * np.pi)
    row, col = int(theta / np.pi * 128), int(phi / (2 * np.pi) * 256)
    assert luminance(img[row, col]) == pytest.approx(5000.0, rel=1e-4)
    # the lamp: brightest texel, fully covered -> the documented 20 000 cd/m2
    r, c = np.unravel_index(np.argmax(img.sum(-1)), img.shape[:2])
    assert luminance(img[r, c]) == pytest.approx(20000.0, rel=1e-4)


def test_sky_through_window_is_cie_overcast(env):
    """Texels through the window: L = 3000 (1 + 2 cos θ)/3 cd/m² (CIE overcast sky), the sky's
    chromaticity that of CIE daylight at 6500 K; below the horizon the foliage ground."""
    _, img = env
    xy_d = colour.temperature.CCT_to_xy_CIE_D(6500.0)
    checked = 0
    for row in range(128):
        col = 63  # u ≈ 0.248: looking along +X
        d = direction(row, col, 256, 128)
        # hit on the x = 2 wall, far from the window edges (> 1 texel ≈ 5 cm there)
        t = 2.0 / d[0]
        y, z = t * d[1], t * d[2]
        if not (-0.3 < y < 1.1 and -0.9 < z < 0.9) or abs(d[1]) < 0.03:
            continue
        L = luminance(img[row, col])
        if d[1] > 0:
            assert L == pytest.approx(3000.0 * (1 + 2 * d[1]) / 3, rel=1e-3)
            xyz = colour.sd_to_XYZ(colour.SpectralDistribution(img[row, col].astype(float), WL),
                                   CMFS, k=683.0, method="Integration")
            assert np.allclose(colour.XYZ_to_xy(xyz), xy_d, atol=2e-3)
        else:
            rho = colour.SDS_COLOURCHECKERS["BabelColor Average"]["foliage"][WL]
            sky = colour.sd_CIE_illuminant_D_series(xy_d)[WL]
            expected = 3000.0 * 7 / 9 * luminance(rho * sky) / luminance(sky)
            assert L == pytest.approx(expected, rel=1e-3)
        checked += 1
    assert checked >= 10


def test_lamp_direction_matches_mapping(env):
    _, img = env
    r, c = np.unravel_index(np.argmax(img.sum(-1)), img.shape[:2])
    d = direction(r, c, 256, 128)
    lamp = se.LAMP_POSITION / np.linalg.norm(se.LAMP_POSITION)
    angle = np.degrees(np.arccos(np.clip(d @ lamp, -1, 1)))
    assert angle < 1.0  # within one texel (1.4°) of the documented lamp direction


def test_wall_radiance_independent(env):
    """One texel on the +Z wall recomputed from the documented model (point-source lamp and
    panel, integrating-sphere indirect term) at its centre direction."""
    _, img = env
    row, col = 64, 128  # looking at +Z, just below the horizon
    d = direction(row, col, 256, 128)
    x = d * (2.5 / d[2])
    n = np.array([0.0, 0.0, -1.0])
    cc = colour.SDS_COLOURCHECKERS["BabelColor Average"]
    rho = cc["bluish green"][WL]
    lamp = colour.SDS_LIGHT_SOURCES["60 A/W (Soft White)"][WL]
    lamp = 20000.0 * lamp / luminance(lamp)
    panel = colour.SDS_LIGHT_SOURCES["F32T8/TL841 (Triphosphor)"][WL]
    panel = 5000.0 * panel / luminance(panel)
    i_lamp = np.pi * 0.06**2 * lamp
    i_panel = 0.72 * panel
    lp = np.array([-1.2, 0.25, -1.5]) - x
    e = i_lamp * max(0.0, n @ lp / np.linalg.norm(lp)) / (lp @ lp)
    pp = np.array([0.0, 1.6, 0.8]) - x
    dp = np.linalg.norm(pp)
    e = e + i_panel * max(0.0, pp[1] / dp) * max(0.0, n @ pp / dp) / dp**2
    area = 2 * (4 * 2.8 + 2.8 * 5 + 4 * 5)
    e = e + (4 * np.pi * i_lamp + np.pi * i_panel) * 0.4 / (area * 0.6)
    expected = rho * e / np.pi
    # the texel averages 4x4 sub-samples of a smooth field: ~1e-3 relative
    assert np.allclose(img[row, col], expected, rtol=5e-3)


def test_bundled_file_matches_generator(env):
    assert STUDIO_ROOM.stat().st_size < 5_000_000
    r = read_spectral_exr_ex(STUDIO_ROOM)
    assert r.kind == "emissive"
    assert r.attributes["emissiveUnits"] == "W.m^-2.sr^-1"
    wl, img = env
    assert np.array_equal(r.wavelengths, wl)
    # stored as half floats: compare with the generator rounded to half
    assert np.allclose(r.image, img.astype(np.float16).astype(np.float32), rtol=1e-3,
                       atol=1e-7)
    assert np.allclose(r.image, img, rtol=1e-3, atol=1e-7)


def test_bundled_sunny_map_matches_its_script():
    """measurements/environment/sunny.exr is what scripts/make_sun_environment.py writes (to
    half-float rounding); its sun, the brightest texel, lies in the direction the script
    gives (within a texel, by our mapping written out above) and is 3000 × the sky's level
    at 560 nm."""
    from helpers import ROOT, load_script

    script = load_script("make_sun_environment")
    wl, img = read_spectral_exr(ROOT / "measurements" / "environment" / "sunny.exr")
    assert np.array_equal(wl, np.arange(400.0, 701.0, 10.0))
    want = se.synthetic_environment(128, 256, wl, lamp_radius_deg=1.5,
                                    lamp_direction=script.sun_direction(),
                                    lamp_luminance_ratio=3000.0)
    assert np.allclose(img, want.astype(np.float16).astype(np.float32), rtol=1e-3, atol=1e-7)
    lum = img[..., 16]  # 560 nm
    r, c = np.unravel_index(np.argmax(lum), lum.shape)
    d = direction(r, c, 256, 128)
    assert float(d @ np.asarray(script.sun_direction())) > np.cos(np.radians(1.5))
    assert lum.max() == pytest.approx(3000 * 0.02, rel=2e-3)


def test_make_env_cli(tmp_path, capsys):
    out = tmp_path / "env.exr"
    assert main(["make-env", "-o", str(out), "--width", "32", "--height", "16",
                 "--pixel-type", "float", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["width"] == 32 and summary["bands"] == 81
    wl, img = read_spectral_exr(out)
    assert np.array_equal(img, se.make_environment(32, 16)[1])


def test_view_cli_on_bundled_map(tmp_path, capsys):
    png = tmp_path / "env.png"
    assert main(["view", str(STUDIO_ROOM), "-o", str(png), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["width"] == 256 and info["height"] == 128
    assert info["wavelength_range_nm"] == [380.0, 780.0]
    assert info["luminance"]["max"] == pytest.approx(20000.0, rel=2e-3)
    im = Image.open(png)
    assert im.size == (256, 128) and im.mode == "RGB"
    # explicit exposure: 1e9 cd/m2 as display white leaves everything (<= 2e4 cd/m2) black
    assert main(["view", str(STUDIO_ROOM), "-o", str(png), "--exposure", "1e9"]) == 0
    assert np.asarray(Image.open(png)).max() <= 3
    capsys.readouterr()
    assert main(["view", str(tmp_path / "missing.exr"), "-o", str(png)]) == 2
    assert "missing.exr" in capsys.readouterr().err


def test_view_cli_rgb_exr(tmp_path, capsys):
    import OpenEXR

    p = tmp_path / "rgb.exr"
    a = np.full((4, 8), 0.5, np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"R": a, "G": a, "B": a}).write(str(p))
    png = tmp_path / "rgb.png"
    assert main(["view", str(p), "-o", str(png), "--exposure", "0.5", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "rgb"
    px = np.asarray(Image.open(png))
    assert px.shape == (4, 8, 3) and np.all(px == 255)  # grey 0.5 at exposure 0.5 -> white

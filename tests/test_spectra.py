"""Wavelength grids, resampling and spectrum files against closed forms and NumPy."""

import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import (
    default_wavelengths,
    parse_spectrum_text,
    read_spectrum_csv,
    resample,
    validate_spectrum,
    wavelength_grid,
)


def test_default_grid():
    wl = default_wavelengths()
    assert wl.shape == (81,)
    assert wl[0] == 380.0 and wl[-1] == 780.0
    np.testing.assert_allclose(np.diff(wl), 5.0)
    assert wavelength_grid(400, 700, 10).shape == (31,)


def test_resample_linear_is_exact_on_piecewise_linear_data():
    rng = np.random.default_rng(0)
    wl_in = np.sort(rng.uniform(370, 790, 57))
    wl_in[0], wl_in[-1] = 376.0, 784.0
    f = lambda x: 0.3 + 0.001 * (x - 380.0)  # noqa: E731
    out = resample(wl_in, f(wl_in))
    np.testing.assert_allclose(out, f(default_wavelengths()), rtol=1e-12)


def test_resample_batched_and_colour_method():
    wl_in = np.arange(360.0, 831.0, 10.0)
    smooth = np.stack([np.exp(-((wl_in - c) / 60.0) ** 2) for c in (450.0, 550.0, 650.0)])
    out = resample(wl_in, smooth, method="colour")
    ref = np.stack([np.exp(-((default_wavelengths() - c) / 60.0) ** 2) for c in (450, 550, 650)])
    assert out.shape == (3, 81)
    # Sprague interpolation of a smooth function: close to the function itself
    np.testing.assert_allclose(out, ref, atol=2e-3)
    lin = resample(wl_in, smooth)
    np.testing.assert_allclose(lin, ref, atol=2e-2)


def test_resample_margin():
    wl_in = np.arange(383.0, 778.0, 1.0)  # 383..777: 3 nm short on both ends
    v = np.ones_like(wl_in)
    out = resample(wl_in, v)  # within the 5 nm margin: end values held
    np.testing.assert_allclose(out, 1.0)
    with pytest.raises(InputError, match="extrapolation"):
        resample(wl_in, v, margin_nm=2.0)
    with pytest.raises(InputError, match="does not cover"):
        resample(np.arange(400.0, 701.0, 10.0), np.ones(31))


@pytest.mark.parametrize(
    "wl, values, match",
    [
        ([400, 500, 500], [1, 2, 3], "increase strictly"),
        ([400, np.nan, 600], [1, 2, 3], "NaN"),
        ([0.4, 0.5, 0.6], [1, 2, 3], "nanometres"),
        ([400, 500, 600], [1, np.nan, 3], "NaN"),
        ([400, 500, 600], [1, 2], "3 samples"),
        ([[400, 500, 600]], [1, 2, 3], "1-D"),
        (["a", "b", "c"], [1, 2, 3], "not numeric"),
    ],
)
def test_resample_rejects_bad_input(wl, values, match):
    with pytest.raises(InputError, match=match):
        resample(wl, values, np.arange(400.0, 601.0, 10.0), path="x.csv")


def test_validate_spectrum_negative():
    with pytest.raises(InputError, match="negative"):
        validate_spectrum([1.0, -0.5], 2, allow_negative=False, field="S")


@pytest.mark.parametrize(
    "text",
    [
        "wavelength,radiance\n380,0.1\n385,0.2\n390,0.3\n",
        "# SR-3A export\n380;0.1\n385;0.2\n390;0.3\n",
        "380\t0.1\n385\t0.2\n390\t0.3\n",
        "380 0.1\n385 0.2\n\n390 0.3\n",
    ],
)
def test_parse_formats(text):
    wl, v = parse_spectrum_text(text)
    np.testing.assert_array_equal(wl, [380, 385, 390])
    np.testing.assert_allclose(v, [0.1, 0.2, 0.3])


def test_parse_repeated_readings(tmp_path):
    p = tmp_path / "spot.csv"
    p.write_text("nm,r1,r2\n380,1,2\n390,3,4\n400,5,6\n")
    wl, v = read_spectrum_csv(p)
    assert v.shape == (2, 3)
    np.testing.assert_allclose(v[1], [2, 4, 6])


@pytest.mark.parametrize(
    "text, match",
    [
        ("380,0.1\n385,abc\n", r"line 2: column 2: not a number"),
        ("380,0.1\n385,0.2,0.3\n", r"line 2: expected 2 columns"),
        ("380,0.1\n375,0.2\n", r"line 2: wavelength 375 nm does not increase"),
        ("380,0.1\n385,nan\n", r"line 2: column 2: 'nan' is not a finite number"),
        ("380,0.1\n385,-0.2\n", r"line 2: column 2: negative value"),
        ("380,0.1\n", "at least 2 rows"),
        ("", "at least 2 rows"),
        ("380\n390\n", "line 1: need a wavelength"),
        ("380,,1\n", "line 1: empty cell"),
    ],
)
def test_parse_errors_name_file_and_line(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as exc:
        read_spectrum_csv(p)
    assert "bad.csv" in str(exc.value)


def test_read_missing_and_binary(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_spectrum_csv(tmp_path / "nope.csv")
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00\x01\x80")
    with pytest.raises(InputError, match="UTF-8"):
        read_spectrum_csv(p)

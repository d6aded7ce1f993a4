"""Spectral OpenEXR I/O (Fichet, Pacanowski & Wilkie 2021 layout): round trips, channel
spellings, colour-science's own reader/writer as the second implementation, malformed files,
and fuzzing of the EXR reader and the spectrum text loader."""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import OpenEXR
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import parse_spectrum_text, read_spectrum_csv
from spectral_fit.io import (
    parse_channel_name,
    read_rgb_exr,
    read_spectral_exr,
    read_spectral_exr_ex,
    write_spectral_exr,
)

SPEED_OF_LIGHT = 299_792_458.0


def _write_raw(path, channels: dict, **header) -> None:
    """Write an EXR with exactly these channels (name -> 2-D array) with the OpenEXR binding."""
    h = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
    OpenEXR.File(h, {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))


def _rng_image(h=3, w=4, n=5, seed=0, dtype=np.float32):
    return np.random.default_rng(seed).uniform(0.0, 2.0, (h, w, n)).astype(dtype)


# --------------------------------------------------------------------------------------------
# round trips and spellings


@pytest.mark.parametrize("kind", ["emissive", "reflective"])
def test_round_trip_exact_float32(tmp_path, kind):
    wl = np.arange(380.0, 781.0, 5.0)
    img = _rng_image(6, 7, wl.size, seed=1)
    p = tmp_path / "a.exr"
    write_spectral_exr(p, wl, img, spectral_kind=kind, comment="hello")
    r = read_spectral_exr_ex(p)
    assert r.kind == kind
    assert np.array_equal(r.wavelengths, wl)
    assert r.image.dtype == np.float32 and np.array_equal(r.image, img)
    assert r.attributes["spectralLayoutVersion"] == "1.0"
    assert r.attributes["comment"] == "hello"
    if kind == "emissive":
        assert r.attributes["emissiveUnits"] == "W.m^-2.sr^-1"
        assert r.channels[34] == "S0.550,000000nm"
    else:
        assert "emissiveUnits" not in r.attributes
        assert r.channels[34] == "T.550,000000nm"
    chans = OpenEXR.File(str(p), separate_channels=True).channels()
    assert {"R", "G", "B"} <= set(chans)
    assert OpenEXR.File(str(p), header_only=True).header()["compression"] == \
        OpenEXR.ZIP_COMPRESSION
    wl2, img2 = read_spectral_exr(p)
    assert np.array_equal(wl2, wl) and np.array_equal(img2, img)


def test_preview_of_d65_is_white(tmp_path):
    """A uniform D65-shaped radiance image: the sRGB preview (linear, normalised by the
    99th-percentile luminance) is (1, 1, 1) because D65 is sRGB's white (IEC 61966-2-1)."""
    import colour

    wl = np.arange(380.0, 781.0, 5.0)
    d65 = colour.SDS_ILLUMINANTS["D65"][wl] * 1e-3
    img = np.broadcast_to(d65, (2, 3, wl.size)).astype(np.float32)
    p = tmp_path / "d65.exr"
    write_spectral_exr(p, wl, img)
    ch = OpenEXR.File(str(p), separate_channels=True).channels()
    rgb = np.stack([ch[c].pixels for c in "RGB"], -1)
    assert np.allclose(rgb, 1.0, atol=2e-3)


def test_half_pixels_read(tmp_path):
    wl = [450.0, 550.0, 650.0]
    img = _rng_image(3, 5, 3, seed=2, dtype=np.float16)
    p = tmp_path / "h.exr"
    _write_raw(p, {f"S0.{int(x)},000000nm": img[..., i] for i, x in enumerate(wl)})
    w, out = read_spectral_exr(p)
    assert np.array_equal(w, wl)
    assert out.dtype == np.float32 and np.array_equal(out, img.astype(np.float32))
    # our writer's half option too
    q = tmp_path / "h2.exr"
    write_spectral_exr(q, wl, img.astype(np.float32), pixel_type="half")
    assert np.array_equal(read_spectral_exr(q)[1], img.astype(np.float32))


SPELLINGS_550 = [
    "S0.550,000000nm", "S0.550,0nm", "S0.550nm", "S0.550.0nm", "S0.0,55um", "S0.0,55µm",
    "S0.0,55μm", "S0.5,5e-7m", "S0.5,5E-7m", "S0.0,00055mm", "S0.5,5e-5cm",
]


@pytest.mark.parametrize("name", SPELLINGS_550)
def test_channel_spellings(tmp_path, name):
    assert parse_channel_name(name) == ("S0", pytest.approx(550.0, abs=1e-9))
    p = tmp_path / "s.exr"
    img = _rng_image(2, 3, 2, seed=3)
    _write_raw(p, {"S0.500nm": img[..., 0], name: img[..., 1], "R": img[..., 0]})
    w, out = read_spectral_exr(p)
    assert np.allclose(w, [500.0, 550.0], atol=1e-9)
    assert np.array_equal(out, img)


def test_frequency_channels(tmp_path):
    """Frequencies (Hz with SI multipliers) are converted with λ = c / f."""
    wl = np.array([450.0, 550.0, 650.0])
    f_thz = SPEED_OF_LIGHT / (wl * 1e-9) / 1e12
    names = [f"S0.{f:.9f}THz".replace(".", ",").replace("S0,", "S0.") for f in f_thz]
    p = tmp_path / "f.exr"
    img = _rng_image(2, 2, 3, seed=4)
    _write_raw(p, {n: img[..., i] for i, n in enumerate(names)})
    w, out = read_spectral_exr(p)
    # channels come back sorted by wavelength (descending frequency order reversed)
    assert np.allclose(w, wl, rtol=1e-9)
    assert np.array_equal(out, img)


def test_reflective_and_kind_selection(tmp_path):
    p = tmp_path / "t.exr"
    img = _rng_image(2, 2, 4, seed=5)
    _write_raw(p, {"T.400nm": img[..., 0], "T.500nm": img[..., 1],
                   "S0.400nm": img[..., 2], "S0.500nm": img[..., 3]})
    with pytest.raises(InputError, match="both emissive"):
        read_spectral_exr(p)
    r = read_spectral_exr_ex(p, kind="reflective")
    assert r.kind == "reflective" and np.array_equal(r.image, img[..., :2])
    e = read_spectral_exr_ex(p, kind="emissive")
    assert e.kind == "emissive" and np.array_equal(e.image, img[..., 2:])


def test_polarisation_components_ignored(tmp_path):
    p = tmp_path / "pol.exr"
    img = _rng_image(2, 2, 4, seed=6)
    _write_raw(p, {"S0.400nm": img[..., 0], "S0.500nm": img[..., 1],
                   "S1.400nm": img[..., 2], "S2.500nm": img[..., 3]})
    w, out = read_spectral_exr(p)
    assert np.array_equal(w, [400, 500]) and np.array_equal(out, img[..., :2])


# --------------------------------------------------------------------------------------------
# colour-science's Fichet 2021 implementation (OpenImageIO) as the independent second reader
# and writer


@pytest.mark.parametrize("emissive", [True, False])
def test_colour_writer_read_by_us(tmp_path, emissive):
    pytest.importorskip("OpenImageIO")
    from colour.io import Specification_Fichet2021, write_spectral_image_Fichet2021

    wl = np.arange(400.0, 701.0, 10.0)
    img = _rng_image(4, 5, wl.size, seed=7)
    comp = "S0" if emissive else "T"
    p = tmp_path / "colour.exr"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_spectral_image_Fichet2021({comp: (wl, img)}, str(p), "float32",
                                        Specification_Fichet2021(is_emissive=emissive))
    r = read_spectral_exr_ex(p)
    assert r.kind == ("emissive" if emissive else "reflective")
    assert np.array_equal(r.wavelengths, wl)
    assert np.array_equal(r.image, img)


def test_colour_reader_reads_ours(tmp_path):
    pytest.importorskip("OpenImageIO")
    from colour.io import read_spectral_image_Fichet2021

    wl = np.arange(380.0, 781.0, 5.0)
    img = _rng_image(3, 4, wl.size, seed=8)
    p = tmp_path / "ours.exr"
    write_spectral_exr(p, wl, img)
    comps = read_spectral_image_Fichet2021(str(p))
    assert set(comps) == {"S0"}
    w, v = comps["S0"]
    order = np.argsort(w)
    assert np.allclose(np.asarray(w)[order], wl, atol=1e-9)
    assert np.array_equal(np.asarray(v)[..., order], img)


# --------------------------------------------------------------------------------------------
# malformed files: InputError naming the file and the channel


def _assert_input_error(path, *fragments, call=read_spectral_exr, **kw):
    with pytest.raises(InputError) as ei:
        call(path, **kw)
    msg = str(ei.value)
    assert str(path) in msg, msg
    for f in fragments:
        assert f in msg, msg
    return ei.value


def test_no_spectral_channels(tmp_path):
    p = tmp_path / "rgb.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"R": a, "G": a, "B": a})
    err = _assert_input_error(p, "no spectral channels")
    assert err.field == "channels"


def test_duplicated_wavelength(tmp_path):
    p = tmp_path / "dup.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"S0.500nm": a, "S0.550nm": a, "S0.550,000000nm": a})
    _assert_input_error(p, "duplicated wavelength 550", "S0.550nm", "S0.550,000000nm")


def test_missing_band(tmp_path):
    p = tmp_path / "gap.exr"
    a = np.ones((2, 2), np.float32)
    wl = [x for x in range(400, 705, 5) if x != 550]
    _write_raw(p, {f"S0.{x}nm": a for x in wl})
    _assert_input_error(p, "missing", "545", "S0.545nm")
    w, _ = read_spectral_exr(p, allow_gaps=True)
    assert w.size == len(wl)


def test_non_uniform_grid_is_accepted(tmp_path):
    p = tmp_path / "nonuni.exr"
    a = np.ones((2, 2), np.float32)
    wl = [380, 385, 390, 395, 400] + list(range(410, 710, 10))
    _write_raw(p, {f"S0.{x}nm": a for x in wl})
    assert np.array_equal(read_spectral_exr(p)[0], wl)


def test_mixed_kinds_and_grids(tmp_path):
    p = tmp_path / "mixed.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"S0.400nm": a, "S0.500nm": a, "T.450nm": a, "T.550nm": a})
    _assert_input_error(p, "both emissive (S0) and reflective (T)")
    assert np.array_equal(read_spectral_exr(p, kind="reflective")[0], [450, 550])
    q = tmp_path / "pol_only.exr"
    _write_raw(q, {"S1.400nm": a, "S1.500nm": a})
    _assert_input_error(q, "no spectral channels", "S1")


@pytest.mark.parametrize("bad", ["S0.abcnm", "S0.nm", "S0.0nm", "S0.550", "T.5,5,5nm",
                                 "S0.550parsec", "S0.-550nm"])
def test_non_numeric_channel_name(tmp_path, bad):
    p = tmp_path / "nn.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"S0.400nm": a, "S0.500nm": a, bad: a})
    _assert_input_error(p, repr(bad))


def test_bispectral_rejected(tmp_path):
    p = tmp_path / "bi.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"T.400nm": a, "T.500nm": a, "T.400nm.500nm": a})
    _assert_input_error(p, "bi-spectral", "T.400nm.500nm")


def test_wavelengths_out_of_range(tmp_path):
    p = tmp_path / "range.exr"
    a = np.ones((2, 2), np.float32)
    _write_raw(p, {"S0.400m": a, "S0.500m": a})  # metres, not nm
    _assert_input_error(p, "S0.400m")


def test_single_channel(tmp_path):
    p = tmp_path / "one.exr"
    _write_raw(p, {"S0.550nm": np.ones((2, 2), np.float32)})
    _assert_input_error(p, "S0.550nm", "at least 2")


def test_uint_channel(tmp_path):
    p = tmp_path / "uint.exr"
    _write_raw(p, {"S0.500nm": np.ones((2, 2), np.float32),
                   "S0.550nm": np.ones((2, 2), np.uint32)})
    _assert_input_error(p, "S0.550nm", "uint32")


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_non_finite_pixels(tmp_path, value, dtype):
    p = tmp_path / "nan.exr"
    a = np.ones((3, 4), dtype)
    b = a.copy()
    b[2, 1] = value
    _write_raw(p, {"S0.500nm": a, "S0.550nm": b})
    _assert_input_error(p, "S0.550nm", "row 2, column 1")


def _uncompressed_with_sampling(path, x_sampling: int) -> None:
    """A valid uncompressed 2-channel file whose second channel's xSampling field is then
    overwritten in the header (a sub-sampled / wrongly sized channel)."""
    a = np.ones((4, 4), np.float32)
    _write_raw(path, {"S0.500nm": a, "S0.550nm": a}, compression=OpenEXR.NO_COMPRESSION)
    data = bytearray(path.read_bytes())
    name = b"S0.550nm\x00"
    i = data.index(name) + len(name)
    # chlist entry: name\0, int32 pixel type, uint8 pLinear, 3 reserved bytes, int32 xSampling,
    # int32 ySampling
    data[i + 8:i + 12] = struct.pack("<i", x_sampling)
    path.write_bytes(bytes(data))


def test_subsampled_or_wrongly_sized_channel(tmp_path):
    p = tmp_path / "sub.exr"
    _uncompressed_with_sampling(p, 2)
    _assert_input_error(p)


def test_truncated_file(tmp_path):
    p = tmp_path / "full.exr"
    write_spectral_exr(p, [500.0, 550.0, 600.0], _rng_image(8, 8, 3, seed=9))
    data = p.read_bytes()
    for n in (0, 3, 4, 20, len(data) // 2, len(data) - 1):
        q = tmp_path / f"trunc{n}.exr"
        q.write_bytes(data[:n])
        _assert_input_error(q)


def test_not_exr_missing_and_directory(tmp_path):
    p = tmp_path / "text.exr"
    p.write_text("not an image\n")
    _assert_input_error(p, "not an OpenEXR file")
    _assert_input_error(tmp_path / "nope.exr", "no such file")
    _assert_input_error(tmp_path, "directory")


def test_write_rejects_bad_input(tmp_path):
    wl = [500.0, 550.0]
    img = np.ones((2, 2, 2), np.float32)
    bad = img.copy()
    bad[1, 0, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_spectral_exr(tmp_path / "x.exr", wl, bad)
    with pytest.raises(InputError, match="shape"):
        write_spectral_exr(tmp_path / "x.exr", wl, img[..., :1])
    with pytest.raises(InputError, match="increase"):
        write_spectral_exr(tmp_path / "x.exr", [550.0, 500.0], img)
    assert not list(tmp_path.iterdir())  # nothing written, no temp files left


def test_read_rgb_exr(tmp_path):
    p = tmp_path / "rgb.exr"
    img = _rng_image(3, 4, 4, seed=10)
    _write_raw(p, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2], "A": img[..., 3]})
    assert np.array_equal(read_rgb_exr(p), img[..., :3])
    q = tmp_path / "rg.exr"
    _write_raw(q, {"R": img[..., 0], "G": img[..., 1]})
    _assert_input_error(q, "'B'", call=read_rgb_exr)
    r = tmp_path / "nan.exr"
    bad = img[..., 0].copy()
    bad[0, 0] = np.nan
    _write_raw(r, {"R": img[..., 0], "G": bad, "B": img[..., 2]})
    _assert_input_error(r, "'G'", call=read_rgb_exr)


# --------------------------------------------------------------------------------------------
# fuzzing


@pytest.fixture(scope="module")
def seed_exr(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    p = d / "seed.exr"
    write_spectral_exr(p, [450.0, 550.0, 650.0], _rng_image(3, 2, 3, seed=11), preview=False)
    return d, p.read_bytes()


def _check_result(path, n_bands=None):
    try:
        img = read_spectral_exr_ex(path)
    except InputError as exc:
        assert str(path) in str(exc)
        return None
    assert img.image.ndim == 3 and img.image.dtype == np.float32
    assert img.image.shape[-1] == img.wavelengths.size >= 2
    assert np.all(np.isfinite(img.image))
    assert np.all(np.isfinite(img.wavelengths)) and np.all(np.diff(img.wavelengths) > 0)
    if n_bands is not None:
        assert img.wavelengths.size == n_bands
    return img


@settings(max_examples=1000, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_exr_bytes(seed_exr, data):
    """Mutated and truncated copies of a valid tiny file: InputError or a finite image."""
    d, raw = seed_exr
    b = bytearray(raw)
    n_mut = data.draw(st.integers(0, 6))
    for _ in range(n_mut):
        i = data.draw(st.integers(0, len(b) - 1))
        b[i] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):
        b = b[: data.draw(st.integers(0, len(b)))]
    p = d / "mut.exr"
    p.write_bytes(bytes(b))
    _check_result(p)


_name_chars = st.sampled_from(list("ST0123.,eE-+nmuµkHzGTRBA") + ["da", "Hz", "nm", "S0.", "T."])


@settings(max_examples=1000, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    names=st.lists(st.lists(_name_chars, min_size=1, max_size=8).map("".join), min_size=1,
                   max_size=5, unique=True),
    shape=st.tuples(st.integers(1, 3), st.integers(1, 3)),
    half=st.booleans(),
    values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=1,
                    max_size=4),
)
def test_fuzz_exr_channel_names(seed_exr, names, shape, half, values):
    """Random channel names (close to the layout's alphabet), sizes, types and pixel values."""
    d, _ = seed_exr
    dt = np.float16 if half else np.float32
    chans = {}
    for k, n in enumerate(names):
        with np.errstate(over="ignore"):
            chans[n] = np.full(shape, values[k % len(values)], dtype=dt)
    p = d / "names.exr"
    try:
        _write_raw(p, chans)
    except Exception:  # names the OpenEXR library itself refuses to write
        return
    img = _check_result(p)
    if img is not None:
        assert img.image.shape[:2] == shape


_csv_tokens = st.sampled_from(
    ["380", "385.5", "400", "1e3", "-1", "0", "0.5", "nan", "inf", "-inf", "1e400", "abc", "",
     ",", ";", "\t", " ", "  ", "#", "\n", "\r\n", "wavelength", "value", "1,5", "\ufeff",
     "١٢٣", "0x10", "1_000", "+2", ".5", "5.", "e5"])


@settings(max_examples=1000, deadline=None)
@given(st.lists(_csv_tokens, max_size=40).map("".join))
def test_fuzz_spectrum_text(text):
    """The spectrum text parser: only InputError escapes; results are finite, increasing, >= 0."""
    try:
        wl, v = parse_spectrum_text(text, path="fuzz.csv")
    except InputError as exc:
        assert "fuzz.csv" in str(exc)
        return
    assert wl.ndim == 1 and wl.size >= 2 and np.all(np.isfinite(wl))
    assert np.all(np.diff(wl) > 0)
    assert v.shape[-1] == wl.size and v.ndim in (1, 2)
    assert np.all(np.isfinite(v)) and np.all(v >= 0)


@settings(max_examples=1000, deadline=None, suppress_health_check=list(HealthCheck))
@given(raw=st.binary(max_size=200))
def test_fuzz_spectrum_file_bytes(tmp_path_factory, raw):
    """Arbitrary bytes as a spectrum file (invalid UTF-8, NULs, ...)."""
    p = tmp_path_factory.getbasetemp() / "fuzz_spectrum.csv"
    p.write_bytes(raw)
    try:
        wl, v = read_spectrum_csv(p)
    except InputError as exc:
        assert str(p) in str(exc)
        return
    assert np.all(np.isfinite(wl)) and np.all(np.isfinite(v)) and np.all(v >= 0)
    assert math.isfinite(float(wl.sum()))

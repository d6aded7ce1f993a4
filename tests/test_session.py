"""Measurement sessions: the documented format loads; every malformed input gives an InputError
naming the file, the line and the field; fuzzing with hypothesis."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.fitting import SMALL_CONFIG, spots
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import estimate_noise, load_scene, load_session, write_session

WL = np.arange(400.0, 701.0, 20.0)


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A valid session (3 spots, repeats, white standard, dark, SCI reflectance) beside a
    scene config (the loader only checks that the environment file exists)."""
    root = tmp_path_factory.mktemp("sess")
    (root / "env.exr").write_bytes(b"stand-in")
    (root / "scene.toml").write_text(SMALL_CONFIG)
    rng = np.random.default_rng(0)
    sp = [spots()[i] for i in (0, 1, 5)]
    readings = [{**{k: s[k] for k in ("id", "object", "kind", "aim", "position")},
                 "spectra": 1e-3 * (1 + 0.01 * rng.standard_normal((3, WL.size)))}
                for s in sp]
    write_session(root / "s", scene="../scene.toml", wavelengths=WL, readings=readings,
                  instrument={"field_angle_deg": 1.0},
                  white={"reflectance": 0.98, "position": [0, 0, -0.275], "normal": [0, 0, 1],
                         "spectra": 2e-3 * np.ones((2, WL.size))},
                  dark=1e-5 * np.ones((1, WL.size)),
                  objects={"red": {"reflectance": np.full(WL.size, 0.3), "geometry": "SCI",
                                   "free": ["alpha", "mu"]}})
    return root


def _copy(base: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "c"
    shutil.copytree(base, dst)
    return dst / "s"


def test_valid_session_loads(base):
    s = load_session(base / "s")
    assert len(s.readings) == 3
    assert s.calibration == "white"
    r = s.readings[0]
    assert r.repeats.shape == (3, WL.size)
    # dark subtracted
    np.testing.assert_allclose(s.white.mean, 2e-3 - 1e-5, rtol=1e-6)
    assert s.objects["red"].geometry == "SCI"
    assert s.objects["red"].free == ("alpha", "mu")
    assert s.noise.source == "repeats"
    np.testing.assert_allclose(r.aim, spots()[0]["aim"], atol=1e-6)


def test_resampling_and_units(base, tmp_path):
    """A reading on a 1 nm grid is resampled onto the scene grid; a session in mW is scaled."""
    d = _copy(base, tmp_path)
    f = d / "readings" / "yellow_0_1.csv"
    wl = np.arange(380.0, 781.0, 1.0)
    rad = 1.0 + (wl - 380.0) / 400.0
    f.write_text("nm;value\n" + "\n".join(
        f"{a:g};{b:.6f}" for a, b in zip(wl, rad, strict=True)) + "\n")
    s = load_session(d)
    np.testing.assert_allclose(s.readings[0].repeats[0], 1.0 + (WL - 380.0) / 400.0 - 1e-5,
                               rtol=1e-9)
    # the whole session in mW: every file without a unit line, values scaled by 1e-3
    for g in d.rglob("*.csv"):
        if "reflectance" not in g.name:
            g.write_text("\n".join(x for x in g.read_text().splitlines()
                                   if not x.startswith("# unit")) + "\n")
    _replace_in(d / "session.toml", 'units = "W.sr^-1.m^-2.nm^-1"',
                'units = "mW.sr^-1.m^-2.nm^-1"')
    s2 = load_session(d)
    np.testing.assert_allclose(s2.readings[0].repeats[0], 1e-3 * s.readings[0].repeats[0],
                               rtol=1e-9)


def _error(d: Path) -> InputError:
    with pytest.raises(InputError) as ei:
        load_session(d)
    return ei.value


def _replace_in(path: Path, old: str, new: str, count: int = 1) -> None:
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, count))


def _line_of(path: Path, needle: str, nth: int = 0) -> int:
    lines = [i + 1 for i, line in enumerate(path.read_text().splitlines()) if needle in line]
    return lines[nth]


def test_non_monotonic_wavelengths(base, tmp_path):
    d = _copy(base, tmp_path)
    f = d / "readings" / "yellow_1_2.csv"
    lines = f.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("500,"))
    lines[i] = "470," + lines[i].split(",")[1]
    f.write_text("\n".join(lines) + "\n")
    e = _error(d)
    assert e.path.endswith("yellow_1_2.csv") and e.line == i + 1
    assert "does not increase" in str(e)


def test_nan_value(base, tmp_path):
    d = _copy(base, tmp_path)
    f = d / "readings" / "red_0_1.csv"
    text = f.read_text().splitlines()
    text[5] = text[5].split(",")[0] + ",nan"
    f.write_text("\n".join(text) + "\n")
    e = _error(d)
    assert e.path.endswith("red_0_1.csv") and e.line == 6 and "finite" in str(e)


def test_negative_radiance(base, tmp_path):
    d = _copy(base, tmp_path)
    f = d / "readings" / "yellow_0_3.csv"
    text = f.read_text().splitlines()
    text[7] = text[7].split(",")[0] + ",-0.002"
    f.write_text("\n".join(text) + "\n")
    e = _error(d)
    assert e.path.endswith("yellow_0_3.csv") and e.line == 8 and "negative" in str(e)


def test_unit_not_radiance(base, tmp_path):
    d = _copy(base, tmp_path)
    f = d / "readings" / "yellow_0_1.csv"
    _replace_in(f, "# unit: W.sr^-1.m^-2.nm^-1", "# unit: cd/m2")
    e = _error(d)
    assert e.path.endswith("yellow_0_1.csv") and e.line == 2
    assert "not a spectral radiance" in str(e)


def test_unit_mismatch_between_file_and_session(base, tmp_path):
    d = _copy(base, tmp_path)
    _replace_in(d / "session.toml", 'units = "W.sr^-1.m^-2.nm^-1"',
                'units = "mW.sr^-1.m^-2.nm^-1"')
    e = _error(d)
    assert "unit mismatch" in str(e) and e.line == 2 and e.path.endswith(".csv")


def test_unknown_object(base, tmp_path):
    d = _copy(base, tmp_path)
    m = d / "session.toml"
    _replace_in(m, 'object = "red"', 'object = "blue"')
    e = _error(d)
    assert e.field == "readings[2].object" and "unknown object 'blue'" in str(e)
    assert e.line == _line_of(m, 'object = "blue"')
    assert e.path == str(m)


def test_missing_config(base, tmp_path):
    d = _copy(base, tmp_path)
    _replace_in(d / "session.toml", 'scene = "../scene.toml"', 'scene = "../nowhere.toml"')
    e = _error(d)
    assert e.field == "session.scene" and "not found" in str(e) and e.line == 5


def test_nul_character_in_a_path(base, tmp_path):
    """A TOML string may hold a NUL (\\u0000), which no file name can: a clear error (the
    scene config's paths are resolved, where pathlib raises ValueError for one)."""
    d = _copy(base, tmp_path)
    _replace_in(d / "session.toml", 'scene = "../scene.toml"', 'scene = "../scene\\u0000.toml"')
    e = _error(d)
    assert e.field == "session.scene" and "not found" in str(e)


def test_missing_spectrum_file(base, tmp_path):
    d = _copy(base, tmp_path)
    (d / "readings" / "red_0_2.csv").unlink()
    e = _error(d)
    assert e.field == "readings[2].files[1]" and "not found" in str(e)


def test_bad_kind_and_unknown_key(base, tmp_path):
    d = _copy(base, tmp_path)
    m = d / "session.toml"
    _replace_in(m, 'kind = "object"', 'kind = "gloss"')
    e = _error(d)
    assert e.field == "readings[0].kind" and e.line == _line_of(m, 'kind = "gloss"')
    d2 = _copy(base, tmp_path / "b")
    _replace_in(d2 / "session.toml", "field_angle_deg = 1.0", "field_angle = 1.0")
    e = _error(d2)
    assert e.field == "instrument.field_angle" and "unknown key" in str(e)


def test_bad_aim_and_free(base, tmp_path):
    d = _copy(base, tmp_path)
    m = d / "session.toml"
    text = m.read_text()
    m.write_text(re.sub(r"aim = \[[^\]]*\]", "aim = [0.0, \"x\", 1.0]", text, count=1))
    e = _error(d)
    assert e.field == "readings[0].aim" and "3 numbers" in str(e)
    d2 = _copy(base, tmp_path / "b")
    _replace_in(d2 / "session.toml", 'free = ["alpha", "mu"]', 'free = ["alpha", "rho"]')
    e = _error(d2)
    assert e.field == "objects.red.free" and "rho" in str(e)


def test_model_error_table(base, tmp_path):
    """``[model_error]``: a fraction or "auto" per reading kind; absent: none; anything else
    is refused with the field named."""
    assert load_session(base / "s").model_error == {}
    for i, (body, want) in enumerate((
            ('object = 0.01\ninterreflection = "auto"',
             {"object": 0.01, "interreflection": "auto"}),
            ("interreflection = 0.05", {"interreflection": 0.05}))):
        d = _copy(base, tmp_path / f"ok{i}")
        _replace_in(d / "session.toml", "[dark]", f"[model_error]\n{body}\n\n[dark]")
        assert load_session(d).model_error == want
    for i, (body, field, words) in enumerate((
            ("object = 1.5", "model_error.object", "<= 1"),
            ('object = "guess"', "model_error.object", "auto"),
            ("glossy = 0.1", "model_error.glossy", "unknown"),
            ("[model_error.level]\nobject = -0.01", "model_error.level.object", ">= 0"),
            ("[model_error.level]\nglossy = 0.01", "model_error.level.glossy", "unknown"),
            ("[model_error.tilt]\nobject = 2", "model_error.tilt.object", "<= 1"))):
        d = _copy(base, tmp_path / f"bad{i}")
        _replace_in(d / "session.toml", "[dark]", f"[model_error]\n{body}\n\n[dark]")
        e = _error(d)
        assert e.field == field and words in str(e), (e.field, str(e))


def test_level_error_table(base, tmp_path):
    """``[model_error.level]`` and ``[model_error.tilt]``: the model's error shared by a
    reading's bands, fractions per kind, beside the per-band fractions; written by
    ``write_session`` and read back."""
    assert load_session(base / "s").level_error == {}
    d = _copy(base, tmp_path / "lvl")
    _replace_in(d / "session.toml", "[dark]", '[model_error]\ninterreflection = "auto"\n\n'
                "[model_error.level]\nobject = 0.005\ninterreflection = 0.02\n\n"
                "[model_error.tilt]\nobject = 0.002\n\n[dark]")
    s = load_session(d)
    assert s.level_error == {"object": 0.005, "interreflection": 0.02}
    assert s.tilt_error == {"object": 0.002}
    assert s.model_error == {"interreflection": "auto"}
    from spectral_fit.io import write_session

    m = write_session(tmp_path / "w", scene=str(s.scene_path), wavelengths=s.wavelengths,
                      readings=[{"id": "a", "object": s.readings[0].object,
                                 "aim": s.readings[0].aim, "position": s.readings[0].position,
                                 "spectra": s.readings[0].repeats}],
                      calibration={"mode": "none"}, level_error={"object": 0.01},
                      tilt_error={"object": 0.003})
    assert load_session(m).level_error == {"object": 0.01}
    assert load_session(m).tilt_error == {"object": 0.003}


def test_bounds_and_prior_tables(base, tmp_path):
    """``[objects.NAME.bounds]`` ({parameter: [lower, upper]}, "none" for an open end) and
    ``[objects.NAME.prior]`` ({parameter: {mean, sigma}}) load; a reversed or unphysical
    bound, a prior outside its bound, a non-positive σ, a start outside a bound and an
    unknown parameter are refused with the field named."""
    assert load_session(base / "s").objects["red"].bounds == {}
    ok = ('[objects.red.bounds]\nmu = [0.05, 0.3]\nn = ["none", 1.7]\n\n'
          '[objects.red.prior]\nn = { mean = 1.49, sigma = 0.02 }\n\n')
    d = _copy(base, tmp_path / "ok")
    _replace_in(d / "session.toml", "[[readings]]", ok + "[[readings]]")
    om = load_session(d).objects["red"]
    assert om.bounds == {"mu": (0.05, 0.3), "n": (None, 1.7)}
    assert om.prior == {"n": (1.49, 0.02)}
    for i, (body, field, words) in enumerate((
            ("[objects.red.bounds]\nmu = [0.3, 0.05]", "objects.red.bounds.mu", "below"),
            ("[objects.red.bounds]\nn = [0.9, 1.7]", "objects.red.bounds.n", "> 1.0"),
            ("[objects.red.bounds]\nmu = [0.05]", "objects.red.bounds.mu", "[lower, upper]"),
            ("[objects.red.bounds]\nrho = [0, 1]", "objects.red.bounds.rho", "unknown"),
            ("[objects.red.bounds]\nn = [1.3, 1.4]\n[objects.red.prior]\n"
             "n = { mean = 1.5, sigma = 0.1 }", "objects.red.prior.n.mean", "outside"),
            ("[objects.red.prior]\nn = { mean = 1.5, sigma = 0 }", "objects.red.prior.n.sigma",
             "> 0"),
            ("[objects.red.prior]\nn = { mean = 1.5 }", "objects.red.prior.n.sigma",
             "missing"),
            ("[objects.red.start]\nmu = 0.5\n[objects.red.bounds]\nmu = [0.05, 0.3]",
             "objects.red.start.mu", "outside"))):
        d = _copy(base, tmp_path / f"bad{i}")
        _replace_in(d / "session.toml", "[[readings]]", body + "\n\n[[readings]]")
        e = _error(d)
        assert e.field == field and words in str(e), (e.field, str(e))


def test_white_standard_errors(base, tmp_path):
    d = _copy(base, tmp_path)
    _replace_in(d / "session.toml", "reflectance = 0.98", "reflectance = 0.01")
    e = _error(d)
    assert e.field == "white_standard.reflectance"
    d2 = _copy(base, tmp_path / "b")
    _replace_in(d2 / "session.toml", "normal = [0.0, 0.0, 1.0]", "normal = [0, 0, 0]")
    e = _error(d2)
    assert e.field == "white_standard.normal"


def test_toml_syntax_error_line(base, tmp_path):
    d = _copy(base, tmp_path)
    m = d / "session.toml"
    lines = m.read_text().splitlines()
    lines[9] = "this is = = not toml"
    m.write_text("\n".join(lines) + "\n")
    e = _error(d)
    assert e.line == 10 and "TOML" in str(e)


def test_no_white_means_global(base, tmp_path):
    d = _copy(base, tmp_path)
    m = d / "session.toml"
    text = m.read_text()
    a = text.index("[white_standard]")
    b = text.index("[objects.red]")
    m.write_text(text[:a] + text[b:])
    s = load_session(d)
    assert s.calibration == "global" and s.reference == "yellow"


def test_noise_model_recovered():
    """σ² = a² + (b L)² is recovered from many repeated spots."""
    rng = np.random.default_rng(1)
    a, b = 2e-6, 0.004
    groups = []
    for k in range(40):
        mean = np.linspace(1e-5, 2e-3, 31) * (0.5 + k / 40)
        sig = np.sqrt(a ** 2 + (b * mean) ** 2)
        groups.append(mean + sig * rng.standard_normal((3, 31)))
    nm = estimate_noise(groups)
    assert nm.absolute == pytest.approx(a, rel=0.15)
    assert nm.relative == pytest.approx(b, rel=0.1)
    assert estimate_noise([np.ones((1, 5))]) is None


# ----------------------------------------------------------------------------- fuzzing

_MANIFEST_MUTATIONS = [
    ("field_angle_deg = 1.0", ["field_angle_deg = -1", "field_angle_deg = nan",
                               "field_angle_deg = inf", "field_angle_deg = \"1\"",
                               "field_angle_deg = 1e9", "field_angle_deg = []"]),
    ("reflectance = 0.98", ["reflectance = 2.0", "reflectance = \"missing.csv\"",
                            "reflectance = true", "reflectance = [0.9]", "reflectance = nan"]),
    ('kind = "object"', ['kind = 3', 'kind = ""', 'kind = "interreflection"']),
    ('object = "yellow"', ['object = "red"', 'object = 1', 'object = ""']),
    ("normal = [0.0, 0.0, 1.0]", ["normal = [0, 0]", "normal = [nan, 0, 1]",
                                  "normal = [1e30, 0, 0]", "normal = \"up\""]),
    ('units = "W.sr^-1.m^-2.nm^-1"', ['units = "lux"', 'units = 5',
                                     'units = "uW.sr^-1.m^-2.nm^-1"']),
    ("[dark]", ["[dark]\nbogus = 1", "[noise]\nabsolute = 0\nrelative = 0\n[dark]",
                "[noise]\nabsolute = -1\n[dark]", "[noise]\nrelative = 1e-3\n[dark]"]),
    ("format = 1", ["format = 2", "format = \"1\"", "format = 1\nformat = 1"]),
    ("[[readings]]", ["[[readings]]\ndistance_m = -3", "[[readings]]\nposition = [0, 0]",
                      "[[readings]]\nid = 5", "[readings]", "[[readings]]\nfiles = []"]),
    ('geometry = "SCI"', ['geometry = "sci"', 'geometry = "SCX"', 'geometry = 8']),
]


def _mutate_spectrum(text: str, rng: np.random.Generator) -> str:
    lines = text.splitlines()
    data = [i for i, line in enumerate(lines) if line and line[0].isdigit()]
    if not data:
        return text + "garbage\n"
    k = rng.integers(0, 9)
    i = int(rng.choice(data))
    cells = re.split(r"[,;]", lines[i]) + ["0"]
    w, v = cells[0], cells[1]
    try:
        float(w), float(v)
    except ValueError:
        w, v = "500", "0.001"
    if k == 0:
        lines[i] = f"{w},{rng.choice(['nan', 'inf', '-inf', '', 'x', '1e400', '-1'])}"
    elif k == 1:
        lines[i] = f"{float(w) - 40:g},{v}"
    elif k == 2:
        del lines[i:]
    elif k == 3:
        lines[i] = lines[i] + ",3"
    elif k == 4:
        lines.insert(i, "# unit: " + str(rng.choice(["%", "W", "mW.sr^-1.m^-2.nm^-1", "1"])))
    elif k == 5:
        lines = [line.replace(",", ";") for line in lines]
    elif k == 6:
        lines[i] = f"{w},{float(v) * 10 ** int(rng.integers(-30, 30)):g}"
    elif k == 7:
        return text[: int(rng.integers(0, len(text)))]
    else:
        lines = [line for j, line in enumerate(lines) if j not in data[::2]]
    return "\n".join(lines) + "\n"


@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.integers(0, 2 ** 32 - 1), st.integers(1, 3))
def test_fuzz_malformed_sessions(base, tmp_path_factory, seed, n_mut):
    """Random manifest and spectrum-file corruptions: the loader returns a valid session or
    raises InputError; a returned session never carries a NaN, an infinite or a non-positive
    noise level into the solver."""
    rng = np.random.default_rng(seed)
    d = tmp_path_factory.mktemp("fz") / "s"
    shutil.copytree(base / "s", d)
    m = d / "session.toml"
    for _ in range(n_mut):
        if rng.random() < 0.6:
            old, news = _MANIFEST_MUTATIONS[int(rng.integers(len(_MANIFEST_MUTATIONS)))]
            text = m.read_text()
            if old in text:
                m.write_text(text.replace(old, str(rng.choice(news)), 1))
        else:
            files = sorted((d / "readings").glob("*.csv")) + sorted((d / "white").glob("*.csv"))
            f = files[int(rng.integers(len(files)))]
            f.write_text(_mutate_spectrum(f.read_text(), rng))
    scene = _SCENE_CACHE.setdefault("scene", load_scene(base / "scene.toml"))
    try:
        s = load_session(d, scene=scene)
    except InputError as exc:
        assert str(exc)
        return
    for r in s.readings:
        assert np.all(np.isfinite(r.repeats))
        assert np.all(np.isfinite(r.aim)) and np.all(np.isfinite(r.position))
        assert math.isfinite(r.field_angle_deg) and r.field_angle_deg > 0
    sig = s.noise.sigma(np.stack([r.mean for r in s.readings]))
    assert np.all(np.isfinite(sig)) and np.all(sig > 0)
    if s.white is not None:
        assert np.all(np.isfinite(s.white.mean)) and np.all(s.white.mean > 0)


_SCENE_CACHE: dict = {}

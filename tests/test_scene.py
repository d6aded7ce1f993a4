"""Scene configs: the shipped configs parse, malformed configs give clear errors, fuzzing."""

import copy
import math
import shutil
import tomllib

import colour
import numpy as np
import pytest
from helpers import ROOT
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import load_scene, parse_scene

CONFIG = ROOT / "configs" / "two_spheres.toml"


@pytest.fixture()
def config_dir(tmp_path):
    """A copy of configs/two_spheres.toml beside a stand-in environment file."""
    (tmp_path / "env.exr").write_bytes(b"stand-in: the loader only checks that the file exists")
    text = CONFIG.read_text().replace("../measurements/environment/studio_room.exr", "env.exr")
    (tmp_path / "scene.toml").write_text(text)
    return tmp_path


def _base(config_dir):
    return tomllib.loads((config_dir / "scene.toml").read_text())


def test_two_spheres_config(config_dir):
    scene = load_scene(config_dir / "scene.toml")
    assert (scene.width, scene.height) == (720, 480)
    assert [o.name for o in scene.objects] == ["yellow", "red"]
    assert scene.wavelengths.shape == (81,)
    red = scene.objects[1]
    sd = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["red"]
    np.testing.assert_allclose(red.material.reflectance[(scene.wavelengths >= 380)
                                                        & (scene.wavelengths <= 780)],
                               np.interp(scene.wavelengths, sd.wavelengths, sd.values),
                               atol=1e-12)
    np.testing.assert_allclose(red.model_matrix()[:3, 3], [0.045, 0.0, -0.275])
    assert scene.environment.file == (config_dir / "env.exr").resolve()


def test_benchmark_config_matches_benchmark_md():
    data = tomllib.loads((ROOT / "configs" / "benchmark.toml").read_text())
    assert data["environment"]["rotation_y_deg"] == 180.0
    assert (data["spectral"]["start_nm"], data["spectral"]["end_nm"],
            data["spectral"]["step_nm"]) == (400.0, 700.0, 10.0)
    assert [o["position"] for o in data["objects"]] == [[-0.045, 0.0, -0.275],
                                                        [0.045, 0.0, -0.275]]


def test_model_matrix_against_hand_built():
    from spectral_fit.io import MaterialSpec, ObjectSpec

    m = MaterialSpec(reflectance=np.ones(3), reflectance_source="x")
    o = ObjectSpec(name="a", shape="uv_sphere", material=m, position=(1.0, 2.0, 3.0),
                   rotation_deg=(0.0, 90.0, 0.0), scale=2.0)
    M = o.model_matrix()
    # +X rotated 90° about +Y goes to −Z; scaled by 2; translated
    np.testing.assert_allclose(M @ [1, 0, 0, 1], [1.0, 2.0, 1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(M @ [0, 1, 0, 1], [1.0, 4.0, 3.0, 1.0], atol=1e-12)


def _set(d, keys, value):
    for k in keys[:-1]:
        d = d[k]
    if value is _DELETE:
        del d[keys[-1]]
    else:
        d[keys[-1]] = value


_DELETE = object()

MALFORMED = [
    (("frame", "width"), -5, "frame.width: must be in"),
    (("frame", "height"), 1.5, "frame.height: must be an integer"),
    (("camera", "fov_y_deg"), "wide", "camera.fov_y_deg: must be a number"),
    (("camera", "far"), 0.001, "camera.far: must be greater than near"),
    (("camera", "up"), [0.0, 0.0, -1.0], "camera.up: must not be parallel"),
    (("camera", "position"), [0.0, 0.0], "camera.position: must be a list of 3 numbers"),
    (("camera", "blur_px"), -0.5, "camera.blur_px: must be"),
    # finite but beyond float32's reach once multiplied (norms overflowed with a warning)
    (("camera", "position"), [1e200, 0.0, 0.0], r"camera.position: each component must be "
     r"within ±1e\+06"),
    (("objects", 0, "position"), [0.0, -3e6, 0.0], r"objects\[0\].position: each component"),
    (("camera", "noise"), "grainy", "camera.noise: must be a number"),
    (("environment", "file"), "missing.exr", "environment.file: file not found"),
    (("environment", "file"), "\x00", "environment.file: must be a file path"),
    (("camera", "distortion"), [0.1, 0.2, 0.3], "camera.distortion: must be a list of 4, 5"),
    (("camera", "distortion"), [0.1, math.inf, 0.0, 0.0], "camera.distortion: must be finite"),
    (("environment",), _DELETE, "environment: required key is missing"),
    (("environment", "scale"), math.nan, "environment.scale: must be finite"),
    (("environment", "compress_tol"), -1e-3, "environment.compress_tol: must be >= 0"),
    (("environment", "compress_tol"), 0.5, "environment.compress_tol: must be <= 0.1"),
    (("spectral", "mode"), "rgb", "spectral.mode: must be one of"),
    (("spectral", "end_nm"), 300.0, "spectral.end_nm: must be >= 360"),
    (("interreflection", "mode"), "radiosity", "interreflection.mode: must be one of"),
    (("interreflection", "bounces"), 99, "interreflection.bounces: must be in"),
    (("interreflection", "gather_size"), 24, "interreflection.gather_size: must be a power"),
    (("interreflection", "gather_size"), 128, "interreflection.gather_size: must be in"),
    (("objects",), [], "objects: need at least one"),
    (("objects", 0, "material", "mu"), -0.1, r"objects\[0\].material.mu: must be > 0"),
    (("objects", 1, "material", "n"), 1.0, r"objects\[1\].material.n: must be > 1"),
    (("objects", 0, "material", "reflectance"), "colourchecker:ColorChecker N Ohta/teal",
     "unknown patch"),
    (("objects", 0, "material", "reflectance"), "nofile.csv", "file not found"),
    (("objects", 0, "material", "reflectance"), "a\x00.csv", "reflectance"),
    (("objects", 1, "name"), "yellow", "names must be unique"),
    (("objects", 0, "shape"), "cube", r"objects\[0\].shape: must be one of"),
    (("objects", 0, "colour"), "blue", r"objects\[0\].colour: unknown key"),
    (("display", "colourspace"), "Nope RGB", "display.colourspace: unknown RGB colourspace"),
]


@pytest.mark.parametrize("keys, value, match", MALFORMED)
def test_malformed_configs(config_dir, keys, value, match):
    data = _base(config_dir)
    _set(data, keys, value)
    with pytest.raises(InputError, match=match) as exc:
        parse_scene(data, path=config_dir / "scene.toml")
    assert "scene.toml" in str(exc.value)


def test_syntax_error_and_missing_file(config_dir):
    p = config_dir / "broken.toml"
    p.write_text("[frame\nwidth = 3\n")
    with pytest.raises(InputError, match="broken.toml: TOML syntax error"):
        load_scene(p)
    with pytest.raises(InputError, match="cannot read"):
        load_scene(config_dir / "absent.toml")


def test_reflectance_from_csv(config_dir):
    (config_dir / "grey.csv").write_text("nm,R\n370,0.4\n600,0.5\n790,0.6\n")
    data = _base(config_dir)
    data["objects"][0]["material"]["reflectance"] = "grey.csv"
    scene = parse_scene(data, path=config_dir / "scene.toml")
    wl = scene.wavelengths
    np.testing.assert_allclose(scene.objects[0].material.reflectance,
                               np.interp(wl, [370, 600, 790], [0.4, 0.5, 0.6]))
    (config_dir / "pct.csv").write_text("nm,R\n370,40\n790,60\n")
    data["objects"][0]["material"]["reflectance"] = "pct.csv"
    with pytest.raises(InputError, match="percentage"):
        parse_scene(data, path=config_dir / "scene.toml")


_leaf = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                  st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
                  st.lists(st.floats(-10, 10), max_size=5))
_value = st.recursive(_leaf, lambda c: st.one_of(st.lists(c, max_size=3),
                                                  st.dictionaries(st.text(max_size=8), c,
                                                                  max_size=3)), max_leaves=8)


def _paths(d, prefix=()):
    if isinstance(d, dict):
        for k, v in d.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield (*prefix, i)
            yield from _paths(v, (*prefix, i))


@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_config_loader(tmp_path_factory, data):
    """≥ 1000 generated configs (valid ones mutated at random places): a Scene or an InputError,
    never another exception."""
    d = tmp_path_factory.mktemp("fuzz")
    shutil.copy(CONFIG, d / "scene.toml")
    (d / "env.exr").write_bytes(b"x")
    cfg = tomllib.loads(CONFIG.read_text().replace(
        "../measurements/environment/studio_room.exr", "env.exr"))
    cfg = copy.deepcopy(cfg)
    paths = list(_paths(cfg))
    for _ in range(data.draw(st.integers(1, 3))):
        keys = data.draw(st.sampled_from(paths))
        try:
            _set(cfg, keys, data.draw(st.one_of(st.just(_DELETE), _value)))
        except (KeyError, IndexError, TypeError):
            pass
        paths = list(_paths(cfg)) or [("frame",)]
    try:
        scene = parse_scene(cfg, path=d / "scene.toml")
    except InputError:
        return
    assert scene.width > 0 and np.all(np.isfinite(scene.objects[0].material.reflectance))


def test_environment_compression_reaches_the_prepared_map(tmp_path):
    """``[environment] compress_tol`` of the two-sphere config (the bundled studio room, a
    measured map of nearly full spectral rank) sets how many principal spectra the prepared
    map keeps: 75 of 81 at the default 1e-4, 34 at 1e-3 (docs/lighting.md); the loader keeps
    the value."""
    from spectral_fit.rendering import prepare

    text = CONFIG.read_text().replace('../measurements/', str(ROOT / "measurements") + "/")
    ranks = {}
    for tol in (None, 1e-3):
        t = text if tol is None else text.replace("rotation_y_deg = 0.0",
                                                   f"rotation_y_deg = 0.0\ncompress_tol = {tol}")
        p = tmp_path / f"s{tol}.toml"
        p.write_text(t)
        scene = load_scene(p)
        assert scene.environment.compress_tol == (1e-4 if tol is None else tol)
        prep = prepare(scene, size=(48, 32), mode="none")
        ranks[tol] = prep.lighting.env.spectral_basis.shape[0]
    assert ranks == {None: 75, 1e-3: 34}

"""Camera photographs as readings of a fit (``[[images]]``): the pixel rays' convention, the
Bayer sites, the loader's errors, and a synthetic raw photograph rendered by the frame renderer
(a second implementation of the model) fitted back."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from spectral_fit import fitting
from spectral_fit._runtime.errors import InputError
from spectral_fit.io import load_scene, load_session, write_session

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "two_spheres_photo.toml"
POSE = {"position": [0.0, 0.05, 0.0], "aim": [0.045, 0.0, -0.275], "fov_y_deg": 16.0}


def _sensitivities(wl: np.ndarray) -> np.ndarray:
    """(3, L) camera sensitivities from colour-science (Nikon D5100, NPL), counts per unit."""
    import colour

    cam = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    s = np.stack([np.interp(wl, cam.wavelengths, cam.values[:, c], left=0.0, right=0.0)
                  for c in range(3)])
    return s / s.max() * 3.0e6


def _one_sphere(truth: dict[str, float]) -> object:
    """The photo config with only the red sphere, its material set to ``truth``."""
    scene = load_scene(CONFIG)
    red = next(o for o in scene.objects if o.name == "red")
    return dataclasses.replace(scene, objects=(red,)), dataclasses.replace(
        scene, objects=(dataclasses.replace(red, material=dataclasses.replace(
            red.material, **truth)),))


def _image(pixels: np.ndarray, **kw: object) -> dict:
    wl = load_scene(CONFIG).wavelengths
    return {"id": "photo", "pixels": pixels, "sensitivities": _sensitivities(wl),
            "exposure_s": 0.01, "camera": POSE} | kw


def test_pixel_rays_follow_the_frame_convention() -> None:
    """A world point projected by the OpenGL camera (spectral_fit.geometry) lands on the pixel
    whose ray passes through it, for a field of view and for the equivalent intrinsics."""
    import jax.numpy as jnp

    from spectral_fit.geometry import look_at, perspective
    from spectral_fit.io import ImageReading

    W, H, fov = 64, 48, 30.0
    base = dict(id="x", file=Path("x"), pixels=np.zeros((H, W)), mosaic="RGGB",
                sensitivities=np.ones((3, 2)), exposure_s=1.0, black_level=0.0,
                white_level=1.0, saturation=1.0, read_noise=1.0, gain=0.0, superpixel=8,
                samples=2, objects=(), position=np.array([0.1, 0.2, 0.3]),
                aim=np.array([-0.05, 0.0, -0.3]), up=np.array([0.0, 1.0, 0.0]), line=None,
                index=0)
    f = H / 2 / math.tan(math.radians(fov) / 2)
    cams = [ImageReading(fov_y_deg=fov, intrinsics=None, **base),
            ImageReading(fov_y_deg=None, intrinsics=np.array([f, f, W / 2 - 0.5,
                                                              H / 2 - 0.5]), **base)]
    p = np.array([0.02, -0.03, -0.25])
    V = np.asarray(look_at(jnp.asarray(base["position"]), jnp.asarray(base["aim"])))
    P = np.asarray(perspective(fov, W / H))
    clip = P @ V @ np.append(p, 1.0)
    ndc = clip[:2] / clip[3]
    xy = np.array([[(ndc[0] + 1) / 2 * W, (1 - ndc[1]) / 2 * H]])
    for cam in cams:
        d = fitting.pixel_rays(cam, xy)[0]
        to_p = (p - base["position"]) / np.linalg.norm(p - base["position"])
        assert np.degrees(np.arccos(min(1.0, float(d @ to_p)))) < 1e-3


def test_mosaic_rows_sample_their_own_sites() -> None:
    """In an RGGB bin the R samples sit half a pixel up-left of the G samples and B half a
    pixel down-right (the centroids of their sites), each row weighs only its own set, and the
    measured counts are the means over each channel's sites."""
    scene = load_scene(CONFIG)
    geoms = fitting.scene_geometry(scene)
    H, W = 480, 720
    rng = np.random.default_rng(0)
    px = 100.0 + rng.uniform(0, 50, (H, W))
    px[:, W // 2:] = 100.0 + rng.uniform(0, 10, (H, W - W // 2))  # smooth: k = 2
    from spectral_fit.io import ImageReading

    cam = ImageReading(id="x", file=Path("x"), pixels=px, mosaic="RGGB",
                       sensitivities=np.ones((3, scene.wavelengths.size)), exposure_s=1.0,
                       black_level=10.0, white_level=4095.0, saturation=0.98, read_noise=2.0,
                       gain=0.5, superpixel=8, samples=2, objects=(),
                       position=np.array(POSE["position"]), aim=np.array(POSE["aim"]),
                       up=np.array([0.0, 1.0, 0.0]), fov_y_deg=POSE["fov_y_deg"],
                       intrinsics=None, line=None, index=0)
    ir = fitting.image_rows(cam, 0, geoms, [o.name for o in scene.objects], scene.wavelengths)
    assert ir.row_bin.size == 3 * ir.bins.shape[0] > 100
    # each row's weights: 1/k² on its own k × k samples (k = 2, or 4 in a steep bin)
    count = np.bincount(ir.sample_row, minlength=ir.row_bin.size)
    per = np.where(ir.steep[ir.row_bin], 16, 4)
    assert np.array_equal(count, per)
    assert np.allclose(np.bincount(ir.sample_row, ir.sample_weight), 1.0)
    # sample positions: rays through pixel coordinates; compare the first smooth bin's
    first = int(np.flatnonzero(~ir.steep)[0])
    i, j = ir.bins[first]
    g = np.array([2.0, 6.0])
    for c, shift in enumerate((-0.5, 0.0, 0.5)):
        xy = np.array([[j * 8 + gx + shift, i * 8 + gy + shift] for gy in g for gx in g])
        d = fitting.pixel_rays(cam, xy)
        to = ir.pos[ir.sample_row == 3 * first + c] - cam.position
        to /= np.linalg.norm(to, axis=1, keepdims=True)
        assert np.max(np.degrees(np.arccos(np.clip(np.sum(d * to, -1), -1, 1)))) < 1e-3
    block = px[i * 8:(i + 1) * 8, j * 8:(j + 1) * 8] - 10.0
    r0 = 3 * first
    means = [block[0::2, 0::2].mean(), 0.5 * (block[0::2, 1::2].mean()
                                              + block[1::2, 0::2].mean()),
             block[1::2, 1::2].mean()]
    for c in range(3):
        assert ir.measured[r0 + c, c] == pytest.approx(means[c])
        n = 16 if c != 1 else 32
        assert ir.sigma[r0 + c, c] == pytest.approx(math.sqrt((4.0 + 0.5 * means[c]) / n))


def test_bad_images_get_clear_errors(tmp_path: Path) -> None:
    scene = load_scene(CONFIG)
    wl = scene.wavelengths
    good = np.full((48, 64), 500, np.uint16)

    def write(**kw: object) -> Path:
        return write_session(tmp_path / "s", scene=str(CONFIG), wavelengths=wl, readings=[],
                             calibration={"mode": "none"}, images=[_image(good) | kw])

    load_session(write())  # the good one loads
    as_png = load_session(write(format="png"))  # and as a 16-bit PNG, the same counts
    assert np.array_equal(as_png.images[0].pixels, good)
    cases = [
        (dict(mosaic="RGBG"), "images[0].mosaic"),
        (dict(pixels=np.full((47, 64), 500.0)), "pixels"),
        (dict(pixels=np.full((48, 64, 3), 500.0)), "pixels"),
        (dict(mosaic="none"), "pixels"),
        (dict(superpixel=7), "images[0].superpixel"),
        (dict(black_level=5000.0, white_level=4095.0), "images[0].black_level"),
        (dict(objects=["blue"]), "images[0].objects"),
        (dict(camera={"position": [0, 0, 0], "aim": [0, 0, -1]}), "images[0].camera"),
        (dict(camera={**POSE, "intrinsics": [100, 100, 32, 24]}), "images[0].camera"),
    ]
    for kw, field in cases:
        with pytest.raises(InputError) as e:
            load_session(write(**kw))
        assert e.value.field == field, (kw, e.value)
    bad = good.astype(np.float64)
    bad[3, 4] = np.nan
    with pytest.raises(InputError) as e:
        load_session(write(pixels=bad))
    assert e.value.field == "pixels" and "photo.npy" in str(e.value.path)
    m = write()
    (m.parent / "images" / "photo_sensitivities.csv").write_text(
        "wavelength,r,g,b\n400,1,-1,0\n700,1,1,1\n")
    with pytest.raises(InputError) as e:
        load_session(m)
    assert "sensitivities" in e.value.field


@pytest.fixture(scope="module")
def photo_session(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    """A 240 × 160 raw RGGB photograph of one glossy sphere, rendered by the frame renderer
    (gloss by its quadrature, diffuse by the exact texel sum; not the fit's radiance cache),
    with shot and read noise and a clipped highlight."""
    truth = {"alpha": 0.9, "beta": 0.9, "chi": 0.0, "mu": 0.08, "n": 1.52}
    scene, true_scene = _one_sphere(truth)
    wl = scene.wavelengths
    sens = _sensitivities(wl)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ph = fitting.simulate_photograph(true_scene, position=POSE["position"],
                                         aim=POSE["aim"], fov_y_deg=POSE["fov_y_deg"],
                                         size=(240, 160), sensitivities=sens, exposure_s=0.01,
                                         read_noise=2.0, gain=0.05, seed=3,
                                         render_options={"diffuse": "exact"})
    folder = tmp_path_factory.mktemp("photo")
    cfg = folder / "scene.toml"
    cfg.write_text(CONFIG.read_text().replace(
        '"../measurements/', f'"{(ROOT / "measurements").as_posix()}/'))
    m = write_session(folder / "session", scene="../scene.toml", wavelengths=wl, readings=[],
                      calibration={"mode": "none"},
                      objects={"red": {"free": ["alpha", "beta", "mu", "n"]}},
                      images=[{"id": "photo", "pixels": ph["raw"].astype(np.uint16),
                               "sensitivities": sens, "exposure_s": 0.01, "black_level": 64.0,
                               "white_level": 4095.0, "read_noise": 2.0, "gain": 0.05,
                               "objects": ["red"], "camera": POSE}])
    return scene, load_session(m, scene=scene), truth, ph


def test_synthetic_photograph_is_fitted_back(photo_session: tuple) -> None:
    scene, session, truth, ph = photo_session
    assert np.sum(ph["raw"] >= 4095) > 0  # the highlight clips
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fitting.fit(scene, session, holdout=False, starts=1)
    im = res.images[0]
    assert im["dropped"]["clipped"] > 0 and im["bins"] > 100
    assert 0 < im["steep_bins"] < im["bins"]
    p = res.params["red"]
    assert p["alpha"] == pytest.approx(truth["alpha"], rel=0.01)
    assert p["beta"] == pytest.approx(truth["beta"], rel=0.03)
    assert p["mu"] == pytest.approx(truth["mu"], rel=0.03)
    assert p["n"] == pytest.approx(truth["n"], abs=0.02)
    # dof: 3 channels' rows of one datum each, 4 unknowns
    assert res.dof == 3 * im["bins"] - 4
    assert im["rms_relative_residual"] < 0.03


def test_photograph_and_spots_fit_together(photo_session: tuple, tmp_path: Path) -> None:
    """Spots of the fit's own model at the truth added to the photograph: one fit uses both
    (rows and data counted per kind), and ``kinds`` selects either."""
    scene, session, truth, _ = photo_session
    spots = [{"object": "red", "position": POSE["position"],
              "aim": [0.045 + dx, dy, -0.275 + 0.0375 * 0.9], "field_angle_deg": 1.0}
             for dx, dy in ((0.0, 0.0), (0.01, 0.005), (-0.01, -0.01))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        meas = fitting.simulate_readings(scene, spots, params={"red": truth})
    from spectral_fit.io import NoiseModel, Reading

    reads = tuple(Reading(id=f"s{i}", object="red", kind="object", files=(),
                          repeats=meas[i][None], position=np.asarray(s["position"], float),
                          aim=np.asarray(s["aim"], float), field_angle_deg=1.0,
                          distance_m=None, line=None, index=i) for i, s in enumerate(spots))
    both = session.replace(readings=reads, noise=NoiseModel(1e-6, 0.005, "manifest"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = fitting.prepare_fit(scene, both)
        res = fitting.fit(scene, both, prepared=prep, holdout=False, starts=1, aim_step_m=0)
        spots_only = fitting.fit(scene, both, prepared=prep, holdout=False, starts=1,
                                 aim_step_m=0, kinds=("object",))
    L = scene.wavelengths.size
    n_img = res.images[0]["bins"] * 3
    assert prep.n_spots == 3 and prep.n_image_rows == n_img
    assert res.dof == 3 * L + n_img - 4
    assert spots_only.dof == 3 * L - 4
    assert len(res.readings) == 3 and res.measured.shape == (3, L)
    assert res.params["red"]["alpha"] == pytest.approx(truth["alpha"], rel=0.01)


@pytest.mark.slow  # the bundled 720 x 480 photograph: preparation ~1 min, solve ~20 s
def test_bundled_photograph_session_recovers_the_materials() -> None:
    """The bundled session (measurements/sessions/two_spheres_photo): one raw photograph and
    a white standard, path-traced by the reference renderer (independent of the fit's model;
    scripts/make_photo_session.py). Recovery tolerances of docs/fitting.md: α 2 %, β 3 %,
    μ 3 %, n 0.02; χ of the glossy yellow sphere, whose highlight clips, within two of its
    reported standard errors (about 0.02: one clipped photograph does not pin it to 0.01)."""
    import json

    folder = ROOT / "measurements" / "sessions" / "two_spheres_photo"
    truth = json.loads((folder / "truth.json").read_text())["params"]
    session = load_session(folder)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fitting.fit(session.scene, session, holdout=False)
    for name, t in truth.items():
        p, se = res.params[name], res.stderr[name]
        assert p["alpha"] == pytest.approx(t["alpha"], rel=0.02)
        assert p["beta"] == pytest.approx(t["beta"], rel=0.03)
        assert p["mu"] == pytest.approx(t["mu"], rel=0.03)
        assert p["n"] == pytest.approx(t["n"], abs=0.02)
        assert abs(p["chi"] - t["chi"]) <= max(0.01, 2.0 * se["chi"])


def test_sensitivities_from_a_chart_predict_other_spectra(tmp_path: Path) -> None:
    """Sensitivities estimated from a ColorChecker shot under D65 (0.5 % noise) predict the
    camera's counts of another chart's patches under illuminant A within 1 % rms and 3 %
    at worst per channel (the true curves: colour-science's Nikon D5100); and a session
    that names the chart files instead of a sensitivity file loads with them."""
    import colour

    from spectral_fit.color import chart_radiance, colour_sd, estimate_camera_sensitivities

    wl = load_scene(CONFIG).wavelengths
    s = _sensitivities(wl)
    dl = np.gradient(wl)
    white = colour_sd(colour.SDS_ILLUMINANTS["D65"], wl) * 1e-4
    chart = chart_radiance(white, wl)
    counts = 0.01 * chart @ (s * dl).T
    noisy = counts * (1 + 0.005 * np.random.default_rng(0).standard_normal(counts.shape))
    est = estimate_camera_sensitivities(noisy, chart, wl, 0.01)
    other = chart_radiance(colour_sd(colour.SDS_ILLUMINANTS["A"], wl) * 1e-4, wl,
                           chart="BabelColor Average")
    rel = (other @ (est * dl).T) / (other @ (s * dl).T) - 1.0
    assert np.all(np.sqrt(np.mean(rel ** 2, axis=0)) < 0.01)
    assert np.all(np.abs(rel) < 0.03)
    # in a session
    m = write_session(tmp_path / "s", scene=str(CONFIG), wavelengths=wl, readings=[],
                      calibration={"mode": "none"},
                      images=[_image(np.full((48, 64), 500, np.uint16))])
    (m.parent / "chart_counts.csv").write_text(
        "patch,r,g,b\n" + "".join(f"{i + 1},{a:.6g},{b:.6g},{c:.6g}\n"
                                  for i, (a, b, c) in enumerate(noisy)))
    (m.parent / "chart_radiance.csv").write_text(
        "wavelength," + ",".join(f"p{i}" for i in range(24)) + "\n" + "".join(
            f"{w:g}," + ",".join(f"{x:.8g}" for x in chart[:, j]) + "\n"
            for j, w in enumerate(wl)))
    text = m.read_text().replace('sensitivities = "images/photo_sensitivities.csv"',
                                 'sensitivities = { chart_counts = "chart_counts.csv", '
                                 'chart_radiance = "chart_radiance.csv", exposure_s = 0.01 }')
    m.write_text(text)
    got = load_session(m).images[0].sensitivities
    assert np.allclose(got, est, rtol=1e-2, atol=1e-3 * est.max())  # CSV rounding

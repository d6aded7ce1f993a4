"""The video camera's colour model from a ColorChecker shot: a synthetic chart photographed by
a camera with measured spectral sensitivities (colour-science's Nikon 5100) under the scene's
environment; the fitted 3×3 reproduces held-out patches; ``spectral-fit calibrate-colour``
writes ``[camera_colour]`` and the live session uses it."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("cv2")

from helpers import ANCHOR_ENV
from helpers.live import scene_dict

from spectral_fit.io import parse_scene
from spectral_fit.live import (
    CameraModel,
    calibrate_colour,
    camera_model_from_sensitivities,
    chart_xyz,
    colorchecker_reflectances,
    encode_frame,
    frame_delta_e00,
)

CORNERS = np.array([[140, 100], [590, 120], [570, 410], [120, 380]], np.float32)
HELD_OUT = [2, 7, 10, 15, 19, 22]


@pytest.fixture(scope="module")
def scene():
    return parse_scene(scene_dict())


def _shot(scene, *, tone="srgb", gamma=2.2, seed=0):
    """(720×480 image of the chart in perspective, encoded patch values (24, 3)) as a Nikon
    5100 white-balanced on the table's white sees the chart on the table."""
    import cv2

    from spectral_fit.lighting import white_reference
    from spectral_fit.rendering import load_environment

    wl = scene.wavelengths
    white = white_reference(load_environment(scene, wl))
    cam = camera_model_from_sensitivities("Nikon 5100 (NPL)", wl, white, white_level=0.8)
    lin = np.asarray(cam.linear_from_spectra(jnp.asarray(colorchecker_reflectances(wl)
                                                         * white)))
    curve = CameraModel(cam.spectral_weights, cam.xyz_matrix, cam.wavelengths, tone=tone,
                        gamma=gamma)
    enc = np.asarray(encode_frame(jnp.asarray(lin), curve), np.float64)
    cells = np.zeros((200, 300, 3), np.float32)
    for i in range(24):
        r, c = divmod(i, 6)
        cells[r * 50 + 5:r * 50 + 45, c * 50 + 5:c * 50 + 45] = enc[i] * 255
    h = cv2.getPerspectiveTransform(np.float32([[0, 0], [300, 0], [300, 200], [0, 200]]),
                                    CORNERS)
    img = cv2.warpPerspective(cells, h, (720, 480), flags=cv2.INTER_LINEAR,
                              dst=np.full((480, 720, 3), 90, np.float32),
                              borderMode=cv2.BORDER_TRANSPARENT)
    rng = np.random.default_rng(seed)
    img = np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8)
    return img, enc


def test_chart_fit_reproduces_held_out_patches(scene):
    img, enc = _shot(scene)
    xyz, white = chart_xyz(scene)
    cal = calibrate_colour(img, CORNERS, xyz, white, hold_out=HELD_OUT)
    unclipped = np.all((enc > 0.02) & (enc < 0.98), axis=1)  # the cyan's red is clipped
    assert not cal.used[HELD_OUT].any()
    np.testing.assert_array_equal(cal.used, unclipped & ~np.isin(np.arange(24), HELD_OUT))
    # held-out patches: predicted frame colour vs the true (noise-free) one
    pred = np.asarray(encode_frame(cal.model.linear_from_xyz(jnp.asarray(xyz[HELD_OUT],
                                                                         jnp.float32)),
                                   cal.model))
    de = frame_delta_e00(pred, enc[HELD_OUT])
    assert de.mean() < 1.0 and de.max() < 2.0, de
    # the fit is not exact (the Nikon is not colorimetric): a wrong matrix would show
    assert cal.delta_e00[cal.used].mean() > 0.2
    # decomposition: diag(wb)·matrix is the fitted map; the matrix makes the white neutral
    np.testing.assert_allclose(np.diag(cal.white_balance) @ cal.matrix,
                               np.asarray(cal.model.xyz_matrix), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(cal.matrix @ white, white[1] * np.ones(3), rtol=1e-5)
    # the camera was white-balanced on this white, shown at 0.8: equal gains of 0.8 / Y_w
    np.testing.assert_allclose(cal.white_balance * white[1], 0.8, rtol=0.03)


def test_tone_curve_exponent_fitted_on_the_neutral_patches(scene):
    img, _ = _shot(scene, tone="gamma", gamma=2.0, seed=1)
    xyz, white = chart_xyz(scene)
    cal = calibrate_colour(img, CORNERS, xyz, white, tone="fit")
    assert cal.tone == "gamma" and abs(cal.gamma - 2.0) < 0.06
    assert cal.delta_e00[cal.used].mean() < 1.5
    # fitting with the wrong curve is measurably worse
    wrong = calibrate_colour(img, CORNERS, xyz, white, tone="srgb")
    assert wrong.delta_e00[wrong.used].mean() > cal.delta_e00[cal.used].mean() + 0.3


def test_calibrate_colour_command_writes_the_config_and_live_uses_it(scene, tmp_path, capsys):
    import cv2

    from spectral_fit.cli import main
    from spectral_fit.io import load_scene
    from spectral_fit.live import scene_camera_model

    img, enc = _shot(scene, seed=2)
    png = tmp_path / "chart.png"
    cv2.imwrite(str(png), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    cfg = tmp_path / "scene.toml"
    cfg.write_text("\n".join([
        "# my scene", "[frame]", "width = 720", "height = 480", "",
        "[environment]", f'file = "{ANCHOR_ENV}"', "rotation_y_deg = 180.0  # keep me", "",
        "[spectral]", "start_nm = 400.0", "end_nm = 700.0", "step_nm = 10.0", "",
        "[camera_colour]", "matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]", "",
        "[[objects]]", 'name = "ball"', "radius = 0.03", ""]))
    corners = " ".join(f"{x:g},{y:g}" for x, y in CORNERS)
    rc = main(["calibrate-colour", str(png), "--config", str(cfg), "--corners", corners,
               "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    out = tmp_path / "scene.colour.toml"
    unclipped = np.all((enc > 0.02) & (enc < 0.98), axis=1)
    assert res["output"] == str(out) and res["patches_used"] == unclipped.sum() >= 20
    assert res["delta_e00_mean"] < 1.5
    text = out.read_text()
    assert "# my scene" in text and "# keep me" in text and text.count("[camera_colour]") == 1
    spec = load_scene(out).camera_colour
    np.testing.assert_allclose(spec.matrix, res["matrix"], rtol=1e-7)
    np.testing.assert_allclose(spec.white_balance, res["white_balance"], rtol=1e-7)
    # the live session's camera model is the config's: it reproduces the shot
    model = scene_camera_model(load_scene(out))
    assert not model.has_spectral and model.tone == "srgb"
    xyz, _ = chart_xyz(scene)
    pred = np.asarray(encode_frame(model.linear_from_xyz(jnp.asarray(xyz, jnp.float32)),
                                   model))
    assert frame_delta_e00(pred, enc).mean() < 1.5
    # an explicit --sensitivities (here: the Python keyword) overrides the config
    assert scene_camera_model(load_scene(out), sensitivities="Nikon 5100 (NPL)").has_spectral
    # errors name the option; an existing output is kept
    rc = main(["calibrate-colour", str(png), "--config", str(cfg), "--corners", corners])
    assert rc == 2 and "--output: exists" in capsys.readouterr().err
    rc = main(["calibrate-colour", str(png), "--config", str(cfg), "--corners", "1,2 3,4",
               "-o", str(tmp_path / "x.toml")])
    assert rc == 2 and "--corners: need 4 corners" in capsys.readouterr().err


@pytest.mark.parametrize(("table", "key"), [
    ({"matrix": [[1, 0], [0, 1]]}, "camera_colour.matrix"),
    ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 0]]}, "camera_colour.matrix"),
    ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "white_balance": [1, 0, 1]},
     "camera_colour.white_balance"),
    ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "tone": "log"}, "camera_colour.tone"),
    ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "gain": 2}, "camera_colour.gain"),
])
def test_camera_colour_table_errors_name_the_key(table, key):
    from spectral_fit._runtime.errors import InputError

    d = scene_dict()
    d["camera_colour"] = table
    with pytest.raises(InputError) as e:
        parse_scene(d, path="live.toml")
    assert e.value.field == key

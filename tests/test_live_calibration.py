"""Calibration: known intrinsics and distortion recovered from synthetic target images; the
calibrated config is a new, valid file; the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("cv2")

import cv2
from helpers import ANCHOR_ENV
from helpers.live import DIST, SIZE, K

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import load_scene
from spectral_fit.live import (
    CalibrationTarget,
    Table,
    calibrate_images,
    camera_pose_looking_at,
    render_table,
    target_image,
    write_calibrated_config,
)


def _views(target, n, seed=0):
    pitch = target.square_size / 80
    img = cv2.copyMakeBorder(target_image(target, 80), 40, 40, 40, 40, cv2.BORDER_CONSTANT,
                             value=255)
    h, w = img.shape
    table = Table(np.repeat(img[..., None], 3, -1), -w * pitch / 2, -h * pitch / 2, pitch, ())
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        eye = (rng.uniform(-0.2, 0.2), rng.uniform(0.2, 0.35), rng.uniform(-0.05, 0.25))
        look = (rng.uniform(-0.04, 0.04), 0.0, rng.uniform(-0.03, 0.03))
        r, t = camera_pose_looking_at(eye, look, up=(np.sin(rng.uniform(-0.5, 0.5)), 0, -1))
        out.append(render_table(table, K, DIST, r, t, SIZE, blur_px=0.7, noise=2.0, rng=rng))
    return out


def _max_map_error_px(cal):
    """Largest difference (px) between the true and calibrated undistortion over the central
    80 % of the frame (the region the views covered)."""
    jj, ii = np.meshgrid(np.linspace(0.1, 0.9, 25) * SIZE[1], np.linspace(0.1, 0.9, 17) * SIZE[0])
    pts = np.stack([jj.ravel(), ii.ravel()], -1).reshape(-1, 1, 2)
    a = cv2.undistortPoints(pts, K, DIST, P=K).reshape(-1, 2)
    b = cv2.undistortPoints(pts, cal.k, cal.dist, P=K).reshape(-1, 2)
    return float(np.max(np.linalg.norm(a - b, axis=1)))


@pytest.fixture(scope="module")
def charuco():
    target = CalibrationTarget(kind="charuco", squares=(9, 6), square_size=0.03,
                               marker_size=0.022)
    return target, _views(target, 8, seed=2)


@pytest.mark.parametrize(("kind", "map_px"), [("charuco", 2.5), ("chessboard", 0.5)])
def test_calibration_recovers_known_camera(kind, map_px, charuco):
    """ChArUco corners are noisier here (RMS ~0.12 px against ~0.03 px for the chessboard's
    saddle-point detector), hence its looser ray-direction bound."""
    if kind == "charuco":
        target, images = charuco
    else:
        target = CalibrationTarget(kind="chessboard", squares=(9, 6), square_size=0.03)
        images = _views(target, 7, seed=2)
    cal = calibrate_images(images, target)
    assert cal.views >= 6
    assert cal.rms_px < 0.3
    np.testing.assert_allclose([cal.k[0, 0], cal.k[1, 1]], [K[0, 0], K[1, 1]], rtol=5e-3)
    np.testing.assert_allclose([cal.k[0, 2], cal.k[1, 2]], [K[0, 2], K[1, 2]], atol=2.0)
    np.testing.assert_allclose(cal.dist[:2], DIST[:2], atol=0.01)
    assert _max_map_error_px(cal) < map_px
    # ignoring distortion would be far off: the test can tell
    zero = type(cal)(K, np.zeros(5), 0.0, SIZE, 0, ())
    assert _max_map_error_px(zero) > 10


def _config(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_text(f'''# my scene
[frame]
width = 720
height = 480

[camera]
fov_y_deg = 60.0  # replaced by the intrinsics
distortion = [0.0, 0.0, 0.0, 0.0]

[environment]
file = "{ANCHOR_ENV}"

[[objects]]
name = "ball"
radius = 0.03
stacks = 8
slices = 8

[objects.material]
reflectance = 0.5
''')
    return p


def test_calibrated_config_is_a_new_valid_file(tmp_path, charuco):
    target, images = charuco
    cal = calibrate_images(images, target)
    src = _config(tmp_path)
    before = src.read_text()
    dest = write_calibrated_config(src, cal)
    assert dest == tmp_path / "scene.calibrated.toml"
    assert src.read_text() == before
    scene = load_scene(dest)
    assert scene.camera.intrinsics == pytest.approx(cal.intrinsics(), abs=1e-5)
    assert scene.camera.distortion == pytest.approx(tuple(cal.dist), abs=1e-8)
    text = dest.read_text()
    assert "# my scene" in text and text.count("distortion") == 1
    with pytest.raises(InputError, match="--overwrite"):
        write_calibrated_config(src, cal)
    # recalibrating over the calibrated file replaces its keys in place
    again = write_calibrated_config(dest, cal, dest, overwrite=True)
    assert again.read_text().count("intrinsics =") == 1


def test_frame_size_must_match(tmp_path, charuco):
    target, images = charuco
    cal = calibrate_images(images, target)
    src = _config(tmp_path)
    src.write_text(src.read_text().replace("width = 720", "width = 640"))
    with pytest.raises(InputError, match="640x480 but the images are 720x480"):
        write_calibrated_config(src, cal)
    assert not (tmp_path / "scene.calibrated.toml").exists()


def test_too_few_views_is_a_clear_error():
    target = CalibrationTarget()
    blank = [np.full((120, 160, 3), 128, np.uint8)] * 4
    with pytest.raises(InputError, match="at least 3 images, found it in 0"):
        calibrate_images(blank, target)


def test_calibrate_command(tmp_path, charuco, capsys):
    from spectral_fit.cli import main

    _, images = charuco
    paths = []
    for i, im in enumerate(images[:5]):
        p = tmp_path / f"view{i}.png"
        cv2.imwrite(str(p), im[..., ::-1])
        paths.append(str(p))
    src = _config(tmp_path)
    out = tmp_path / "cal.toml"
    rc = main(["calibrate", *paths, "--squares", "9x6", "--config", str(src), "-o", str(out),
               "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["views"] == 5 and res["output"] == str(out)
    assert load_scene(out).camera.intrinsics["fx"] == pytest.approx(K[0, 0], rel=0.01)
    rc = main(["calibrate", str(tmp_path / "missing.png"), "--config", str(src), "-o",
               str(tmp_path / "x.toml")])
    assert rc == 2
    assert "missing.png: images: cannot read image" in capsys.readouterr().err

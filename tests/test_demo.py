"""The README's main command (`spectral-fit demo`) on the bundled data."""

import json

import numpy as np
from PIL import Image

from spectral_fit.cli import main
from spectral_fit.colorimetry import radiance_to_xyz
from spectral_fit.exr import read_spectral_exr


def test_demo_writes_pictures_and_summary(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == json.loads((out / "summary.json").read_text())
    env = summary["environment"]
    wl, img = read_spectral_exr(env["file"])
    y = radiance_to_xyz(img.astype(np.float64), wl)[..., 1]
    assert env["luminance_cd_m2"]["median"] == np.median(y)
    png = np.asarray(Image.open(out / "environment.png"))
    assert png.shape == (img.shape[0], img.shape[1], 3)
    for name in env["pictures"]:
        assert (out / name).stat().st_size > 1000

"""Frame outputs: EXR/PNG round trips, composite, atomic writes, clear errors (no rendering:
a synthetic Frame)."""

from __future__ import annotations

import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError


def _frame(h=12, w=16, bands=31, seed=0):
    import jax.numpy as jnp

    from spectral_fit.rendering import Frame

    rng = np.random.default_rng(seed)
    mask = np.zeros((h, w), bool)
    mask[3:9, 4:11] = True
    return Frame(
        xyz=jnp.asarray(rng.uniform(0.0, 300.0, (h, w, 3)), jnp.float32),
        rgb=jnp.asarray(rng.uniform(0.0, 1.0, (h, w, 3)), jnp.float32),
        linear_rgb=jnp.asarray(rng.uniform(-0.2, 1.4, (h, w, 3)), jnp.float32),
        mask=jnp.asarray(mask),
        object_id=jnp.asarray(np.where(mask, 0, -1), jnp.int32),
        spectral=jnp.asarray(rng.uniform(0.0, 0.05, (h, w, bands)), jnp.float32),
        stats={},
    )


def test_round_trips(tmp_path):
    from PIL import Image

    from spectral_fit.io import read_channels_exr, read_spectral_exr
    from spectral_fit.rendering import write_frame

    f = _frame()
    wl = np.arange(400.0, 701.0, 10.0)
    files = dict(png=tmp_path / "f.png", exr=tmp_path / "f.exr", xyz_exr=tmp_path / "x.exr",
                 rgb_exr=tmp_path / "r.exr", mask_png=tmp_path / "m.png")
    written = write_frame(f, wavelengths=wl, **files)
    assert sorted(written) == sorted(str(p) for p in files.values())
    wl2, spec = read_spectral_exr(files["exr"])
    np.testing.assert_allclose(wl2, wl)
    np.testing.assert_array_equal(spec, np.asarray(f.spectral))
    np.testing.assert_array_equal(read_channels_exr(files["xyz_exr"], "XYZ"), np.asarray(f.xyz))
    np.testing.assert_array_equal(read_channels_exr(files["rgb_exr"], "RGB"),
                                  np.asarray(f.linear_rgb))
    png = np.asarray(Image.open(files["png"]).convert("RGB"))
    np.testing.assert_array_equal(png, np.round(np.asarray(f.rgb, np.float64) * 255))
    m = np.asarray(Image.open(files["mask_png"]))
    np.testing.assert_array_equal(m, np.where(np.asarray(f.mask), 255, 0))
    # atomic writes leave no temporary files behind
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in files.values())


def test_composite_over_a_background_picture(tmp_path):
    from PIL import Image

    from spectral_fit.rendering import write_frame

    f = _frame()
    bg = np.random.default_rng(5).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    Image.fromarray(bg).save(tmp_path / "bg.png")
    write_frame(f, composite_png=tmp_path / "c.png", background=tmp_path / "bg.png")
    c = np.asarray(Image.open(tmp_path / "c.png").convert("RGB"))
    mask = np.asarray(f.mask)
    np.testing.assert_array_equal(c[~mask], bg[~mask])
    np.testing.assert_array_equal(c[mask], np.round(np.asarray(f.rgb, np.float64) * 255)[mask])


def test_errors_name_the_file_or_field(tmp_path):
    from PIL import Image

    from spectral_fit.io import read_channels_exr
    from spectral_fit.rendering import write_frame, write_xyz_exr

    f = _frame()
    Image.fromarray(np.zeros((5, 5, 3), np.uint8)).save(tmp_path / "small.png")
    with pytest.raises(InputError, match="small.png.*background"):
        write_frame(f, composite_png=tmp_path / "c.png", background=tmp_path / "small.png")
    with pytest.raises(InputError, match="background"):
        write_frame(f, composite_png=tmp_path / "c.png")
    (tmp_path / "junk.png").write_bytes(b"not a picture")
    with pytest.raises(InputError, match="junk.png"):
        write_frame(f, composite_png=tmp_path / "c.png", background=tmp_path / "junk.png")
    with pytest.raises(InputError, match="exr"):
        write_frame(f._replace(spectral=None) if hasattr(f, "_replace") else
                    _no_spectral(f), exr=tmp_path / "s.exr", wavelengths=np.arange(31))
    with pytest.raises(InputError, match="NaN"):
        write_xyz_exr(tmp_path / "n.exr", np.full((2, 2, 3), np.nan))
    write_xyz_exr(tmp_path / "ok.exr", np.ones((2, 2, 3)))
    with pytest.raises(InputError, match="channel"):
        read_channels_exr(tmp_path / "ok.exr", "RGB")
    assert not (tmp_path / "c.png").exists() and not (tmp_path / "n.exr").exists()


def _no_spectral(f):
    import dataclasses

    return dataclasses.replace(f, spectral=None)

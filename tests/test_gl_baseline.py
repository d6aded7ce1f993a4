"""The OpenGL baseline (spectral_fit.bench.cases.gl) against the JAX renderer.

Both render the benchmark scene (configs/benchmark.toml: two UV spheres of 100 × 100, 31 bands,
the bundled anchor environment) at 360×240 from the same ``prepare(scene, mode="paper")``
precomputation: the baseline in OpenGL (pass 1 into textures, pass 2 reading them back,
llvmpipe), the JAX renderer through its own rasteriser and shading. Colours are compared as
CIEDE2000 of absolute XYZ against a stated white: the display white (D65) at the frame's
exposure luminance, i.e. the luminance shown as display white. Skipped when moderngl is not
installed or EGL cannot make an OpenGL 4.5 context.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

# one worker runs this module's tests (ONE_WORKER_MODULES in tests/conftest.py), and the
# frames are a session fixture: the OpenGL context and both frames are built once per run

SIZE = (360, 240)


@pytest.fixture(scope="session")
def frames(tmp_path_factory):
    pytest.importorskip("moderngl", reason="moderngl not installed (pip install "
                        "'spectral_fit[gl]')")
    from spectral_fit.bench.cases.gl import GLUnavailable, create_context

    try:
        ctx = create_context()
    except GLUnavailable as exc:
        pytest.skip(f"no OpenGL 4.5 context through EGL: {exc}")
    from spectral_fit.bench.cases.frame import benchmark_scene
    from spectral_fit.bench.cases.gl import BaselineInputs, GLBaseline, baseline_inputs
    from spectral_fit.rendering import prepare, render_frame

    prep = prepare(benchmark_scene(), size=SIZE, mode="paper")
    inputs = baseline_inputs(prep)
    # the inputs travel through their file format (what a fresh process of the bench reads)
    path = tmp_path_factory.mktemp("gl") / "inputs.npz"
    inputs.save(path)
    inputs = BaselineInputs.load(path)
    gl = GLBaseline(inputs, ctx=ctx)
    out = {"white": inputs.white_xyz}
    out["gl_paper"], out["gl_object"] = gl.render_xyz(True)
    out["gl_none"], out["gl_object_none"] = gl.render_xyz(False)
    out["gl_rgb8"] = gl.render(True)
    # the anchor workload (60° pass-1 views, no culling, mip chains, lookups everywhere)
    wide = GLBaseline(baseline_inputs(prep, pass1_fov_deg=60.0), ctx=ctx, cull="none",
                      pass1_mipmaps=True, interreflection_everywhere=True)
    out["gl_anchor_workload"], out["gl_object_anchor"] = wide.render_xyz(True)
    f = render_frame(prep)
    f0 = render_frame(dataclasses.replace(prep, interreflection=dataclasses.replace(
        prep.interreflection, mode="none")))
    out["jax_paper"], out["jax_none"] = np.asarray(f.xyz), np.asarray(f0.xyz)
    out["jax_rgb"] = np.asarray(f.rgb)
    out["jax_object"] = np.asarray(f.object_id)
    ctx.release()
    return out


def _delta_e(a: np.ndarray, b: np.ndarray, white: np.ndarray) -> np.ndarray:
    from spectral_fit.color import delta_e00, xyz_to_lab

    return delta_e00(xyz_to_lab(a, white), xyz_to_lab(b, white))


def _spheres(frames: dict) -> np.ndarray:
    """Pixels both renderers cover with the same object."""
    g, j = frames["gl_object"], frames["jax_object"]
    return (g >= 0) & (g == j)


def test_the_two_renderers_cover_the_same_pixels(frames):
    g, j = frames["gl_object"] >= 0, frames["jax_object"] >= 0
    assert j.sum() > 1000
    assert (g & j).sum() / (g | j).sum() > 0.99
    assert np.array_equal(frames["gl_object"] >= 0, frames["gl_object_none"] >= 0)


@pytest.mark.parametrize("mode", ["paper", "none"])
def test_frame_colours_match_the_jax_renderer(frames, mode):
    m = _spheres(frames)
    de = _delta_e(frames[f"gl_{mode}"][m], frames[f"jax_{mode}"][m], frames["white"])
    assert np.percentile(de, 90) <= 0.5, np.percentile(de, [50, 90, 100])
    assert np.median(de) <= 0.1
    # the background: the environment through every pixel centre
    bg = (frames["gl_object"] < 0) & (frames["jax_object"] < 0)
    de_bg = _delta_e(frames[f"gl_{mode}"][bg], frames[f"jax_{mode}"][bg], frames["white"])
    assert np.percentile(de_bg, 99) <= 0.1


def test_interreflection_adds_the_same_light(frames):
    """Eq. (6)'s lookup (the pass-1 textures seen from the receiver's centre): the light each
    renderer adds to the frame without interreflection, where either adds any."""
    m = _spheres(frames)
    add_gl = (frames["gl_paper"] - frames["gl_none"])[m]
    add_jax = (frames["jax_paper"] - frames["jax_none"])[m]
    peak = np.abs(add_jax[:, 1]).max()
    assert peak > 1e-3 * frames["white"][1]  # paper mode lights a sliver beside the gap
    lit_jax = np.abs(add_jax[:, 1]) > 0.05 * peak
    lit_gl = np.abs(add_gl[:, 1]) > 0.05 * peak
    assert lit_jax.sum() >= 5
    assert (lit_gl & lit_jax).sum() >= 0.8 * (lit_gl | lit_jax).sum()
    err = np.abs(add_gl - add_jax)[lit_gl | lit_jax].max()
    assert err <= 0.05 * peak, (err, peak)


def test_anchor_workload_renders_the_same_interreflection(frames):
    """``gl_paper_anchor_workload`` only adds work: no face culling (the depth test keeps the
    nearest), a narrower pass-1 view (the sender sampled more finely), mip chains the frame does
    not read, and lookups weighted by zero outside the sender's view. Its frame is
    ``gl_paper``'s, up to the pass-1 sampling in the interreflection."""
    assert np.array_equal(frames["gl_object_anchor"], frames["gl_object"])
    m = _spheres(frames)
    de = _delta_e(frames["gl_anchor_workload"][m], frames["gl_paper"][m], frames["white"])
    assert np.percentile(de, 99) <= 0.5 and np.median(de) <= 0.01, np.percentile(de, [50, 99])
    add = (frames["gl_anchor_workload"] - frames["gl_none"])[m]
    ref = (frames["gl_paper"] - frames["gl_none"])[m]
    peak = np.abs(ref[:, 1]).max()
    assert np.abs(add[:, 1]).max() > 0.5 * peak  # it lights the same sliver
    assert np.abs(add - ref).max() <= 0.1 * peak


def test_display_image_matches_the_jax_renderer(frames):
    """The 8-bit image the timed frame reads back (exposure, 3 × 3, clip, sRGB curve in the
    shader) against the JAX frame's display RGB."""
    ref = np.rint(np.clip(frames["jax_rgb"], 0.0, 1.0) * 255.0).astype(int)
    diff = np.abs(frames["gl_rgb8"].astype(int) - ref).max(axis=-1)
    m = _spheres(frames)
    assert np.percentile(diff[m], 99) <= 1
    assert np.percentile(diff, 99.9) <= 1


def test_missing_moderngl_is_a_one_line_error(monkeypatch, capsys):
    from spectral_fit.cli import main

    monkeypatch.setitem(sys.modules, "moderngl", None)
    assert main(["bench", "--gl-baseline", "--quick"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "moderngl" in err and "Traceback" not in err

"""The two work layouts (spectral_fit._runtime.backend): the accelerator layout (whole batches at
once, no device loops or conditionals) renders the same frame, with the same gradients, as the CPU
layout (chunks in a loop, empty chunks skipped). Both run here on the CPU."""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers.rendering import write_scene

from spectral_fit import rendering
from spectral_fit._runtime import backend
from spectral_fit._runtime.errors import InputError
from spectral_fit.geometry import _prefix as prefix
from spectral_fit.geometry import _raster_setup as raster_setup
from spectral_fit.rendering import _shading as shading

# the interreflection's modules that look up the layout and the chunk sizes
ir_atlas = importlib.import_module("spectral_fit.rendering.interreflection._atlas")
ir_gather = importlib.import_module("spectral_fit.rendering.interreflection._gather")
ir_gloss = importlib.import_module("spectral_fit.rendering.interreflection._gloss")


def test_layout_variable(monkeypatch):
    monkeypatch.setenv(backend.LAYOUT_VARIABLE, "accelerator")
    assert backend.on_accelerator()
    monkeypatch.setenv(backend.LAYOUT_VARIABLE, "CPU")
    assert not backend.on_accelerator()
    monkeypatch.setenv(backend.LAYOUT_VARIABLE, "auto")
    assert backend.on_accelerator() == (jax.default_backend() != "cpu")
    monkeypatch.delenv(backend.LAYOUT_VARIABLE)
    assert backend.on_accelerator() == (jax.default_backend() != "cpu")
    monkeypatch.setenv(backend.LAYOUT_VARIABLE, "gpu")
    with pytest.raises(InputError, match="SPECTRAL_FIT_LAYOUT.*'gpu'"):
        backend.on_accelerator()


@pytest.fixture(scope="module")
def prep(scene_folder):
    # gather interreflection, two colours, a mirror term: every layout-dependent path runs
    return rendering.prepare(write_scene(scene_folder, mode="gather", same_colour=False,
                                        chi=0.3))


def _with_layout(monkeypatch, accelerator: bool, fn):
    """fn() traced afresh with the given layout; returns (result, layout queries made)."""
    calls = []

    def layout() -> bool:
        calls.append(accelerator)
        return accelerator

    # small chunks: the CPU layout runs the gloss quadrature of these few receivers in a loop
    monkeypatch.setattr(ir_gloss, "_GLOSS_MIN_CHUNK", 128)
    # and its per-receiver terms in chunks of valid receivers (_receive_valid_first)
    monkeypatch.setattr(ir_gather, "_RECEIVER_CHUNK", 256)
    monkeypatch.setattr(shading, "on_accelerator", layout)
    monkeypatch.setattr(raster_setup, "on_accelerator", layout)
    monkeypatch.setattr(prefix, "on_accelerator", layout)
    for module in (ir_atlas, ir_gather, ir_gloss):
        monkeypatch.setattr(module, "on_accelerator", layout)
    jax.clear_caches()
    out = jax.block_until_ready(fn())
    jax.clear_caches()
    return out, len(calls)


@pytest.mark.slow  # test_interreflection compares the two receiver layouts in the default tier
def test_accelerator_layout_renders_the_cpu_layout_frame(prep, monkeypatch):
    """Also the gather's receivers two ways: the CPU layout puts the valid ones first and runs
    their per-receiver terms in chunks, skipping the empty slots' chunks
    (``_receive_valid_first``); the accelerator layout runs all slots at once (``_receive``)."""
    valid_first, calls = ir_gather._receive_valid_first, []

    def counted(*a, **k):
        calls.append(1)
        return valid_first(*a, **k)

    monkeypatch.setattr(ir_gather, "_receive_valid_first", counted)
    cpu, n_cpu = _with_layout(monkeypatch, False, lambda: rendering.render_frame(prep))
    assert len(calls) == 1
    acc, n_acc = _with_layout(monkeypatch, True, lambda: rendering.render_frame(prep))
    assert len(calls) == 1
    assert n_cpu > 0 and n_acc > 0  # both traced, each with its layout
    assert sum(prep.buffers.pixel_capacity) >= 2 * 128  # the CPU layout's gloss ran in chunks
    # valid receivers in several chunks, and at least one chunk of empty slots skipped
    count = int(cpu.stats["covered_pixels"])
    assert count > 256 and sum(prep.buffers.pixel_capacity) >= count + 256
    a, b = np.asarray(cpu.xyz), np.asarray(acc.xyz)
    mask = np.asarray(cpu.mask)
    assert mask.sum() > 200 and np.array_equal(mask, np.asarray(acc.mask))
    assert np.max(np.abs(a - b)) <= 1e-5 * np.max(a[mask])


@pytest.mark.slow
def test_accelerator_layout_gradients_match_the_cpu_layout(prep, monkeypatch):
    mats = prep.materials
    wgt = jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, prep.camera.shape + (3,)),
                      jnp.float32)

    def grad():
        return jax.grad(lambda m: jnp.sum(rendering.render_frame(prep, m).xyz * wgt))(mats)

    g_cpu, _ = _with_layout(monkeypatch, False, grad)
    g_acc, _ = _with_layout(monkeypatch, True, grad)
    for name in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance"):
        x, y = np.asarray(getattr(g_cpu, name)), np.asarray(getattr(g_acc, name))
        assert np.all(np.isfinite(y)), name
        assert np.max(np.abs(x - y)) <= 1e-4 * np.max(np.abs(x)) + 1e-8, name


def test_default_visibility_is_concrete_when_first_made_inside_a_trace():
    """The cached all-visible default of render_frame/render_pixels (called inside a caller's
    jit by the live step) must be an array, not the tracer of the first trace."""
    rendering.all_visible.cache_clear()
    inside = jax.jit(lambda: rendering.all_visible(3) & True)()
    outside = rendering.all_visible(3)
    assert not isinstance(outside, jax.core.Tracer)
    np.testing.assert_array_equal(np.asarray(outside), [True, True, True])
    np.testing.assert_array_equal(np.asarray(inside), np.asarray(outside))


@pytest.mark.parametrize("x", [np.linspace(-2.0, 3.0, 64), np.array([0.0, -0.0, np.nan, 1.0]),
                               np.zeros((0, 3))])
def test_materialise_cut_is_the_identity(monkeypatch, x):
    """``materialise(x, cut=True)`` (a conditional that XLA cannot fold, so x is computed once
    instead of inside every consumer) returns x, whatever its first element (±0, NaN, empty),
    with the gradient of the identity; on the CPU layout the compiled program holds the
    conditional, with the accelerator layout it does not."""
    monkeypatch.setenv(backend.LAYOUT_VARIABLE, "cpu")
    idx = jnp.asarray(np.arange(x.shape[0])[::-1].copy())

    def f(a):
        return jnp.sum(backend.materialise(jnp.sin(a) * a, cut=True)[idx] ** 2)

    a = jnp.asarray(x, jnp.float32)
    got = jax.jit(lambda a: backend.materialise(jnp.sin(a) * a, cut=True))(a)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(jnp.sin(a) * a))
    if x.size and np.all(np.isfinite(x)):
        g = jax.grad(f)(a)
        ref = jax.grad(lambda a: jnp.sum((jnp.sin(a) * a)[idx] ** 2))(a)
        np.testing.assert_allclose(np.asarray(g), np.asarray(ref), rtol=1e-6)
        assert "conditional" in jax.jit(f).lower(a).compile().as_text()
        monkeypatch.setenv(backend.LAYOUT_VARIABLE, "accelerator")
        # (a new function: the trace of f is cached, and the layout is read when tracing)
        assert "conditional" not in jax.jit(lambda a: f(a)).lower(a).compile().as_text()


@pytest.mark.parametrize("cut", [False, True])
def test_materialise_each_returns_its_inputs_with_their_gradients(cut):
    """``materialise_each(a, b, c)`` (one (3, ...) buffer, its planes returned) is the identity
    on each input, with the identity's gradient, for both kinds of cut."""
    x = jnp.asarray(np.linspace(-1.0, 2.0, 24).reshape(4, 6), jnp.float32)

    def parts(a):
        return backend.materialise_each(jnp.sin(a), a * a, jnp.exp(-a), cut=cut)

    got = jax.jit(parts)(x)
    for g, want in zip(got, (jnp.sin(x), x * x, jnp.exp(-x)), strict=True):
        assert g.shape == x.shape
        np.testing.assert_array_equal(np.asarray(g), np.asarray(want))
    grad = jax.grad(lambda a: sum(jnp.sum(p * (i + 1.0)) for i, p in enumerate(parts(a))))(x)
    ref = jnp.cos(x) + 2.0 * (2.0 * x) - 3.0 * jnp.exp(-x)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(ref), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n, count, size", [(1000, 1000, 256), (1000, 300, 256),
                                            (1024, 0, 256), (1024, 1024, 256), (100, 40, 256)])
def test_prefix_chunks_runs_fn_on_the_leading_items_and_zeros_after(n, count, size):
    """``prefix_chunks`` equals ``fn`` on every chunk that starts before ``count`` (padded
    last chunk included) and gives zeros / False for the chunks after it; with N <= size or
    the accelerator layout it is ``fn`` on everything."""
    rng = np.random.default_rng(n + count)
    x = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    k = jnp.asarray(rng.integers(0, 9, n), jnp.int32)
    calls = []

    def fn(a, b):
        calls.append(a.shape[0])
        return {"s": jnp.sin(a) * b[:, None], "pos": jnp.sum(a, -1) > 0, "k": b * 2}

    got = jax.jit(lambda a, b, c: backend.prefix_chunks(fn, c, [a, b], size=size))(
        x, k, jnp.int32(count))
    ref = fn(x, k)
    assert calls[0] == min(n, size)  # traced on one chunk (or all of it)
    covered = n if n <= size else min(n, -(-count // size) * size)
    for key in ref:
        g, r = np.asarray(got[key]), np.asarray(ref[key])
        assert g.shape == r.shape and g.dtype == r.dtype
        np.testing.assert_allclose(g[:covered], r[:covered], rtol=1e-6)
        assert not np.any(g[covered:])


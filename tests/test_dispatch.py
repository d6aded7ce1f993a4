"""dispatch.array_jit: equinox.filter_jit's split of the arguments, without waiting."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spectral_fit._runtime import dispatch
from spectral_fit._runtime.dispatch import array_jit


class Box(eqx.Module):
    a: jax.Array
    b: np.ndarray
    scale: float  # a non-array leaf: static, as in equinox.filter_jit
    name: str = eqx.field(static=True)


def _fun(box: Box, x: jax.Array, power: int, *, shift: jax.Array) -> dict[str, jax.Array]:
    return {"y": box.scale * jnp.sin(box.a * x) ** power + box.b.sum() + shift,
            "n": jnp.asarray(len(box.name))}


def test_values_gradients_and_vmap_match_filter_jit():
    box = Box(jnp.linspace(0.1, 1.0, 5), np.arange(3.0), 1.5, "abc")
    x, shift = jnp.float32(0.7), jnp.float32(-0.25)
    ours, theirs = array_jit(_fun), eqx.filter_jit(_fun)
    a, b = ours(box, x, 3, shift=shift), theirs(box, x, 3, shift=shift)
    # the closed form, independently of either compiler path
    want = 1.5 * np.sin(np.linspace(0.1, 1.0, 5) * 0.7) ** 3 + 3.0 - 0.25
    np.testing.assert_allclose(np.asarray(a["y"]), want, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(a["y"]), np.asarray(b["y"]))
    assert int(a["n"]) == 3

    def loss(f, x):
        return f(box, x, 2, shift=shift)["y"].sum()

    g = jax.grad(lambda x: loss(ours, x))(x)
    a5 = np.linspace(0.1, 1.0, 5)
    want_g = np.sum(1.5 * 2 * np.sin(a5 * 0.7) * np.cos(a5 * 0.7) * a5)
    np.testing.assert_allclose(float(g), want_g, rtol=1e-5)
    xs = jnp.array([0.1, 0.2, 0.3], jnp.float32)
    v = jax.vmap(lambda x: ours(box, x, 1, shift=shift)["y"])(xs)
    w = jax.vmap(lambda x: theirs(box, x, 1, shift=shift)["y"])(xs)
    np.testing.assert_allclose(np.asarray(v), np.asarray(w), rtol=1e-6)


def test_static_leaves_key_the_compilation_and_arrays_do_not():
    traces = []

    def fun(x, k, *, label):
        traces.append((k, label))
        return x * k

    f = array_jit(fun)
    for value in (1.0, 2.0, 3.0):  # new array values: one trace
        f(jnp.float32(value), 2, label="a")
    assert len(traces) == 1
    f(np.float32(4.0), 2, label="a")  # a NumPy scalar is an array leaf as well
    assert len(traces) == 1
    assert float(f(jnp.float32(1.0), 3, label="a")) == 3.0  # a new static value: a new trace
    f(jnp.float32(1.0), 2, label="b")
    assert traces == [(2, "a"), (3, "a"), (2, "b")]
    assert "stablehlo.multiply" in f.lower(jnp.float32(1.0), 5, label="c").as_text()


def test_a_call_returns_before_its_computation_finishes():
    # ~0.2 s of work behind a loop with a traced trip count (XLA:CPU runs a program it deems
    # cheap synchronously in the caller's thread whatever the caller does): right after the
    # call the result is not ready yet; equinox.filter_jit waits for it on every call
    def fun(x):
        steps = 500 + (x[0, 0] > 0).astype(jnp.int32)
        return jax.lax.fori_loop(0, steps, lambda i, c: jnp.tanh(c @ c), x)

    x = jnp.full((256, 256), 1.0 / 256, jnp.float32)
    ours, theirs = array_jit(fun), eqx.filter_jit(fun)
    jax.block_until_ready((ours(x), theirs(x)))  # compiled
    out = ours(x)
    pending = not out.is_ready()
    assert theirs(x).is_ready()
    np.testing.assert_array_equal(np.asarray(out), np.asarray(theirs(x)))
    assert pending


def test_unhashable_static_leaf_is_refused():
    f = array_jit(lambda x, s: x)
    with pytest.raises(TypeError, match="unhashable"):
        f(jnp.ones(2), bytearray(b"x"))


def test_cpu_programs_compile_without_library_fusions_and_nest_in_a_callers_jit():
    """On the CPU the top-level program carries cpu_compiler_options (XLA's YNNPACK fusions
    off: the (N, 3) norm below is one of XLA's own loops, not a library call); inside a
    caller's jit (tracers, or concrete arguments closed over) the same function runs without
    them (JAX refuses compiler options on a nested jit) and gives the same values."""
    from spectral_fit._runtime.dispatch import cpu_compiler_options

    def unit(x):
        return x / jnp.linalg.norm(x, axis=-1, keepdims=True)

    f = array_jit(unit)
    x = jnp.asarray(np.random.default_rng(0).normal(size=(12288, 3)), jnp.float32)
    want = np.asarray(x) / np.linalg.norm(np.asarray(x), axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(f(x)), want, rtol=2e-6, atol=1e-7)
    opts = cpu_compiler_options()
    if jax.default_backend() == "cpu":
        assert opts["xla_cpu_experimental_ynn_fusion_type"] == ""
        assert ("xla_cpu_prefer_vector_width" in opts) == dispatch._has_avx512()
        assert "ynn_fusion" in jax.jit(unit).lower(x).compile().as_text()  # XLA's default
        assert "ynn_fusion" not in f.lower(x).compile().as_text()
    traced = jax.jit(lambda y: f(y) * 2.0)(x)
    closed = jax.jit(lambda: f(x) * 2.0)()
    np.testing.assert_allclose(np.asarray(traced), 2 * want, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(closed), 2 * want, rtol=2e-6, atol=1e-7)

"""Where the compiled programs run, and the work layout that follows from it.

The same JAX code runs on the CPU and on accelerators (GPU, TPU), but a few layout choices that
make it fast on one make it slow on the other:

* **CPU** (XLA:CPU): large batches are split into chunks of a few thousand points run by a
  ``lax.map`` loop, and chunks with nothing to do are skipped by ``lax.cond``: the chunk's
  intermediates stay in cache and the cost follows the number of covered pixels.
* **Accelerator**: every iteration of a device loop and every ``lax.cond`` costs a round trip
  to the host for its predicate and a few kernel launches, which on a frame of a few
  milliseconds is what dominates; there the batches run whole (or in a few very large
  chunks), all at once.

The choice is read when a function is traced (not when it runs), from the default backend; the
environment variable ``SPECTRAL_FIT_LAYOUT`` overrides it (``auto``, the default; ``cpu``;
``accelerator``) for benchmarking one layout against the other on the same device. Both layouts
compute the same values (tests/test_backend.py).
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["LAYOUT_VARIABLE", "on_accelerator", "materialise", "materialise_each",
           "prefix_chunks"]

#: environment variable that overrides the layout: "auto" (default), "cpu", "accelerator"
LAYOUT_VARIABLE = "SPECTRAL_FIT_LAYOUT"


def on_accelerator() -> bool:
    """Whether the accelerator layout applies: the default JAX backend is not the CPU, unless
    ``SPECTRAL_FIT_LAYOUT`` says ``cpu`` or ``accelerator``. Read at trace time.

    Raises:
        InputError: ``SPECTRAL_FIT_LAYOUT`` holds another value.
    """
    value = os.environ.get(LAYOUT_VARIABLE, "auto").strip().lower()
    if value == "cpu":
        return False
    if value == "accelerator":
        return True
    if value not in ("", "auto"):
        from .errors import InputError

        raise InputError(f"expected 'auto', 'cpu' or 'accelerator', got {value!r}",
                         field=LAYOUT_VARIABLE)
    import jax

    return jax.default_backend() != "cpu"


def materialise(x: Any, *, cut: bool = False) -> Any:
    """x, computed once into memory, so that XLA does not recompute x's whole expression
    inside every consumer (a gather's taps, every channel of a product). Exact, with the same
    gradients.

    By default an optimisation barrier. XLA:CPU (jaxlib 0.10) expands barriers before it
    fuses, so there the barrier is only a hint and x may still be fused into a gather that
    reads it many times. ``cut=True`` forces the cut on the CPU layout: x passes through a
    ``lax.cond`` whose predicate is always true but unknown to the compiler (from the bits of
    x's first element). That costs a conditional and a buffer, and it stops fusions that
    pay: used everywhere it makes the frame slower, so it is used only where it pays (the
    gloss anchors' tests and taps of a frame's pixels, otherwise recomputed inside one large
    fusion of the interreflection's tail; the gloss quadrature's reordered result; a frame's
    shaded slots before the composite or the image scatter). With the accelerator layout
    (:func:`on_accelerator`: a conditional there waits for the host) it is the barrier;
    under a batching ``vmap`` the conditional becomes a select (no cut)."""
    import jax
    import jax.numpy as jnp

    if not cut or on_accelerator() or x.size == 0:
        return jax.lax.optimization_barrier(x)
    v = x.reshape(-1)[0]
    if v.dtype == jnp.bool_ or jnp.dtype(v.dtype).itemsize != 4:
        v = v.astype(jnp.float32)
    bits = jax.lax.bitcast_convert_type(v, jnp.int32)
    return jax.lax.cond((bits | 1) != 0, lambda a: a, jnp.zeros_like, x)


def materialise_each(*xs: Any, cut: bool = False) -> list[Any]:
    """:func:`materialise` of several arrays of one shape (...) at once: stacked on a new
    leading axis (n, ...) and returned as its planes ``[p[0], ..., p[n − 1]]``. A stack on the
    last axis instead (..., n) is a concatenate that XLA:CPU writes element by element,
    switching between the n expressions at every element (not vectorised), several times
    slower than the leading-axis stack."""
    import jax.numpy as jnp

    p = materialise(jnp.stack(xs, axis=0), cut=cut)
    return [p[i] for i in range(len(xs))]


def as_chunks(arrays: Any, size: int) -> list[Any]:
    """Each array (N, ...) of ``arrays`` as (ceil(N / size), size, ...) chunks, padded at the
    end with copies of its first item (a valid input for whatever runs on the chunks; callers
    skip or drop the padding's results)."""
    import jax.numpy as jnp

    out = []
    for a in arrays:
        nc = -(-a.shape[0] // size)
        pad = nc * size - a.shape[0]
        if pad:
            a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad, *a.shape[1:]))])
        out.append(a.reshape(nc, size, *a.shape[1:]))
    return out


def prefix_chunks(fn: Any, count: Any, arrays: Any, *, size: int) -> Any:
    """``fn`` over consecutive chunks of ``size`` items of ``arrays`` (a sequence of arrays
    with a common leading axis N), skipping the chunks that start at or after ``count`` (a
    traced int: the items that matter come first). Their results are zeros (False, 0) of
    ``fn``'s output structure.

    CPU layout: a ``lax.map`` over the chunks with a ``lax.cond`` per chunk, so the cost
    follows ``count`` rather than N (to within one chunk), and a chunk's intermediates stay
    in cache. Accelerator layout (:func:`on_accelerator`): ``fn`` on all N items at once.

    Args:
        fn: items (size, ...) of each array → a pytree of arrays (size, ...).
        count: () int32, the number of leading items that matter.
        arrays: the items, each (N, ...).
        size: items per chunk (static).

    Returns:
        ``fn``'s pytree with leading axis N.
    """
    import jax
    import jax.numpy as jnp

    arrays = list(arrays)
    n = arrays[0].shape[0]
    if on_accelerator() or n <= size:
        return fn(*arrays)
    chunks = as_chunks(arrays, size)
    nc = chunks[0].shape[0]
    shapes = jax.eval_shape(fn, *[jax.ShapeDtypeStruct(c.shape[1:], c.dtype) for c in chunks])
    count = jnp.asarray(count, jnp.int32)

    def zeros(*_: Any) -> Any:
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    def body(x: tuple[Any, ...]) -> Any:
        start, *chunk = x
        return jax.lax.cond(start < count, fn, zeros, *chunk)

    out = jax.lax.map(body, (jnp.arange(nc, dtype=jnp.int32) * size, *chunks))
    return jax.tree.map(lambda o: o.reshape(nc * size, *o.shape[2:])[:n], out)

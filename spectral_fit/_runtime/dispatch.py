"""Compiled calls that return as soon as the work is enqueued.

:func:`array_jit` compiles a function of pytrees like ``equinox.filter_jit``: every array leaf
(``jax.Array``, NumPy array or scalar, a tracer) is traced, every other leaf (Python numbers,
strings, tuples, static module fields) is part of the compilation key and must be hashable. It
differs in two ways that matter for a frame of a few milliseconds:

* it returns without waiting for the result. ``equinox.filter_jit`` blocks on every call
  (``block_until_ready`` of a marker, equinox 0.13), so the host cannot prepare frame N + 1
  while the device renders frame N, and a caller that only enqueues work still waits for all of
  it;
* a call costs one ``tree_flatten``, one hash of the static parts and a scan of the array
  leaves for tracers before JAX's own dispatch (``equinox.filter_jit`` partitions and
  recombines the arguments through ``tree_map`` on every call).

Values, gradients and ``vmap`` are those of ``jax.jit`` on the same function (the function is
traced with the same leaves as tracers). Runtime checks of ``equinox.error_if`` are not turned
into readable errors here: the functions compiled with it use none.

On the CPU the programs are compiled with :func:`cpu_compiler_options` (XLA's YNNPACK library
fusions off: the frame's many reductions over 3 or 4 components and its tiny matrix products
run slower as library calls than as XLA's own loops).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

__all__ = ["array_jit", "cpu_compiler_options", "is_array"]


def is_array(x: Any) -> bool:
    """Whether ``x`` is traced by :func:`array_jit`: a ``jax.Array`` (tracers included), a NumPy
    array or a NumPy scalar (``equinox.is_array``'s rule)."""
    return isinstance(x, jax.Array | np.ndarray | np.generic)


class _Skeleton:
    """The static part of a call: argument structure, the non-array leaves, and which leaves are
    arrays. Hashable (the compilation key of :func:`array_jit`); equal skeletons compile once."""

    __slots__ = ("treedef", "statics", "mask", "_hash")

    def __init__(self, treedef: Any, statics: tuple[Any, ...], mask: tuple[bool, ...]) -> None:
        self.treedef = treedef
        self.statics = statics
        self.mask = mask
        self._hash = hash((treedef, statics, mask))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, _Skeleton) and self._hash == other._hash
                and self.mask == other.mask and self.treedef == other.treedef
                and self.statics == other.statics)

    def merge(self, arrays: list[Any]) -> list[Any]:
        it_a, it_s = iter(arrays), iter(self.statics)
        return [next(it_a) if m else next(it_s) for m in self.mask]


def array_jit(fun: Callable[..., Any], **jit_options: Any) -> Callable[..., Any]:
    """``fun`` compiled once per argument structure; calls return without waiting.

    Args:
        fun: a function of positional and keyword pytrees; its result must be a pytree of
            arrays.
        jit_options: passed to ``jax.jit`` (e.g. ``compiler_options``); not
            ``static_argnums``/``static_argnames`` (non-array leaves are static already).

    Returns:
        A function with ``fun``'s signature. Its result holds the arrays of an enqueued
        computation (``jax.block_until_ready`` waits for them).
    """
    def body(skeleton: _Skeleton, arrays: list[Any]) -> Any:
        args, kwargs = jax.tree_util.tree_unflatten(skeleton.treedef, skeleton.merge(arrays))
        return fun(*args, **kwargs)

    # made at first use: the compiler options depend on the backend, which must not be
    # started at import (process.split_cpu_devices has to come first). JAX takes compiler
    # options only on a top-level jit: inside a caller's trace the "nested" one is called
    jitted: dict[str, Any] = {}

    def run(kind: str = "top") -> Any:
        if kind not in jitted:
            options = {k: v for k, v in jit_options.items() if k != "compiler_options"}
            if kind == "top":
                options["compiler_options"] = {**cpu_compiler_options(),
                                               **(jit_options.get("compiler_options") or {})}
            jitted[kind] = jax.jit(body, static_argnums=0, **options)
        return jitted[kind]

    @functools.wraps(fun)
    def call(*args: Any, **kwargs: Any) -> Any:
        skeleton, arrays = _split(args, kwargs)
        if any(isinstance(x, jax.core.Tracer) for x in arrays):
            return run("nested")(skeleton, arrays)
        try:
            return (jitted.get("top") or run())(skeleton, arrays)
        except ValueError as e:  # concrete arguments inside a caller's trace
            if "compiler_options" not in str(e):
                raise
            return run("nested")(skeleton, arrays)

    call.lower = lambda *args, **kwargs: run().lower(*_split(args, kwargs))  # type: ignore[attr-defined]
    return call


#: XLA options of the CPU programs (:func:`cpu_compiler_options`)
_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}

#: added to ``_CPU_OPTIONS`` on a CPU with AVX-512 (:func:`_has_avx512`)
_AVX512_OPTIONS = {"xla_cpu_prefer_vector_width": 512}


@functools.cache
def _has_avx512() -> bool:
    """Whether this machine's CPU has AVX-512F (Linux ``/proc/cpuinfo``; False elsewhere)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return "avx512f" in line.split()
    except OSError:
        pass
    return False


def requested_cpu_options() -> dict[str, Any]:
    """The options :func:`cpu_compiler_options` asks for on this backend, without checking
    that this jaxlib takes them (no compile; for keys of stored programs): ``_CPU_OPTIONS``
    (and ``_AVX512_OPTIONS`` on a CPU with AVX-512) on the CPU backend, {} elsewhere or with
    ``SPECTRAL_FIT_XLA_CPU_DEFAULTS=0``."""
    if os.environ.get("SPECTRAL_FIT_XLA_CPU_DEFAULTS", "1") in ("0", ""):
        return {}
    if jax.default_backend() != "cpu":
        return {}
    return {**_CPU_OPTIONS, **(_AVX512_OPTIONS if _has_avx512() else {})}


@functools.cache
def cpu_compiler_options() -> dict[str, Any]:
    """The XLA compile options of this package's frame programs on the CPU backend: YNNPACK
    library fusions off (``xla_cpu_experimental_ynn_fusion_type = ""``) and, on a CPU with
    AVX-512, 512-bit vectors preferred (``xla_cpu_prefer_vector_width = 512``); {} elsewhere.

    jaxlib 0.10's XLA:CPU hands reductions and dot products to YNNPACK: for the frame's
    (N, 3) norms and (N, 4) products a library call per kernel costs more than XLA's own
    fused loops (values within 1e-6 of the display range). XLA:CPU's loops use 256-bit
    vectors by default even where the CPU has AVX-512; 512-bit ones make the frames faster
    there (display RGB within 6e-6); they are not asked for on a CPU without AVX-512 (wider
    vectors split in two there). :func:`requested_cpu_options`, checked once per process with
    a one-op compile (so only where a program is compiled); a jaxlib that does not know an
    option gets {} (its defaults).
    ``SPECTRAL_FIT_XLA_CPU_DEFAULTS=0`` in the environment keeps XLA's defaults."""
    opts = requested_cpu_options()
    if not opts:
        return {}
    try:
        jax.jit(lambda x: x + 1).lower(np.float32(0)).compile(compiler_options=opts)
    except Exception:  # an older or newer jaxlib without the option
        return {}
    return opts


def _split(args: tuple[Any, ...], kwargs: dict[str, Any]) -> tuple[_Skeleton, list[Any]]:
    leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
    mask = tuple(is_array(x) for x in leaves)
    statics = tuple(x for x, m in zip(leaves, mask, strict=True) if not m)
    arrays = [x for x, m in zip(leaves, mask, strict=True) if m]
    return _Skeleton(treedef, statics, mask), arrays

"""Compiled calls that return as soon as the work is enqueued.

:func:`array_jit` compiles a function of pytrees like ``equinox.filter_jit``: every array leaf
(``jax.Array``, NumPy array or scalar, a tracer) is traced, every other leaf (Python numbers,
strings, tuples, static module fields) is part of the compilation key and must be hashable. It
differs in two ways that matter for a frame of a few milliseconds:

* it returns without waiting for the result. ``equinox.filter_jit`` blocks on every call
  (``block_until_ready`` of a marker, equinox 0.13), so the host cannot prepare frame N + 1
  while the device renders frame N, and a caller that only enqueues work still waits for all of
  it;
* a call costs one ``tree_flatten`` and one hash of the static parts before JAX's own
  dispatch (``equinox.filter_jit`` partitions and recombines the arguments through
  ``tree_map`` on every call).

Values, gradients and ``vmap`` are those of ``jax.jit`` on the same function (the function is
traced with the same leaves as tracers). Runtime checks of ``equinox.error_if`` are not turned
into readable errors here: the functions compiled with it use none.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

__all__ = ["array_jit", "is_array"]


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
    @functools.partial(jax.jit, static_argnums=0, **jit_options)
    def run(skeleton: _Skeleton, arrays: list[Any]) -> Any:
        args, kwargs = jax.tree_util.tree_unflatten(skeleton.treedef, skeleton.merge(arrays))
        return fun(*args, **kwargs)

    @functools.wraps(fun)
    def call(*args: Any, **kwargs: Any) -> Any:
        return run(*_split(args, kwargs))

    call.lower = lambda *args, **kwargs: run.lower(*_split(args, kwargs))  # type: ignore[attr-defined]
    return call


def _split(args: tuple[Any, ...], kwargs: dict[str, Any]) -> tuple[_Skeleton, list[Any]]:
    leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
    mask = tuple(is_array(x) for x in leaves)
    statics = tuple(x for x, m in zip(leaves, mask, strict=True) if not m)
    arrays = [x for x, m in zip(leaves, mask, strict=True) if m]
    return _Skeleton(treedef, statics, mask), arrays

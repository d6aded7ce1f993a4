"""One stored executable of a frame program: compiled from its lowered program (source locations
stripped, JAX's persistent compilation cache bypassed), serialised into a cache entry with the
external kernels it calls, and loaded back (those kernels prepared first; an entry that cannot
be loaded here is compiled again).
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Any

from .._runtime.process import WhileInside
from ._cache import _read_entry, _write_entry


def _custom_call_targets(compiled: Any) -> list[str] | None:
    """The custom-call targets (external kernels) of a compiled program; None if unknown."""

    try:
        return sorted(set(re.findall(r'custom_call_target="([^"]+)"', compiled.as_text())))
    except Exception:
        return None


def _prepare_custom_calls(targets: list[str] | None) -> bool:
    """Make the external kernels of a program loaded from disk callable; False when it calls
    one that this module does not know how to prepare (then the program is recompiled).

    JAX initialises the LAPACK kernels (``jnp.linalg``) lazily, while lowering a program that
    uses them; a program loaded from disk is never lowered, and calling an uninitialised
    kernel crashed the process."""
    if targets is None or any(not t.startswith("lapack_") for t in targets):
        return False
    if targets:
        try:  # a private JAX function: if it moves, programs are compiled instead of loaded
            from jax._src.lax import linalg

            linalg.initialize_lapack()
        except Exception:
            return False
    return True


def _strip_locations(lowered: Any) -> bool:
    """Drop the source locations (op names, files, lines, stack frames) from a lowered
    program before it is compiled, in place; False if this JAX does not allow it (then the
    program is compiled with them: the same executable code either way).

    XLA keeps each location as the op metadata of an HLO instruction, and a stored executable
    carries its HLO module, which a new process parses again when it loads the program: on the
    benchmark frame the locations are over a quarter of the stored bytes and a matching share
    of the load. Names in a profile of a loaded program are
    lost with them (profile :func:`~spectral_fit.rendering.render_frame` instead)."""
    try:
        from jax._src.lib.mlir import passmanager

        module = lowered.compiler_ir("stablehlo")  # the module that compile() compiles
        with module.context:
            passmanager.PassManager.parse("builtin.module(strip-debuginfo)").run(
                module.operation)
    except Exception:  # a JAX without this module or pass: keep the locations
        return False
    return True


def _recheck_cache() -> None:
    """Make JAX decide again whether its persistent cache is in use. JAX decides once per
    process, at its first compile, and keeps the answer: changing the setting afterwards alone
    would leave the cache on (a program compiled then could be a stored one, with the source
    locations of whoever stored it)."""
    try:
        from jax.experimental.compilation_cache import compilation_cache

        compilation_cache.reset_cache()
    except Exception:  # a JAX without it: the setting alone
        pass


def _cache_off() -> bool:
    import jax

    saved = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    _recheck_cache()
    return saved


def _cache_back(saved: bool) -> None:
    import jax

    jax.config.update("jax_enable_compilation_cache", saved)
    _recheck_cache()


_BYPASS = WhileInside(_cache_off, _cache_back)


def _without_persistent_cache() -> WhileInside:
    """JAX's persistent compilation cache off while any thread is inside (the setting is
    process-global: compiles on several threads restore it once, when the last one ends)."""
    return _BYPASS


def _load_entry(folder: Path, key: str) -> Any:
    """The executable stored under ``key`` in ``folder``, loaded; None if there is none, or if
    it cannot be loaded here (another jaxlib build, a kernel this module cannot prepare)."""
    from jax.experimental.serialize_executable import deserialize_and_load

    entry = _read_entry(folder, key)
    if entry is None or not _prepare_custom_calls(entry.get("custom_calls")):
        return None
    try:
        return deserialize_and_load(entry["payload"], entry["in_tree"], entry["out_tree"])
    except Exception:  # e.g. written by another jaxlib build: compiled again
        return None


def _fresh(fn: Any) -> Any:
    """``fn`` as a new function object: JAX keeps the lowering and the executable of a function
    it has compiled before for the same arguments, and would hand back that executable (with
    its source locations) instead of compiling the stripped program."""

    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        return fn(*args, **kwargs)

    return call


def _compile(key: str, fn: Any, arrays: Any, compiler_options: dict[str, Any] | None,
             folder: Path | None) -> Any:
    """The compiled ``jax.jit(fn)`` for ``arrays`` (a list of arrays or shape structs, or a
    function returning one, called only to compile), stored in ``folder`` under ``key`` (which
    must determine the program, see :func:`_program_key`) unless ``folder`` is None. Compiled
    with :func:`~spectral_fit._runtime.dispatch.cpu_compiler_options` and ``compiler_options`` on
    top,
    bypassing JAX's persistent compilation cache (what is stored is a fresh compile)."""
    import jax
    from jax.experimental.serialize_executable import serialize

    from .._runtime.dispatch import cpu_compiler_options

    compiler_options = {**cpu_compiler_options(), **(compiler_options or {})}
    lowered = jax.jit(_fresh(fn)).lower(arrays() if callable(arrays) else arrays)
    _strip_locations(lowered)
    with _without_persistent_cache():
        compiled = (lowered.compile(compiler_options=compiler_options) if compiler_options
                    else lowered.compile())
    if folder is not None:
        try:
            targets = _custom_call_targets(compiled)
            if _prepare_custom_calls(targets):  # else: a kernel a new process could not call
                payload, in_tree, out_tree = serialize(compiled)
                _write_entry(folder, key, {"payload": payload, "in_tree": in_tree,
                                           "out_tree": out_tree, "custom_calls": targets})
        except Exception:  # a backend without executable serialisation: memory only
            pass
    return compiled

"""The fit's compiled programs kept on disk as exported StableHLO (``jax.export``), so that a
new process neither traces nor lowers them again: :func:`stored_call`.

JAX's persistent compilation cache skips only XLA's compile; a new process still traces the
solver (the forward model, its ``jax.jacfwd`` and the Levenberg–Marquardt loop) in Python
and lowers it before the cache is consulted. An exported program is the lowered module
itself: loading it is a parse, and its compile is then found in JAX's persistent cache (when
that is on). Entries (pickled ``jax.export.Exported``) live in ``<cache_dir>/fit_programs``,
keyed by the package's source files, the library versions, the backend and the JAX settings
(the rendering caches' ``environment_digest``), the function's name, the arguments' tree
structure with every static value and every array's shape and dtype. Anything that fails (a
JAX without ``jax.export``, a program it cannot serialise, a damaged entry) falls back to
calling the function directly.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["stored_call", "PROGRAM_STATS"]

#: entries loaded from disk, exported and stored, and calls that fell back to the function
PROGRAM_STATS: dict[str, int] = {"loaded": 0, "stored": 0, "direct": 0}

# (folder, key) -> jitted call of the exported program, for the process's later calls
_MEMORY: dict[tuple[str, str], Any] = {}


def _key(name: str, treedef: Any, leaves: list[Any]) -> str:
    import hashlib

    from ..rendering import program_key

    text = f"fit_program={name}\n{program_key(treedef, leaves, False, None)}"
    return hashlib.sha256(text.encode()).hexdigest()[:40]


def stored_call(fn: Callable[..., Any], *args: Any,
                cache_dir: str | os.PathLike[str] | None = None) -> Any:
    """``fn(*args)`` (``fn`` a jit-compiled function of pytrees of arrays and static values)
    through its exported program stored under ``cache_dir`` (``fit_programs``), exported and
    stored on the first call; ``fn(*args)`` itself when ``cache_dir`` is None or anything
    fails. The result is the function's (the same lowered program is compiled)."""
    if cache_dir is None:
        return fn(*args)
    try:
        import jax
        import numpy as np

        leaves, treedef = jax.tree_util.tree_flatten(args)
        arrays = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array | np.ndarray)]
        key = _key(getattr(fn, "__name__", repr(fn)), treedef, leaves)
        folder = Path(cache_dir) / "fit_programs"
        call = _MEMORY.get((str(folder), key))
        if call is None:
            call = _load_or_export(fn, args, leaves, treedef, arrays, key, folder)
            _MEMORY[(str(folder), key)] = call
        return call(*[leaves[i] for i in arrays])
    except Exception:
        PROGRAM_STATS["direct"] += 1
        return fn(*args)


def _load_or_export(fn: Callable[..., Any], args: tuple[Any, ...], leaves: list[Any],
                    treedef: Any, arrays: list[int], key: str, folder: Path) -> Any:
    """The jitted call of the exported program under ``key`` in ``folder``: loaded, or
    exported from ``fn`` and stored (pickled without its derivative rule: the stored program
    is only called, never differentiated)."""
    import dataclasses

    import jax
    from jax import export

    from ..rendering import read_cache_entry, write_cache_entry

    exported = read_cache_entry(folder, key)
    if isinstance(exported, export.Exported):
        PROGRAM_STATS["loaded"] += 1
    else:
        def on_arrays(*xs: Any) -> Any:
            full = list(leaves)
            for i, x in zip(arrays, xs, strict=True):
                full[i] = x
            return fn(*jax.tree_util.tree_unflatten(treedef, full))

        specs = [jax.ShapeDtypeStruct(leaves[i].shape, leaves[i].dtype) for i in arrays]
        exported = export.export(jax.jit(on_arrays))(*specs)
        write_cache_entry(folder, key, dataclasses.replace(exported, _get_vjp=None))
        PROGRAM_STATS["stored"] += 1
    return jax.jit(exported.call)

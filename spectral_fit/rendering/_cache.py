"""Cold start: persistent caches for the first frame of a process.

A fresh process that renders a frame pays for three things before the first pixel: preparing the
scene (:func:`~spectral_fit.rendering.prepare`: meshes, the environment's prefiltered levels and
split-sum tables, capacity plans), tracing and lowering the frame program to XLA, and compiling
it (by far the largest of the three).
JAX's persistent compilation cache removes only the last of these: a cache hit still traces and
lowers the whole program. This module keeps all three between processes:

* :func:`enable_compilation_cache`: JAX's persistent compilation cache in a folder named for
  the library versions (:func:`library_versions_tag`) under ``$SPECTRAL_FIT_JAX_CACHE``
  (default ``~/.cache/spectral_fit/jax``), for every program;
* :func:`prepare_cached`: :func:`~spectral_fit.rendering.prepare` of a config file, stored on disk
  (``$SPECTRAL_FIT_CACHE/prepared``, default ``~/.cache/spectral_fit/prepared``);
* :func:`render_frame_cached`: :func:`~spectral_fit.rendering.render_frame` through a compiled
  executable stored on disk (``.../programs``): a hit loads the executable without tracing. A
  gather-mode frame is kept as two executables (the interreflection's senders' half, then the
  rest) that load, or compile, side by side on two threads. A missing program is compiled and
  stored by a fresh child process (JAX's persistent cache off there), so that what is stored
  does not depend on what the calling process compiled or loaded before (see ``_program``).

Every entry is keyed by a SHA-256 of everything it depends on: the text of the package's source
files, the Python version and the versions of jax, jaxlib, every installed JAX plugin (CUDA,
ROCm, TPU), equinox, optimistix, lineax, numpy and colour-science (:func:`library_versions`),
the backend and device kind, ``XLA_FLAGS`` and the JAX settings that change lowering; for a
prepared scene also the config file's bytes, the size and modification time of every file the
config names, and the options; for a program the full structure of its arguments (every static
field, every array's shape and dtype) and the compiler options. A changed input therefore misses
and recomputes; it never loads a stale entry. In particular nothing written under one
jax/jaxlib is loaded by another, JAX's own compiled programs included (their folder is named for
the versions). Set ``SPECTRAL_FIT_CACHE`` (or ``SPECTRAL_FIT_JAX_CACHE``) to an empty string to
disable a cache. Applications (the CLI, the benchmarks, the notebooks) opt in; the library never
enables a cache by itself, because JAX's setting is process-global.

Where a first frame's time goes: docs/rendering.md ("Cold start").

This module holds the caches' folders (:func:`cache_root`), their entries on disk (pickled,
the oldest removed beyond a few per folder), the hit and miss counters (``CACHE_STATS``) and the
switch of JAX's persistent compilation cache (:func:`enable_compilation_cache`). The keys:
``_keys``; the prepared scenes: ``_prepared_cache``; the frame programs: ``_program_cache``
and ``_executables``.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import threading
from pathlib import Path
from typing import Any

from ._keys import library_versions_tag

__all__ = [
    "cache_root",
    "enable_compilation_cache",
    "compilation_counts",
    "read_cache_entry",
    "write_cache_entry",
    "CACHE_STATS",
]


#: hits and misses of the two disk caches in this process (for the benchmarks and tests)
CACHE_STATS: dict[str, int] = {"prepared_hit": 0, "prepared_miss": 0, "program_hit": 0,
                               "program_miss": 0, "program_memory_hit": 0}


# entries kept per cache folder (oldest removed first)
_MAX_ENTRIES = 8


# CACHE_STATS' program counts are updated from the threads of _load_parts
_STATS_LOCK = threading.Lock()


def cache_root() -> Path | None:
    """The folder of the prepared-scene and program caches: ``$SPECTRAL_FIT_CACHE`` or
    ``~/.cache/spectral_fit``; None when the variable is set to an empty string."""
    path = os.environ.get("SPECTRAL_FIT_CACHE",
                          os.path.join(os.path.expanduser("~"), ".cache", "spectral_fit"))
    return Path(path) if path else None


def enable_compilation_cache(path: str | os.PathLike[str] | None = None, *,
                             min_compile_time_s: float = 0.0) -> str | None:
    """Turn on JAX's persistent compilation cache (process-global) and return its folder.

    Programs go to a subfolder named by :func:`library_versions_tag`, so that a program compiled
    under one jax/jaxlib (or CUDA plugin) is never loaded by another, whatever JAX's own cache
    key holds.

    Args:
        path: the cache's base folder; default ``$SPECTRAL_FIT_JAX_CACHE`` or
            ``~/.cache/spectral_fit/jax`` (an empty variable disables the cache: returns None).
        min_compile_time_s: programs that compile faster than this are not stored. The default
            0 stores every program, so that a warm process compiles nothing at all (a frame's
            few small eager programs add up to a noticeable compile otherwise).

    Returns:
        The folder in use (``<path>/<library_versions_tag()>``), or None when the cache is off.
        A folder that cannot be created (read-only home) leaves the cache off.
    """
    import jax

    if path is None:
        path = os.environ.get("SPECTRAL_FIT_JAX_CACHE",
                              os.path.join(os.path.expanduser("~"), ".cache", "spectral_fit",
                                           "jax"))
    if not path:
        return None
    compilation_counts()  # count its hits from here on
    path = os.path.join(os.fspath(path), library_versions_tag())
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(min_compile_time_s))
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception:  # a cache must never stop the application
        return None
    return path


# JAX's events of its persistent compilation cache, counted from the first call of
# compilation_counts (or enable_compilation_cache) on
_COMPILE_EVENTS = {"/jax/compilation_cache/compile_requests_use_cache": "requested",
                   "/jax/compilation_cache/cache_hits": "loaded"}
_COMPILE_COUNTS: dict[str, int] = {"requested": 0, "loaded": 0}
_LISTENING: list[bool] = []


def _count_compile_event(event: str, **_kwargs: Any) -> None:
    name = _COMPILE_EVENTS.get(event)
    if name is not None:
        _COMPILE_COUNTS[name] += 1


def compilation_counts() -> dict[str, int]:
    """Programs XLA was asked for through JAX's persistent compilation cache in this process,
    since the first call of this function or of :func:`enable_compilation_cache`:
    ``{"loaded": n, "compiled": m}`` (loaded from the cache, compiled and stored). Both stay 0
    while the cache is off; programs found in the process's own memory count in neither.
    Take the difference of two calls for one stage."""
    if not _LISTENING:
        try:
            import jax.monitoring

            jax.monitoring.register_event_listener(_count_compile_event)
        except Exception:  # no events: the counts stay 0
            pass
        _LISTENING.append(True)
    return {"loaded": _COMPILE_COUNTS["loaded"],
            "compiled": _COMPILE_COUNTS["requested"] - _COMPILE_COUNTS["loaded"]}


# --------------------------------------------------------------------------------------------
# disk entries


def _read_entry(folder: Path, key: str) -> Any:
    p = folder / f"{key}.pkl"
    try:
        with open(p, "rb") as fh:
            return pickle.load(fh)
    except FileNotFoundError:
        return None
    except Exception:  # a damaged entry is recomputed (and overwritten)
        with contextlib.suppress(OSError):
            p.unlink()
        return None


def _write_entry(folder: Path, key: str, value: Any) -> None:
    from .._runtime.fileio import atomic_write_bytes

    try:
        data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(folder / f"{key}.pkl", data)
        entries = sorted(folder.glob("*.pkl"), key=lambda q: q.stat().st_mtime_ns)
        for old in entries[:-_MAX_ENTRIES]:
            with contextlib.suppress(OSError):
                old.unlink()
    except Exception:  # a cache that cannot be written must not stop the application
        return


#: one entry of a disk cache folder, read (None on a miss) and written atomically, for the
#: other layers' disk caches (the fit's)
read_cache_entry = _read_entry
write_cache_entry = _write_entry

"""The process the renderer runs in: BLAS threads, glibc's malloc, JAX's CPU devices.

Settings that belong to the whole process, not to one computation: NumPy's OpenBLAS on one
thread around the scene preparation (:func:`single_threaded_blas`), memory that XLA frees kept
for reuse (:func:`retain_freed_memory`), glibc's fastbins off while stored programs load
(:func:`without_fastbins`), the CPU exposed as several JAX devices (:func:`split_cpu_devices`),
and :class:`WhileInside`, a process-global setting held while any thread needs it. The library
never changes a process-global setting by itself except inside such a block; applications opt
in.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import threading
from typing import Any

__all__ = [
    "single_threaded_blas",
    "retain_freed_memory",
    "split_cpu_devices",
    "without_fastbins",
    "WhileInside",
]


_BLAS_SYMBOLS = (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                 ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                 ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
                 ("openblas_get_num_threads", "openblas_set_num_threads"))


@contextlib.contextmanager
def single_threaded_blas() -> Any:
    """Run NumPy's OpenBLAS on one thread inside the block (restored afterwards).

    OpenBLAS threads busy-wait for work. On a small, shared machine (2 cores, other processes
    running) its second thread competes with everything else, and :func:`prepare`'s matrix
    products (the environment's spherical blurs and principal spectra) cost several times the
    CPU they take on one thread (docs/rendering.md, "Cold start"). Only
    OpenBLAS libraries already loaded by the process are changed (found in /proc/self/maps);
    elsewhere this does nothing."""
    import ctypes

    saved = []
    try:
        with open("/proc/self/maps") as fh:
            libs = sorted({line.split()[-1] for line in fh
                           if "openblas" in line.lower() and line.split()[-1].startswith("/")})
    except OSError:
        libs = []
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in _BLAS_SYMBOLS:
            get, put = getattr(lib, get_name, None), getattr(lib, set_name, None)
            if get is not None and put is not None:
                get.restype = ctypes.c_int
                saved.append((put, int(get())))
                put(ctypes.c_int(1))
                break
    try:
        yield
    finally:
        for put, n in saved:
            put(ctypes.c_int(n))



# glibc's mallopt parameters (malloc.h)
_M_MXFAST = 1
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_MAX = -4


def retain_freed_memory() -> bool:
    """Keep the memory that XLA frees for reuse instead of returning it to the OS
    (process-global; glibc only, elsewhere nothing happens). Returns whether it was applied.

    XLA:CPU allocates each run's temporaries with ``malloc`` and frees them at its end. glibc
    serves blocks above its mmap threshold (at most 32 MB) with a fresh ``mmap`` and unmaps
    them on ``free``, and it unmaps a thread arena's extra heap (64 MB) as soon as it empties,
    so every frame touches new pages (tens of MB of page faults per close-up frame, paid in
    kernel CPU). With no mmap'd blocks (``M_MMAP_MAX`` = 0), no trimming
    (``M_TRIM_THRESHOLD`` 2 GB) and a top pad of a whole arena heap (``M_TOP_PAD`` 64 MB, which
    keeps emptied heaps) the same memory is reused from the second frame on: < 150 faults per
    frame (docs/rendering.md, "Steady-state memory"). The
    cost: the process keeps its peak heap instead of shrinking.

    Applications opt in (the ``spectral-fit`` command does, for every subcommand); the library
    never changes it by itself."""
    mallopt = _mallopt()
    if mallopt is None:
        return False
    ok = [mallopt(_M_MMAP_MAX, 0), mallopt(_M_TRIM_THRESHOLD, 2**31 - 1),
          # a thread arena's extra heap is unmapped whenever it empties unless the top pad
          # covers a whole heap (64 MB): XLA's threads free a frame's temporaries there
          mallopt(_M_TOP_PAD, 64 << 20)]
    return all(ok)


@functools.cache
def _mallopt() -> Any:
    """glibc's ``mallopt`` (int, int) -> int, or None (not Linux with glibc); looked up once."""
    import ctypes
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        fn = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int)
    fn.restype = ctypes.c_int
    return fn


def _default_mxfast() -> int:
    """glibc's fastbin limit in bytes as this process started: ``glibc.malloc.mxfast`` of
    ``GLIBC_TUNABLES`` where set, else glibc's default (64 · sizeof(size_t) / 4)."""
    import ctypes

    m = re.search(r"glibc\.malloc\.mxfast=(\d+)", os.environ.get("GLIBC_TUNABLES", ""))
    return int(m.group(1)) if m else 16 * ctypes.sizeof(ctypes.c_size_t)


class WhileInside:
    """A process-global setting changed while any thread is inside ``with`` it, and restored
    once, when the last one leaves: ``enter()`` returns what ``leave(saved)`` restores."""

    def __init__(self, enter: Any, leave: Any) -> None:
        self._enter, self._leave = enter, leave
        self._lock = threading.Lock()
        self._depth = 0
        self._saved: Any = None

    def __enter__(self) -> None:
        with self._lock:
            if self._depth == 0:
                self._saved = self._enter()
            self._depth += 1

    def __exit__(self, *exc: Any) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                self._leave(self._saved)


def _fastbins_off() -> None:
    mallopt = _mallopt()
    if mallopt is not None:
        mallopt(_M_MXFAST, 0)


def _fastbins_back(_: Any) -> None:
    mallopt = _mallopt()
    if mallopt is not None:
        mallopt(_M_MXFAST, _default_mxfast())


_FASTBINS = WhileInside(_fastbins_off, _fastbins_back)


def without_fastbins() -> WhileInside:
    """glibc's malloc fastbins off while any thread is inside (process-global; restored when
    the last one leaves; glibc only, elsewhere nothing changes).

    Loading a stored executable is XLA rebuilding the program's HLO module, buffer assignment
    and kernel thunks from their protos: millions of small blocks allocated and freed, a
    quarter of the load's CPU under malloc. Without fastbins (``M_MXFAST`` = 0) small frees
    are merged at once, and the programs load and run their first time sooner
    (docs/rendering.md, "Cold start"). Frames themselves allocate
    many small blocks, so the default comes back afterwards."""
    return _FASTBINS


def split_cpu_devices(n: int) -> int:
    """Expose the CPU as ``n`` JAX devices (``jax_num_cpu_devices``; process-global). Returns
    the number of CPU devices the process will have: ``n``, or the count already in force
    when JAX's backend has started (then nothing changes; call this before any JAX array is
    made).

    Each CPU device runs its own programs in order while all of them share the process's
    worker threads, so ``n`` devices can run ``n`` independent frames at once. A live step
    that leaves cores idle (the benchmark scene's reusing step keeps one of two cores busy)
    gains throughput with two frames in flight
    (:class:`~spectral_fit.live.LiveSession` ``devices``; docs/live.md "Frames in flight").
    A program placed on one device is compiled for it: the second device's first frame
    compiles again, or loads the program from JAX's persistent cache
    (:func:`enable_compilation_cache`)."""
    import jax
    from jax._src import xla_bridge

    n = int(n)
    if n < 1:
        from .errors import InputError

        raise InputError(f"must be >= 1, got {n}", field="cpu devices")
    if xla_bridge.backends_are_initialized():
        return len(jax.devices("cpu"))
    forced = re.search(r"--xla_force_host_platform_device_count=(\d+)",
                       os.environ.get("XLA_FLAGS", ""))
    if forced:  # the user's XLA flag rules (JAX refuses both)
        return int(forced.group(1))
    jax.config.update("jax_num_cpu_devices", n)
    return n

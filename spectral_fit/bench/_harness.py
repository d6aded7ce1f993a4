"""Benchmark harness behind ``spectral-fit bench``.

Case modules live in ``spectral_fit/bench/cases/``; each defines ``CASES``, a dict mapping a case
name to a function ``case(opts: BenchOptions) -> dict``. A case builds its inputs, then calls
:func:`measure` on the jitted function it times, and returns measure's dict with any extra
figures added (pixel counts, accuracy, sizes).

Every case reports compile time and steady-state time separately (docs/conventions.md, 'Stable
public API'): ``{"median_ms", "min_ms", "max_ms", "compile_s", "n", ...}``. Steady-state times are
medians over ``n`` calls after the first (compiling) call; every call blocks until its result is
ready.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import statistics
import time
from collections.abc import Callable
from typing import Any

__all__ = ["BenchOptions", "measure", "discover_cases", "run_benchmarks"]


@dataclasses.dataclass(frozen=True)
class BenchOptions:
    """Options every case receives.

    Attributes:
        repeats: timed calls after the compiling one.
        quick: smaller inputs (for smoke tests of the harness; figures are then not comparable).
    """

    repeats: int = 20
    quick: bool = False


def _block(x: Any) -> Any:
    import jax

    return jax.block_until_ready(x)


#: untimed calls between the first call and the timed ones (:func:`measure`)
WARMUP = 2


def measure(fn: Callable[..., Any], *args: Any, repeats: int = 20, **kwargs: Any
            ) -> dict[str, float]:
    """Time ``fn(*args, **kwargs)``: the first call (tracing + compilation + one run) is reported
    as ``compile_s`` (minus nothing: it is the user's first-call latency); after ``WARMUP``
    untimed calls (the first runs after compiling write their buffers' fresh memory and are
    several times slower than the steady ones), the next ``repeats`` calls as median/min/max
    milliseconds."""
    t0 = time.perf_counter()
    _block(fn(*args, **kwargs))
    compile_s = time.perf_counter() - t0
    for _ in range(WARMUP):
        _block(fn(*args, **kwargs))
    times = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        _block(fn(*args, **kwargs))
        times.append((time.perf_counter() - t) * 1e3)
    return {
        "median_ms": statistics.median(times),
        "min_ms": min(times),
        "max_ms": max(times),
        "compile_s": compile_s,
        "n": len(times),
    }


def discover_cases() -> dict[str, Callable[[BenchOptions], dict[str, Any]]]:
    """All cases of all modules in ``spectral_fit.bench.cases``, by name."""
    from . import cases as benchmarks

    cases: dict[str, Callable[[BenchOptions], dict[str, Any]]] = {}
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{benchmarks.__name__}.{info.name}")
        for name, fn in getattr(module, "CASES", {}).items():
            if name in cases:
                raise RuntimeError(f"benchmark case {name!r} defined twice")
            cases[name] = fn
    return cases


def run_benchmarks(
    names: list[str] | None = None,
    opts: BenchOptions | None = None,
    progress: Callable[[str], None] | None = None,
    *,
    cases: dict[str, Callable[[BenchOptions], dict[str, Any]]] | None = None,
) -> dict[str, Any]:
    """Run the named cases (all when None) of ``cases`` (default: :func:`discover_cases`);
    returns ``{case: figures}``."""
    opts = opts or BenchOptions()
    cases = discover_cases() if cases is None else dict(cases)
    if names:
        unknown = sorted(set(names) - set(cases))
        if unknown:
            from .._runtime.errors import InputError

            raise InputError(f"unknown case(s) {unknown}; known: {sorted(cases)}",
                             field="--cases")
        cases = {n: cases[n] for n in names}
    results: dict[str, Any] = {}
    for name, fn in cases.items():
        if progress:
            progress(name)
        results[name] = fn(opts)
    return results

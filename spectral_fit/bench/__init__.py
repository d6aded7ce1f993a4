"""Benchmarks behind 'spectral-fit bench'.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "BenchOptions": "_harness",
    "discover_cases": "_harness",
    "measure": "_harness",
    "run_benchmarks": "_harness",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

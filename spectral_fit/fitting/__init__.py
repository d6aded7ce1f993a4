"""Fitting the reflection model to spectroradiometer readings, and fit reports.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "CacheOptions": "_radiance_cache",
    "CompactLM": "_fit",
    "DEMO_CONFIG": "_report",
    "DEMO_SESSION": "_report",
    "FitOptions": "_fit",
    "FitProblem": "_fit",
    "FitResult": "_fit",
    "GlossNodes": "_radiance_cache",
    "PARAMETERS": "_fit",
    "PARAM_INDEX": "_fit",
    "RadianceCache": "_radiance_cache",
    "SOLVERS": "_fit",
    "Sphere": "_radiance_cache",
    "band_matrix": "_fit",
    "build_gloss_nodes": "_radiance_cache",
    "build_radiance_cache": "_radiance_cache",
    "cached_radiance": "_radiance_cache",
    "disc_pixels": "_fit",
    "field_radiance": "_radiance_cache",
    "fit": "_fit",
    "fit_many": "_fit",
    "gloss_from_nodes": "_radiance_cache",
    "interreflection_term": "_fit",
    "make_solver": "_fit",
    "materials_json": "_report",
    "mitsuba_snippet": "_report",
    "physical_from_y": "_fit",
    "predict": "_fit",
    "prepare_fit": "_fit",
    "probe_radiance": "_radiance_cache",
    "recovery_table": "_report",
    "residuals": "_fit",
    "run_demo_fit": "_report",
    "scene_environment": "_fit",
    "scene_geometry": "_fit",
    "simulate_readings": "_fit",
    "solve_batch": "_fit",
    "to_physical": "_fit",
    "to_unconstrained": "_fit",
    "with_interreflection": "_fit",
    "write_report": "_report",
    "y_start": "_fit",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

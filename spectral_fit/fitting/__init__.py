"""Fitting the reflection model to spectroradiometer readings, and fit reports.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "CacheOptions": "_radiance_cache",
    "CompactLM": "_solver",
    "DEMO_CONFIG": "_report",
    "DEMO_SESSION": "_report",
    "FitOptions": "_options",
    "FitInstrument": "_problem",
    "FitProblem": "_problem",
    "FitReadings": "_problem",
    "FitSurfaces": "_problem",
    "PreparedFit": "_problem",
    "FitResult": "_fit",
    "GlossNodes": "_radiance_cache",
    "PARAMETERS": "_params",
    "PARAM_INDEX": "_params",
    "RadianceCache": "_radiance_cache",
    "SOLVERS": "_options",
    "Sphere": "_radiance_cache",
    "band_matrix": "_prepare",
    "build_gloss_nodes": "_gloss_nodes",
    "build_radiance_cache": "_cache_build",
    "cached_radiance": "_cache_model",
    "disc_pixels": "_spots",
    "field_radiance": "_cache_model",
    "fit": "_fit",
    "fit_many": "_fit",
    "gloss_from_nodes": "_cache_model",
    "interreflection_term": "_model",
    "make_solver": "_solver",
    "materials_json": "_report",
    "mitsuba_snippet": "_report",
    "physical_from_y": "_params",
    "predict": "_model",
    "prepare_fit": "_prepare",
    "probe_radiance": "_cache_model",
    "recovery_table": "_report",
    "residuals": "_model",
    "run_demo_fit": "_report",
    "scene_environment": "_prepare",
    "scene_geometry": "_prepare",
    "simulate_readings": "_simulate",
    "solve_batch": "_solver",
    "to_physical": "_params",
    "to_unconstrained": "_params",
    "write_report": "_report",
    "y_start": "_params",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

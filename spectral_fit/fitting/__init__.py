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
    "PlanResult": "_plan",
    "PreparedFit": "_problem",
    "FitResult": "_fit",
    "GlossNodes": "_radiance_cache",
    "PARAMETERS": "_params",
    "PARAM_INDEX": "_params",
    "RadianceCache": "_radiance_cache",
    "RenderUncertainty": "_render_uncertainty",
    "Region": "_plan_candidates",
    "SOLVERS": "_options",
    "Sphere": "_radiance_cache",
    "TOLERANCES": "_plan_design",
    "band_matrix": "_prepare",
    "build_gloss_nodes": "_gloss_nodes",
    "build_radiance_cache": "_cache_build",
    "cached_radiance": "_cache_model",
    "candidate_information": "_plan_information",
    "default_range": "_plan_design",
    "disc_pixels": "_spots",
    "draws_in_box": "_plan_design",
    "field_radiance": "_cache_model",
    "fit": "_fit",
    "fit_many": "_fit",
    "gloss_from_nodes": "_cache_model",
    "interreflection_term": "_model",
    "load_region": "_plan_candidates",
    "make_solver": "_solver",
    "materials_json": "_report",
    "mitsuba_snippet": "_report",
    "physical_from_y": "_params",
    "plan_candidates": "_plan_candidates",
    "plan_measurements": "_plan",
    "plan_objective": "_plan_design",
    "predict": "_model",
    "prepare_candidates": "_plan_information",
    "prepare_fit": "_prepare",
    "prepare_fit_cached": "_prepare_cache",
    "probe_radiance": "_cache_model",
    "reading_information": "_plan_design",
    "reading_sensitivity": "_plan_design",
    "recovery_table": "_report",
    "render_uncertainty": "_render_uncertainty",
    "residuals": "_model",
    "run_demo_fit": "_report",
    "scaled_variances": "_plan_design",
    "scene_environment": "_prepare",
    "scene_geometry": "_prepare",
    "select_readings": "_plan_design",
    "simulate_readings": "_simulate",
    "solve_batch": "_solver",
    "to_physical": "_params",
    "to_unconstrained": "_params",
    "write_plan": "_plan_report",
    "write_report": "_report",
    "y_start": "_params",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

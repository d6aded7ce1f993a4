"""spectral_fit: a differentiable spectral renderer in JAX.

Fits the reflection model of plastic objects (Lambert + Torrance–Sparrow gloss + mirror, after
Mochizuki & Tanaka) to spectroradiometer readings, and renders mixed-reality frames with the same
renderer. The public names below are imported lazily, so ``import spectral_fit`` stays fast and
does not start JAX until a JAX-based function is used.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> submodule that defines it (the stable API of docs/conventions.md, plus
# data-layer helpers)
_EXPORTS: dict[str, str] = {
    "SpectralFitError": "errors",
    "InputError": "errors",
    "default_wavelengths": "spectra",
    "wavelength_grid": "spectra",
    "resample": "spectra",
    "read_spectrum_csv": "spectra",
    "radiance_to_xyz": "colorimetry",
    "reflectance_to_xyz": "colorimetry",
    "xyz_weights": "colorimetry",
    "xyz_to_lab": "colorimetry",
    "delta_e00": "colorimetry",
    "SpectralBasis": "basis",
    "pca_basis": "basis",
    "fresnel_dielectric": "reflectance",
    "Material": "reflectance",
    "make_material": "reflectance",
    "EnvironmentMap": "environment",
    "shade": "environment",
    "shade_points": "environment",
    "Scene": "scene",
    "load_scene": "scene",
    "Display": "display",
    "to_display": "display",
    "read_spectral_exr": "exr",
    "write_spectral_exr": "exr",
    "read_rgb_exr": "exr",
    "rgb_to_spectra": "upsampling",
    "read_rgb_environment": "upsampling",
    "make_environment": "synthetic_environment",
    # reference (Mitsuba ground truth; the loader needs no Mitsuba)
    "load_reference": "reference.data",
    "Reference": "reference.data",
    # session, fitting, report
    "Session": "session",
    "load_session": "session",
    "write_session": "session",
    "FitResult": "fitting",
    "FitOptions": "fitting",
    "fit": "fitting",
    "fit_many": "fitting",
    "prepare_fit": "fitting",
    "write_report": "report",
    "run_demo_fit": "report",
    # live mixed reality (live, markers, compositing, camera_calibration, video)
    "LiveSession": "live",
    "MarkerDetector": "markers",
    "MarkerTracker": "markers",
    "CameraModel": "compositing",
    "camera_model_from_sensitivities": "compositing",
    "camera_model_from_colorchecker": "compositing",
    "composite": "compositing",
    "CalibrationTarget": "camera_calibration",
    "calibrate_images": "camera_calibration",
    "write_calibrated_config": "camera_calibration",
    "VideoSource": "video",
    "VideoSink": "video",
    # geometry, cameras and the rasteriser
    "Mesh": "mesh",
    "uv_sphere": "mesh",
    "icosphere": "mesh",
    "load_mesh": "mesh",
    "concat_meshes": "mesh",
    "Camera": "camera",
    "perspective": "camera",
    "look_at": "camera",
    "perspective_camera": "camera",
    "interreflection_camera": "camera",
    "relative_transform": "camera",
    "project": "camera",
    "Raster": "raster",
    "RasterConfig": "raster",
    "rasterize": "raster",
    "rasterize_batch": "raster",
    "plan_config": "raster",
    "interpolate": "raster",
    "covered_pixels": "raster",
    "interpolate_pixels": "raster",
    "scatter_pixels": "raster",
    # interreflection (paper eq. 6 and the gather mode)
    "interreflection": "interreflection",
    "interreflection_from": "interreflection",
    "prepare_interreflection": "interreflection",
    "IRGeometry": "interreflection",
    # renderer (multipass frames), outputs, validation against the references
    "render": "renderer",
    "prepare": "renderer",
    "render_frame": "renderer",
    "Frame": "renderer",
    "Prepared": "renderer",
    "write_frame": "outputs",
    "validate": "validation",
    # live: colour calibration from a chart shot, per-stage run statistics (compositing, live)
    "calibrate_colour": "compositing",
    "chart_xyz": "compositing",
    "write_colour_config": "compositing",
    "camera_model_from_spec": "compositing",
    "scene_camera_model": "live",
    "RunStats": "live",
    # radiance_cache (the fit's material-independent precomputation)
    "CacheOptions": "radiance_cache",
    "GlossNodes": "radiance_cache",
    "RadianceCache": "radiance_cache",
    "Sphere": "radiance_cache",
    "build_gloss_nodes": "radiance_cache",
    "build_radiance_cache": "radiance_cache",
    "gloss_from_nodes": "radiance_cache",
    "cached_radiance": "radiance_cache",
    "field_radiance": "radiance_cache",
    "probe_radiance": "radiance_cache",
    # cold start: persistent caches of compiled programs and prepared scenes (startup)
    "enable_compilation_cache": "startup",
    "prepare_cached": "startup",
    "render_frame_cached": "startup",
    # frame program: covered pixels without background, output channels, pixel composite
    # (renderer, compositing)
    "PixelFrame": "renderer",
    "render_pixels": "renderer",
    "with_output": "renderer",
    "composite_pixels": "compositing",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'spectral_fit' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = sorted(_EXPORTS)

"""spectral_fit: a differentiable spectral renderer in JAX.

Fits the reflection model of plastic objects (Lambert + Torrance–Sparrow gloss + mirror, after
Mochizuki & Tanaka) to spectroradiometer readings, and renders mixed-reality frames with the same
renderer. The public names below are imported lazily, so ``import spectral_fit`` stays fast and
does not start JAX until a JAX-based function is used.
"""

from __future__ import annotations

from ._runtime.lazy import lazy_exports

__version__ = "0.1.0"

# public name -> submodule that defines it (the stable API of docs/conventions.md, plus
# data-layer helpers)
_EXPORTS: dict[str, str] = {
    "SpectralFitError": "_runtime.errors",
    "InputError": "_runtime.errors",
    "default_wavelengths": "color",
    "wavelength_grid": "color",
    "resample": "color",
    "read_spectrum_csv": "color",
    "radiance_to_xyz": "color",
    "reflectance_to_xyz": "color",
    "xyz_weights": "color",
    "xyz_to_lab": "color",
    "delta_e00": "color",
    "SpectralBasis": "color",
    "pca_basis": "color",
    "fresnel_dielectric": "lighting",
    "Material": "lighting",
    "make_material": "lighting",
    "EnvironmentMap": "lighting",
    "shade": "lighting",
    "shade_points": "lighting",
    "Scene": "io",
    "load_scene": "io",
    "Display": "color",
    "to_display": "color",
    "read_spectral_exr": "io",
    "write_spectral_exr": "io",
    "read_rgb_exr": "io",
    "rgb_to_spectra": "lighting",
    "read_rgb_environment": "lighting",
    "make_environment": "lighting",
    # reference (Mitsuba ground truth; the loader needs no Mitsuba)
    "load_reference": "validation.reference.data",
    "Reference": "validation.reference.data",
    # session, fitting, report
    "Session": "io",
    "load_session": "io",
    "write_session": "io",
    "FitResult": "fitting",
    "FitOptions": "fitting",
    "fit": "fitting",
    "fit_many": "fitting",
    "prepare_fit": "fitting",
    "write_report": "fitting",
    "run_demo_fit": "fitting",
    # live mixed reality (live, markers, compositing, camera_calibration, video)
    "LiveSession": "live",
    "MarkerDetector": "live",
    "MarkerTracker": "live",
    "CameraModel": "live",
    "camera_model_from_sensitivities": "live",
    "camera_model_from_colorchecker": "live",
    "composite": "live",
    "CalibrationTarget": "live",
    "calibrate_images": "live",
    "write_calibrated_config": "live",
    "VideoSource": "live",
    "VideoSink": "live",
    # geometry, cameras and the rasteriser
    "Mesh": "io",
    "uv_sphere": "io",
    "icosphere": "io",
    "load_mesh": "io",
    "concat_meshes": "io",
    "Camera": "geometry",
    "perspective": "geometry",
    "look_at": "geometry",
    "perspective_camera": "geometry",
    "interreflection_camera": "geometry",
    "relative_transform": "geometry",
    "project": "geometry",
    "Raster": "geometry",
    "RasterConfig": "geometry",
    "rasterize": "geometry",
    "rasterize_batch": "geometry",
    "plan_config": "geometry",
    "interpolate": "geometry",
    "covered_pixels": "geometry",
    "interpolate_pixels": "geometry",
    "scatter_pixels": "geometry",
    # interreflection (paper eq. 6 and the gather mode)
    "interreflection": "rendering.interreflection",
    "interreflection_from": "rendering.interreflection",
    "prepare_interreflection": "rendering.interreflection",
    "IRGeometry": "rendering.interreflection",
    # renderer (multipass frames), outputs, validation against the references
    "render": "rendering",
    "prepare": "rendering",
    "render_frame": "rendering",
    "Frame": "rendering",
    "Prepared": "rendering",
    "write_frame": "rendering",
    "validate": "validation",
    # live: colour calibration from a chart shot, per-stage run statistics (compositing, live)
    "calibrate_colour": "live",
    "chart_xyz": "live",
    "write_colour_config": "live",
    "camera_model_from_spec": "live",
    "scene_camera_model": "live",
    "RunStats": "live",
    # radiance_cache (the fit's material-independent precomputation)
    "CacheOptions": "fitting",
    "GlossNodes": "fitting",
    "RadianceCache": "fitting",
    "Sphere": "fitting",
    "build_gloss_nodes": "fitting",
    "build_radiance_cache": "fitting",
    "gloss_from_nodes": "fitting",
    "cached_radiance": "fitting",
    "field_radiance": "fitting",
    "probe_radiance": "fitting",
    # cold start: persistent caches of compiled programs and prepared scenes (startup)
    "enable_compilation_cache": "rendering",
    "prepare_cached": "rendering",
    "render_frame_cached": "rendering",
    # process settings for interactive sessions: XLA's freed frame memory kept for reuse, the
    # CPU split into devices for frames in flight
    "retain_freed_memory": "_runtime.process",
    "split_cpu_devices": "_runtime.process",
    # frame program: covered pixels without background, output channels, pixel composite
    # (renderer, compositing)
    "PixelFrame": "rendering",
    "render_pixels": "rendering",
    "with_output": "rendering",
    "composite_pixels": "live",
}


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

__all__ = sorted(_EXPORTS)

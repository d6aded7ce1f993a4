"""The frame renderer: prepare a scene once, render frames of poses without recompiling, write
outputs, keep prepared scenes and programs on disk.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "CACHE_STATS": "_cache",
    "Frame": "_prepared",
    "PixelFrame": "_prepared",
    "Prepared": "_prepared",
    "PreparedBuffers": "_prepared",
    "PreparedCamera": "_prepared",
    "PreparedColour": "_prepared",
    "PreparedInterreflection": "_prepared",
    "PreparedLighting": "_prepared",
    "SceneMeshes": "_prepared",
    "SurfaceLayer": "_surfaces",
    "SurfaceTexture": "_surfaces",
    "SurfaceTransfer": "_surfaces",
    "TRACE_COUNT": "_prepared",
    "all_visible": "_inputs",
    "cache_root": "_cache",
    "compilation_counts": "_cache",
    "distribution_version": "_keys",
    "environment_digest": "_keys",
    "plain_repr": "_keys",
    "program_key": "_keys",
    "read_cache_entry": "_cache",
    "scene_text": "_keys",
    "write_cache_entry": "_cache",
    "camera_clip": "_camera",
    "composite": "_outputs",
    "draw_surfaces": "_surfaces",
    "enable_compilation_cache": "_cache",
    "ground_surfaces": "_environment",
    "ir_fallback": "_regrow",
    "library_versions": "_keys",
    "library_versions_tag": "_keys",
    "load_environment": "_environment",
    "mirror_needed": "_materials",
    "plan_capacities": "_capacities",
    "prepare": "_prepare",
    "prepare_cached": "_prepared_cache",
    "read_background": "_outputs",
    "regrow": "_regrow",
    "render": "_regrow",
    "render_frame": "_frame",
    "render_frame_cached": "_program_cache",
    "render_pixels": "_pixels",
    "render_senders": "_ir_stage",
    "scene_materials": "_materials",
    "surface_layer": "_surfaces",
    "surface_pixels": "_surfaces",
    "surface_vertices": "_surfaces",
    "table_changes": "_surfaces",
    "neighbour_irradiance": "_surfaces",
    "TableChange": "_surfaces",
    "surface_ratio": "_surfaces",
    "surface_ratio_lookup": "_surfaces",
    "surface_ratio_textures": "_surfaces",
    "surface_texels": "_surfaces",
    "surface_textures": "_surfaces",
    "surface_transfer": "_surfaces",
    "build_surface_transfer": "_surfaces",
    "with_output": "_frame",
    "write_frame": "_outputs",
    "write_rgb_exr": "_outputs",
    "write_xyz_exr": "_outputs",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

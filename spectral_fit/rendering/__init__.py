"""The frame renderer: prepare a scene once, render frames of poses without recompiling, write
outputs, keep prepared scenes and programs on disk.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "CACHE_STATS": "_cache",
    "Frame": "_renderer",
    "PixelFrame": "_renderer",
    "Prepared": "_renderer",
    "TRACE_COUNT": "_renderer",
    "all_visible": "_renderer",
    "cache_root": "_cache",
    "camera_clip": "_renderer",
    "composite": "_outputs",
    "enable_compilation_cache": "_cache",
    "ir_fallback": "_renderer",
    "library_versions": "_cache",
    "library_versions_tag": "_cache",
    "load_environment": "_renderer",
    "mirror_needed": "_renderer",
    "plan_capacities": "_renderer",
    "prepare": "_renderer",
    "prepare_cached": "_cache",
    "read_background": "_outputs",
    "regrow": "_renderer",
    "render": "_renderer",
    "render_frame": "_renderer",
    "render_frame_cached": "_cache",
    "render_pixels": "_renderer",
    "render_senders": "_renderer",
    "scene_materials": "_renderer",
    "with_output": "_renderer",
    "write_frame": "_outputs",
    "write_rgb_exr": "_outputs",
    "write_xyz_exr": "_outputs",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

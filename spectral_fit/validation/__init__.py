"""Colour against path-traced references (ΔE00 per region) and the Mitsuba 3 reference renderer.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from .._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "FIGURE_FORMATS": "_compare",
    "SAMPLES": "_compare",
    "TARGETS": "_compare",
    "check_samples": "_compare",
    "pixel_means": "_compare",
    "delta_e_figure": "_compare",
    "delta_e_patches": "_compare",
    "scene_white_xyz": "_compare",
    "validate": "_compare",
    "IR_THRESHOLD": "_scenes",
    "SCENE_TARGETS": "_scenes",
    "region_report": "_scenes",
    "scene_figure": "_scenes",
    "scene_regions": "_scenes",
    "validate_scene": "_scenes",
    "validate_reference": "_scenes",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)

"""Buffer capacities planned from the configured poses, in NumPy (no compilation): the camera
raster's window capacities and the covered pixels (:func:`plan_capacities`), the window
capacities of the interreflection's pass-1 rasters, and the size of the culled clusters' list.
They carry headroom so that objects can move without recompiling; a frame whose buffers were
too small flags the overflow in its stats.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

__all__ = [
    "plan_capacities",
]


def plan_capacities(clip: np.ndarray, triangles: np.ndarray, shape: tuple[int, int], *,
                    headroom: float = 1.5, cull: str = "none") -> tuple[Any, int]:
    """Rasteriser window capacities and a bound on the covered pixels for one pose, in NumPy
    (no compilation): :func:`spectral_fit.geometry.plan_counts` (the rasteriser's own window
    counting, with its ``cull`` mode). Returns (RasterConfig, pixel bound); the capacities
    are ``headroom`` × the counts on the rasteriser's ladder."""
    from ..geometry import RasterConfig, plan_counts

    counts = plan_counts(clip, triangles, shape, cull=cull)
    return RasterConfig.from_counts(counts, headroom=headroom), counts.pixels


def _ir_generic_config(mode: str, texture_size: int, triangles: int, gather_size: int = 16
                       ) -> Any:
    """The generic window capacities of a pass-1 raster of ``triangles`` triangles
    (:func:`~spectral_fit.rendering.interreflection._pass1.pass1_config`) on the pass-1 frame:
    (4 g)² for gather (4× supersampled g² samples, g = ``gather_size``), ``texture_size``²
    for paper."""
    from .interreflection._pass1 import SUPERSAMPLE, pass1_config

    return pass1_config(triangles, texture_size if mode == "paper" else SUPERSAMPLE * gather_size)


def _ir_raster_config(mode: str, texture_size: int, triangles: int,
                      paper_clips: list[np.ndarray] | None = None,
                      paper_tris: list[np.ndarray] | None = None,
                      meshes: list[tuple[np.ndarray, np.ndarray]] | None = None,
                      gather_size: int = 16) -> Any:
    """Window capacities of the interreflection pass-1 rasters (inside the compiled frame, so
    they cannot be grown there; an overflow is flagged and :func:`render` / the live session
    then fall back to :func:`_ir_generic_config`). Gather: planned per sender mesh for any
    pose (``meshes``: (vertices in the object's frame, triangles);
    :func:`~spectral_fit.rendering.interreflection._pass1.plan_gather_pass1`: 1.5× the most
    that 24 views (six
    axes, four rolls each) need;
    the generic sizes give the 4×4 windows 80× what the benchmark spheres use, a cost paid
    every frame); without meshes the generic sizes. Paper: the generic sizes, and at least twice
    what the configured poses need (:func:`plan_capacities` on each pair's view)."""
    if mode == "none":
        return None
    if mode == "gather" and meshes:
        from .interreflection._pass1 import plan_gather_pass1

        planned: dict[bytes, Any] = {}
        for v, t in meshes:  # identical meshes (the paper's two spheres) planned once
            key = hashlib.sha1(np.ascontiguousarray(v, np.float32).tobytes()
                               + np.ascontiguousarray(t, np.int32).tobytes()).digest()
            if key not in planned:
                planned[key] = plan_gather_pass1(v, t, gather_size=gather_size)
        cfgs = list(planned.values())
        return cfgs[0]._replace(
            capacities=tuple(max(c) for c in zip(*(g.capacities for g in cfgs), strict=True)))
    cfg = _ir_generic_config(mode, texture_size, triangles, gather_size)
    for clip, tris in zip(paper_clips or [], paper_tris or [], strict=True):
        need, _ = plan_capacities(clip, tris, (texture_size, texture_size), headroom=2.0)
        cfg = cfg._replace(capacities=tuple(max(a, b) for a, b in
                                            zip(cfg.capacities, need.capacities, strict=True)))
    return cfg


def _plan_clusters(clusters: Any, model: np.ndarray, view: np.ndarray, proj: np.ndarray,
                   cull: str) -> Any:
    """``clusters`` with its kept-list capacity: the clusters kept at the pose, or seen
    from any direction (:func:`~spectral_fit.geometry.worst_direction_count`: objects that
    turn), whichever is more, + 5 %, on the capacity ladder."""
    from ..geometry import count_clusters, sized, worst_direction_count

    need = max(count_clusters(clusters, model, view, proj, cull=cull),
               worst_direction_count(clusters))
    return sized(clusters, 1.05 * need + 4)
